"""The launcher forks its Python children from a pre-imported template (flocktrack/launch/forkserver.py): the same
run, lockstep, gives the same numbers bit for bit whether every process is forked from the template or is
a fresh interpreter (``FLOCKTRACK_FORKSERVER=0``), a forked child's exit code and output reach the
launcher as a fresh one's do, and the forked flock is up sooner."""

import json
import os
import subprocess
import sys
from pathlib import Path

from flocktrack.launch.forkserver import ForkedProcess, forkable
from processes import descendants

ROOT = Path(__file__).resolve().parents[2]


def _run(out: Path, forked: bool) -> dict:
    env = dict(os.environ, FLOCKTRACK_FORKSERVER="1" if forked else "0")
    r = subprocess.run([sys.executable, "-m", "flocktrack", "run", str(ROOT / "scenarios" / "demo.toml"), "--ticks",
                        "40", "--mode", "lockstep", "--quiet", "--out", str(out)], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads((out / "events.json").read_text())


def test_forked_and_fresh_children_give_the_same_run(tmp_path):
    ev_f = _run(tmp_path / "forked", True)
    ev_p = _run(tmp_path / "fresh", False)
    spawned_f = {e["name"]: e["forked"] for e in ev_f if e["event"] == "spawn"}
    spawned_p = {e["name"]: e["forked"] for e in ev_p if e["event"] == "spawn"}
    assert len(spawned_f) == 15 and all(spawned_f.values()), spawned_f     # 12 sensors, target, world, recorder
    assert not any(spawned_p.values()), spawned_p
    for name in ("summary.json", "metrics.csv"):
        assert (tmp_path / "forked" / name).read_bytes() == (tmp_path / "fresh" / name).read_bytes(), name
    exits = json.loads((tmp_path / "forked" / "run.json").read_text())["exits"]
    assert all(v == [0] for v in exits.values()), exits


def test_a_forked_child_reports_its_exit_code_output_and_signal(tmp_path):
    argv = [sys.executable, "-m", "agent", "sensor", "--id", "99", "--scenario", str(ROOT / "scenarios" / "demo.toml")]
    assert forkable(argv)
    p = ForkedProcess(argv, dict(os.environ), str(ROOT))
    out = p.stdout.read().decode()
    assert p.wait(30) == 2 and "--id 99 is not a sensor" in out      # main()'s own exit code and message
    p = ForkedProcess([sys.executable, "-m", "json.tool", "--no-such-flag"], dict(os.environ), str(ROOT))
    assert p.wait(30) == 2 and "usage" in p.stdout.read().decode()    # argparse's SystemExit(2)
    p = ForkedProcess([sys.executable, "-m", "http.server", "0", "--bind", "127.0.0.1"], dict(os.environ), str(tmp_path))
    assert p.poll() is None
    p.kill()
    assert p.wait(10) == -9 and p.returncode == -9


def _alive(pid: int) -> bool:
    try:
        return "zombie" not in (Path(f"/proc/{pid}/status").read_text().lower())
    except OSError:
        return False


def test_kill_9_of_the_launcher_takes_the_template_and_every_forked_child_with_it(tmp_path):
    import signal
    import time

    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "flocktrack", "run", str(ROOT / "scenarios" / "demo.toml"),
                             "--ticks", "100000", "--mode", "lockstep", "--quiet", "--out", str(out)], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not (out / "recording.mcap").is_file():
            time.sleep(0.2)
        time.sleep(2.0)                       # the flock is up and ticking
        below = descendants(proc.pid)
        assert len(below) >= 16, below        # the template and its 15 children (12 sensors, target, world, recorder)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline and any(_alive(p) for p in below):
        time.sleep(0.2)
    assert not [p for p in below if _alive(p)]
