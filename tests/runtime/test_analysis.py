"""A run as tables (``flocktrack.load``) and as files (``flocktrack export``), from real in-process runs: a row
per tick and per tick and node, the same numbers as ``summary.json`` and ``metrics.csv``, the fault schedule
with the ticks the world applied it, Parquet and CSV that read back as they were written, and a recording cut
short read as far as it goes, with the ticks it lost."""

import json
import math
import warnings

import numpy as np
import pandas as pd
import pytest

import flocktrack
from flocktrack.analysis import TruncatedRecordingWarning
from flocktrack.cli import main

from conftest import SCENARIOS

TICKS = 40
N = 10     #: gu_hu_normal's sensors
BYZANTINE = '[{kind = "byzantine", targets = "agents:2", mode = "bias", bias = [1.0, 1.0], start = 10, heal = 20}]'


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A recorded in-process run of 40 ticks with link loss all run long and a Byzantine sensor for ten ticks."""
    out = tmp_path_factory.mktemp("analysis") / "run"
    rc = main(["run", str(SCENARIOS / "gu_hu_normal.toml"), "--transport", "inproc", "--record", "--ticks", str(TICKS),
               "--set", "faults.link_loss=0.1", "--set", f"faults.events={BYZANTINE}", "--out", str(out)])
    assert rc == 0
    return out


@pytest.fixture(scope="module")
def run(run_dir):
    return flocktrack.load(run_dir)


def test_a_run_directory_loads_as_a_row_per_tick_and_a_row_per_tick_and_node(run, run_dir):
    assert run.complete and run.lost_ticks == 0 and run.rejected == 0
    assert run.path == run_dir / "recording.mcap" and run.scenario.run.ticks == TICKS
    assert run.summary["ticks_seen"] == TICKS
    T = run.scenario.run.T
    assert list(run.ticks.k) == list(range(TICKS)) and np.allclose(run.ticks.t, run.ticks.k * T)
    assert len(run.estimates) == TICKS * N
    assert sorted(zip(run.estimates.k, run.estimates.node)) == [(k, i) for k in range(TICKS) for i in range(N)]
    assert {"px", "py", "vx", "vy", "err", "P_trace", "P_px", "estimator"} <= set(run.estimates.columns)
    assert {"truth_px", "truth_py", "truth_vx", "truth_vy", "rmse", "tmsee", "disagreement", "lambda2", "links",
            "links_directed", "alive"} <= set(run.ticks.columns)
    assert np.isfinite(run.estimates.err).all() and np.isfinite(run.ticks.rmse).all()


def test_the_tables_have_the_numbers_of_summary_json_and_metrics_csv(run, run_dir):
    s = json.loads((run_dir / "summary.json").read_text())
    assert run.summary == s
    scored = run.ticks[run.ticks.k >= run.scenario.run.burn_in]
    assert math.isclose(float(np.sqrt(np.mean(scored.rmse ** 2))), s["network_rmse"], rel_tol=0, abs_tol=1e-9)
    per_node = run.estimates[run.estimates.k >= run.scenario.run.burn_in].groupby("node").err
    assert np.allclose(per_node.apply(lambda e: np.sqrt(np.mean(e ** 2))), s["per_node_rmse"], rtol=0, atol=1e-12)
    assert np.allclose(run.ticks.tmsee, s["tmsee"], rtol=0, atol=1e-12)
    assert np.allclose(run.ticks.lambda2, s["lambda2"], rtol=0, atol=1e-12)
    csv = pd.read_csv(run_dir / "metrics.csv")
    shared = [c for c in csv.columns if c != "t"]
    assert set(shared) < set(run.ticks.columns)
    pd.testing.assert_frame_equal(run.ticks[shared], csv[shared], check_dtype=False, rtol=0, atol=1e-12)
    # each row's error is its estimate's position against the truth of its tick
    e = run.estimates.merge(run.ticks[["k", "truth_px", "truth_py"]], on="k")
    assert np.allclose(np.hypot(e.px - e.truth_px, e.py - e.truth_py), e.err, rtol=0, atol=1e-12)


def test_links_are_the_directed_links_of_each_tick(run):
    links = run.links
    assert (links.src != links.dst).all() and links.src.between(0, N - 1).all() and links.dst.between(0, N - 1).all()
    per_tick = links.groupby("k").size().reindex(run.ticks.k, fill_value=0)
    assert list(per_tick) == list(run.ticks.links_directed)
    assert list(run.ticks.links) == list(run.ticks.links_directed // 2)   # metrics.csv's undirected count
    assert not links.duplicated(["k", "src", "dst"]).any()


def test_the_faults_hold_the_schedule_and_the_events_its_transitions(run):
    f = run.faults.set_index("source")
    assert f.loc["link_loss", "kind"] == "link_loss" and f.loc["link_loss", "p"] == 0.1
    byz = f.loc["scenario"]
    assert (byz["id"], byz["kind"], byz["targets"], byz["agents"]) == (0, "byzantine", "agents:2", "2")
    assert (byz["start"], byz["heal"], byz["started"], byz["healed"]) == (10, 20, 10, 20)
    ev = run.events
    faults = ev[ev.verb == "fault"]
    assert list(zip(faults.k, faults.phase, faults.fault_id)) == [(10, "start", 0), (20, "heal", 0)]
    assert (faults.key == "world/event").all() and (faults.agents == "2").all()
    end = ev[ev.key == "world/end"]
    assert list(end.k) == [TICKS] and json.loads(end.args.iloc[0]) == {"reason": "done"}


@pytest.mark.parametrize("fmt", ["parquet", "csv"])
def test_export_writes_every_table_and_it_reads_back(run, run_dir, tmp_path, capsys, fmt):
    out = tmp_path / "tables"
    assert main(["export", str(run_dir), "--format", fmt, "--out", str(out)]) == 0
    said = capsys.readouterr().out
    for name, df in run.tables().items():
        f = out / f"{name}.{fmt}"
        assert f"{f.name}" in said and f"{len(df)} rows" in said
        back = pd.read_parquet(f) if fmt == "parquet" else pd.read_csv(f)
        assert len(back) == len(df) and list(back.columns) == list(df.columns)
    if fmt == "parquet":
        for name, df in run.tables().items():
            pd.testing.assert_frame_equal(pd.read_parquet(out / f"{name}.parquet"), df)
    else:
        for name in ("ticks", "estimates", "links"):
            pd.testing.assert_frame_equal(pd.read_csv(out / f"{name}.csv"), getattr(run, name), check_dtype=False)
    assert len(pd.read_parquet(out / "ticks.parquet") if fmt == "parquet" else pd.read_csv(out / "ticks.csv")) == TICKS


def test_a_recording_cut_short_gives_what_it_holds_and_the_ticks_it_lost(run_dir, tmp_path, capsys):
    data = (run_dir / "recording.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])            # the writer killed half-way: no summary, a torn chunk
    with pytest.warns(TruncatedRecordingWarning, match="flocktrack recover") as caught:
        run = flocktrack.load(cut)
    assert not run.complete and 0 < len(run.ticks) < TICKS
    assert run.lost_ticks == TICKS - len(run.ticks)
    line = str(caught[0].message)
    assert str(cut) in line and f"{run.lost_ticks} of the scenario's {TICKS} ticks are lost" in line
    assert "\n" not in line
    assert list(run.ticks.k) == list(range(len(run.ticks)))
    assert 0 < len(run.estimates) <= len(run.ticks) * N and run.estimates.k.max() <= run.ticks.k.max()
    assert run.links.k.max() <= run.ticks.k.max() and run.summary == {}   # no summary.json beside it

    with warnings.catch_warnings():
        warnings.simplefilter("error")                 # the command says it in a line, not as a warning
        assert main(["export", str(cut), "--format", "csv", "--out", str(tmp_path / "t")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "flocktrack recover" in err[0] and f"{run.lost_ticks} of the scenario's" in err[0]
    assert len(pd.read_csv(tmp_path / "t" / "ticks.csv")) == len(run.ticks)
