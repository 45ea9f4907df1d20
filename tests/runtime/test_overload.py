"""A realtime run the machine cannot keep degrades and recovers, it does not collapse: the README's main job
with half its sensors (6; at 12 the main job at full speed is at the edge of the 2-core VMs it is tested on, and
in their slow phases past it — its clock stretched now and then without a burst, and kept stretched to the end
in one run beside another suite) over Zenoh, starved for 2 s in the middle: confined to one core that CPU
burners share with it. With ``run.pace = "adaptive"`` the world stretches its clock while the flock cannot keep
it (topology/pace.py) and is back at the nominal pace once the load is gone (the ticks' own periods say so);
every round a sensor missed is counted, the estimates after the burst are as good as before it, and the
recording lost nothing. Counts and errors are checked, not timing."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from agent.bus import ZenohBus
from agent.scenario import parse_scenario, scenario_data
from flocktrack.engine.run import run_zenoh_to_dir
from flocktrack.record.reader import read_recording
from processes import descendants

ROOT = Path(__file__).resolve().parents[2]
BURN = "import time\nend = time.monotonic() + {s}\nwhile time.monotonic() < end:\n    pass\n"


def confine(pids: set[int], cpus: set[int]) -> None:
    """Every thread of ``pids`` (Zenoh's runtime threads too) allowed on ``cpus`` only."""
    for pid in pids:
        try:
            tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
        except OSError:
            continue                # gone meanwhile
        for tid in tids:
            try:
                os.sched_setaffinity(tid, cpus)
            except OSError:
                pass                # a thread that ended meanwhile


def run_processes() -> set[int]:
    """This test's process (the launcher and its router) and every process below it."""
    return {os.getpid(), *descendants(os.getpid())}


class StarveAt:
    """on_poll hook: when the world's tick k comes, the run (this process, the router, every role) is confined
    to one core and ``2 × cores`` busy processes burn that core for ``seconds``; then the run has its cores
    back. (Burners beside a flock that fits in the machine were not enough: the scheduler serves a process
    that wakes from a short sleep before a burner, and in 2 of 3 runs the 6-sensor flock never missed a
    state.)"""

    def __init__(self, k: int, seconds: float):
        self.k, self.seconds, self.bus, self.seen = k, seconds, None, -1
        self.started_at: int | None = None
        self.burners: list[subprocess.Popen] = []
        self.cores = os.sched_getaffinity(0)
        self.ends: float | None = None

    def __call__(self, launcher) -> None:
        if self.bus is None:
            self.bus = ZenohBus(launcher.run, connect=launcher.endpoint)
            self.bus.subscribe("world/tick", lambda key, m: setattr(self, "seen", max(self.seen, m.k)))
        self.bus.poll(0)
        if self.started_at is None and self.seen >= self.k:
            self.started_at = self.seen
            one = {min(self.cores)}
            confine(run_processes(), one)
            code = f"import os\nos.sched_setaffinity(0, {one!r})\n" + BURN.format(s=self.seconds)
            self.burners = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(2 * len(self.cores))]
            self.ends = time.monotonic() + self.seconds
        if self.ends is not None and time.monotonic() >= self.ends:
            self.release()

    def release(self) -> None:
        if self.ends is not None:
            confine(run_processes(), self.cores)
            self.ends = None

    def close(self) -> None:
        self.release()
        for p in self.burners:
            p.wait(30)
        if self.bus is not None:
            self.bus.close()


@pytest.mark.slow
def test_a_starved_realtime_run_slows_its_clock_counts_its_misses_and_recovers(tmp_path):
    ticks, k_burst = 300, 80
    data = scenario_data(str(ROOT / "scenarios" / "demo.toml"), [],
                         **{"run.ticks": ticks, "run.mode": "realtime", "run.pace": "adaptive", "sensors.n": 6})
    sc = parse_scenario(data, "demo.toml")
    hook = StarveAt(k_burst, 2.0)
    try:
        _summary, info = run_zenoh_to_dir(sc, data, tmp_path, quiet=True, on_poll=hook, timeout_s=600)
    finally:
        hook.close()
    assert info["rc"] == 0, info
    assert hook.started_at is not None
    stats = {p.stem: json.loads(p.read_text()) for p in (tmp_path / "stats").glob("*.json")}
    world = stats["world-0"]["role"]
    rec = read_recording(tmp_path / "recording.mcap")
    # the clock yielded while the machine was starved, and came back after it: judged from the ticks' own
    # periods, not from how many were stretched (measured there without a burst: 6 sensors 0 stretched ticks,
    # 12 sensors 14; with it, 6 sensors: 1.6–2.0 × the period at most, 16–28 ticks above 1.2 ×, back at nominal
    # within 2 s)
    nominal = sc.run.T / sc.run.speed
    period = {m.k: m.period for key, m, _ in rec.messages if key == "world/tick"}
    per_s = int(round(sc.run.speed / sc.run.T))
    burst = [period[k] for k in range(hook.started_at, hook.started_at + 3 * per_s) if k in period]
    end = [period[k] for k in range(ticks - ticks // 5, ticks) if k in period]
    assert max(burst) > 1.2 * nominal, (nominal, burst)
    assert np.median(end) < 1.01 * nominal, (nominal, end)
    assert info["pace"] == {"stretched_ticks": world["pace_stretched_ticks"], "max_stretch": world["pace_max_stretch"]}
    # every round a sensor closed by its deadline is in its counters, its log and its tick rows, and in the
    # launcher's count (which has the target's waits too)
    counted = 0
    for i in range(sc.sensors.n):
        n = stats[f"agent-{i}"]["role"].get("deadline_rounds", 0)
        log = (tmp_path / "logs" / f"agent-{i}.log").read_text(errors="replace")
        rows = list(csv.DictReader(open(tmp_path / "stats" / f"agent-{i}-ticks.csv")))
        assert log.count("deadline on") == n and sum(int(r["deadline_rounds"]) for r in rows) <= n, i
        counted += n
    assert counted <= info["missed_deadlines"]
    # the recording lost nothing: every message a process sent on a recorded key is in it
    assert rec.complete and info["unrecorded_messages"] == {}, info["unrecorded_messages"]
    assert len(rec.messages) > 20 * ticks
    # recovery: the network's error after the burst (from 1 s of ticks after it) as before it, every sensor
    # estimating again
    err = {int(r["k"]): float(r["rmse"]) for r in csv.DictReader(open(tmp_path / "metrics.csv"))}
    after = hook.started_at + 3 * per_s
    before = [err[k] for k in range(sc.run.burn_in, k_burst) if k in err]
    late = [err[k] for k in range(after, ticks) if k in err]
    assert len(late) > ticks // 3
    assert np.median(late) < 3 * max(np.median(before), 0.02), (np.median(before), np.median(late))
    est = Counter(m.src for key, m, _ in rec.messages if key.endswith("/estimate") and m.k >= after)
    assert all(est[i] >= 0.9 * (ticks - after) for i in range(sc.sensors.n)), est
