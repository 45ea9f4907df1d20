"""agent/roles/routes.py: a sensor's exchange keys per tick — addressed to each hearer on its own host, one
copy per other host with hearers (naming them), the observers' copy once a tick, every round in it; and the
``--hosts`` map."""

from __future__ import annotations

import numpy as np
import pytest

from agent import wire
from agent.bus import LocalBus
from agent.roles.common import Role
from agent.roles.routes import ExchangeRoutes, format_hosts, parse_hosts

HOSTS = ["a", "a", "a", "b", "b", "c", "b"]
# links[j]: the sensors j hears; 0 is heard by 1 (a), 3 and 4 (b) and 5 (c), not by 6 (b)
LINKS = [[1], [0], [], [0, 4], [0, 3], [0], []]


class Sender(Role):
    def subscribe(self, bus) -> None:
        pass


def test_one_host_addresses_every_hearer():
    r = ExchangeRoutes(0)
    r.route(LINKS)
    assert r.inboxes() == ["agent/*/to/0/xchg"]
    assert r.direct == ["agent/0/to/1/xchg", "agent/0/to/3/xchg", "agent/0/to/4/xchg", "agent/0/to/5/xchg"]
    assert r.via == [] and r.remote == []


def test_placed_on_hosts_each_other_host_gets_one_copy_naming_its_hearers():
    r = ExchangeRoutes(0, HOSTS)
    r.route(LINKS)
    assert r.inboxes() == ["agent/*/to/0/xchg", "agent/*/via/a/xchg"]
    assert r.direct == ["agent/0/to/1/xchg"]
    assert r.via == ["agent/0/via/b/xchg", "agent/0/via/c/xchg"] and r.remote == [3, 4, 5]
    # over a bus, every sensor subscribed to its inboxes: each hearer keeps one copy, a sensor of host b
    # that does not hear 0 gets b's copy and drops it, host a's other sensor and the observers' key see
    # nothing of the host copies
    bus = LocalBus()
    sender = Sender(ticks=1)
    sender.attach(bus)
    kept: dict[int, list] = {j: [] for j in range(len(HOSTS))}
    dropped: dict[int, int] = dict.fromkeys(range(len(HOSTS)), 0)
    for j in range(1, len(HOSTS)):
        mine = ExchangeRoutes(j, HOSTS)

        def on(key, msg, j=j, mine=mine):
            if mine.for_me(msg):
                kept[j].append(msg)
            else:
                dropped[j] += 1

        for key in mine.inboxes():
            bus.subscribe(key, on)
    observed: list = []
    bus.subscribe("agent/*/xchg", lambda key, msg: observed.append(msg))
    r.send(sender, wire.Xchg(src=0, k=7, r=1, payload={"z": np.arange(3.0)}))
    bus.drain()
    assert sorted(bus.stats.sent_by_key) == sorted([*r.direct, *r.via]) and observed == []
    assert [type(m) for m in kept[1]] == [wire.Xchg]
    for j in (3, 4, 5):
        assert [type(m) for m in kept[j]] == [wire.ViaXchg], j
        assert kept[j][0].to == [3, 4, 5] and (kept[j][0].k, kept[j][0].r) == (7, 1)
        assert np.array_equal(kept[j][0].payload["z"], np.arange(3.0))
    assert kept[2] == [] and dropped[2] == 0
    assert kept[6] == [] and dropped[6] == 1


def test_a_sensor_heard_by_nobody_sends_observers_only():
    r = ExchangeRoutes(2, HOSTS)
    r.route(LINKS)
    assert r.direct == [] and r.via == []


def test_the_observers_get_a_ticks_rounds_once_when_it_ends():
    """Every round's payload, in the order sent, in one message on ``agent/<i>/xchg``; the next tick starts
    afresh."""
    bus = LocalBus()
    sender = Sender(ticks=1)
    sender.attach(bus)
    observed: list = []
    bus.subscribe("agent/*/xchg", lambda key, msg: observed.append((key, msg)))
    r = ExchangeRoutes(0)
    for k in (3, 4):
        r.route(LINKS)
        for rnd in range(3):
            r.send(sender, wire.Xchg(src=0, k=k, r=rnd, payload={"z": np.full(2, 10.0 * k + rnd)}))
        r.send_observed(sender, k)
    bus.drain()
    assert [(key, type(m), m.src, m.k) for key, m in observed] == [("agent/0/xchg", wire.Rounds, 0, 3),
                                                                   ("agent/0/xchg", wire.Rounds, 0, 4)]
    assert [p["z"].tolist() for p in observed[1][1].payloads] == [[40.0] * 2, [41.0] * 2, [42.0] * 2]
    assert bus.stats.sent_by_key["agent/0/xchg"] == 2 and bus.stats.sent_by_key["agent/0/to/1/xchg"] == 6


def test_hosts_map_round_trips_and_bad_maps_say_what_is_wrong():
    assert format_hosts(HOSTS) == "a:0-2,b:3-4,c:5,b:6"
    assert parse_hosts("a:0-2,b:3-4,c:5,b:6", 7) == HOSTS
    assert parse_hosts(format_hosts(["x", "y", "x"]), 3) == ["x", "y", "x"]
    for bad, says in [("a:0-2", "agent/3 has no host"), ("a:0-6", "sensors are 0..5"), ("A:0-5", "HOST:FIRST"),
                      ("a:0-3,b:3-5", "agent/3 is placed twice"), ("a0-5", "HOST:FIRST"), ("a:3-1", "sensors are")]:
        with pytest.raises(ValueError, match=says):
            parse_hosts(bad, 6)


def test_a_host_copy_is_read_from_its_key_only_and_says_whom_it_is_for():
    msg = wire.ViaXchg(src=4, k=1, r=0, payload={"z": np.ones(2)}, to=[0, 1])
    data = wire.encode(msg)
    assert wire.decode("agent/4/via/a/xchg", data).to == [0, 1]
    for key, reason in [("agent/5/via/a/xchg", "not_owner"), ("agent/4/via/A/xchg", "bad_key"),
                        ("agent/x/via/a/xchg", "bad_key")]:
        with pytest.raises(wire.WireError) as e:
            wire.decode(key, data)
        assert e.value.reason == reason
    bad = wire.encode(wire.Xchg(src=4, k=1, r=0, payload={"z": np.ones(2)}))   # no "to": not a host copy
    with pytest.raises(wire.WireError) as e:
        wire.decode("agent/4/via/a/xchg", bad)
    assert e.value.reason == "bad_field"
    assert wire.addressed("agent/4/via/a/xchg")
