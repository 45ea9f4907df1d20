"""agent/roles/target.py on a real LocalBus with real wire messages: what the target publishes for a tick,
how an intelligent target waits for the trackers' estimates, and what it does with ticks it never got."""

import numpy as np
import pytest
from wire_messages import Heard, estimate, send, tick

from agent.bus import LocalBus
from agent.models import IntelligentTarget, LinearTarget, double_integrator
from agent.roles.target import TargetRole
from agent.wire import Control

T = 0.1
A, B = double_integrator(T)
X0 = np.array([1.0, 2.0, 1.0, 0.0])      # at (1, 2), moving along x at 1 m/s
KE = 0.5
LINKS3 = [[1], [0, 2], [1]]


def on_bus(role: TargetRole) -> tuple[LocalBus, Heard]:
    bus = LocalBus()
    role.attach(bus)
    return bus, Heard(bus, "target/truth", "target/state")


def normal(ticks: int = 5) -> TargetRole:
    still = LinearTarget(A, B, np.zeros((2, 2)), X0, np.random.default_rng(0))    # no process noise: w = 0
    return TargetRole(ticks, still, False, 2, T=T)


def intelligent(source: str = "mean") -> TargetRole:
    return TargetRole(5, IntelligentTarget(A, KE, X0), True, 2, estimate_source=source, T=T)


def pushed(xhat) -> np.ndarray:
    """Gu & Hu's intelligent move x⁺ = A x + kₑ (x − x̂) from X0."""
    return A @ X0 + KE * (X0 - np.asarray(xhat, float))


def test_a_normal_target_publishes_its_truth_then_its_state_after_the_move():
    role = normal()
    bus, heard = on_bus(role)
    send(bus, "world/tick", tick(0, LINKS3))
    assert [k for k, _ in heard.got] == ["target/truth", "target/state"]
    truth, state = heard.on("target/truth")[0], heard.on("target/state")[0]
    assert truth.k == 0 and truth.t == pytest.approx(0.0)
    np.testing.assert_array_equal(truth.x, X0)
    assert state.k == 0
    np.testing.assert_allclose(state.pos, (A @ X0)[:2])
    np.testing.assert_allclose(state.vel, (A @ X0)[2:])
    np.testing.assert_array_equal(state.w, [0.0, 0.0])   # the disturbance it drew (zero: Q = 0)
    assert role.k == 1


def test_an_intelligent_target_waits_for_every_alive_trackers_estimate_then_moves_against_their_mean():
    role = intelligent()
    bus, heard = on_bus(role)
    send(bus, "world/tick", tick(0, LINKS3))
    assert len(heard.on("target/truth")) == 1 and role.waiting
    send(bus, "agent/0/estimate", estimate(0, 0, [0.0, 2.0, 1.0, 0.0]))
    send(bus, "agent/2/estimate", estimate(2, 0, [2.0, 0.0, 1.0, 0.0]))
    assert heard.on("target/state") == []                     # agent 1's is still missing
    send(bus, "agent/1/estimate", estimate(1, 0, [1.0, 1.0, 1.0, 3.0]))
    (state,) = heard.on("target/state")
    np.testing.assert_allclose(state.pos, pushed([1.0, 1.0, 1.0, 1.0])[:2])
    np.testing.assert_allclose(state.vel, pushed([1.0, 1.0, 1.0, 1.0])[2:])
    assert not role.waiting


@pytest.mark.parametrize("how", ["the world lists it dead", "its process vanished", "the deadline passed"])
def test_an_intelligent_target_moves_against_the_estimates_that_came_once_it_stops_waiting_for_one(how):
    role = intelligent()
    bus, heard = on_bus(role)
    send(bus, "world/tick", tick(0, LINKS3, alive=[True, True, how != "the world lists it dead"]))
    send(bus, "agent/0/estimate", estimate(0, 0, [0.0, 2.0, 0.0, 0.0]))
    send(bus, "agent/1/estimate", estimate(1, 0, [2.0, 0.0, 0.0, 0.0]))
    if how != "the world lists it dead":
        assert heard.on("target/state") == []            # agent 2's estimate is still awaited
    if how == "its process vanished":
        role.on_member("agent", 2, False)
    elif how == "the deadline passed":
        role.on_deadline()
    bus.drain()
    (state,) = heard.on("target/state")
    np.testing.assert_allclose(state.pos, pushed([1.0, 1.0, 0.0, 0.0])[:2])


def test_without_any_estimate_the_target_is_not_pushed():
    role = intelligent()
    bus, heard = on_bus(role)
    send(bus, "world/tick", tick(0, LINKS3))
    role.on_deadline()
    bus.drain()
    np.testing.assert_allclose(heard.on("target/state")[0].pos, (A @ X0)[:2])


def test_an_estimate_of_another_tick_does_not_count_for_this_one():
    role = intelligent(source="node:1")
    bus, heard = on_bus(role)
    send(bus, "world/tick", tick(0, LINKS3))
    send(bus, "agent/1/estimate", estimate(1, 1, [0.0, 0.0, 0.0, 0.0]))      # tick 1's, early
    assert heard.on("target/state") == [] and role.waiting


def test_a_target_told_to_follow_one_node_moves_against_that_nodes_estimate_alone():
    role = intelligent(source="node:1")
    bus, heard = on_bus(role)
    send(bus, "world/tick", tick(0, LINKS3))
    send(bus, "agent/0/estimate", estimate(0, 0, [9.0, 9.0, 9.0, 9.0]))
    assert heard.on("target/state") == []
    send(bus, "agent/1/estimate", estimate(1, 0, [0.0, 1.0, 0.0, 1.0]))
    np.testing.assert_allclose(heard.on("target/state")[0].pos, pushed([0.0, 1.0, 0.0, 1.0])[:2])


def test_ticks_the_target_never_got_are_stepped_through_without_a_truth():
    role = normal()
    bus, heard = on_bus(role)
    send(bus, "world/tick", tick(0, LINKS3))
    send(bus, "world/tick", tick(3, LINKS3))         # ticks 1 and 2 were lost on the way
    assert [m.k for m in heard.on("target/truth")] == [0, 3]
    np.testing.assert_allclose(heard.on("target/truth")[1].x, np.linalg.matrix_power(A, 3) @ X0)
    assert [m.k for m in heard.on("target/state")] == [0, 3]


def test_a_tick_beyond_the_run_is_refused_and_counted():
    role = normal(ticks=2)
    bus, heard = on_bus(role)
    send(bus, "world/tick", tick(2, LINKS3))
    assert heard.got == [] and role.counters["rejected_ticks"] == 1


def test_while_an_evade_fault_is_active_the_target_turns_hard_across_its_velocity():
    role = normal()
    bus, heard = on_bus(role)
    start = {"id": 4, "kind": "evade", "phase": "start", "accel": 2.0}
    send(bus, "world/event", Control(verb="fault", args=start))
    send(bus, "world/tick", tick(0, LINKS3))
    a = 2.0 * np.array([0.0, 1.0])                  # ⟂ to the velocity (1, 0)
    plain = A @ X0
    np.testing.assert_allclose(heard.on("target/state")[0].pos, plain[:2] + 0.5 * T * T * a)
    np.testing.assert_allclose(heard.on("target/state")[0].vel, plain[2:] + T * a)
    send(bus, "world/event", Control(verb="fault", args={**start, "phase": "heal"}))
    before = heard.on("target/truth")[0].x
    send(bus, "world/tick", tick(1, LINKS3))
    x1 = heard.on("target/truth")[1].x
    assert not np.allclose(x1, A @ before)          # (the turn of tick 0 is in the truth of tick 1)
    np.testing.assert_allclose(heard.on("target/state")[1].pos, (A @ x1)[:2])   # healed: a plain move
