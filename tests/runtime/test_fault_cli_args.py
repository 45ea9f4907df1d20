"""``flocktrack fault`` before and around the network: the argument names each verb takes come from its
typed command (agent/wire.py), a name it does not take is refused with a "did you mean" and nothing is
sent, ``--connect`` alone on a router with several runs names them, and a launcher's answer without a tick
says when it came. (The live runs: tests/runtime/test_fault_cli.py.)"""

from __future__ import annotations

import time

import pytest

from agent.wire import CONTROL_VERBS, command
from flocktrack.launch import fault_client as fc
from flocktrack.cli import main

#: a valid call of every verb (for a flock of 2)
SAMPLES = {"pause": {}, "resume": {}, "heal": {}, "step": {"n": 2}, "speed": {"factor": 2.0},
           "link_drop": {"a": 0, "b": 1}, "link_heal": {"a": 1, "b": 0}, "link_loss": {"p": 0.1},
           "partition": {"groups": [0, 1]}, "inject": {"kind": "delay", "delay_ms": 80, "ticks": 10},
           "heal_fault": {"id": 3}, "kill": {"agent": 1}, "restart": {"agent": 0},
           "outlier_burst": {"agent": 1, "ticks": 2, "magnitude": 40.0}}
NOWHERE = ["--run", "x", "--connect", "tcp/127.0.0.1:9"]   # (never reached: refused before anything is sent)


@pytest.mark.parametrize("verb", CONTROL_VERBS)
def test_each_verbs_argument_names_are_its_typed_commands_fields(verb):
    assert set(fc.COMMAND_TYPES) == set(CONTROL_VERBS)
    cmd = command(verb, SAMPLES[verb], 2)
    assert type(cmd) is fc.COMMAND_TYPES[verb]
    assert set(SAMPLES[verb]) <= set(fc.arg_names(verb)) and "verb" not in fc.arg_names(verb)
    fc.check(verb, {**SAMPLES[verb], "req": "abc123"}, 2)   # the request id goes with any verb


@pytest.mark.parametrize("words,said", [
    (["pause", "foo=1"], "pause takes no argument 'foo'; pause takes no arguments"),
    (["kill", "agnet=3"], "kill takes no argument 'agnet'; did you mean 'agent'? kill takes: agent"),
    (["link_loss", "prob=0.2"], "link_loss takes: p"),
    (["outlier_burst", "magnitud=9"], "did you mean 'magnitude'?"),
    (["inject", "kind=delay", "delya_ms=80"], "did you mean 'delay_ms'?"),
    (["inject", "kind=delay", "heal=30"], "inject takes no argument 'heal'"),
])
def test_an_argument_name_the_verb_does_not_take_is_refused_with_did_you_mean(words, said, capsys):
    assert main(["fault", *words, *NOWHERE]) == fc.NO_ANSWER
    err = capsys.readouterr().err
    assert said in err and "nothing sent" in err, err


def test_connect_without_run_names_the_runs_when_the_router_has_several(tmp_path, capsys):
    """A real router with two runs' members on it (their liveliness tokens): ``--connect`` alone names both and
    sends nothing; once they are gone, it says there is no run."""
    import subprocess
    import sys

    from agent.bus import ZenohBus
    from flocktrack.launch.launcher import free_port

    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    router = subprocess.Popen([sys.executable, "-m", "flocktrack.launch.router", "--listen", ep], stdout=subprocess.PIPE,
                              text=True)
    buses = []
    try:
        assert "listening on" in router.stdout.readline()
        for run in ("beta", "alpha"):
            buses.append(ZenohBus(run, connect=ep))
            buses[-1].declare_token("world/0")
        assert main(["fault", "pause", "--connect", ep]) == fc.NO_ANSWER
        err = capsys.readouterr().err
        assert f"2 runs on {ep}, say which with --run: alpha, beta" in err, err
        for b in buses:
            b.close()
        assert main(["fault", "pause", "--connect", ep]) == fc.NO_ANSWER
        assert f"no run on {ep}" in capsys.readouterr().err
    finally:
        for b in buses:
            b.close()
        router.terminate()
        router.wait(30)


def test_the_launchers_answer_names_its_tick_or_else_the_time():
    """A kill or restart is applied at the newest tick the launcher has seen; before the first one it answers
    k = 0, and the time the answer came is said instead. (The full answers, live: tests/runtime/test_fault_cli.py.)"""
    at = time.mktime((2026, 12, 2, 14, 5, 9, 0, 0, -1))
    assert fc.when_applied(412, at) == "at tick 412"
    assert fc.when_applied(0, at) == fc.when_applied(None, at) == "at 14:05:09"
