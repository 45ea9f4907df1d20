"""``flocktrack fault`` before and around the network: the argument names each verb takes come from its
typed command (agent/wire.py), a name it does not take is refused with a "did you mean" and nothing is
sent, ``--connect`` alone finds the only run on a router, and the answers without a tick or without an
acknowledgement say so. A fake bus stands in for the run where one is needed (the live runs:
tests/test_fault_cli.py)."""

from __future__ import annotations

import re

import pytest

from agent.wire import CONTROL_VERBS, Control, command
from flocktrack import fault_client as fc
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


def test_connect_without_run_names_the_runs_when_the_router_has_several(monkeypatch, capsys):
    import flocktrack.ps as ps

    monkeypatch.setattr(ps, "runs_on", lambda ep, cfg=None, run=None, listen_s=0.6: {
        "beta": ps.RunSeen("beta", ep), "alpha": ps.RunSeen("alpha", ep)})
    assert main(["fault", "pause", "--connect", "tcp/127.0.0.1:9"]) == fc.NO_ANSWER
    assert "2 runs on tcp/127.0.0.1:9, say which with --run: alpha, beta" in capsys.readouterr().err
    monkeypatch.setattr(ps, "runs_on", lambda ep, cfg=None, run=None, listen_s=0.6: {})
    assert main(["fault", "pause", "--connect", "tcp/127.0.0.1:9"]) == fc.NO_ANSWER
    assert "no run on tcp/127.0.0.1:9" in capsys.readouterr().err


class FakeBus:
    """The run as ``fault_client.send`` sees it: whoever listens answers ``answer(verb, args)`` (or nothing)."""

    prefix = "ft/fake/"

    def __init__(self, answer):
        self.answer, self.subs, self.sent = answer, {}, []

    def subscribe(self, key, fn):
        self.subs[key] = fn

    def watch_members(self, fn):
        fn("agent/1", True)

    def await_subscriber(self, key, timeout_s):
        return True

    def publish(self, key, msg):
        self.sent.append((key, msg))
        reply = self.answer(msg.verb, msg.args)
        if reply is not None:
            self.subs[reply[0]](*reply)

    def poll(self, s):
        pass


def test_a_kill_answered_without_a_tick_says_when_it_came():
    bus = FakeBus(lambda verb, a: ("launcher/event", Control(k=0, verb=verb, args={
        "agent": 1, "applied": True, "reason": "", "req": a["req"]})))
    ans = fc.send(bus, "kill", {"agent": 1}, timeout_s=1)
    assert ans.code == fc.APPLIED and ans.k is None
    assert re.match(r"applied at \d\d:\d\d:\d\d: agent/1 killed \(SIGKILL\)", ans.text), ans.text


def test_a_launcher_answer_with_a_tick_says_the_tick():
    bus = FakeBus(lambda verb, a: ("launcher/event", Control(k=412, verb=verb, args={
        "agent": 1, "applied": True, "reason": "", "req": a["req"]})))
    ans = fc.send(bus, "restart", {"agent": 1}, timeout_s=1)
    assert ans.code == fc.APPLIED and ans.k == 412
    assert ans.text == "applied at tick 412: agent/1 restarted and back in the run", ans.text


def test_an_outlier_burst_is_reported_sent_not_applied():
    bus = FakeBus(lambda verb, a: None)
    ans = fc.send(bus, "outlier_burst", {"agent": 1, "ticks": 2}, timeout_s=1)
    assert ans.code == fc.APPLIED and [k for k, _m in bus.sent] == ["control/outlier_burst"]
    assert "sent control/outlier_burst" in ans.text
    assert "no acknowledgement for this verb: the sensors apply it" in ans.text and "applied" not in ans.text
