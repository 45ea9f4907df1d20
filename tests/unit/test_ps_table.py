"""flocktrack/launch/ps.py without a live run: a run's row, the aligned table and the JSON of ``flocktrack ps``,
and ``discover`` over this machine's launcher files when no router answers."""

import json
import os
import socket
import subprocess
import time

import pytest

from flocktrack.launch.ps import RunSeen, as_json, discover, table
from flocktrack.launch.runs import LocalRun, register


def seen(run: str = "demo", **kw) -> RunSeen:
    members = {"agent/0", "agent/2", "world/0", "target/0", "launcher/0"}
    return RunSeen(run, "tcp/127.0.0.1:7447", members=kw.pop("members", members), **kw)


def test_a_runs_row_counts_the_sensors_alive_and_lists_its_other_members_sorted():
    row = seen(tick=41, mode="lockstep", n_sensors=3, out="runs/demo").row()
    assert row == {"run": "demo", "tick": 41, "mode": "lockstep", "sensors": "2/3",
                   "members": "launcher/0 target/0 world/0", "endpoint": "tcp/127.0.0.1:7447", "out": "runs/demo"}


def test_a_run_of_unknown_size_shows_its_sensors_out_of_a_question_mark():
    assert seen().row()["sensors"] == "2/?"
    assert seen(members=set()).sensors_alive == 0


def test_the_table_puts_every_value_under_its_upper_case_header():
    text = table([seen("a", tick=7, n_sensors=3), seen("a-much-longer-name", tick=None, mode="realtime")])
    header, *rows = text.split("\n")
    assert header.split() == ["RUN", "TICK", "MODE", "SENSORS", "MEMBERS", "ENDPOINT", "OUT"]
    col = header.index("TICK"), header.index("MODE"), header.index("ENDPOINT")
    assert rows[0][col[0]:].startswith("7 ") and rows[1][col[0]:].startswith(" ")   # a run that ticked nothing: blank
    assert rows[0][col[1]:].startswith("?") and rows[1][col[1]:].startswith("realtime")
    assert all(r[col[2]:].startswith("tcp/127.0.0.1:7447") for r in rows)
    assert all(line == line.rstrip() for line in text.split("\n"))


def test_the_table_of_no_run_is_its_header_alone():
    assert table([]) == "RUN  TICK  MODE  SENSORS  MEMBERS  ENDPOINT  OUT"


def test_the_json_lists_every_member_sorted_the_sensors_included():
    (got,) = json.loads(as_json([seen(tick=3, n_sensors=3)]))
    assert got["members"] == ["agent/0", "agent/2", "launcher/0", "target/0", "world/0"]
    assert got["sensors"] == "2/3" and got["tick"] == 3


@pytest.fixture
def runtime_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("FLOCKTRACK_RUNTIME_DIR", str(tmp_path))
    return tmp_path


def nobody_listens() -> str:
    """A local TCP endpoint with no router behind it (a port just freed)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def local(run: str, endpoint: str, pid: int | None = None) -> LocalRun:
    return LocalRun(run=run, endpoint=endpoint, mode="lockstep", n_sensors=4, out=f"runs/{run}",
                    pid=os.getpid() if pid is None else pid, started=time.time())


def test_without_a_local_run_discover_finds_nothing_and_asks_nobody(runtime_dir):
    assert discover() == ([], [])


def test_a_local_run_whose_router_does_not_answer_is_reported_as_failed_not_raised(runtime_dir):
    ep = nobody_listens()
    register(local("gone", ep))
    runs, failed = discover()
    assert runs == []
    assert len(failed) == 1 and failed[0].startswith(f"{ep} (")


def test_only_the_named_local_run_is_asked(runtime_dir):
    a, b = nobody_listens(), nobody_listens()
    register(local("a", a))
    register(local("b", b))
    _, failed = discover(run="b")
    assert [f.split(" ")[0] for f in failed] == [b]


def test_the_file_of_a_launcher_that_died_is_neither_asked_nor_kept(runtime_dir):
    dead = subprocess.Popen(["true"])
    dead.wait()
    register(local("crashed", nobody_listens(), pid=dead.pid))
    assert discover() == ([], [])
    assert not (runtime_dir / "crashed.json").exists()
