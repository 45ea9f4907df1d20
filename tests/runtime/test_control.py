"""The control plane (control/**): world-side link faults and pause/step, launcher-side kill/restart,
sensor-side outlier bursts — unit-level on the world, then end to end over Zenoh."""

import json
import time
from pathlib import Path

import numpy as np
import pytest

from agent.bus import LocalBus
from agent.scenario import load_scenario, parse_scenario
from agent.scenario import scenario_data
from flocktrack.record.reader import read_recording
from flocktrack.engine.run import run_zenoh_to_dir
from topology.world import build_world

from control_plan import ControlPlan

SCEN = Path(__file__).resolve().parents[2] / "scenarios"


def _links(t):
    return {(i, j) for i, nb in enumerate(t.links) for j in nb if i < j}


def test_world_link_faults_and_heal():
    sc = load_scenario(SCEN / "gu_hu_normal.toml")
    w = build_world(sc)
    w.attach(LocalBus())
    base = _links(w.make_tick(0))
    a, b = sorted(base)[0]
    assert w.apply_control("link_drop", {"a": a, "b": b})
    assert (a, b) not in _links(w.make_tick(0))
    groups = [0] * 5 + [1] * 5
    assert w.apply_control("partition", {"groups": groups})
    t = w.make_tick(0)
    assert all(groups[i] == groups[j] for i, j in _links(t))
    assert w.apply_control("heal", {})
    assert _links(w.make_tick(0)) == base
    assert w.apply_control("link_loss", {"p": 0.5})
    lossy = [len(_links(w.make_tick(0))) for _ in range(50)]
    assert 0.3 * len(base) < np.mean(lossy) < 0.7 * len(base)
    assert not w.apply_control("link_loss", {"p": 3.0})      # rejected, not applied
    assert not w.apply_control("link_drop", {"a": 0, "b": 99})
    assert not w.apply_control("no_such_verb", {})


def test_late_states_are_each_counted_and_logged_a_line_a_second(caplog):
    """An overloaded flock's states arrive after their tick closed by the hundred: every one is counted, the
    log gets one line (with the count) per second, not one per state."""
    import logging

    from agent.wire import State

    sc = load_scenario(SCEN / "gu_hu_normal.toml")
    w = build_world(sc)
    w.attach(LocalBus())
    w.k = 5
    with caplog.at_level(logging.INFO, logger="topology.world"):
        for i in range(300):
            w._on_state("agent/1/state", State(src=1, k=i % 5, pos=np.zeros(2), vel=np.zeros(2)))
    assert w.stats["late_states"] == 300
    lines = [r.getMessage() for r in caplog.records if "after their tick closed" in r.getMessage()]
    assert len(lines) == 1 and ": 1 since the last such line" in lines[0]


def test_a_paused_realtime_world_holds_its_clock_through_deadlines():
    sc = load_scenario(SCEN / "gu_hu_normal.toml")
    w = build_world(sc, realtime=True)
    w.attach(LocalBus())
    w.start()
    w.on_timer(0.0)
    assert w.k == 0                        # tick 0, the warm-up, waits for its states, not the clock
    w.on_timer(5 * w.period)
    assert w.k == 0
    w.on_deadline()                        # (no sensor here: the guard closes it) — the clock starts at
    w.on_timer(0.0)                        # the next timer: tick 1 closes a period later
    k0 = w.k
    assert k0 == 1
    assert w.apply_control("pause", {})
    w.on_timer(0.5 * w.period)             # paused half-way through tick 1
    for s in range(1, 50):                 # wall time passes, deadlines fire: nothing moves
        w.on_timer(s * 10 * w.period)
        w.on_deadline()
    assert w.k == k0
    assert w.apply_control("resume", {})
    w.on_timer(490.4 * w.period)        # resumed: tick 1 still has half a period to go
    assert w.k == k0
    w.on_timer(490.8 * w.period)
    assert w.k == k0
    w.on_timer(491.0 * w.period)
    assert w.k == k0 + 1
    w.on_deadline()                        # unpaused, the guard works again
    assert w.k == k0 + 2


def test_a_realtime_world_held_up_slips_its_clock_instead_of_shortening_the_next_tick():
    sc = load_scenario(SCEN / "gu_hu_normal.toml")
    w = build_world(sc, realtime=True)
    w.attach(LocalBus())
    w.start()
    for i in range(w.n):                   # no sensor here (none whose missing state would stretch the clock)
        w.on_member("agent", i, False)
    w.on_deadline()                        # the warm-up tick 0 (closed by the guard)
    w.on_timer(0.0)                        # the clock starts: tick 1 closes at 1.0 period
    w.on_timer(0.99 * w.period)
    assert w.k == 1
    w.on_timer(1.04 * w.period)            # 4 % late: on time enough, no slip
    assert w.k == 2 and "clock_slips" not in w.stats
    w.on_timer(2.5 * w.period)             # tick 2 closes half a period late (this process was held up) ...
    assert w.k == 3 and w.stats["clock_slips"] == 1
    assert w.stats["clock_slip_ms_max"] == pytest.approx(500 * w.period, abs=0.1)
    w.on_timer(3.4 * w.period)             # ... so tick 3 still gets a whole period: it closes at 3.5, not 3.0
    assert w.k == 3
    w.on_timer(3.5 * w.period)
    assert w.k == 4


def test_a_realtime_world_whose_flock_runs_out_of_its_period_stretches_the_next_and_then_comes_back():
    """topology/pace.py in the world: no state by the clock → the next tick lasts 1.5 periods and says so
    (Tick.period, which the sensors fit their rounds into); every state at once → on its way back."""
    from agent.wire import State
    from topology.pace import RELAX, STRETCH

    sc = load_scenario(SCEN / "gu_hu_normal.toml")
    w = build_world(sc, realtime=True, adaptive_pace=True)
    bus = LocalBus()
    ticks = []
    bus.subscribe("world/tick", lambda key, m: ticks.append(m))
    w.attach(bus)
    w.start()
    w.on_deadline()                        # the warm-up tick 0 (nobody answers: closed by the guard)
    w.on_timer(0.0)                        # the clock starts: tick 1 closes at 1.0 period
    nominal = w.period
    w.on_timer(1.0 * nominal)              # tick 1 closes without a single state
    bus.drain()
    assert w.k == 2 and ticks[-1].k == 2 and ticks[-1].period == pytest.approx(STRETCH * nominal)
    assert w.stats["pace_stretched_ticks"] == 1 and w.stats["missing_states"] == 2 * w.n
    w.on_timer(2.0 * nominal)              # tick 2 now lasts 1.5 periods: not closed yet ...
    assert w.k == 2
    for i in range(w.n):                   # ... and every state comes at once
        bus.publish(f"agent/{i}/state", State(src=i, k=2, pos=np.zeros(2), vel=np.zeros(2)))
    bus.publish("target/state", State(k=2, pos=np.zeros(2), vel=np.zeros(2)))
    bus.drain()
    w.on_timer(2.5 * nominal)
    bus.drain()
    back = RELAX * STRETCH * nominal       # on its way back, by at most RELAX a tick
    assert w.k == 3 and ticks[-1].period == pytest.approx(back)
    assert w.stats["pace_max_stretch"] == pytest.approx(STRETCH)
    w.on_timer(2.5 * nominal + 0.95 * back)
    assert w.k == 3
    w.on_timer(2.5 * nominal + back)
    assert w.k == 4


def test_controls_end_to_end_over_zenoh(tmp_path):
    data = scenario_data(str(SCEN / "gu_hu_normal.toml"), [], **{"run.ticks": 160, "run.mode": "lockstep"})
    sc = parse_scenario(data, "gu_hu_normal.toml")
    plan = {20: ("link_drop", {"a": 0, "b": 1}), 40: ("partition", {"groups": [0.0] * 5 + [1.0] * 5}),
            60: ("heal", {}), 70: ("kill", {"agent": 3}), 100: ("restart", {"agent": 3}),
            110: ("outlier_burst", {"agent": 4, "ticks": 5, "magnitude": 50.0}), 120: ("pause", {})}
    ctl = ControlPlan(plan)

    def hook(launcher):
        ctl(launcher)
        paused = ctl.sent_at.get("pause")
        if paused is not None and "resume" not in ctl.sent_at and time.monotonic() - paused > 1.5:
            ctl.send("resume")

    try:
        summary, info = run_zenoh_to_dir(sc, data, tmp_path, quiet=True, on_poll=hook, timeout_s=300)
    finally:
        ctl.close()
    assert info["rc"] == 0
    rec = read_recording(tmp_path / "recording.mcap")
    events = {m.verb: m.k for key, m, _ in rec.messages if key == "world/event"}
    assert {"link_drop", "partition", "heal", "pause", "resume"} <= set(events), events
    ticks = {m.k: m for key, m, _ in rec.messages if key == "world/tick"}
    assert (0, 1) not in _links(ticks[events["link_drop"]])
    tp = ticks[events["partition"]]
    assert all((i < 5) == (j < 5) for i, j in _links(tp))
    th = ticks[events["heal"] + 1]
    assert any((i < 5) != (j < 5) for i, j in _links(th))
    # kill/restart by the launcher: the world saw agent 3 leave and come back
    alive3 = [ticks[k].alive[3] for k in sorted(ticks)]
    assert not all(alive3) and alive3[-1]
    assert any(key == "control/kill" for key, _, _ in rec.messages)
    # the outlier burst shows in agent 4's measurements
    y4 = {m.k: m.y for key, m, _ in rec.messages if key == "agent/4/meas"}
    truth = {m.k: m.x for key, m, _ in rec.messages if key == "target/truth"}
    big = [k for k in y4 if np.linalg.norm(y4[k] - truth[k][:2]) > 40]
    assert 1 <= len(big) <= 5 and min(big) >= 110
    stats = json.loads((tmp_path / "stats" / "world-0.json").read_text())["role"]
    assert stats["controls"] >= 5
