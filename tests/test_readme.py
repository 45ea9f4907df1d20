"""The README tells the truth: its two commands, its description of a run's outputs, and the first
minutes of a new user (status line, "did you mean", a default output directory)."""

import json
import re
from pathlib import Path

import pytest

from flocktrack.cli import default_out, main

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def _bash_blocks(text: str) -> list[str]:
    return [b.strip() for b in re.findall(r"```bash\n(.*?)```", text, re.S)]


def test_ci_runs_exactly_the_readmes_test_command():
    blocks = _bash_blocks(README)
    test_cmd = next(b for b in blocks if "pytest" in b)
    ci = [ln for ln in (ROOT / ".ci" / "run").read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    assert ci[-1] == test_cmd, "the last command of .ci/run must be the README's test command"
    assert not any(w in ln for ln in ci[:-1] for w in ("apt", "npm", "pip ")), "no extra steps in .ci/run"


def test_readmes_main_command_parses(monkeypatch):
    main_cmd = next(b for b in _bash_blocks(README) if "flocktrack run" in b)
    argv = main_cmd.split("&& flocktrack ", 1)[1].split()
    seen = {}
    # parse only: the sub-command's function is replaced before dispatch
    monkeypatch.setattr("flocktrack.cli.cmd_run", lambda args: seen.setdefault("args", args) and 0)
    assert main(argv) == 0
    a = seen["args"]
    assert a.scenario == "scenarios/demo.toml" and a.dashboard and (ROOT / a.scenario).is_file()


def _outputs_table() -> dict[str, str]:
    sect = README[README.index("### Outputs"):]
    sect = sect[: sect.index("\n\n", sect.index("| file |"))]
    rows = {}
    for ln in sect.splitlines():
        m = re.match(r"\| `([^`]+)` \| (.*) \|$", ln)
        if m:
            rows[m.group(1)] = m.group(2)
    return rows


def test_readmes_outputs_are_what_a_real_run_writes(tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(["run", str(ROOT / "scenarios" / "demo.toml"), "--ticks", "20", "--mode", "lockstep",
               "--out", str(out)])
    assert rc == 0
    cap = capsys.readouterr()
    rows = _outputs_table()
    assert {"summary.json", "metrics.csv", "run.json", "recording.mcap", "logs/", "stats/"} <= set(rows)
    for name in rows:
        assert (out / name.rstrip("/")).exists(), f"README names {name}, the run did not write it"
    summary = json.loads((out / "summary.json").read_text())
    always = rows["summary.json"].split("where the paper defines them")[0]
    fields = re.findall(r"`([a-z_0-9]+)`", always)
    assert len(fields) >= 15
    missing = [f for f in fields if f not in summary]
    assert not missing, f"README lists summary fields the run does not write: {missing}"
    assert "missed_deadlines" in json.loads((out / "run.json").read_text())
    assert list((out / "logs").glob("agent-*.log")) and list((out / "stats").glob("agent-*.json"))
    # the terminal: a status line that counted to the end, and where the results are
    assert "tick 20/20" in cap.err and "sensors 12/12" in cap.err
    assert f"results in {out}/" in cap.out
    assert "deadline on" not in cap.err            # INFO lines stay in the logs without -v


def test_default_output_directory_is_runs_scenario_timestamp(tmp_path, monkeypatch):
    assert re.fullmatch(r"runs/demo-\d{8}-\d{6}", str(default_out("scenarios/demo.toml")))
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(ROOT / "scenarios" / "gu_hu_normal.toml"), "--transport", "inproc", "--ticks", "5"]) == 0
    (made,) = (tmp_path / "runs").iterdir()
    assert made.name.startswith("gu_hu_normal-") and (made / "summary.json").is_file()


@pytest.mark.parametrize("argv,hint", [
    (["rnu", "x"], "did you mean 'run'?"),
    (["run", "scenarios/demo.toml", "--estimator", "kalmn"], "did you mean 'kalman'?"),
])
def test_cli_says_did_you_mean(argv, hint, capsys):
    with pytest.raises(SystemExit):
        main(argv)
    assert hint in capsys.readouterr().err


def test_fault_verb_did_you_mean(capsys):
    assert main(["fault", "pasue", "--run", "x"]) == 2
    assert "did you mean 'pause'?" in capsys.readouterr().err


@pytest.mark.parametrize("over,key,hint", [
    ({"estimator.rundos": 3}, "estimator.rundos", "did you mean `rounds`?"),
    ({"estimator.name": "minmax"}, "estimator.name", "did you mean 'minimax'?"),
    ({"run.tick": 3}, "run.tick", "did you mean `ticks`?"),
])
def test_scenario_errors_say_did_you_mean(over, key, hint):
    from agent.scenario import ScenarioError, parse_scenario
    from agent.scenario import scenario_data

    data = scenario_data(str(ROOT / "scenarios" / "demo.toml"), [], **over)
    with pytest.raises(ScenarioError) as e:
        parse_scenario(data, "demo.toml")
    assert e.value.key == key and hint in str(e.value)


def test_fault_kind_did_you_mean():
    from agent.scenario import ScenarioError, parse_scenario
    from agent.scenario import scenario_data

    data = scenario_data(str(ROOT / "scenarios" / "demo.toml"), [])
    data["faults"] = {"events": [{"kind": "crsh", "targets": "agents:1", "start": 3}]}
    with pytest.raises(ScenarioError) as e:
        parse_scenario(data, "demo.toml")
    assert e.value.key == "faults.events[0].kind" and "did you mean 'crash'?" in str(e.value)


def test_only_warnings_errors_and_tracebacks_reach_the_terminal_without_v():
    from flocktrack.launch.launcher import worth_showing

    lines = ["INFO agent.runner: agent/7: deadline on (93, 0)\n", "WARNING agent.runner: agent/7: starting without\n",
             "Traceback (most recent call last):\n", '  File "x.py", line 1, in <module>\n', "ValueError: boom\n",
             "INFO world: done\n", "2026-12-01T17:26:15Z  WARN zenoh::net: lost the router\n", "error: bad scenario\n"]
    shown, tb = [], False
    for ln in lines:
        show, tb = worth_showing(ln, tb)
        shown.append(show)
    assert shown == [False, True, True, True, True, False, True, True]


def test_results_are_written_when_the_run_ends_while_the_dashboard_stays_up(tmp_path):
    """The README's main job keeps its dashboard up after the run (no ``--no-linger``): summary.json,
    metrics.csv and run.json are on disk, and the terminal says where, before Ctrl-C — not after it."""
    import signal
    import subprocess
    import sys
    import threading
    import time

    from flocktrack.launch.launcher import free_port

    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "flocktrack", "run", str(ROOT / "scenarios" / "demo.toml"),
                             "--dashboard", "--dashboard-port", str(free_port()), "--ticks", "20", "--mode",
                             "lockstep", "--out", str(out)], cwd=str(ROOT), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True).start()
    err: list[str] = []
    lingering = threading.Event()

    def read_err():
        for line in proc.stderr:
            err.append(line)
            if "the dashboard stays up" in line:
                lingering.set()

    threading.Thread(target=read_err, daemon=True).start()
    try:
        assert lingering.wait(180), "".join(err)[-3000:]
        assert proc.poll() is None                       # still serving the dashboard
        for name in ("summary.json", "metrics.csv", "run.json"):
            assert (out / name).is_file(), f"{name} not written before Ctrl-C"
        assert json.loads((out / "summary.json").read_text())["ticks"] == 20
        deadline = time.monotonic() + 10
        while not any(f"results in {out}/" in line for line in lines) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert any(f"results in {out}/" in line for line in lines), lines
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            rc = proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    assert rc == 0, "".join(err)[-3000:]
    assert (out / "events.json").is_file()
