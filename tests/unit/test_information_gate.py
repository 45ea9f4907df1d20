"""The consistency gate of the resilient minimax consensus (agent/estimators/information_gate.py): honest
(18a) payloads and their mixtures pass, forged information matrices and lying measurements do not."""

import numpy as np

from agent.estimators.information_gate import InformationGate
from agent.estimators.minimax import sensor_information

C = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
R = 0.04 * np.eye(2)
R_INV, S_INV = np.linalg.inv(R), np.linalg.inv(0.5 * np.eye(2))


def _payload(y, b=1.0):
    c1, c2, c3 = sensor_information(C, R_INV, S_INV, np.asarray(y, float), b)
    return {"chi1": c1, "chi2": c2, "chi3": c3}


def _mix(ps, w):
    return {k: sum(wi * p[k] for wi, p in zip(w, ps)) for k in ps[0]}


def test_honest_payloads_and_mixtures_pass_and_liars_do_not():
    rng = np.random.default_rng(1)
    gate = InformationGate(C, R_INV, S_INV)
    x_true, x_hat = np.array([3.0, -2.0, 0.5, 0.1]), np.array([3.4, -2.3, 0.4, 0.0])   # a poor prediction
    meas = [C @ x_true + rng.multivariate_normal(np.zeros(2), R) for _ in range(4)]
    own = _payload(meas[0])
    honest = {1: _payload(meas[1]), 2: _mix([_payload(m) for m in meas[1:]], [0.5, 0.3, 0.2])}
    assert gate.suspects(own, honest, x_hat) == []          # the prediction error is common: it cancels
    liars = {3: {k: 1e6 * v for k, v in honest[1].items()},                               # huge
             4: _payload(meas[2] + np.array([2.0, 0.0])),                                 # a biased measurement
             5: {**honest[1], "chi3": 2 * honest[1]["chi3"]},                             # forged χ³
             6: {**honest[1], "chi1": honest[1]["chi1"] + 0.3 * np.eye(4)},               # not C′R⁻¹C's shape
             7: _payload(meas[3], b=3.0)}                                                 # β beyond b_max
    assert gate.suspects(own, {**honest, **liars}, x_hat) == [3, 4, 5, 6, 7]


def test_the_false_alarm_rate_is_the_stated_one():
    rng = np.random.default_rng(7)
    gate = InformationGate(C, R_INV, S_INV, alpha=0.01)
    x = np.zeros(4)
    alarms = 0
    for _ in range(4000):
        own, other = (_payload(rng.multivariate_normal(np.zeros(2), R)) for _ in range(2))
        alarms += len(gate.suspects(own, {1: other}, x))
    assert 0.005 < alarms / 4000 < 0.02


def test_a_small_steady_lie_is_caught_by_the_running_residual_and_the_truth_is_not():
    """A neighbour whose measurements are biased by 0.75 σ of the noise passes nearly every single test, but its
    running residual gives it away within a few hundred ticks and keeps it caught; an honest one's does not
    (2 000 ticks)."""
    rng = np.random.default_rng(3)
    x = np.zeros(4)
    for bias, ticks, caught in ((np.array([0.15, 0.15]), 400, True), (np.zeros(2), 2000, False)):
        gate = InformationGate(C, R_INV, S_INV)
        seen = []
        for _ in range(ticks):
            own = _payload(rng.multivariate_normal(np.zeros(2), R))
            other = _payload(rng.multivariate_normal(np.zeros(2), R) + bias)
            seen.append(gate.suspects(own, {1: other}, x, r=0) == [1])
            assert gate.suspects(own, {1: other}, x, r=1) == ([1] if seen[-1] else [])   # for the whole tick
        assert any(seen) is caught, (bias, sum(seen))
        if caught:
            after = seen[seen.index(True) + 50:]
            assert sum(after) >= 0.9 * len(after)        # and stays caught


def test_a_lie_told_in_every_round_is_caught_by_the_later_rounds_agreement():
    """In later rounds honest payloads are mixtures that agree closely; a neighbour that replays one with its
    estimate moved by 0.1 (half the noise's σ: invisible to the round-0 tests) is caught within ~30 ticks,
    and two honest mixtures are not told apart in 2 000 ticks."""
    rng = np.random.default_rng(5)
    x, delta = np.zeros(4), np.array([0.1, 0.1, 0.0, 0.0])
    w_own, w_honest = np.array([0.3, 0.25, 0.25, 0.2]), np.array([0.2, 0.3, 0.25, 0.25])
    for lie, ticks in ((True, 120), (False, 2000)):
        gate = InformationGate(C, R_INV, S_INV)
        caught = []
        for _ in range(ticks):
            raw = [_payload(rng.multivariate_normal(np.zeros(2), R)) for _ in range(4)]
            own, other = _mix(raw, w_own), _mix(raw, w_honest)
            if lie:
                other = {**other, "chi2": other["chi2"] + other["chi1"] @ delta}
            caught.append(gate.suspects(own, {1: other}, x, r=3) == [1])
        if lie:
            assert caught.index(True) <= 40 and all(caught[caught.index(True):])
        else:
            assert not any(caught)
