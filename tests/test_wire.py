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
    d = wire.decode("agent/1/xchg", wire.encode(x))
    assert set(d.payload) == {"chi1", "chi2"} and d.r == 2


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
        wire.decode("agent/0/xchg", msgpack.packb(d, use_bin_type=True))


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
        key = {"control": "control/fault", "xchg": "agent/1/xchg", "meas": "agent/1/meas", "state": "agent/4/state",
               "estimate": f"agent/{m.src}/estimate", "tick": "world/tick", "truth": "target/truth", "end": "world/end"}
        assert wire.encode(back) == wire.encode(wire.decode(key[m.TYPE], wire.encode(m))), m.TYPE
    odd = wire.State(src=4, k=1, pos=np.arange(6.0).reshape(2, 3)[:, 1], vel=np.zeros(2))  # not contiguous
    assert json.loads(odd.to_json_bytes()) == json.loads(json.dumps(odd.to_json()))
