"""``flocktrack fault`` / ``ps`` / ``logs`` against two real runs (their launchers, embedded routers and
processes), as a user types them: a verb checked before it is sent, the run's answer reported with the
exit code (0 applied, 1 refused, 2 no answer), the runs found without copying names or endpoints."""

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from flocktrack.cli import main
from flocktrack.record.reader import read_recording

ROOT = Path(__file__).resolve().parents[2]


def _start(out: Path, env: dict) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "flocktrack", "run", "scenarios/chen_switching.toml", "--mode",
                             "realtime", "--ticks", "100000", "--quiet", "--out", str(out)],
                            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _ps(capsys) -> list[dict]:
    assert main(["ps", "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def _fault(capsys, *words) -> tuple[int, str]:
    rc = main(["fault", *words])
    cap = capsys.readouterr()
    return rc, cap.out + cap.err


@pytest.mark.slow
def test_fault_ps_and_logs_on_two_live_runs(tmp_path, monkeypatch, capsys):
    rt = tmp_path / "runtime"
    monkeypatch.setenv("FLOCKTRACK_RUNTIME_DIR", str(rt))
    env = dict(os.environ, FLOCKTRACK_RUNTIME_DIR=str(rt))
    procs = [_start(tmp_path / "a", env), _start(tmp_path / "b", env)]
    try:
        end = time.monotonic() + 120
        runs: list[dict] = []
        while time.monotonic() < end:   # both runs listed, each ticking with its three sensors
            runs = _ps(capsys)
            if len(runs) == 2 and all(r["tick"] is not None and r["sensors"] == "3/3" for r in runs):
                break
            time.sleep(1.0)
        assert len(runs) == 2, runs
        assert {Path(r["out"]).name for r in runs} == {"a", "b"}
        for r in runs:
            assert r["mode"] == "realtime" and r["tick"] >= 0 and r["sensors"] == "3/3", r
            assert {"world/0", "target/0", "recorder/0", "launcher/0"} <= set(r["members"]), r
        a = next(r for r in runs if Path(r["out"]).name == "a")

        # two runs are going: which one must be said
        rc, text = _fault(capsys, "pause")
        assert rc == 2 and "2 runs are going" in text, text
        on_a = ["--run", a["run"]]
        # checked here, nothing sent: an unknown verb (with a suggestion), a value out of range
        rc, text = _fault(capsys, "lnk_loss", "p=0.2", *on_a)
        assert rc == 2 and "did you mean 'link_loss'?" in text, text
        rc, text = _fault(capsys, "link_loss", "p=7", *on_a)
        assert rc == 1 and "p must be in [0, 1]" in text and "nothing sent" in text, text
        # refused by the run itself (the flock's size is the world's to check when --connect is given)
        rc, text = _fault(capsys, "partition", "groups=[0,1]", *on_a, "--connect", a["endpoint"])
        assert rc == 1 and "refused" in text and "each of the 3 sensors" in text, text
        # applied, at a tick; an injected fault healed by its id
        rc, text = _fault(capsys, "link_loss", "p=0.2", *on_a)
        assert rc == 0 and "applied: link_loss at tick" in text, text
        rc, text = _fault(capsys, "inject", "kind=delay", "targets=agents:2", "delay_ms=80", *on_a)
        assert rc == 0 and "fault id" in text, text
        fid = int(text.split("fault id ")[1].split()[0])
        rc, text = _fault(capsys, "heal_fault", f"id={fid}", *on_a)
        assert rc == 0 and "applied: heal_fault" in text, text
        rc, text = _fault(capsys, "heal_fault", f"id={fid + 50}", *on_a)
        assert rc == 1 and f"no live fault {fid + 50}" in text, text
        # the sensors' own verb: sent, with no acknowledgement to wait for (it is recorded below)
        rc, text = _fault(capsys, "outlier_burst", "agent=2", "ticks=2", *on_a)
        assert rc == 0 and "sent control/outlier_burst" in text and "the sensors apply it" in text, text
        assert "applied" not in text, text
        # the launcher's verbs: kill, then restart — both acknowledged, and the member is back
        rc, text = _fault(capsys, "kill", "agent=1", *on_a)
        assert rc == 0 and re.search(r"applied at tick \d+: agent/1 killed", text), text
        rc, text = _fault(capsys, "kill", "agent=1", *on_a)
        assert rc == 1 and "agent/1 is not running" in text, text
        rc, text = _fault(capsys, "restart", "agent=1", *on_a, "--timeout", "30")
        assert rc == 0 and "agent/1 restarted and back in the run" in text, text
        assert next(r for r in _ps(capsys) if r["run"] == a["run"])["sensors"] == "3/3"
        # nobody there: no answer
        rc, text = _fault(capsys, "pause", "--run", "no-such-run", "--connect", a["endpoint"], "--timeout", "1")
        assert rc == 2 and "nobody in run no-such-run" in text, text
        # the logs of one member, by run name
        assert main(["logs", a["run"], "agent/1"]) == 0
        assert "agent/1: member of the run" in capsys.readouterr().out
        assert main(["logs", a["run"], "agent/7"]) == 2
        assert "there are: agent/0, agent/1, agent/2" in capsys.readouterr().err
    finally:
        for p in procs:
            p.send_signal(signal.SIGINT)
        for p in procs:
            p.wait(120)
    assert not list(rt.glob("*.json")), "a launcher left its run file behind"
    # what was sent: only what was applied or refused by the run — nothing for what was refused here
    keys = {k for k, _m, _t in read_recording(tmp_path / "a" / "recording.mcap").messages if k.startswith("control/")}
    assert keys == {"control/partition", "control/link_loss", "control/inject", "control/heal_fault", "control/kill",
                    "control/restart", "control/outlier_burst"}, keys


@pytest.mark.slow
def test_ps_and_fault_find_a_run_through_connect_alone(tmp_path, monkeypatch, capsys):
    """With nothing local to go by (this process reads another, empty runtime directory), ``ps --connect EP``
    lists the run on that router — its name, tick, members and size from its ticks; its mode, which nothing
    on a router tells, ``?`` — and ``fault --connect EP`` without ``--run`` sends to the only run there."""
    rt = tmp_path / "runtime"
    monkeypatch.setenv("FLOCKTRACK_RUNTIME_DIR", str(tmp_path / "elsewhere"))
    proc = _start(tmp_path / "a", dict(os.environ, FLOCKTRACK_RUNTIME_DIR=str(rt)))
    try:
        end = time.monotonic() + 120
        while not list(rt.glob("*.json")) and time.monotonic() < end:
            time.sleep(0.5)
        entry = json.loads(next(rt.glob("*.json")).read_text())
        ep = entry["endpoint"]
        runs: list[dict] = []
        while time.monotonic() < end:
            assert main(["ps", "--connect", ep, "--json"]) == 0
            runs = json.loads(capsys.readouterr().out)
            if runs and runs[0]["tick"] is not None and runs[0]["sensors"] == "3/3":
                break
            time.sleep(1.0)
        assert len(runs) == 1 and runs[0]["run"] == entry["run"] and runs[0]["endpoint"] == ep, runs
        r = runs[0]
        assert r["tick"] >= 0 and r["sensors"] == "3/3" and r["mode"] == "?" and r["out"] == "", r
        assert {"world/0", "target/0", "recorder/0", "launcher/0", "agent/0", "agent/1", "agent/2"} <= set(r["members"])
        assert main(["ps", "--connect", ep]) == 0
        table = capsys.readouterr().out
        assert entry["run"] in table and "3/3" in table and ep in table, table

        rc, text = _fault(capsys, "pause", "--connect", ep)
        assert rc == 0 and f"{entry['run']}: applied: pause at tick" in text, text
        rc, text = _fault(capsys, "kill", "agnet=1", "--connect", ep)
        assert rc == 2 and "did you mean 'agent'?" in text and "nothing sent" in text, text
        rc, text = _fault(capsys, "resume", "--connect", ep)
        assert rc == 0 and "applied: resume at tick" in text, text
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(120)
    keys = {k for k, _m, _t in read_recording(tmp_path / "a" / "recording.mcap").messages if k.startswith("control/")}
    assert keys == {"control/pause", "control/resume"}, keys


def test_logs_follow_a_growing_log_until_the_run_is_over(tmp_path):
    """``flocktrack logs DIR -f``: every process's lines tagged with its name, the ones appended while it
    follows included, a partial line only once complete; it returns once the run is over and quiet."""
    import io
    import threading

    from flocktrack.launch.logs import show

    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "agent-3.log").write_text("INFO one\n")
    (logs / "world-0.log").write_text("INFO w\n")
    out, running = io.StringIO(), [True]
    th = threading.Thread(target=show, args=(tmp_path, None, True, out), kwargs={"still_running": lambda: running[0],
                                                                                  "poll_s": 0.05})
    th.start()
    time.sleep(0.3)
    with open(logs / "agent-3.log", "a") as f:
        f.write("INFO two\nINFO thr")
        f.flush()
        time.sleep(0.3)
        f.write("ee\n")
    time.sleep(0.3)
    running[0] = False
    th.join(10)
    assert not th.is_alive()
    assert out.getvalue().splitlines() == ["[agent/3] INFO one", "[world/0] INFO w", "[agent/3] INFO two",
                                           "[agent/3] INFO three"]
