"""The declared wait budgets of the node loop (agent/runner.py ``WaitBudget``, agent/__main__.py
``role_budget``): lockstep waits only catch dead processes; in realtime a sensor's exchange rounds share the
period as a slot schedule anchored at the tick's start and bounded by a window from the tick's arrival, round 0
with a head start, the target's wait for the estimates ends before the world's clock closes the tick, and the
warm-up tick 0 waits long."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from agent.__main__ import TAIL_MAX_S, role_budget
from agent.runner import WaitBudget
from agent.scenario import parse_scenario, scenario_data

SCEN = Path(__file__).resolve().parents[2] / "scenarios"


def _demo(**over):
    return parse_scenario(scenario_data(str(SCEN / "demo.toml"), [], **over), "demo.toml")


def test_a_scheduled_round_inherits_the_time_an_earlier_round_left_unused():
    b = WaitBudget(0.01, schedule=True, head=1)
    # round 0 due two slots after the tick began, whenever the wait itself began
    assert b.due((5, 0), began=100.0, step_began=100.0) == pytest.approx(100.02)
    # round 0 closed fast (at +1 ms): round 1 is still due at +30 ms, not 10 ms after it began
    assert b.due((5, 1), began=100.001, step_began=100.0) == pytest.approx(100.03)
    # a per-wait budget (lockstep) counts from each wait's own start
    assert WaitBudget(5.0).due((5, 1), began=100.001, step_began=100.0) == pytest.approx(105.001)
    # the window: a step learned of at 99.95 (its tick came) but begun at 100.0 ends its waits by 99.95 + 0.08
    w = WaitBudget(0.01, schedule=True, head=1, window_s=0.08)
    assert w.due((5, 0), 100.0, 100.0, anchor=99.95) == pytest.approx(100.02)     # round 0 fits in the window
    assert w.due((5, 2), 100.03, 100.0, anchor=99.95) == pytest.approx(100.03)    # round 2 is cut to it
    assert w.due((5, 2), 100.03, 100.0) == pytest.approx(100.04)                  # no anchor: no window
    # the last round (final) waits until the window's end, whatever its slot; the rounds before it keep theirs
    f = WaitBudget(0.01, schedule=True, head=1, window_s=0.08, final=2)
    assert f.due((5, 1), 100.0, 100.0, anchor=99.99) == pytest.approx(100.03)
    assert f.due((5, 2), 100.0, 100.0, anchor=99.99) == pytest.approx(100.07)    # its slot: 100.04
    assert f.due((5, 2), 100.0, 100.0) == pytest.approx(100.04)                  # no anchor: its slot
    assert f.scaled(None).final == 2 and replace(f, period_s=1.0).scaled(2.0).final == 2
    # every wait of tick 0 gets the warm-up budget, scheduled or not
    assert WaitBudget(0.01, schedule=True, head=1, warmup_s=0.5).due((0, 2), 7.0, 1.0) == pytest.approx(7.5)


def test_realtime_budgets_fit_the_sensors_rounds_and_the_targets_wait_into_one_period():
    for speed in (1.0, 0.4):          # the demo at 25 Hz, and at 10 Hz (bench/bench_capacity.py)
        sc = _demo(**{"run.speed": speed})
        period, R = sc.run.T / sc.run.speed, sc.estimator.rounds
        s, t = role_budget(sc, "realtime", "sensor"), role_budget(sc, "realtime", "target")
        last_round, target = s.due((3, R - 1), 0.0, 0.0), t.due((3, 0), 0.0, 0.0)
        tail = period - last_round
        assert tail == pytest.approx(min(2 * period / (R + 3), TAIL_MAX_S))
        assert s.due((3, 0), 0.0, 0.0) == pytest.approx(2 * (period - tail) / (R + 1))   # round 0: two slots
        assert last_round < target < period                # the estimates in, then the target moves
        assert period - target == pytest.approx(tail / 2)  # and its state has half the tail to reach the world
        assert s.due((0, 0), 0.0, 0.0) == t.due((0, 0), 0.0, 0.0) == pytest.approx(2 * period)
        # the last round ends where the target stops waiting — for a sensor that began the tick as it came, and
        # for one that began it 0.3 periods later; the rounds before it end on their slots
        assert s.due((3, R - 1), 0.0, 0.0, anchor=0.0) == pytest.approx(target)
        assert s.due((3, R - 1), 0.3 * period, 0.3 * period, anchor=0.0) == pytest.approx(target)
        assert s.due((3, R - 2), 0.0, 0.0, anchor=0.0) == pytest.approx(R * (period - tail) / (R + 1))
    lock = role_budget(sc, "lockstep", "sensor")
    assert not lock.schedule and lock.slot_s == sc.run.deadline_s and lock.warmup_s is None
    # an outer wait outlasts the ones inside it: the target's outlasts a sensor's whole tick, the world's the target's
    from agent.roles.target import TargetRole
    from topology.world import WorldRole

    target = role_budget(sc, "lockstep", "target", depth=TargetRole.wait_depth).slot_s
    world = role_budget(sc, "lockstep", "world", depth=WorldRole.wait_depth).slot_s
    assert (R + 1) * lock.slot_s < target < world


def test_a_stretched_tick_gives_every_round_and_the_targets_wait_its_share_of_the_longer_period():
    sc = _demo(**{"run.speed": 0.4})
    R = sc.estimator.rounds
    s, t = role_budget(sc, "realtime", "sensor"), role_budget(sc, "realtime", "target")
    for factor in (2.5, 0.5):        # the world stretched under overload; a live speed-up
        p = s.period_s * factor
        s2, t2 = s.scaled(p), t.scaled(p)
        for r in range(R):
            assert s2.due((3, r), 0.0, 0.0) == pytest.approx(factor * s.due((3, r), 0.0, 0.0))
        assert s2.due((3, R - 1), 0.0, 0.0, anchor=0.0) == pytest.approx(t2.due((3, 0), 0.0, 0.0))
        assert s2.due((3, R - 2), 0.0, 0.0, anchor=0.0) < t2.due((3, 0), 0.0, 0.0) < p
        assert s2.due((0, 0), 0.0, 0.0) == s.due((0, 0), 0.0, 0.0)          # the warm-up as it was
    assert s.scaled(None) is s and s.scaled(0.0) is s and s.scaled(-1.0) is s   # no period announced: nominal
    # a hostile tick's period is bounded: a sensor neither waits for ever nor not at all
    assert s.scaled(1e9).slot_s == pytest.approx(WaitBudget.MAX_SCALE * s.slot_s)
    assert s.scaled(1e-9).slot_s == pytest.approx(s.slot_s / WaitBudget.MAX_SCALE)
    lock = role_budget(sc, "lockstep", "sensor")
    assert lock.scaled(1.0) is lock       # lockstep waits do not follow a period
