"""The process-per-agent runtime over a real Zenoh router on loopback, with real OS processes."""

import csv
import json
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from agent import wire
from agent.bus import ZenohBus
from agent.scenario import scenario_data
from flocktrack.cli import main
from flocktrack.record.reader import read_recording
from flocktrack.engine.run import run_zenoh_to_dir

ROOT = Path(__file__).resolve().parents[2]
SCEN = ROOT / "scenarios"


def _flat(d, prefix=""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _flat(v, prefix + k + ".")
        elif isinstance(v, list):
            for i, x in enumerate(v):
                yield f"{prefix}{k}[{i}]", x
        else:
            yield prefix + k, v


def assert_same_summary(a: dict, b: dict, tol=1e-12):
    fa, fb = dict(_flat(a)), dict(_flat(b))
    assert fa.keys() == fb.keys()
    for k in fa:
        x, y = fa[k], fb[k]
        if isinstance(x, float) and isinstance(y, float):
            assert abs(x - y) <= tol * max(1.0, abs(x)), (k, x, y)
        else:
            assert x == y, (k, x, y)


@pytest.mark.parametrize("name,ticks", [("chen_switching.toml", 300), ("gu_hu_normal.toml", 100),
                                        ("gu_hu_intelligent.toml", 100)])
def test_zenoh_lockstep_equals_inproc_and_recording_is_faithful(tmp_path, name, ticks):
    scen = str(SCEN / name)
    args = ["--ticks", str(ticks), "--mode", "lockstep"]
    assert main(["run", scen, "--transport", "inproc", *args, "--out", str(tmp_path / "in")]) == 0
    assert main(["run", scen, "--transport", "zenoh", "--quiet", *args, "--out", str(tmp_path / "z")]) == 0
    a = json.loads((tmp_path / "in" / "summary.json").read_text())
    b = json.loads((tmp_path / "z" / "summary.json").read_text())
    assert_same_summary(a, b)
    assert (tmp_path / "in" / "metrics.csv").read_bytes() == (tmp_path / "z" / "metrics.csv").read_bytes()

    # every published message is in the recording: counted per key ...
    sent: Counter = Counter()
    for f in (tmp_path / "z" / "stats").glob("*.json"):
        sent.update(json.loads(f.read_text()).get("sent_by_key", {}))
    recorded = json.loads((tmp_path / "z" / "stats" / "recorder-0.json").read_text())["recorded_by_key"]
    # ... once: the addressed copies of the exchange payloads (one per neighbour) are not recorded
    addressed = Counter({k: v for k, v in sent.items() if wire.addressed(k)})
    assert dict(sent - addressed) == recorded and sum(sent.values()) > 0
    n = b["n_sensors"]
    rounds = {}
    for i in range(n):     # where each sensor's ticks went: a row per tick in its stats
        with (tmp_path / "z" / "stats" / f"agent-{i}-ticks.csv").open() as f:
            rows = list(csv.DictReader(f))
        rounds[i] = sum(int(r["rounds"]) for r in rows)
        assert [int(r["k"]) for r in rows] == list(range(ticks)), i
        assert all(int(r["deadline_rounds"]) == 0 and int(r["rounds"]) >= 1 for r in rows)   # lockstep
        t = {c: np.array([float(r[c]) for r in rows]) for c in ("compute_ms", "publish_ms", "wait_ms", "total_ms")}
        assert t["compute_ms"].sum() > 0 and t["publish_ms"].sum() > 0 and min(v.min() for v in t.values()) >= 0
        assert np.all(t["total_ms"] + 1e-3 >= t["compute_ms"] + t["publish_ms"] + t["wait_ms"])
    for i in range(n):     # each payload went to this tick's neighbours only, never to everyone; the observers
        to_nbrs = sum(v for k, v in addressed.items() if k.startswith(f"agent/{i}/to/"))   # got each tick once
        assert sent[f"agent/{i}/xchg"] == ticks, (i, sent[f"agent/{i}/xchg"])
        assert 0 < to_nbrs < (n - 1) * rounds[i], (i, to_nbrs, rounds[i])
    # ... and in publication order per key
    rec = read_recording(tmp_path / "z" / "recording.mcap")
    assert rec.complete and len(rec.messages) == sum(recorded.values())
    last: dict[str, tuple] = {}
    for key, msg, _t in rec.messages:
        stamp = (msg.k, getattr(msg, "r", 0))
        assert key not in last or stamp > last[key], (key, last[key], stamp)
        last[key] = stamp
    # and `flocktrack metrics` on the recording reproduces the live summary
    assert main(["metrics", str(tmp_path / "z" / "recording.mcap"), "--out", str(tmp_path / "m")]) == 0
    assert_same_summary(json.loads((tmp_path / "m" / "summary.json").read_text()), b)


def test_inproc_recording_rescored_equals_live(tmp_path):
    assert main(["run", str(SCEN / "chen_switching.toml"), "--transport", "inproc", "--record", "--ticks", "80",
                 "--out", str(tmp_path / "in")]) == 0
    assert main(["metrics", str(tmp_path / "in" / "recording.mcap"), "--out", str(tmp_path / "m")]) == 0
    assert_same_summary(json.loads((tmp_path / "in" / "summary.json").read_text()),
                        json.loads((tmp_path / "m" / "summary.json").read_text()))


class KillAt:
    """on_poll hook: watch world/tick through our own Zenoh client; SIGKILL a child at tick k."""

    def __init__(self, run_prefix: str, victim: str, k: int):
        self.victim, self.k, self.bus, self.seen, self.killed_at = victim, k, None, -1, None
        self.run_prefix = run_prefix

    def __call__(self, launcher):
        if self.bus is None:
            self.bus = ZenohBus(launcher.run, connect=launcher.endpoint)
            self.bus.subscribe("world/tick", lambda key, m: setattr(self, "seen", max(self.seen, m.k)))
        self.bus.poll(0)
        if self.killed_at is None and self.seen >= self.k and launcher.alive(self.victim):
            launcher.kill(self.victim, signal.SIGKILL)
            self.killed_at = self.seen

    def close(self):
        if self.bus is not None:
            self.bus.close()


def _crash_run(tmp_path, scen: str, ticks: int, mode: str, victim: int, k_kill: int):
    data = scenario_data(str(SCEN / scen), [], **{"run.ticks": ticks, "run.mode": mode})
    from agent.scenario import parse_scenario

    sc = parse_scenario(data, scen)
    hook = KillAt("", f"agent/{victim}", k_kill)
    try:
        summary, info = run_zenoh_to_dir(sc, data, tmp_path, restart="on-failure", max_restarts=2, quiet=True,
                                         on_poll=hook, timeout_s=300)
    finally:
        hook.close()
    return sc, summary, info, hook


@pytest.mark.slow
@pytest.mark.parametrize("mode,scen,ticks", [("lockstep", "gu_hu_normal.toml", 220),
                                             ("realtime", "chen_switching.toml", 150)])
def test_kill_9_a_sensor_mid_run_restart_and_rejoin(tmp_path, mode, scen, ticks):
    victim = 2
    sc, summary, info, hook = _crash_run(tmp_path, scen, ticks, mode, victim, k_kill=40)
    assert info["rc"] == 0, info
    assert hook.killed_at is not None
    assert info["restarts"] == {f"agent/{victim}": 1}
    assert info["exits"][f"agent/{victim}"][0] == -signal.SIGKILL
    rec = read_recording(tmp_path / "recording.mcap")
    assert rec.complete
    est: dict[int, set[int]] = {i: set() for i in range(sc.sensors.n)}
    alive_flag: dict[int, bool] = {}
    for key, msg, _ in rec.messages:
        if key.endswith("/estimate") and key.startswith("agent/"):
            est[msg.src].add(msg.k)
        elif key == "world/tick":
            alive_flag[msg.k] = msg.alive[victim]
    missing = sorted(set(range(ticks)) - est[victim])
    # realtime on a loaded machine: a sensor behind the clock coasts through a few ticks (≤ 5 % of them)
    slack = ticks // 20 if mode == "realtime" else 0
    early = [k for k in missing if k < hook.killed_at]
    assert len(early) <= slack, (early, hook.killed_at)
    assert missing and missing[-1] >= hook.killed_at, (missing[:5], hook.killed_at)  # a gap after the kill ...
    assert max(est[victim]) == ticks - 1                                            # ... and it rejoined
    assert any(not a for a in alive_flag.values()) and alive_flag[ticks - 1]        # the world saw it leave and return
    for i in range(sc.sensors.n):                                                   # the others kept estimating
        if i != victim:
            n_missing = len(set(range(ticks)) - est[i])
            assert n_missing <= slack, (i, n_missing)
    # the rejoined node re-initialised from its neighbours: its error is small right after rejoining
    rows = {int(r["k"]): r for r in __import__("csv").DictReader(open(tmp_path / "metrics.csv"))}
    back = min(k for k in est[victim] if k > missing[-1])
    errs = [float(rows[k][f"err_{victim}"]) for k in range(back, min(back + 20, ticks))]
    others = [float(rows[k]["rmse"]) for k in range(back, min(back + 20, ticks))]
    assert max(errs) < max(1.0, 5 * max(others)), (errs, others)
    # the crash and the rejoin are on the recording's timeline: the launcher's process events
    life = [(m.args["event"], m.args.get("rc"), m.args.get("rejoin")) for key, m, _ in rec.messages
            if key == "launcher/event" and m.verb == "process" and m.args.get("name") == f"agent/{victim}"]
    assert ("exit", -signal.SIGKILL, None) in life and ("spawn", None, True) in life, life


@pytest.mark.slow
def test_sigterm_to_launcher_leaves_no_process_and_a_complete_recording(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "flocktrack", "run", str(SCEN / "gu_hu_normal.toml"),
                             "--ticks", "100000", "--quiet", "--out", str(out)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    rec_file = out / "recording.mcap"
    t0 = time.time()
    while time.time() - t0 < 120:
        if rec_file.exists() and rec_file.stat().st_size > 200_000:
            break
        time.sleep(0.2)
    else:
        proc.kill()
        pytest.fail("the run never got going")
    events_pids = []
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=60)
    events = json.loads((out / "events.json").read_text())
    events_pids = [e["pid"] for e in events if e["event"] == "spawn"]
    assert len(events_pids) >= 13  # 10 sensors, target, world, recorder
    time.sleep(0.5)
    for pid in events_pids:
        assert not Path(f"/proc/{pid}").exists() or "zombie" in Path(f"/proc/{pid}/status").read_text().lower(), pid
    rec = read_recording(rec_file)
    assert rec.complete and len(rec.messages) > 100
    assert (out / "summary.json").exists()
    ticks = {m.k for key, m, _ in rec.messages if key == "world/tick"}
    assert ticks == set(range(max(ticks) + 1))  # no hole in what was recorded
