"""flocktrack sweep: grid parsing, a real parallel sweep (tidy CSV, figures, resume), fail-fast on a bad grid
key, a bad cell recorded without aborting, and the link-loss fault as a grid key."""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from agent.scenario import ScenarioError
from dashboards import sweep_plots as sp
from flocktrack.experiment import grid as gr
from flocktrack.experiment import results
from flocktrack.experiment import runs as rn
from flocktrack.experiment import sweep as sw

ROOT = Path(__file__).resolve().parents[2]
NORMAL = str(ROOT / "scenarios" / "gu_hu_normal.toml")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _rows(path: Path) -> list[dict]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


# ---------------------------------------------------------------------------- parsing (no runs)

def test_grid_parsing_shorthands_and_toml_values():
    a = gr.parse_grid("estimator=kalman,minimax")
    assert (a.key, a.label, a.values) == ("estimator.name", "estimator", ("kalman", "minimax"))
    assert not a.numeric
    r = gr.parse_grid("rounds=1,2,5")
    assert (r.key, r.values) == ("estimator.rounds", (1, 2, 5)) and r.numeric
    f = gr.parse_grid("faults.link_loss=0,0.1,0.3,0.5")
    assert f.key == "faults.link_loss" and f.label == "link_loss" and f.values == (0, 0.1, 0.3, 0.5)
    arr = gr.parse_grid("sensors.origin=[0, 0],[-16.0,-4.0]")
    assert arr.values == ([0, 0], [-16.0, -4.0])
    assert gr.split_values('[1,2],"a,b",3') == ["[1,2]", '"a,b"', "3"]
    assert gr.parse_grid("run.mode=true,false").values == (True, False)


@pytest.mark.parametrize("spec, words", [
    ("seed=0,1", "--seeds"),
    ("run.seed=0,1", "--seeds"),
    ("bogus=1,2", "section.key"),
    ("rounds", "KEY=V1,V2"),
    ("rounds=1,,2", "empty value"),
    ("rounds=1,2,1", "repeated"),
])
def test_grid_parsing_rejects(spec, words):
    with pytest.raises(ScenarioError, match=words):
        gr.parse_grid(spec)


def test_run_ids_unique_and_readable():
    axes = [gr.parse_grid("link_loss=0,0.1"), gr.parse_grid("sensors.origin=[0,0],[1,1]"),
            gr.parse_grid("estimator=kalman,minimax")]
    specs = gr.expand(axes, [0, 1, 2])
    assert len(specs) == 2 * 2 * 2 * 3
    ids = [s.run_id for s in specs]
    assert len(set(ids)) == len(ids)
    assert all("/" not in i and " " not in i for i in ids)
    assert gr.expand([gr.parse_grid("rounds=1,2")], [3])[0].run_id == "rounds-1_seed-3"


def test_scalar_metrics_flatten_summary():
    s = {"scenario": "x", "seed": 1, "n_sensors": 3, "network_rmse": 0.5, "final_rmse": None,
         "per_node_rmse": [0.1, 0.2, None], "tmsee": [1.0, 2.0, 3.0, 4.0], "faults": {"dropped": 7},
         "lambda2": [0.1, 0.2, 0.3]}
    m = dict(results.scalar_metrics(s))
    assert m["network_rmse"] == 0.5 and m["final_rmse"] is None
    assert m["per_node_rmse[0]"] == 0.1 and m["per_node_rmse[2]"] is None
    assert m["faults.dropped"] == 7.0
    assert "seed" not in m and "tmsee" not in m and "lambda2" not in m and "scenario" not in m


def test_mean_ci_and_log_decision():
    m, lo, hi = sp.mean_ci([1.0, 2.0, 3.0, 4.0])
    assert m == 2.5 and lo < m < hi and 1.0 <= lo and hi <= 4.0
    assert sp.mean_ci([1.0, 2.0, 3.0, 4.0]) == (m, lo, hi)  # deterministic
    assert sp.mean_ci([5.0]) == (5.0, 5.0, 5.0)
    assert all(math.isnan(v) for v in sp.mean_ci([]))
    assert sp.wants_log([0.05, 0.06, 0.07, 12.0, 15.0]) and not sp.wants_log([0.05, 0.2, 0.1])


def test_register_adds_sweep_subcommand():
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd")
    sw.register(sub)
    args = ap.parse_args(["sweep", NORMAL, "--grid", "rounds=1,2", "--seeds", "3", "--out", "x"])
    assert args.fn is sw.cmd_sweep and args.seeds == [0, 1, 2] and args.grid == ["rounds=1,2"]


# ---------------------------------------------------------------------------- a real sweep

ARGS = [NORMAL, "--grid", "rounds=1,2", "--grid", "estimator=kalman,minimax", "--seeds", "2", "--ticks", "40",
        "--jobs", "2"]


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep")
    rc = sw.main([*ARGS, "--out", str(out)])
    return rc, out


def test_sweep_runs_every_cell_and_seed(sweep):
    rc, out = sweep
    assert rc == 0
    runs = sorted(p.name for p in (out / "runs").iterdir() if not p.name.startswith("."))
    assert len(runs) == 2 * 2 * 2
    assert all((out / "runs" / r / "summary.json").exists() and (out / "runs" / r / "metrics.csv").exists()
               for r in runs)
    meta = json.loads((out / "sweep.json").read_text())
    assert meta["runs"] == 8 and meta["ok"] == 8 and meta["failed"] == 0 and meta["failures"] == []
    assert meta["grid"] == {"estimator.rounds": [1, 2], "estimator.name": ["kalman", "minimax"]}
    assert meta["seeds"] == [0, 1] and meta["wall_s"] > 0 and set(meta["run_wall_s"]) == set(runs)
    # each run got its cell and seed
    for r in runs:
        s = json.loads((out / "runs" / r / "summary.json").read_text())
        assert f"rounds-{s['rounds']}_estimator-{s['estimator']}_seed-{s['seed']}" == r
        assert s["ticks"] == 40


def test_results_csv_is_tidy(sweep):
    _, out = sweep
    rows = _rows(out / "results.csv")
    assert list(rows[0]) == ["estimator.rounds", "estimator.name", "seed", "run_id", "status", "metric", "value",
                             "error"]
    by_run: dict[str, list[str]] = {}
    for r in rows:
        assert r["status"] == "ok" and r["error"] == ""
        by_run.setdefault(r["run_id"], []).append(r["metric"])
        if r["value"] != "":
            float(r["value"])  # one number per row
    assert len(by_run) == 8
    metrics = next(iter(by_run.values()))
    assert all(sorted(m) == sorted(metrics) for m in by_run.values())  # the same metrics for every run
    assert all(len(set(m)) == len(m) for m in by_run.values())          # each once per run
    assert len(rows) == 8 * len(metrics)
    for name in ("network_rmse", "final_rmse", "max_error", "mean_estimate_rmse", "tmsee_mean", "disagreement_mean",
                 "min_inter_agent_distance", "lambda2_min", "connected_fraction"):
        assert name in metrics
    assert [f"per_node_rmse[{i}]" for i in range(10)] == [m for m in metrics if m.startswith("per_node")]
    # values agree with the runs' own summary.json
    r0 = next(r for r in rows if r["metric"] == "network_rmse")
    s = json.loads((out / "runs" / r0["run_id"] / "summary.json").read_text())
    assert float(r0["value"]) == s["network_rmse"]
    # seeds differ, cells differ
    v = {(r["estimator.rounds"], r["estimator.name"], r["seed"]): float(r["value"]) for r in rows
         if r["metric"] == "network_rmse"}
    assert len(set(v.values())) == 8
    agg = _rows(out / "summary.csv")
    nr = [a for a in agg if a["metric"] == "network_rmse"]
    assert len(nr) == 4 and all(a["n"] == "2" and float(a["ci95_lo"]) <= float(a["mean"]) <= float(a["ci95_hi"])
                                for a in nr)


def test_consistency_csv_gives_each_cells_anees_over_its_seeds(sweep):
    """The Monte-Carlo consistency: per cell, the mean of its runs' ANEES (from the same results.csv), the
    verdict by whether m lies in the seeds' interval, and the pooled textbook interval beside it."""
    from dashboards.nees import chi2_interval

    _, out = sweep
    rows = _rows(out / "results.csv")
    cons = _rows(out / "consistency.csv")
    assert len(cons) == 4
    for c in cons:
        mine = [r for r in rows if (r["estimator.rounds"], r["estimator.name"]) == (c["estimator.rounds"],
                                                                                    c["estimator.name"])]
        anees = [float(r["value"]) for r in mine if r["metric"] == "credibility.network.anees"]
        samples = sum(int(float(r["value"])) for r in mine if r["metric"] == "credibility.network.samples")
        assert int(c["runs"]) == 2 and int(c["samples"]) == samples and int(c["dof"]) == 4
        assert float(c["anees"]) == pytest.approx(np.mean(anees), rel=1e-5)
        lo, hi = float(c["seeds_ci95_lo"]), float(c["seeds_ci95_hi"])
        assert lo <= float(c["anees"]) <= hi
        assert c["verdict"] == ("consistent" if lo <= 4 <= hi else "conservative" if hi < 4 else "optimistic")
        assert (float(c["chi2_lo"]), float(c["chi2_hi"])) == pytest.approx(chi2_interval(4 * samples, samples),
                                                                           rel=1e-5)
    meta = json.loads((out / "sweep.json").read_text())
    assert len(meta["consistency"]) == 4 and meta["outputs"]["consistency"] == "consistency.csv"


def test_figures_are_real_pngs(sweep):
    import matplotlib.image as mpimg

    _, out = sweep
    figs = sorted((out / "figures").glob("*.png"))
    names = {p.name for p in figs}
    assert {"traces_rmse.png", "traces_disagreement.png", "network_rmse_vs_rounds.png",
            "final_rmse_vs_rounds.png"} <= names
    for p in figs:
        assert p.read_bytes()[:8] == PNG_MAGIC and p.stat().st_size > 15_000
        img = mpimg.imread(p)
        assert img.shape[0] > 300 and img.shape[1] > 500
        assert float(np.std(img[..., :3])) > 0.05  # not a blank canvas
    meta = json.loads((out / "sweep.json").read_text())
    assert sorted(meta["figures"]) == sorted(f"figures/{n}" for n in names)


def test_resume_skips_finished_runs(sweep):
    _, out = sweep
    stamps = {p.parent.name: p.stat().st_mtime_ns for p in (out / "runs").glob("*/summary.json")}
    before = (out / "results.csv").read_text()
    victim = sorted(stamps)[0]
    import shutil

    shutil.rmtree(out / "runs" / victim)
    assert sw.main([*ARGS, "--out", str(out), "--no-figures", "--quiet"]) == 0
    meta = json.loads((out / "sweep.json").read_text())
    assert meta["executed"] == 1 and meta["resumed"] == 7
    after = {p.parent.name: p.stat().st_mtime_ns for p in (out / "runs").glob("*/summary.json")}
    assert all(after[r] == t for r, t in stamps.items() if r != victim)
    assert after[victim] != stamps[victim]
    assert (out / "results.csv").read_text() == before  # deterministic: the re-run gives the same numbers


def test_changed_scenario_reruns_instead_of_resuming(tmp_path):
    args = [NORMAL, "--grid", "rounds=1", "--seeds", "1", "--jobs", "1", "--no-figures", "--quiet"]
    assert sw.main([*args, "--ticks", "10", "--out", str(tmp_path)]) == 0
    assert sw.main([*args, "--ticks", "12", "--out", str(tmp_path)]) == 0
    meta = json.loads((tmp_path / "sweep.json").read_text())
    assert meta["rerun_stale"] == 1 and meta["resumed"] == 0
    s = json.loads((tmp_path / "runs" / "rounds-1_seed-0" / "summary.json").read_text())
    assert s["ticks"] == 12


# ---------------------------------------------------------------------------- failures

@pytest.mark.parametrize("grid, key", [("estimator.bogus=1,2", "[estimator.bogus] unknown key"),
                                       ("nosuch.key=1,2", "[nosuch] unknown table")])
def test_bad_grid_key_fails_fast_with_the_scenario_error(tmp_path, capsys, grid, key):
    rc = sw.main([NORMAL, "--grid", grid, "--seeds", "2", "--ticks", "10", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and key in err and "gu_hu_normal.toml" in err and "fix:" in err
    assert not (tmp_path / "o").exists()  # nothing ran, nothing written
    cfg = sw.SweepConfig(NORMAL, [gr.parse_grid(grid)], [0], tmp_path / "o2")
    with pytest.raises(ScenarioError) as ei:
        sw.run_sweep(cfg)
    assert key in str(ei.value)


def test_bad_set_fails_fast(tmp_path, capsys):
    rc = sw.main([NORMAL, "--grid", "rounds=1,2", "--set", "run.T=-1", "--seeds", "1", "--out", str(tmp_path / "o")])
    assert rc == 2 and "[run.T]" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_bad_value_in_one_cell_is_recorded_not_fatal(tmp_path, capsys):
    rc = sw.main([NORMAL, "--grid", "rounds=-1,1", "--seeds", "2", "--ticks", "15", "--jobs", "2", "--no-figures",
                  "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 1 and "[estimator.rounds] must be ≥ 0, got -1" in err
    rows = _rows(tmp_path / "results.csv")
    bad = [r for r in rows if r["estimator.rounds"] == "-1"]
    good = [r for r in rows if r["estimator.rounds"] == "1"]
    assert len(bad) == 2 and all(r["status"] == "failed" and "must be ≥ 0" in r["error"] and r["value"] == ""
                                 for r in bad)
    assert {r["seed"] for r in good} == {"0", "1"} and all(r["status"] == "ok" for r in good)
    meta = json.loads((tmp_path / "sweep.json").read_text())
    assert meta["failed"] == 2 and meta["ok"] == 2
    assert {f["cell"]["estimator.rounds"] for f in meta["failures"]} == {-1}


def test_worker_error_is_returned_not_raised(tmp_path):
    res = rn.execute_run({"run_id": "x", "dir": str(tmp_path / "x"), "data": {"run": {}}, "source": "s.toml"})
    assert res["status"] == "failed" and "table is required" in res["error"]
    assert not (tmp_path / "x").exists() and not (tmp_path / ".x.tmp").exists()


# ---------------------------------------------------------------------------- the fault key

def test_link_loss_is_a_grid_key(tmp_path):
    rc = sw.main([NORMAL, "--grid", "faults.link_loss=0,0.6", "--seeds", "1", "--ticks", "20", "--jobs", "1",
                  "--no-figures", "--quiet", "--out", str(tmp_path)])
    assert rc == 0
    rows = {(r["faults.link_loss"], r["metric"]): float(r["value"]) for r in _rows(tmp_path / "results.csv")
            if r["value"]}
    assert rows[("0.6", "lambda2_mean")] < rows[("0", "lambda2_mean")]  # the dropped links are really dropped


def test_array_and_string_grid_values(tmp_path):
    """Array values (unhashable lists) and a categorical first key go through runs, CSV and figures."""
    rc = sw.main([NORMAL, "--grid", "estimator=kalman,minimax", "--grid", "sensors.origin=[-16.0,-4.0],[-12.0,-4.0]",
                  "--seeds", "1", "--ticks", "10", "--jobs", "1", "--quiet", "--out", str(tmp_path)])
    assert rc == 0
    rows = _rows(tmp_path / "results.csv")
    assert {r["sensors.origin"] for r in rows} == {"[-16.0, -4.0]", "[-12.0, -4.0]"}
    assert len({r["run_id"] for r in rows}) == 4
    figs = {p.name for p in (tmp_path / "figures").glob("*.png")}
    assert "traces_rmse.png" in figs and "network_rmse_vs_estimator.png" in figs
