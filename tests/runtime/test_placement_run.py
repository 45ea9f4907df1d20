"""A placed flock on one machine's loopback — two "hosts" that are two ports of 127.0.0.1, each started with the
user's command `flocktrack run SCENARIO --placement hosts.toml --host NAME`: their merge is the one-host run, and
a host that never comes up is named while the run waits for it, then the run gives up with an exit code."""

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from agent.scenario import parse_scenario, scenario_data
from flocktrack.engine.run import run_inproc_to_dir
from flocktrack.launch.launcher import free_port

ROOT = Path(__file__).resolve().parents[2]


def _placement(path: Path) -> Path:
    path.write_text(f"""run = "loop-{path.parent.name[-8:]}"
[hosts.a]
address = "127.0.0.1"
port = {free_port()}
listen = "127.0.0.1"
[hosts.b]
address = "127.0.0.1"
port = {free_port()}
listen = "127.0.0.1"
[place]
"agent/0-4" = "a"
"agent/5-9" = "b"
"*" = "a"
""")
    return path


def _run(host: str, placement: Path, out: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "flocktrack", "run", "gu_hu_normal", "--placement", str(placement),
                             "--host", host, "--out", str(out / host), "--mode", "lockstep", "--quiet", *args],
                            cwd=out, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def test_two_hosts_on_loopback_merge_into_the_one_host_run(tmp_path):
    placement = _placement(tmp_path / "hosts.toml")
    procs = {h: _run(h, placement, tmp_path, "--ticks", "40") for h in ("a", "b")}
    outs = {h: p.communicate(timeout=300)[0] for h, p in procs.items()}
    assert all(p.returncode == 0 for p in procs.values()), outs
    assert "its shard of the run" in outs["b"] and "flocktrack merge" in outs["b"]
    merged = subprocess.run([sys.executable, "-m", "flocktrack", "merge", str(tmp_path / "a"), str(tmp_path / "b"),
                             "--out", str(tmp_path / "m")], capture_output=True, text=True, timeout=300)
    assert merged.returncode == 0, merged.stderr
    data = scenario_data(str(ROOT / "scenarios" / "gu_hu_normal.toml"), [], **{"run.ticks": 40, "run.mode": "lockstep"})
    run_inproc_to_dir(parse_scenario(data, "gu_hu_normal.toml"), data, tmp_path / "in")
    assert json.loads((tmp_path / "m" / "summary.json").read_text()) == \
        json.loads((tmp_path / "in" / "summary.json").read_text())
    assert (tmp_path / "m" / "metrics.csv").read_bytes() == (tmp_path / "in" / "metrics.csv").read_bytes()
    info = json.loads((tmp_path / "m" / "run.json").read_text())
    assert info["run"].startswith("loop-") and len(info["shards"]) == 2
    # merging shards of different runs is refused, naming the one that differs
    other = subprocess.run([sys.executable, "-m", "flocktrack", "merge", str(tmp_path / "a"), str(tmp_path / "in"),
                            "--out", str(tmp_path / "x")], capture_output=True, text=True, timeout=300)
    assert other.returncode == 2 and "error:" in other.stderr and "Traceback" not in other.stderr


def test_a_host_that_never_comes_up_is_named_and_the_run_gives_up(tmp_path):
    placement = _placement(tmp_path / "hosts.toml")
    (tmp_path / "other").mkdir()
    other = _placement(tmp_path / "other" / "hosts.toml")   # a second run, on ports of its own: its host b alone
    t0 = time.monotonic()
    p = _run("a", placement, tmp_path, "--ticks", "20", "--startup-timeout", "12")
    q = _run("b", other, tmp_path / "other", "--ticks", "20", "--startup-timeout", "12")
    out, out_b = p.communicate(timeout=120)[0], q.communicate(timeout=120)[0]
    assert p.returncode != 0 and q.returncode != 0 and time.monotonic() - t0 < 60, (out, out_b)
    assert "waiting 5 s for host b: launcher/b, recorder/b, agent/5" in out, out
    assert "did not start within 12 s; still waiting for host b:" in out and "launcher/b" in out, out
    # and whether the network is to blame: neither router has a link to the other's (b dials a)
    assert "; router links: b down (b dials this router)" in out, out
    a_port = next(line.split("=")[1].strip() for line in other.read_text().splitlines() if line.startswith("port"))
    assert "waiting 5 s for host a: " in out_b, out_b
    assert f"; router links: a down (dialling tcp/127.0.0.1:{a_port})" in out_b, out_b
    assert "Traceback" not in out + out_b


def test_a_bad_placement_or_host_is_one_line(tmp_path):
    placement = _placement(tmp_path / "hosts.toml")
    p = _run("z", placement, tmp_path)
    out = p.communicate(timeout=120)[0]
    assert p.returncode == 2 and "--host z: not a host of" in out and "a, b" in out and "Traceback" not in out
    (tmp_path / "bad.toml").write_text(placement.read_text().replace('"agent/5-9"', '"agent/5-12"'))
    p = _run("a", tmp_path / "bad.toml", tmp_path)
    out = p.communicate(timeout=120)[0]
    assert p.returncode == 2 and "[place.'agent/5-12'] names agent/10–12" in out and "Traceback" not in out


@pytest.mark.slow
def test_two_hosts_on_loopback_in_realtime_track_together(tmp_path):
    """Realtime: the run starts when both hosts' members are live, and the merged recording has every tick of
    the world and the estimates of both hosts' sensors."""
    from flocktrack.record.reader import read_recording

    placement = _placement(tmp_path / "hosts.toml")
    procs = {h: subprocess.Popen([sys.executable, "-m", "flocktrack", "run", "gu_hu_normal", "--placement",
                                  str(placement), "--host", h, "--out", str(tmp_path / h), "--mode", "realtime",
                                  "--ticks", "60", "--set", "run.speed=0.5", "--quiet"], cwd=tmp_path, stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, text=True) for h in ("b", "a")}
    outs = {h: p.communicate(timeout=300)[0] for h, p in procs.items()}
    assert all(p.returncode == 0 for p in procs.values()), outs
    merged = subprocess.run([sys.executable, "-m", "flocktrack", "merge", str(tmp_path / "a"), str(tmp_path / "b"),
                             "--out", str(tmp_path / "m")], capture_output=True, text=True, timeout=300)
    assert merged.returncode == 0, merged.stderr
    rec = read_recording(tmp_path / "m" / "recording.mcap")
    ticks = sorted(m.k for k, m, _ in rec.messages if k == "world/tick")
    assert rec.complete and ticks == list(range(60))
    est = {(m.src, m.k) for k, m, _ in rec.messages if k.startswith("agent/") and k.endswith("/estimate")}
    for i in range(10):   # every sensor of both hosts tracked through the run (realtime: a late round is lost)
        mine = [k for k in range(60) if (i, k) in est]
        assert len(mine) >= 30 and mine[-1] >= 55, (i, mine)
