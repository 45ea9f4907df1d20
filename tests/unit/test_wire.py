"""agent.wire: round trips are bit-exact; hostile input is rejected with a reason, never raised raw."""

import msgpack
import numpy as np
import pytest

from agent import wire
from agent.bus import LocalBus, key_matches


def _tick(n=3):
    return wire.Tick(k=4, t=0.4, n=n, links=[[1], [0, 2], [1]], weights=[[1.0], [1.0, 2.0], [2.0]],
                     b=[1.0, 0.0, 1.0], delta_max=2, alive=[True, True, True], positions=np.arange(6.0).reshape(3, 2))


def test_round_trip_is_bit_exact():
    x = np.array([0.1, 1 / 3, -2.5e-300, 1e300])
    m = wire.Estimate(src=2, k=7, x=x, x_next=x * 3, P=np.outer(x[:4] * 0 + 1, x[:4] * 0 + 1))
    d = wire.decode("agent/2/estimate", wire.encode(m))
    assert d.x.tobytes() == x.tobytes() and d.x_next.tobytes() == (x * 3).tobytes()
    t = wire.decode("world/tick", wire.encode(_tick()))
    assert t.links == [[1], [0, 2], [1]] and t.weights[1] == [1.0, 2.0] and t.positions.shape == (3, 2)
    x = wire.Xchg(src=1, k=3, r=2, payload={"chi1": np.eye(4), "chi2": np.ones(4)})
    d = wire.decode("agent/1/to/2/xchg", wire.encode(x))
    assert set(d.payload) == {"chi1", "chi2"} and d.r == 2
    v = np.array([0.1, 1 / 3, -2.5e-300])
    rounds = wire.Rounds(src=1, k=3, payloads=[{"chi1": np.eye(4)}, {}, {"chi1": -np.eye(4), "chi2": v}])
    d = wire.decode("agent/1/xchg", wire.encode(rounds))    # the observers' copy: the tick's rounds at once
    assert [sorted(p) for p in d.payloads] == [["chi1"], [], ["chi1", "chi2"]]
    assert d.payloads[2]["chi2"].tobytes() == v.tobytes() and np.array_equal(d.payloads[2]["chi1"], -np.eye(4))
    rounds.payloads[1] = {"chi1": np.array([np.nan])}
    with pytest.raises(wire.WireError, match="non_finite"):
        wire.decode("agent/1/xchg", wire.encode(rounds))


def _hostile_tick(**rows) -> bytes:
    d = _tick().to_wire()
    d.update(rows)
    return msgpack.packb(d, use_bin_type=True)


@pytest.mark.parametrize("rows,reason", [
    (dict(links=[[1], [0, 2], [True]]), "bad_field"),                      # a boolean is not a sensor id
    (dict(links=[[1], [0, 2], [1.0]]), "bad_field"),
    (dict(links=[[1], [0, 1], [1]]), "bad_field"),                         # a link to itself
    (dict(links=[[1], [2, 0], [1]]), "bad_field"),                         # unsorted
    (dict(links=[[1], [0, 3], [1]]), "bad_field"),                         # no sensor 3
    (dict(links=[[1], [0, 2**64 - 1], [1]]), "bad_field"),                 # beyond int64
    (dict(links=[[1], [-1, 2], [1]]), "bad_field"),
    (dict(links=[[1], [0], [1]]), "bad_field"),                            # weights[1] has two entries
    (dict(links=[[1], "x", [1]]), "bad_field"),
    (dict(weights=[[1.0], [1.0, float("nan")], [2.0]]), "non_finite"),
    (dict(weights=[[1.0], [1.0, False], [2.0]]), "bad_field"),
    (dict(b=[1.0, float("inf"), 1.0]), "non_finite"),
    (dict(b=[1.0, "1", 1.0]), "bad_field"),
    (dict(alive=[True, 1, True]), "bad_field"),
])
def test_a_hostile_tick_table_is_rejected(rows, reason):
    """The tick's neighbour table is validated in vectorised passes (every sensor decodes every tick);
    every entry still counts."""
    with pytest.raises(wire.WireError) as e:
        wire.decode("world/tick", _hostile_tick(**rows))
    assert e.value.reason == reason


def test_a_tick_with_integer_weights_decodes_to_floats():
    t = wire.decode("world/tick", _hostile_tick(weights=[[1], [1.0, 2], [2.0]], b=[1, 0, 1.0]))
    assert t.weights == [[1.0], [1.0, 2.0], [2.0]] and all(type(w) is float for row in t.weights for w in row)
    assert t.b == [1.0, 0.0, 1.0] and all(type(v) is float for v in t.b)


@pytest.mark.parametrize("key,data,reason", [
    ("agent/1/estimate", b"\xc1garbage", "bad_encoding"),
    ("agent/1/estimate", msgpack.packb([1, 2]), "bad_encoding"),
    ("agent/1/estimate", msgpack.packb({"type": "state", "src": 1, "k": 0}), "wrong_type"),
    ("agent/1/estimate", msgpack.packb({"type": "estimate", "src": "x", "k": 0}), "bad_field"),
    ("agent/x/estimate", b"", "bad_key"),
    ("nowhere", b"", "bad_key"),
])
def test_malformed_messages_are_rejected_with_a_reason(key, data, reason):
    with pytest.raises(wire.WireError) as e:
        wire.decode(key, data)
    assert e.value.reason == reason


def test_non_finite_wrong_shape_and_impostor_are_rejected():
    m = wire.Estimate(src=1, k=0, x=np.array([np.nan, 1.0]), x_next=np.zeros(2))
    with pytest.raises(wire.WireError, match="non_finite"):
        wire.decode("agent/1/estimate", wire.encode(m))
    m = wire.Estimate(src=1, k=0, x=np.zeros(2), x_next=np.zeros(3))
    with pytest.raises(wire.WireError, match="bad_shape"):
        wire.decode("agent/1/estimate", wire.encode(m))
    m = wire.Estimate(src=3, k=0, x=np.zeros(2), x_next=np.zeros(2))
    with pytest.raises(wire.WireError, match="not_owner"):
        wire.decode("agent/1/estimate", wire.encode(m))
    bad = _tick()
    bad.links = [[1, 1], [0, 2], [1]]
    bad.weights = [[1.0, 1.0], [1.0, 2.0], [2.0]]
    with pytest.raises(wire.WireError, match="bad_field"):
        wire.decode("world/tick", wire.encode(bad))
    d = wire.Xchg(src=0, k=0, r=0, payload={"a": np.zeros(2)}).to_wire()
    d["payload"]["a"]["d"] = b"\x00" * 7  # truncated array data
    with pytest.raises(wire.WireError, match="bad_shape"):
        wire.decode("agent/0/to/1/xchg", msgpack.packb(d, use_bin_type=True))


def test_local_bus_drops_and_counts_bad_messages_without_reaching_handlers():
    bus = LocalBus()
    got = []
    bus.subscribe("agent/*/estimate", lambda k, m: got.append(m))
    bus.publish("agent/0/estimate", wire.Estimate(src=0, k=0, x=np.zeros(2), x_next=np.zeros(2)))
    bus.publish_raw("agent/0/estimate", b"\x00\x01")
    bus.publish("agent/1/estimate", wire.Estimate(src=2, k=0, x=np.zeros(2), x_next=np.zeros(2)))
    bus.drain()
    assert len(got) == 1
    assert bus.stats.dropped == {"bad_encoding": 1, "not_owner": 1}


def test_key_expressions():
    assert key_matches("agent/*/xchg", "agent/12/xchg")
    assert not key_matches("agent/*/xchg", "agent/12/state")
    assert key_matches("control/**", "control/fault/link")
    assert key_matches("**", "world/tick")
    assert not key_matches("world/tick", "world/tick/x")


def _one_of_each():
    x = np.array([0.1, 1 / 3, -2.5e-300, 1e150])
    return [_tick(), wire.Truth(k=2, t=0.2, x=x), wire.Meas(src=1, k=2, t=0.2, y=x[:2], b=0.0, pos=x[2:]),
            wire.Meas(src=1, k=2, t=0.2, y=x[:2], pos=x[2:], v=x[:2] / 7),
            wire.Xchg(src=1, k=3, r=2, payload={"chi1": np.eye(2) / 3, "chi2": x}),
            wire.Rounds(src=1, k=3, payloads=[{"chi1": np.eye(2) / 3}, {"chi1": np.eye(2), "chi2": x}]),
            wire.Estimate(src=2, k=7, x=x, x_next=x * 3, P=np.outer(x, x) * 1e-301, name="Kalman",
                          aux={"eps_1": x[:2]}),
            wire.Estimate(src=0, k=7, x=x, x_next=x), wire.State(src=4, k=1, pos=x[:2], vel=-x[2:]),
            wire.Control(k=3, verb="fault", args={"kind": "delay", "agents": [1, 2], "p": 0.5, "on": True}),
            wire.End(k=9, reason="stopped")]


def test_fast_json_writes_what_to_json_says_and_reads_back_bit_exact():
    """The recorder's orjson path (to_json_bytes) = json.dumps(to_json()), and from_json inverts it."""
    import json

    for m in _one_of_each():
        fast = m.to_json_bytes()
        assert json.loads(fast) == json.loads(json.dumps(m.to_json())), m.TYPE
        back = wire.from_json(json.loads(fast))
        key = {"control": "control/fault", "xchg": "agent/1/to/2/xchg", "rounds": "agent/1/xchg", "meas": "agent/1/meas", "state": "agent/4/state",
               "estimate": f"agent/{m.src}/estimate", "tick": "world/tick", "truth": "target/truth", "end": "world/end"}
        assert wire.encode(back) == wire.encode(wire.decode(key[m.TYPE], wire.encode(m))), m.TYPE
    odd = wire.State(src=4, k=1, pos=np.arange(6.0).reshape(2, 3)[:, 1], vel=np.zeros(2))  # not contiguous
    assert json.loads(odd.to_json_bytes()) == json.loads(json.dumps(odd.to_json()))


# ------------------------------------------------------------------ typed control arguments

def test_a_fault_event_decodes_into_its_typed_form_bit_for_bit():
    """What the world publishes on world/event (topology/faults.py ActiveFault.event_args) comes back, after
    the wire, as a FaultEvent with every parameter; a launcher ack (id, kind, phase, agents) too."""
    from agent.scenario import FaultEventCfg
    from topology.faults import ActiveFault

    f = ActiveFault(7, FaultEventCfg(kind="byzantine", mode="bias", bias=[0.5, -1.0], p=0.25, delay_ticks=3,
                                     direction="in"), agents=[2, 4], links=[(0, 1), (2, 3)])
    m = wire.decode("world/event", wire.encode(wire.Control(k=3, verb="fault", args=f.event_args("start"))))
    e = wire.fault_event(m.args)
    assert (e.id, e.kind, e.phase, e.agents, e.links, e.groups) == (7, "byzantine", "start", (2, 4),
                                                                   ((0, 1), (2, 3)), None)
    assert (e.mode, e.bias, e.p, e.delay_ticks, e.direction) == ("bias", (0.5, -1.0), 0.25, 3, "in")
    ack = wire.fault_event({"id": 1001, "kind": "crash", "phase": "heal", "agents": [1.0]}, n=3)
    assert (ack.agents, ack.delay_ticks, ack.mode) == ((1,), 1, None)
    with pytest.raises(wire.WireError, match="agents"):
        wire.fault_event({"id": 1, "kind": "crash", "phase": "heal", "agents": [3.0]}, n=3)


def test_the_fault_limits_are_the_scenarios():
    """One set of bounds: a [[faults.events]] entry the scenario accepts is a fault event the wire accepts."""
    from agent.scenario import FAULT_KINDS, ScenarioError, parse_fault_event

    assert tuple(wire.FAULT_KINDS) == tuple(FAULT_KINDS)
    for name, hi in wire.FAULT_LIMITS.items():
        over = hi + 1 if isinstance(hi, int) else hi * 1.01
        parse_fault_event({"kind": "delay", name: hi}, 3)
        wire.fault_event({"id": 0, "kind": "delay", "phase": "start", name: hi})
        with pytest.raises(ScenarioError):
            parse_fault_event({"kind": "delay", name: over}, 3)
        with pytest.raises(wire.WireError, match=name):
            wire.fault_event({"id": 0, "kind": "delay", "phase": "start", name: over})


@pytest.mark.parametrize("verb, args, want", [
    ("pause", {}, wire.Command("pause")),
    ("step", {}, wire.Step("step", 1)),
    ("step", {"n": 0}, wire.Step("step", 1)),
    ("step", {"n": 5.0}, wire.Step("step", 5)),
    ("speed", {"factor": 2}, wire.Speed("speed", 2.0)),
    ("link_drop", {"a": 3, "b": 1.0}, wire.LinkEdit("link_drop", 3, 1)),
    ("link_loss", {"p": 1}, wire.LinkLoss("link_loss", 1.0)),
    ("partition", {"groups": [0.0, 1.0, 1.0, 0.0]}, wire.Partition("partition", (0, 1, 1, 0))),
    ("heal_fault", {"id": 1001}, wire.HealFault("heal_fault", 1001)),
    ("outlier_burst", {}, wire.OutlierBurst("outlier_burst", -1, 1, 0.0)),
    ("outlier_burst", {"agent": 2, "ticks": 5.0, "magnitude": 50}, wire.OutlierBurst("outlier_burst", 2, 5, 50.0)),
    ("inject", {"kind": "delay", "delay_ticks": 2.0, "jitter_ms": 1.0, "ticks": 3, "id": 9, "start": 4},
     wire.Inject("inject", {"kind": "delay", "delay_ticks": 2, "jitter_ms": 1.0}, 3)),
])
def test_control_commands_are_typed(verb, args, want):
    got = wire.command(verb, args, n=4)
    assert got == want and type(got) is type(want)


@pytest.mark.parametrize("verb, args, words", [
    ("speed", {"factor": 0.0}, "factor"), ("speed", {"factor": True}, "factor"), ("speed", {}, "factor"),
    ("step", {"n": "x"}, "n"),
    ("link_drop", {"a": 1, "b": 1}, "different"), ("link_heal", {"a": 0, "b": 4}, "b"),
    ("link_drop", {"a": 0.5, "b": 1}, "a"),
    ("link_loss", {"p": 3.0}, "p"), ("link_loss", {"p": False}, "p"),
    ("partition", {"groups": [0, 1]}, "each of the 4"), ("partition", {"groups": [0, -1, 0, 0]}, "groups"),
    ("heal_fault", {"id": "x"}, "id"),
    ("inject", {"kind": "delay", "ticks": 0}, "inject.ticks"), ("inject", {"ticks": True}, "inject.ticks"),
    ("outlier_burst", {"ticks": 10_001}, "ticks"), ("outlier_burst", {"agent": -2}, "agent"),
    ("outlier_burst", {"magnitude": "big"}, "magnitude"),
])
def test_bad_control_arguments_are_refused_with_the_argument_named(verb, args, words):
    with pytest.raises(wire.WireError) as e:
        wire.command(verb, args, n=4)
    assert e.value.reason == "bad_field" and words in e.value.detail


def test_unknown_verbs_are_refused():
    for verb in ("no_such_verb", "fault", "rejected"):
        with pytest.raises(wire.WireError, match="unknown_verb"):
            wire.command(verb, {})


def test_the_launchers_verbs_name_one_sensor():
    assert wire.command("kill", {"agent": 3.0}, n=4) == wire.Member("kill", 3)
    for args in ({}, {"agent": 4}, {"agent": 1.5}, {"agent": "x"}):
        with pytest.raises(wire.WireError, match="agent must be an integer in \\[0, 3\\]"):
            wire.command("restart", args, n=4)


def test_an_addressed_exchange_payload_is_its_senders_and_unseen_by_observers():
    """``agent/<i>/to/<j>/xchg``: sensor i's payload for sensor j's inbox — owned by i like ``agent/i/xchg``,
    matched by j's inbox and by no observer pattern (the observers get each payload once, unaddressed)."""
    from agent.bus import key_matches

    data = wire.encode(wire.Xchg(src=3, k=12, r=4, payload={"a": np.zeros(2)}))
    assert wire.xchg_key(3, 5) == "agent/3/to/5/xchg" and wire.decode("agent/3/to/5/xchg", data).src == 3
    for key, reason in (("agent/4/to/5/xchg", "not_owner"), ("agent/3/to/3/xchg", "bad_key"),
                        ("agent/3/to/x/xchg", "bad_key"), ("agent/3/to/5/meas", "bad_key"),
                        ("agent/3/over/5/xchg", "bad_key"), ("agent/3/to/-1/xchg", "bad_key")):
        with pytest.raises(wire.WireError) as e:
            wire.decode(key, data)
        assert e.value.reason == reason, key
    assert key_matches(wire.inbox(5), "agent/3/to/5/xchg") and not key_matches(wire.inbox(5), "agent/3/to/6/xchg")
    assert wire.addressed("agent/3/to/5/xchg") and not wire.addressed("agent/3/xchg")
    # a sensor's last estimate handed to a restarted one: addressed, owned by its sender, never observed
    est = wire.encode(wire.Estimate(src=3, k=12, x=np.zeros(4), x_next=np.ones(4)))
    assert wire.estimate_key(3, 5) == "agent/3/to/5/estimate" and wire.addressed(wire.estimate_key(3, 5))
    assert wire.decode("agent/3/to/5/estimate", est).x_next.tolist() == [1.0] * 4
    assert key_matches(wire.estimate_inbox(5), "agent/3/to/5/estimate")
    assert not key_matches(wire.estimate_inbox(5), "agent/3/to/5/xchg") and not key_matches(wire.inbox(5), "agent/3/to/5/estimate")
    for key in ("agent/4/to/5/estimate", "agent/3/to/3/estimate"):
        with pytest.raises(wire.WireError):
            wire.decode(key, est)
    with pytest.raises(wire.WireError):
        wire.decode("agent/3/to/5/estimate", data)     # an exchange payload on it: the wrong type


def test_an_unusable_exchange_payload_is_dropped_but_its_round_hears_that_it_came():
    """NaN or a bad shape in an exchange payload: the arrays are dropped and counted, and the receiver is
    handed only the header (sender, tick, round) — never the arrays — so its round need not wait for it."""
    nan = wire.Xchg(src=2, k=7, r=1, payload={"a": np.array([np.nan, 1.0])})
    with pytest.raises(wire.WireError, match="non_finite") as e:
        wire.decode("agent/2/to/0/xchg", wire.encode(nan))
    h = e.value.header
    assert isinstance(h, wire.UnusableXchg) and (h.src, h.k, h.r, h.payload, h.reason) == (2, 7, 1, {}, "non_finite")
    # a header that lies about its sender says nothing; a malformed header neither
    with pytest.raises(wire.WireError) as e:
        wire.decode("agent/3/to/0/xchg", wire.encode(nan))
    assert e.value.header is None
    d = nan.to_wire()
    d["r"] = -1
    with pytest.raises(wire.WireError) as e:
        wire.decode("agent/2/to/0/xchg", msgpack.packb(d, use_bin_type=True))
    assert e.value.header is None
    # on the bus: counted as dropped, not received; the handler sees the header only
    bus = LocalBus()
    got = []
    bus.subscribe("agent/*/to/0/xchg", lambda k, m: got.append(m))
    bus.publish("agent/2/to/0/xchg", nan)
    bus.publish("agent/1/to/0/xchg", wire.Xchg(src=1, k=7, r=1, payload={"a": np.zeros(2)}))
    bus.drain()
    assert [type(m).__name__ for m in got] == ["UnusableXchg", "Xchg"] and got[0].payload == {}
    assert bus.stats.dropped == {"non_finite": 1} and bus.stats.received == 1


def test_encode_writes_the_bytes_of_the_wire_map():
    """``encode`` (msgspec) writes exactly ``msgpack.packb(msg.to_wire())``: numpy scalars as numbers, arrays as
    ``{s, d}``, ``type`` first."""
    msgs = [_tick(), wire.Truth(k=1, t=0.1, x=np.ones(4)),
            wire.Meas(src=1, k=2, t=0.2, y=np.ones(2), b=np.float64(0.5), pos=np.ones(2), v=None),
            wire.Xchg(src=3, k=9, r=2, payload={"chi1": np.eye(2), "chi2": np.arange(3.0)}),
            wire.ViaXchg(src=3, k=9, r=2, payload={"a": np.ones(2)}, to=[4, 5]),
            wire.Estimate(src=2, k=7, x=np.ones(3), x_next=np.ones(3), P=np.eye(3), name="N", aux={"e": np.ones(1)}),
            wire.State(src=1, k=2, pos=np.ones(2), vel=np.arange(2), w=None),
            wire.Control(verb="speed", args={"factor": 2.0, "l": [1, 2.5], "s": "x", "n": None, "b": True}),
            wire.End(k=3, reason="stopped")]
    msgs[0].alive = [True, np.bool_(True), True]
    for m in msgs:
        assert wire.encode(m) == msgpack.packb(m.to_wire(), use_bin_type=True), type(m).__name__


@pytest.mark.parametrize("edit,reason,header", [
    (lambda d: d.pop("type"), "wrong_type", False),
    (lambda d: d.update(type="estimate"), "wrong_type", False),
    (lambda d: d.update(r=True), "bad_field", False),                       # a flag is not a round
    (lambda d: d["payload"].update({"k" * 65: d["payload"]["a"]}), "bad_field", False),
    (lambda d: d.update(payload=[1]), "bad_field", False),
    (lambda d: d["payload"]["a"].update(e=1), "bad_array", True),          # an array holds s and d only
    (lambda d: d["payload"]["a"].update(d="text"), "bad_array", True),
    (lambda d: d["payload"]["a"].update(s=[2, 2, 2]), "bad_shape", True),
    (lambda d: d["payload"]["a"].update(s=[-2]), "bad_shape", True),
    (lambda d: d["payload"].update(b=5), "bad_array", True),
])
def test_an_exchange_payload_refused_by_its_form_says_why(edit, reason, header):
    """What msgspec refuses is labelled like the rest: a fault inside an array keeps the payload's header
    (its round need not wait for it); anything else says nothing of it."""
    d = wire.Xchg(src=2, k=7, r=1, payload={"a": np.zeros(2)}).to_wire()
    edit(d)
    with pytest.raises(wire.WireError) as e:
        wire.decode("agent/2/to/0/xchg", msgpack.packb(d, use_bin_type=True))
    assert e.value.reason == reason
    assert (e.value.header is not None) == header
    if header:
        assert (e.value.header.src, e.value.header.k, e.value.header.r) == (2, 7, 1)


def test_a_refused_key_is_refused_every_time():
    """Keys are remembered once read; a bad one never is."""
    for _ in range(2):
        with pytest.raises(wire.WireError, match="bad_key"):
            wire.expected_type("agent/3/to/3/xchg")
    assert wire.expected_type("agent/3/to/4/xchg") == (wire.Xchg, 3)
