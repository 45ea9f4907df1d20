"""The realtime world's pace under overload (topology/pace.py): the period stretches while the flock as a whole
runs out of it, comes back by steps once it does not, to about what the flock needs; a few sensors that wait
out a round, or one dead sensor, do not slow the flock."""

from __future__ import annotations

import math

import pytest

from topology.pace import BUSY, IDLE, MAX_STRETCH, RELAX, STRETCH, PaceGovernor, arrival_quantile


def test_the_period_stretches_while_the_flock_runs_out_of_it_and_comes_back_when_it_does_not():
    g = PaceGovernor(0.1)
    assert g.close(20, [0.02] * 20) == pytest.approx(0.1)           # a flock well within its period
    assert g.close(20, [0.099] * 20) == pytest.approx(0.1)          # late in it, but every state came: kept
    assert g.stretched_ticks == 0
    assert g.close(20, [0.02] * 17) == pytest.approx(0.1 * STRETCH)   # 3 of 20 states never came: stretched
    assert g.close(20, [0.02] * 10) == pytest.approx(0.1 * STRETCH ** 2)
    for _ in range(20):
        g.close(20, [])                                                # nothing comes: bounded
    assert g.period == pytest.approx(0.1 * MAX_STRETCH)
    # the load is gone: back towards nominal by at most RELAX a tick, and to no less than nominal
    periods = [g.close(20, [0.01] * 20) for _ in range(30)]
    assert periods[0] == pytest.approx(RELAX * 0.1 * MAX_STRETCH)
    assert all(b <= a for a, b in zip(periods, periods[1:])) and periods[-1] == pytest.approx(0.1)
    back = next(i for i, p in enumerate(periods) if p == pytest.approx(0.1))
    assert back == math.ceil(math.log(1 / MAX_STRETCH) / math.log(RELAX)) - 1
    assert g.max_stretch == pytest.approx(MAX_STRETCH)
    # a flock that needs a little more than the period settles at about that much
    g2 = PaceGovernor(0.1)
    g2.close(20, [])
    settled = [g2.close(20, [0.095] * 20) for _ in range(10)]
    assert settled[0] == pytest.approx(RELAX * 0.1 * STRETCH)
    assert IDLE <= 0.095 / settled[-1] <= BUSY and settled[-1] == settled[-2]     # in the band, held
    # and one that fits in the period (its median at 80 % of it) is back at nominal after a stall
    g3 = PaceGovernor(0.1)
    g3.close(20, [])
    assert [g3.close(20, [0.08] * 20) for _ in range(5)][-1] == pytest.approx(0.1)


def test_a_few_sensors_waiting_out_a_round_or_one_dead_sensor_do_not_slow_the_flock():
    g = PaceGovernor(0.1)
    assert g.close(12, [0.02] * 11) == pytest.approx(0.1)               # one state missing of 12
    assert g.close(12, [0.02] * 9 + [0.099] * 3) == pytest.approx(0.1)  # three waited out their last round
    assert g.close(12, [0.02] * 10) > 0.1                               # two of twelve never came
    # stretched, the same few late sensors (their deadlines scale with the period) do not hold it there
    s = PaceGovernor(0.1)
    s.close(12, [])
    periods = [s.close(12, [0.02] * 9 + [0.9 * s.period] * 3) for _ in range(10)]
    assert periods[-1] == pytest.approx(0.1)
    assert arrival_quantile(12, [0.01] * 11, 0.9) == 0.01
    assert math.isinf(arrival_quantile(10, [0.01] * 8, 0.9))
    assert g.close(0, []) == g.period                                   # nobody expected: nothing to go by


def test_a_new_nominal_period_keeps_the_stretch():
    g = PaceGovernor(0.1)
    g.close(10, [])
    g.set_nominal(0.05)                  # the run's speed doubled while stretched
    assert g.period == pytest.approx(0.05 * STRETCH) and g.stretch == pytest.approx(STRETCH)
