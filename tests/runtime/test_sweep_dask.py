"""flocktrack sweep on Dask: the same rows as the local pool (in-process and over Zenoh), runs that come back
as data with their recordings left on the worker (or shipped back), resume, a worker killed mid-run, a run
that raises, and the bad starts (no scheduler, a worker with another flocktrack, no distributed)."""

from __future__ import annotations

import csv
import importlib.metadata
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import dask
import distributed
import pytest

import flocktrack
from agent.scenario import scenario_data
from flocktrack import extras
from flocktrack.experiment import dask_executor as dx
from flocktrack.experiment import sweep as sw

ROOT = Path(__file__).resolve().parents[2]
NORMAL = str(ROOT / "scenarios" / "gu_hu_normal.toml")
GRID = [NORMAL, "--grid", "faults.link_loss=0,0.2", "--no-figures", "--quiet"]
#: what a run directory of the in-process engine holds
INPROC_FILES = {"summary.json", "metrics.csv", "scenario.toml", "design.json", "meta.json", "run.json"}


@pytest.fixture(scope="module")
def scheduler():
    """One cluster for the module: 2 single-threaded worker processes that a run may kill twice."""
    with dask.config.set({**dx.WORKER_CONFIG, "distributed.scheduler.allowed-failures": 2}):
        cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


def _rows(out: Path) -> list[dict]:
    with (out / "results.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def _meta(out: Path) -> dict:
    return json.loads((out / "sweep.json").read_text())


def _runs(out: Path) -> list[str]:
    return sorted(p.name for p in (out / "runs").iterdir())


def test_local_and_dask_give_the_same_rows_inproc(tmp_path, capsys):
    args = [*GRID, "--seeds", "2", "--ticks", "40", "--jobs", "2"]
    assert sw.main([*args, "--out", str(tmp_path / "local")]) == 0
    # no --scheduler: the sweep starts its own LocalCluster of --jobs workers
    assert sw.main([*args, "--out", str(tmp_path / "dask"), "--executor", "dask"]) == 0
    local, dk = tmp_path / "local", tmp_path / "dask"
    assert _rows(dk) == _rows(local) and len({r["run_id"] for r in _rows(dk)}) == 4
    assert _runs(dk) == _runs(local)   # no .tmp left behind
    for rid in _runs(dk):
        assert {p.name for p in (dk / "runs" / rid).iterdir()} == INPROC_FILES
        assert (dk / "runs" / rid / "summary.json").read_text() == (local / "runs" / rid / "summary.json").read_text()
    meta = _meta(dk)
    assert meta["executor"]["kind"] == "dask" and meta["executor"]["workers"] == 2
    assert meta["ok"] == 4 and meta["executed"] == 4 and set(meta["hosts"]) == set(_runs(dk))
    assert meta["recordings"] == {} and _meta(local)["executor"] == {"kind": "local", "jobs": 2}


@pytest.mark.slow
def test_local_and_dask_give_the_same_rows_over_zenoh(tmp_path, scheduler):
    args = [*GRID, "--seeds", "1", "--ticks", "30", "--jobs", "2", "--transport", "zenoh"]
    wd = tmp_path / "worker"
    assert sw.main([*args, "--out", str(tmp_path / "local")]) == 0
    assert sw.main([*args, "--out", str(tmp_path / "dask"), "--executor", "dask", "--scheduler", scheduler,
                    "--worker-dir", str(wd)]) == 0
    local, dk = tmp_path / "local", tmp_path / "dask"
    assert _rows(dk) == _rows(local) and len(_rows(dk)) > 0
    meta = _meta(dk)
    assert meta["transport"] == "zenoh" and meta["ok"] == 2
    for rid in _runs(dk):
        assert json.loads((local / "runs" / rid / "run.json").read_text())["transport"] == "zenoh"
        assert (local / "runs" / rid / "recording.mcap").exists()       # the local pool writes in place
        # the Dask run came back without its recording: that stays on the worker, named in recording.json
        assert not (dk / "runs" / rid / "recording.mcap").exists()
        where = json.loads((dk / "runs" / rid / "recording.json").read_text())
        assert where == meta["recordings"][rid]
        assert where["host"] == socket.gethostname() and Path(where["path"]) == wd / "dask" / rid / "recording.mcap"
        assert Path(where["path"]).stat().st_size == where["bytes"] > 0
        assert (dk / "runs" / rid / "logs").is_dir()    # the run's small files all came back
    assert sorted(p.name for p in (wd / "dask").iterdir()) == _runs(dk)   # no attempt's .tmp left


@pytest.mark.slow
def test_fetch_recordings_ships_them_back(tmp_path, scheduler):
    wd = tmp_path / "worker"
    rc = sw.main([NORMAL, "--grid", "faults.link_loss=0", "--seeds", "1", "--ticks", "20", "--transport", "zenoh",
                  "--no-figures", "--quiet", "--executor", "dask", "--scheduler", scheduler, "--worker-dir", str(wd),
                  "--fetch-recordings", "--out", str(tmp_path / "o")])
    assert rc == 0
    run = tmp_path / "o" / "runs" / "link_loss-0_seed-0"
    assert (run / "recording.mcap").stat().st_size > 0 and not (run / "recording.json").exists()
    assert _meta(tmp_path / "o")["recordings"] == {}
    assert not wd.exists() or not any((wd / "o").iterdir())


def test_resume_after_a_lost_run_computes_only_that_one(tmp_path, scheduler):
    args = [*GRID, "--seeds", "2", "--ticks", "30", "--executor", "dask", "--scheduler", scheduler,
            "--out", str(tmp_path)]
    assert sw.main(args) == 0
    before = (tmp_path / "results.csv").read_text()
    shutil.rmtree(tmp_path / "runs" / "link_loss-0.2_seed-1")
    assert sw.main(args) == 0
    meta = _meta(tmp_path)
    assert (meta["executed"], meta["resumed"], meta["ok"]) == (1, 3, 4)
    assert set(meta["hosts"]) == {"link_loss-0.2_seed-1"}     # the only run that went to a worker
    assert (tmp_path / "results.csv").read_text() == before


def _kill_a_busy_worker(address: str, stop: threading.Event, killed: list) -> None:
    """SIGKILL the first worker seen holding a sweep run (still holding it a moment later: under way)."""
    with distributed.Client(address, set_as_default=False) as c:
        deadline = time.monotonic() + 120
        while not stop.is_set() and time.monotonic() < deadline:
            busy = sorted(w for w, keys in c.processing().items() if any("flocktrack-run-" in str(k) for k in keys))
            if busy:
                time.sleep(0.3)
                w = busy[0]
                if any("flocktrack-run-" in str(k) for k in c.processing().get(w, ())):
                    pid = c.run(os.getpid, workers=[w])[w]
                    os.kill(pid, signal.SIGKILL)
                    killed.append((w, pid))
                    return
            time.sleep(0.05)


@pytest.mark.slow
def test_a_worker_killed_mid_run_loses_no_run_and_duplicates_none(tmp_path, scheduler, monkeypatch):
    written: Counter = Counter()
    install = dx.install_run

    def counting(final, files):
        written[Path(final).name] += 1
        install(final, files)

    monkeypatch.setattr(dx, "install_run", counting)
    stop, killed = threading.Event(), []
    killer = threading.Thread(target=_kill_a_busy_worker, args=(scheduler, stop, killed), daemon=True)
    killer.start()
    try:
        rc = sw.main([*GRID, "--seeds", "1", "--ticks", "400", "--executor", "dask", "--scheduler", scheduler,
                      "--retries", "2", "--out", str(tmp_path)])
    finally:
        stop.set()
        killer.join(timeout=30)
    assert killed, "no worker was seen running a run"
    assert rc == 0
    meta = _meta(tmp_path)
    assert (meta["ok"], meta["failed"]) == (2, 0)
    assert written == Counter({"link_loss-0_seed-0": 1, "link_loss-0.2_seed-0": 1})
    assert _runs(tmp_path) == ["link_loss-0.2_seed-0", "link_loss-0_seed-0"]
    pairs = [(r["run_id"], r["metric"]) for r in _rows(tmp_path)]
    assert len(pairs) == len(set(pairs)) and {r for r, _ in pairs} == set(written)


def test_a_run_that_raises_is_retried_then_reported_and_the_others_go_on(tmp_path, scheduler):
    good = scenario_data(NORMAL, [], **{"run.ticks": 20})
    tasks = [{"run_id": "bad", "dir": str(tmp_path / "runs" / "bad"), "data": {"run": {}}, "source": "s.toml"},
             {"run_id": "good", "dir": str(tmp_path / "runs" / "good"), "data": good, "source": NORMAL}]
    (tmp_path / "runs").mkdir()
    ex = dx.DaskExecutor(scheduler=scheduler, jobs=2, sweep="raises", retries=1, worker_dir=str(tmp_path / "w"))
    results: dict = {}
    try:
        ex.run(tasks, lambda res: results.__setitem__(res["run_id"], res))
    finally:
        ex.close()
    assert results["good"]["status"] == "ok" and (tmp_path / "runs" / "good" / "summary.json").exists()
    bad = results["bad"]
    assert bad["status"] == "failed" and "table is required" in bad["error"] and "(2 tries)" in bad["error"]
    assert "Traceback" in bad["traceback"] and "parse_scenario" in bad["traceback"]
    assert not (tmp_path / "runs" / "bad").exists()


def test_an_unreachable_scheduler_is_one_line(tmp_path):
    with socket.socket() as s:        # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.run([sys.executable, "-m", "flocktrack", "sweep", *GRID, "--seeds", "1", "--ticks", "10",
                           "--executor", "dask", "--scheduler", f"tcp://127.0.0.1:{port}", "--scheduler-timeout", "2",
                           "--out", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and f"tcp://127.0.0.1:{port}" in lines[0] and "within 2 s" in lines[0], proc.stderr
    assert not (tmp_path / "results.csv").exists()


def test_a_worker_with_another_flocktrack_stops_the_sweep(tmp_path, scheduler, monkeypatch, capsys):
    monkeypatch.setattr(flocktrack, "__version__", "0.0.0+other")   # this client, as if another release
    rc = sw.main([*GRID, "--seeds", "1", "--ticks", "10", "--executor", "dask", "--scheduler", scheduler,
                  "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    assert "runs flocktrack" in err[0] and "this client 0.0.0+other" in err[0] and "tcp://" in err[0]
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


def test_version_problems_name_each_worker_that_differs():
    mine = importlib.metadata.version("flocktrack")
    bad = dx.version_problems(mine, {"tcp://a:1": mine, "tcp://b:2": "9.9.9",
                                     "tcp://c:3": importlib.metadata.PackageNotFoundError("flocktrack")})
    assert bad == [f"worker tcp://b:2 runs flocktrack 9.9.9, this client {mine}",
                   f"worker tcp://c:3 has no flocktrack installed (this client runs {mine})"]
    assert dx.version_problems(mine, {"tcp://a:1": mine}) == []


def test_without_distributed_the_dask_executor_names_the_extra(tmp_path, monkeypatch, capsys):
    real = extras.has
    monkeypatch.setattr(extras, "has", lambda m: False if m == "distributed" else real(m))
    rc = sw.main([*GRID, "--seeds", "1", "--executor", "dask", "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "pip install 'flocktrack[dask]'" in err[0]
    exc = ModuleNotFoundError("No module named 'distributed'", name="distributed")
    assert "flocktrack[dask]" in extras.missing_extra(exc)
