"""flocktrack/launch/status.py StatusBoard, the numbers of ``flocktrack run``'s status line, fed real wire
messages on a LocalBus — no run, no router."""

import numpy as np
import pytest
from wire_messages import estimate, send, tick

from agent.bus import LocalBus
from agent.wire import End, Truth
from flocktrack.launch.status import StatusBoard

LINKS = [[1], [0, 2], [1]]


class Clock:
    """The times the board stamps ticks with, set by the test."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def board(**kw) -> tuple[StatusBoard, LocalBus, Clock]:
    clock = Clock()
    b = StatusBoard(kw.pop("ticks", 100), 3, 2, clock=clock, **kw)
    bus = LocalBus()
    b.subscribe(bus)
    return b, bus, clock


def test_before_the_first_tick_the_line_counts_the_run_processes_up_but_not_the_launcher():
    b, _, _ = board(processes=5)
    for name in ("launcher/0", "world/0", "agent/0", "agent/1"):
        b.on_member(name, True)
    b.on_member("agent/1", False)
    assert b.line() == "starting · 2/5 processes up"


def test_the_line_tells_the_tick_its_rate_the_rmse_the_deadlines_and_the_sensors_alive():
    b, bus, clock = board(target_rate=10.0, deadlines=lambda: 2)
    for k, at in ((1, 0.0), (2, 0.1), (3, 0.2)):
        clock.now = at
        send(bus, "world/tick", tick(k, LINKS, alive=[True, False, True]))
    send(bus, "target/truth", Truth(k=3, x=np.zeros(4)))
    send(bus, "agent/0/estimate", estimate(0, 3, [3.0, 0.0, 0.0, 0.0]))
    send(bus, "agent/2/estimate", estimate(2, 3, [0.0, 4.0, 9.0, 9.0]))     # (velocity errors are not counted)
    assert b.line() == "tick 3/100 · 10.0 ticks/s (target 10.0) · RMSE 3.54 · deadlines 2 · sensors 2/3"


def test_the_rmse_waits_for_both_the_truth_and_an_estimate_of_a_tick():
    b, bus, _ = board()
    send(bus, "world/tick", tick(0, LINKS))
    send(bus, "agent/1/estimate", estimate(1, 0, [1.0, 0.0, 0.0, 0.0]))
    assert b.rmse is None and "RMSE –" in b.line()
    send(bus, "target/truth", Truth(k=0, x=np.zeros(4)))
    assert b.rmse == pytest.approx(1.0)


def test_an_estimate_of_another_shape_is_left_out_of_the_rmse():
    b, bus, _ = board()
    send(bus, "target/truth", Truth(k=0, x=np.zeros(4)))
    send(bus, "agent/0/estimate", estimate(0, 0, [2.0, 0.0, 0.0, 0.0]))
    send(bus, "agent/1/estimate", estimate(1, 0, [50.0, 0.0]))
    assert b.rmse == pytest.approx(2.0)


def test_the_rate_is_unknown_until_two_ticks_have_come():
    b, bus, _ = board()
    send(bus, "world/tick", tick(0, LINKS))
    assert b.rate() is None and "– ticks/s" in b.line()


def test_an_older_tick_arriving_late_does_not_take_the_line_back():
    b, bus, _ = board()
    send(bus, "world/tick", tick(5, LINKS))
    send(bus, "world/tick", tick(3, LINKS, alive=[False, False, False]))
    assert b.k == 5 and b.alive == 3
    assert b.line().startswith("tick 5/100 ")


def test_a_realtime_run_well_below_its_rate_is_said_to_be_behind_after_its_first_ticks():
    b, bus, clock = board(target_rate=25.0)
    for k in range(12):
        clock.now = 0.1 * k                     # 10 ticks/s of the 25 asked for
        send(bus, "world/tick", tick(k, LINKS))
    assert b.rate() == pytest.approx(10.0)
    assert b.line().endswith(" · behind realtime")


def test_a_lockstep_run_is_never_behind():
    b, bus, clock = board()
    for k in range(12):
        clock.now = 10.0 * k
        send(bus, "world/tick", tick(k, LINKS))
    assert "behind" not in b.line() and "(target" not in b.line()


def test_once_the_world_ends_the_line_counts_every_tick_done():
    b, bus, _ = board(ticks=40, processes=5)
    send(bus, "world/tick", tick(37, LINKS))
    send(bus, "world/end", End(k=40))
    assert b.done and b.line().startswith("tick 40/40 ")


def test_a_realtime_run_that_misses_rounds_is_told_what_to_do_once_a_window():
    """3 sensors, 5 rounds, 10 ticks/s: a window of 10 s holds 1 500 rounds; 180 missed (12 %) is warned
    about, with the numbers and what to change; 30 (2 %) is not; a lockstep run never is."""
    missed = {"n": 0}
    b, bus, clock = board(target_rate=10.0, rounds=5, deadlines=lambda: missed["n"])
    k = 0
    warnings = []
    for window_missed in (180, 30):
        for _ in range(100):
            clock.now += 0.1
            k += 1
            send(bus, "world/tick", tick(k, LINKS))
            missed["n"] += window_missed // 100 + (1 if _ < window_missed % 100 else 0)
            warnings.append(b.pace_warning())
        clock.now += 0.1
        warnings.append(b.pace_warning())
    said = [w for w in warnings if w]
    assert len(said) == 1, said
    assert said[0].startswith("12 % of rounds missed in the last 10 s") and "lower run.speed or sensors.n" in said[0]
    # no round missed, but the clock yielded: 4 ticks/s kept of 10
    slow, bus3, clock3 = board(target_rate=10.0, rounds=5, deadlines=lambda: 0)
    said = []
    for k in range(1, 60):
        clock3.now += 0.25
        send(bus3, "world/tick", tick(k, LINKS))
        said.append(slow.pace_warning())
    said = [w for w in said if w]
    assert len(said) == 1 and said[0].startswith("4.0 of 10.0 ticks/s in the last 10 s"), said
    assert "lower run.speed or sensors.n" in said[0]
    lock, bus2, clock2 = board(rounds=5, deadlines=lambda: 10 ** 6)
    for k in range(1, 300):
        clock2.now += 0.1
        send(bus2, "world/tick", tick(k, LINKS))
        assert lock.pace_warning() is None
