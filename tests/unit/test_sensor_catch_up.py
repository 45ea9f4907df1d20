"""A realtime sensor that falls behind the world's clock skips to the newest tick instead of working
through stale ones (agent/roles/sensor.py ``_skip_stale``); a lockstep one never skips."""

from __future__ import annotations

from pathlib import Path

from agent.assemble import build_sensor, build_target
from agent.bus import LocalBus
from agent.scenario import parse_scenario, scenario_data
from topology.world import build_world

SCEN = Path(__file__).resolve().parents[2] / "scenarios"


def _behind(mode: str) -> tuple[object, list[tuple[str, int]]]:
    """Sensor 0 alone with the world and the target: its neighbours never answer, so tick 0's rounds
    end only by deadline — and meanwhile the world's clock announces ticks 1, 2 and 3."""
    data = scenario_data(str(SCEN / "gu_hu_normal.toml"), [], **{"run.ticks": 8, "run.mode": mode})
    sc = parse_scenario(data, "gu_hu_normal.toml")
    bus = LocalBus()
    w, tgt, s0 = build_world(sc, realtime=mode == "realtime"), build_target(sc), build_sensor(sc, 0)
    for r in (w, tgt, s0):
        r.attach(bus)
    pubs: list[tuple[str, int]] = []
    bus.subscribe("agent/0/**", lambda key, m: pubs.append((key.split("/")[-1], m.k)))
    w.start()
    bus.drain()
    assert s0.k == 0 and s0.waiting and s0._nbrs, "sensor 0 should be waiting for its neighbours in tick 0"
    for k in range(1, 4):          # three more ticks announced while tick 0 is under way
        if mode == "realtime" and k > 1:
            w.on_timer(1e3 + k * 10.0)      # (the clock, started at 1e3 after tick 0)
        else:
            w.on_deadline()        # (lockstep, and realtime's warm-up tick 0: only the dead-process guard
            w.on_timer(1e3)        # moves the world without our state)
        bus.drain()
    while s0.k == 0:               # tick 0's rounds close by deadline
        s0.on_deadline()
        bus.drain()
    return s0, pubs


def test_a_realtime_sensor_behind_the_clock_takes_up_the_newest_tick():
    s0, pubs = _behind("realtime")
    assert s0.counters["skipped_ticks"] == 2
    assert s0.k == 3 and s0.waiting                     # in tick 3's rounds now
    assert sorted({k for what, k in pubs if what == "xchg"}) == [0, 3]
    assert [k for what, k in pubs if what == "state"] == [0]   # nothing published for the skipped ticks


def test_a_lockstep_sensor_never_skips():
    s0, pubs = _behind("lockstep")
    assert s0.counters["skipped_ticks"] == 0 and s0.k == 1
    assert sorted({k for what, k in pubs if what == "xchg"}) == [0, 1]


def test_a_missed_round_names_the_neighbours_it_waited_for():
    """The driver's ``deadline on (k, r)`` line says whose payload did not come (agent/runner.py logs
    :meth:`Role.waiting_for`)."""
    data = scenario_data(str(SCEN / "gu_hu_normal.toml"), [], **{"run.ticks": 8, "run.mode": "lockstep"})
    sc = parse_scenario(data, "gu_hu_normal.toml")
    bus = LocalBus()
    w, tgt, s0 = build_world(sc), build_target(sc), build_sensor(sc, 0)
    for r in (w, tgt, s0):
        r.attach(bus)
    w.start()
    bus.drain()
    assert s0.waiting and s0._nbrs
    said = s0.waiting_for()
    assert said == " — no payload from " + ", ".join(f"agent/{j}" for j in s0._nbrs), said
    assert w.waiting_for() == ""          # (a role that does not say)


def test_a_sensors_rounds_end_within_a_window_from_the_ticks_arrival():
    """:meth:`SensorRole.step_anchor` is the moment the world's tick reached it — also when the sensor begins
    the tick later (here: tick 3, announced while tick 0's rounds were still waiting), so a late sensor gets
    what is left of the tick's window, not a new schedule (agent/runner.py ``WaitBudget.window_s``)."""
    import time

    t0 = time.monotonic()
    s0, _pubs = _behind("realtime")
    t1 = time.monotonic()
    assert s0.k == 3 and s0.waiting
    anchor = s0.step_anchor(3)
    assert anchor is not None and t0 <= anchor <= t1
    assert s0.step_anchor(0) is None            # a tick gone by is forgotten with its messages
    assert s0.step_anchor(99) is None           # a tick not seen yet has no anchor
