"""agent.link_emulation on its own: the sensor-side rows of the fault plan (topology/faults.py), seeded and
bus-free. Every draw is checked against the generator it must come from (rng_for(seed, "agent", i, …)), so
that a refactoring that changes the order of the draws — and with it every run's numbers — fails here."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agent import wire
from agent.link_emulation import LinkEmulator, noise_factor
from agent.models import LinearSensor
from agent.seeding import rng_for
from agent.wire import FaultEvent, OutlierBurst, Xchg

ROOT = Path(__file__).resolve().parents[2]
SEED, ME = 7, 2


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def _link(i=ME, seed=SEED, noise=None):
    got: list[tuple[int, int, int]] = []
    clock = Clock()
    em = LinkEmulator(i, seed, lambda key, m: got.append((m.src, m.k, m.r)), clock, noise)
    return em, got, clock


def _start(em, fid=0, phase="start", **args):
    em.apply(FaultEvent(id=fid, phase=phase, **args))


def _x(src=1, k=5, r=0, v=1.0):
    return Xchg(src=src, k=k, r=r, payload={"a": np.full(3, v)})


def _admit(em, *msgs):
    return [em.admit(f"agent/{m.src}/xchg", m) for m in msgs]


# ------------------------------------------------------------------ the plan: start, heal, who is concerned

def test_without_faults_every_payload_goes_straight_through():
    em, got, _ = _link()
    assert _admit(em, _x(1), _x(3), _x(1, r=1)) == [False] * 3
    assert got == [(1, 5, 0), (3, 5, 0), (1, 5, 1)] and not em.counters
    y = np.array([1.0, 2.0])
    assert em.perturb(y) is y and not em.on_idle()


def test_heal_removes_the_fault_and_other_kinds_and_agents_are_ignored():
    em, got, _ = _link()
    _start(em, 0, kind="duplicate", agents=(ME,))
    _start(em, 1, kind="byzantine", mode="nan", agents=(ME + 1,))    # a sender fault of someone else
    _start(em, 2, kind="crash", agents=(ME,))                        # executed by the launcher, not here
    assert set(em.faults) == {0} and em.counters == {"fault_duplicate": 1}
    _admit(em, _x(1))
    assert got == [(1, 5, 0)] * 2
    _start(em, 0, phase="heal", kind="duplicate")
    _admit(em, _x(1, r=1))
    assert got[2:] == [(1, 5, 1)] and not em.faults


@pytest.mark.parametrize("direction, hit", [("both", {1, 3}), ("in", {1, 3}), ("out", set())])
def test_a_link_fault_on_an_agent_acts_on_the_links_by_direction(direction, hit):
    em, got, _ = _link()
    _start(em, kind="duplicate", agents=(ME,), direction=direction)
    _admit(em, _x(1), _x(3))
    assert {s for s in (1, 3) if got.count((s, 5, 0)) == 2} == hit
    em, got, _ = _link()
    _start(em, kind="duplicate", agents=(1,), direction=direction)   # the sender is named
    _admit(em, _x(1), _x(3))
    assert {s for s in (1, 3) if got.count((s, 5, 0)) == 2} == ({1} if direction != "in" else set())


def test_a_link_fault_on_links_acts_on_those_pairs_only():
    em, got, _ = _link()
    _start(em, kind="duplicate", links=((ME, 3), (0, 1)))
    _admit(em, _x(1), _x(3))
    assert got == [(1, 5, 0), (3, 5, 0), (3, 5, 0)]


# ------------------------------------------------------------------ receiver side

def test_duplicate_draws_from_the_netem_generator():
    em, got, _ = _link()
    _start(em, kind="duplicate", agents=(ME,), p=0.5)
    _admit(em, *[_x(1, r=r) for r in range(40)])
    rng = rng_for(SEED, "agent", ME, "netem")
    want = [n for r in range(40) for n in ([(1, 5, r)] * (2 if rng.random() < 0.5 else 1))]
    assert got == want and em.counters["duplicated_payloads"] == len(want) - 40


def test_reorder_holds_one_back_until_its_successor_has_gone_in():
    em, got, _ = _link()
    _start(em, kind="reorder", agents=(ME,), p=1.0)
    _admit(em, _x(1, r=0))
    assert got == []                                  # held back
    _start(em, phase="heal", kind="reorder")
    _admit(em, _x(3, r=0))
    assert got == [(3, 5, 0), (1, 5, 0)]              # after its successor
    _start(em, 1, kind="reorder", agents=(ME,), p=1.0)
    _admit(em, _x(1, r=1))
    assert em.on_idle() and got[-1] == (1, 5, 1)      # nothing else came: let in now
    assert not em.on_idle() and em.counters["reordered_payloads"] == 2


def test_delay_in_ticks_holds_the_payload_past_its_round():
    em, got, _ = _link()
    _start(em, kind="delay", agents=(ME,), delay_ticks=2)
    assert _admit(em, _x(1, k=5, r=3)) == [True]      # held for whole ticks: its round need not wait
    assert got == [] and em.withheld(5, 3) == {1} and em.withheld(5, 2) == ()
    em.release(6)
    assert got == []
    em.release(7)
    assert got == [(1, 5, 3)] and em.withheld(5, 3) == () and em.counters["delayed_payloads"] == 1


def test_delay_in_ticks_with_jitter_draws_uniform_integers_and_zero_is_no_delay():
    em, got, _ = _link()
    _start(em, kind="delay", agents=(ME,), delay_ticks=1, jitter_ticks=1)
    held = _admit(em, *[_x(1, k=5, r=r) for r in range(60)])
    rng = rng_for(SEED, "agent", ME, "netem")
    dt = [1 + int(rng.integers(-1, 2)) for _ in range(60)]
    assert held == [d > 0 for d in dt]
    assert got == [(1, 5, r) for r in range(60) if dt[r] == 0]        # 0 ticks: straight through
    assert em.counters["delayed_payloads"] == sum(d > 0 for d in dt)
    em.release(6)
    assert got[sum(d == 0 for d in dt):] == [(1, 5, r) for r in range(60) if dt[r] == 1]
    em.release(7)
    assert len(got) == 60


def test_delay_in_ms_with_jitter_follows_the_clock():
    em, got, clock = _link()
    _start(em, kind="delay", agents=(ME,), delay_ms=20.0, jitter_ms=15.0)
    assert _admit(em, *[_x(1, r=r) for r in range(20)]) == [False] * 20   # the round waits for them
    rng = rng_for(SEED, "agent", ME, "netem")
    due = [100.0 + max(0.0, 20.0 + rng.uniform(-15.0, 15.0)) / 1000.0 for _ in range(20)]
    assert got == [] and em.withheld(5, 0) == ()
    em.on_timer(100.004)
    assert got == []
    em.on_timer(100.025)
    order = sorted(range(20), key=lambda r: due[r])
    assert got == [(1, 5, r) for r in order if due[r] <= 100.025]
    em.on_timer(101.0)
    assert got == [(1, 5, r) for r in order]
    assert not em.on_idle()                           # a clocked driver: on_idle does not release ms delays


def test_without_a_wall_clock_payloads_delayed_in_ms_come_in_when_idle():
    em, got, _ = _link()
    _start(em, kind="delay", agents=(ME,), delay_ms=5.0)
    _admit(em, _x(1), _x(3))
    assert got == [] and em.on_idle() and got == [(1, 5, 0), (3, 5, 0)] and not em.on_idle()


# ------------------------------------------------------------------ sender side

@pytest.mark.parametrize("mode", ["nan", "huge", "stale", "bias"])
def test_byzantine_payloads(mode):
    em, _, _ = _link()
    _start(em, kind="byzantine", mode=mode, agents=(ME,))
    first = em.corrupt(0, {"a": np.array([1.0, -2.0])})
    second = em.corrupt(0, {"a": np.array([3.0, 4.0])})
    want = {"nan": ([np.nan] * 2, [np.nan] * 2), "huge": ([1e6, -2e6], [3e6, 4e6]),
            "stale": ([1.0, -2.0], [1.0, -2.0]), "bias": ([1.0, -2.0], [3.0, 4.0])}[mode]
    np.testing.assert_array_equal(first["a"], want[0])
    np.testing.assert_array_equal(second["a"], want[1])
    assert em.counters["byzantine_payloads"] == 2


def test_stale_replays_per_round_until_a_heal():
    em, _, _ = _link()
    _start(em, kind="byzantine", mode="stale", agents=(ME,))
    em.corrupt(0, {"a": np.zeros(1)})
    assert em.corrupt(1, {"a": np.ones(1)})["a"][0] == 1.0 and em.corrupt(0, {"a": np.ones(1)})["a"][0] == 0.0
    _start(em, 9, phase="heal", kind="noise")         # any heal of an emulated kind forgets the replay
    assert em.corrupt(0, {"a": np.full(1, 5.0)})["a"][0] == 5.0


def test_byzantine_bias_lies_about_the_measurement():
    em, _, _ = _link()
    y = np.array([1.0, 2.0])
    _start(em, kind="byzantine", mode="bias", bias=(0.5, -1.0), agents=(ME,))
    np.testing.assert_array_equal(em.perturb(y), [1.5, 1.0])
    _start(em, phase="heal", kind="byzantine")
    _start(em, 1, kind="byzantine", mode="bias", magnitude=7.0, agents=(ME,))   # no vector: magnitude everywhere
    np.testing.assert_array_equal(em.perturb(y), [8.0, 9.0])


def test_noise_scales_the_measurement_noise_covariance():
    R = np.array([[0.04, 0.01], [0.01, 0.09]])
    F = noise_factor(LinearSensor(np.eye(2), R))
    np.testing.assert_array_equal(F, np.linalg.cholesky(R))
    em, _, _ = _link(noise=F)
    _start(em, kind="noise", noise_scale=3.0, agents=(ME,))
    y = np.array([1.0, 2.0])
    rng = rng_for(SEED, "agent", ME, "sensor_faults")
    for _ in range(3):
        want = y + np.sqrt(8.0) * (F @ rng.standard_normal(2))
        np.testing.assert_array_equal(em.perturb(y), want)
    _start(em, phase="heal", kind="noise")
    _start(em, 1, kind="noise", noise_scale=0.5, agents=(ME,))   # ≤ 1: nothing to add, nothing drawn
    assert em.perturb(y) is y


def test_outliers_have_the_fault_magnitude_with_probability_p():
    em, _, _ = _link()
    _start(em, kind="outliers", p=0.5, magnitude=30.0, agents=(ME,))
    y = np.zeros(2)
    rng = rng_for(SEED, "agent", ME, "sensor_faults")
    hits = 0
    for _ in range(30):
        out = em.perturb(y)
        if rng.random() < 0.5:
            d = rng.standard_normal(2)
            np.testing.assert_array_equal(out, 30.0 * d / np.linalg.norm(d))
            hits += 1
        else:
            assert out is y
    assert 0 < hits < 30 and em.counters["outliers_injected"] == hits


def test_an_outlier_burst_lasts_its_ticks_and_draws_from_the_outliers_generator():
    em, _, _ = _link()
    em.burst(OutlierBurst("outlier_burst", agent=ME + 1, ticks=5, magnitude=9.0))   # someone else
    y = np.zeros(3)
    assert em.perturb(y) is y
    em.burst(OutlierBurst("outlier_burst", agent=-1, ticks=2, magnitude=4.0))
    rng = rng_for(SEED, "agent", ME, "outliers")
    for _ in range(2):
        d = rng.standard_normal(3)
        np.testing.assert_array_equal(em.perturb(y), 4.0 * d / np.linalg.norm(d))
    assert em.perturb(y) is y and em.counters["outliers_injected"] == 2


def test_same_seed_same_numbers_other_seed_other_numbers():
    def run(seed):
        em, got, _ = _link(seed=seed)
        for fid, ev in enumerate([dict(kind="duplicate", p=0.5), dict(kind="reorder", p=0.5),
                                  dict(kind="delay", delay_ticks=1, jitter_ticks=1),
                                  dict(kind="noise", noise_scale=2.0), dict(kind="outliers", p=0.5)]):
            _start(em, fid, agents=(ME,), **ev)
        ys = [em.perturb(np.zeros(2)) for _ in range(10)]
        for k in range(5, 10):
            em.release(k)
            _admit(em, *[_x(j, k=k, r=r) for j in (1, 3) for r in range(3)])
        em.on_idle()
        return got, np.array(ys), dict(em.counters)

    a, b, c = run(1), run(1), run(2)
    assert a[0] == b[0] and np.array_equal(a[1], b[1]) and a[2] == b[2]
    assert a[0] != c[0] and not np.array_equal(a[1], c[1])


# ------------------------------------------------------------------ typed events, purity

@pytest.mark.parametrize("args", [
    {"id": 1, "kind": "delay", "phase": "start", "links": [1.0]},                   # not pairs
    {"id": True, "kind": "delay", "phase": "start"},
    {"id": 1, "kind": "delay", "phase": "later"},
    {"id": 1, "kind": "meteor", "phase": "start"},
    {"id": 1, "kind": "delay", "phase": "start", "delay_ticks": 5000},
    {"id": 1, "kind": "delay", "phase": "start", "jitter_ms": -1.0},
    {"id": 1, "kind": "noise", "phase": "start", "noise_scale": "x"},
    {"id": 1, "kind": "duplicate", "phase": "start", "p": 1.5},
    {"id": 1, "kind": "byzantine", "phase": "start", "mode": "lies"},
    {"id": 1, "kind": "byzantine", "phase": "start", "bias": [1.0, "x"]},
    {"id": 1, "kind": "delay", "phase": "start", "direction": "sideways"},
    {"id": 1, "kind": "delay", "phase": "start", "agents": [0.5]},
])
def test_a_malformed_fault_event_is_refused_by_the_wire_and_counted_by_the_sensor(args):
    from types import SimpleNamespace

    from agent.bus import LocalBus
    from agent.roles.sensor import SensorRole

    with pytest.raises(wire.WireError) as e:
        wire.fault_event(args)
    assert e.value.reason == "bad_field"
    est = SimpleNamespace(x=np.zeros(2), P=None, rounds=1)    # never runs a tick here
    role = SensorRole(ME, 3, 0.1, est, LinearSensor(np.ones((1, 2)), np.eye(1)), rng=rng_for(0, "agent", ME),
                      q0=np.zeros(2))
    bus = LocalBus()
    role.attach(bus)
    bus.publish("world/event", wire.Control(verb="fault", args=args))
    bus.publish("world/event", wire.Control(verb="fault", args={"id": 4, "kind": "duplicate", "phase": "start",
                                                                "agents": [float(ME)]}))
    bus.drain()
    # counted by the sensor (or, for what a Control cannot even carry, dropped by the bus) — never raised
    assert role.counters["rejected_events"] + bus.stats.dropped["bad_field"] == 1 and bus.stats.handler_errors == 0
    assert list(role.link.faults) == [4]


def test_the_module_is_pure():
    code = ("import sys, agent.link_emulation; bad = {'msgpack', 'zenoh', 'agent.bus', 'agent.wire', 'orjson'}; "
            "print(sorted(bad & set(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
