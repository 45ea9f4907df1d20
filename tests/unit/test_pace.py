"""The realtime world's pace under overload (topology/pace.py): the period stretches while the flock's states
come late or not at all, is back at nominal the first tick after the load goes, and one dead or slow sensor
does not slow the flock."""

from __future__ import annotations

import math

import pytest

from topology.pace import BUSY, IDLE, MAX_STRETCH, STRETCH, PaceGovernor, arrival_quantile


def test_the_period_stretches_while_the_flock_runs_out_of_it_and_comes_back_when_it_does_not():
    g = PaceGovernor(0.1)
    assert g.close(20, [0.02] * 20) == pytest.approx(0.1)           # a flock well within its period
    assert g.stretched_ticks == 0
    assert g.close(20, [0.095] * 20) == pytest.approx(0.1 * STRETCH)  # past BUSY of it: stretched
    assert g.close(20, [0.02] * 10) == pytest.approx(0.1 * STRETCH ** 2)   # half the states never came
    for _ in range(20):
        g.close(20, [])                                                # nothing comes: bounded
    assert g.period == pytest.approx(0.1 * MAX_STRETCH)
    # the load is gone: straight back to what the flock needs, never below nominal
    assert g.close(20, [0.15] * 20) == pytest.approx(0.15 / IDLE)
    assert g.close(20, [0.01] * 20) == pytest.approx(0.1)
    assert g.stretched_ticks == 23 and g.max_stretch == pytest.approx(MAX_STRETCH)
    # between IDLE and BUSY of the period: held
    g2 = PaceGovernor(0.1)
    g2.close(20, [])
    held = g2.period
    assert g2.close(20, [0.75 * held] * 20) == held


def test_one_dead_or_descheduled_sensor_does_not_slow_the_flock():
    g = PaceGovernor(0.1)
    assert g.close(12, [0.02] * 11) == pytest.approx(0.1)              # one state missing of 12
    assert g.close(12, [0.02] * 11 + [0.099]) == pytest.approx(0.1)    # one state at the very end
    assert g.close(12, [0.02] * 10) > 0.1                              # two of twelve: past the quantile
    assert arrival_quantile(12, [0.01] * 11, 0.9) == 0.01
    assert math.isinf(arrival_quantile(10, [0.01] * 8, 0.9))
    assert BUSY > IDLE


def test_a_new_nominal_period_keeps_the_stretch():
    g = PaceGovernor(0.1)
    g.close(10, [])
    g.set_nominal(0.05)                  # the run's speed doubled while stretched
    assert g.period == pytest.approx(0.05 * STRETCH) and g.stretch == pytest.approx(STRETCH)
