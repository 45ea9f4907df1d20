"""Centralized minimax filter (13) and its Kalman limit (Gu & Hu, Sections II-C, III-A, IV)."""

import numpy as np
import pytest
from scipy.linalg import block_diag

from agent.estimators.kalman import CentralizedKalman, KalmanPredictor
from agent.estimators.minimax import CentralizedMinimax
from agent.models import IntelligentTarget, LinearSensor, LinearTarget, double_integrator

N_SENSORS = 10
C = np.hstack([np.eye(2), np.zeros((2, 2))])
R = 0.04 * np.eye(2)
S = 0.09 * np.eye(2)
X0_TARGET = np.array([0.0, 0.0, 1.0, 0.5])


def setting(T):
    A, B = double_integrator(T)
    return A, B, B @ (0.01 * np.eye(2)) @ B.T


def test_covariance_form_equals_information_form_normal_target():
    T = 0.04
    A, B, Q = setting(T)
    rng = np.random.default_rng(0)
    Rs = [R * (1 + 0.1 * j) for j in range(N_SENSORS)]          # heterogeneous sensors, all R < S
    fi = CentralizedMinimax(A, Q, [C] * N_SENSORS, Rs, S, np.zeros(4), np.eye(4), form="information")
    fc = CentralizedMinimax(A, Q, [C] * N_SENSORS, Rs, S, np.zeros(4), np.eye(4), form="covariance")
    tgt = LinearTarget(A, B, 0.01 * np.eye(2), X0_TARGET, rng)
    sensors = [LinearSensor(C, Rj) for Rj in Rs]
    C_st = np.vstack([C] * N_SENSORS)
    R_inv = np.linalg.inv(block_diag(*Rs))
    for t in range(200):
        b = np.ones(N_SENSORS)
        if t % 7 == 3:
            b[[1, 4]] = 0.0                                          # some sensors blind
        if t % 11 == 5:
            b[2] = 0.5
        ys = [s.measure(tgt.x, bj, rng) for s, bj in zip(sensors, b)]
        fi.step(ys, b)
        fc.step(ys, b)
        tgt.step()
        np.testing.assert_allclose(fc.x, fi.x, rtol=0, atol=1e-10)
        np.testing.assert_allclose(fc.P, fi.P, rtol=0, atol=1e-10)
        np.testing.assert_allclose(fc.Sigma, fi.Sigma, rtol=0, atol=1e-10)
        assert fi.admissible and fc.admissible
        if np.all(b == 1.0):   # gain (10): K* = A Σ C'R⁻¹ on the stacked model
            np.testing.assert_allclose(fc.K, A @ fc.Sigma @ C_st.T @ R_inv, atol=1e-12)


def test_s_subtracted_once_per_sensor():
    A, _, Q = setting(0.04)
    f = CentralizedMinimax(A, Q, [C] * N_SENSORS, [R] * N_SENSORS, S, np.zeros(4), np.eye(4))
    f.step([np.zeros(2)] * N_SENSORS)
    Omega = N_SENSORS * C.T @ (np.linalg.inv(R) - np.linalg.inv(S)) @ C
    np.testing.assert_allclose(f.Sigma, np.linalg.inv(np.eye(4) + Omega), atol=1e-12)


def test_s_to_infinity_is_textbook_kalman_predictor():
    T = 0.04
    A, B, Q = setting(T)
    rng = np.random.default_rng(5)
    Rs = [R] * N_SENSORS
    kal = CentralizedKalman(A, Q, [C] * N_SENSORS, Rs, np.zeros(4), np.eye(4))
    kal_cov = CentralizedKalman(A, Q, [C] * N_SENSORS, Rs, np.zeros(4), np.eye(4), form="covariance")
    huge_S = CentralizedMinimax(A, Q, [C] * N_SENSORS, Rs, 1e12 * np.eye(2), np.zeros(4), np.eye(4))
    ref = KalmanPredictor.stacked(A, Q, [C] * N_SENSORS, Rs, np.zeros(4), np.eye(4))
    tgt = LinearTarget(A, B, 0.01 * np.eye(2), X0_TARGET, rng)
    sensor = LinearSensor(C, R)
    for _ in range(300):
        ys = [sensor.measure(tgt.x, 1.0, rng) for _ in range(N_SENSORS)]
        for f in (kal, kal_cov, huge_S):
            f.step(ys)
        ref.step(np.concatenate(ys))
        tgt.step()
        for f in (kal, kal_cov):
            np.testing.assert_allclose(f.x, ref.x, atol=1e-9)
            np.testing.assert_allclose(f.P, ref.P, atol=1e-10)
        np.testing.assert_allclose(huge_S.x, ref.x, atol=1e-7)
    np.testing.assert_allclose(kal_cov.K, ref.K, atol=1e-9)


def test_missing_measurement_and_blind_sensor_contribute_nothing():
    A, _, Q = setting(0.04)
    ys = [np.array([1.0, 2.0])] * N_SENSORS
    f_all = CentralizedMinimax(A, Q, [C] * N_SENSORS, [R] * N_SENSORS, S, np.zeros(4), np.eye(4))
    f_sub = CentralizedMinimax(A, Q, [C] * 7, [R] * 7, S, np.zeros(4), np.eye(4))
    f_none = CentralizedMinimax(A, Q, [C] * N_SENSORS, [R] * N_SENSORS, S, np.zeros(4), np.eye(4),
                                form="covariance")
    b = np.ones(N_SENSORS)
    b[7:] = 0.0
    f_all.step(ys, b)
    f_sub.step(ys[:7])
    f_none.step(ys[:7] + [None] * 3)
    np.testing.assert_allclose(f_all.x, f_sub.x, atol=1e-12)
    np.testing.assert_allclose(f_none.x, f_sub.x, atol=1e-10)
    f_none.step([None] * N_SENSORS)                                   # no data: pure prediction
    f_sub.step([None] * 7)
    np.testing.assert_allclose(f_none.x, f_sub.x, atol=1e-10)


def run_intelligent(S_, T, seed, steps=2000, ke=0.04):
    """Noise-free intelligent target (Section IV) tracked by the centralized filter; the target
    uses the filter's one-step prediction x̂_t. Returns the position error per step."""
    A, _, Q = setting(T)
    f = CentralizedMinimax(A, Q, [C] * N_SENSORS, [R] * N_SENSORS, S_, np.zeros(4), np.eye(4))
    tgt = IntelligentTarget(A, ke, X0_TARGET)
    sensor = LinearSensor(C, R)
    rng = np.random.default_rng(seed)
    err = np.empty(steps)
    for t in range(steps):
        x_hat = f.x.copy()
        err[t] = np.linalg.norm(tgt.x[:2] - x_hat[:2])
        f.step([sensor.measure(tgt.x, 1.0, rng) for _ in range(N_SENSORS)])
        tgt.step(x_hat)
    return err


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_intelligent_target_kalman_diverges_minimax_bounded(seed):
    ek = run_intelligent(None, 0.04, seed)
    em = run_intelligent(S, 0.04, seed)
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))
    assert rms(ek[-200:]) > 100 * rms(ek[:200])
    assert ek[-1] > 100.0
    assert em.max() < 1.0
    assert rms(em[-200:]) < 2 * rms(em[:200]) + 0.05


def test_intelligent_target_t_matters():
    """At T = 0.1 (k_e = 0.04) the Kalman filter does not diverge (PAPER_NOTES 000: T matters)."""
    ek = run_intelligent(None, 0.1, 0)
    assert ek.max() < 1.0


def test_inadmissible_game_is_flagged_not_hidden():
    """S < R makes P⁻¹ + Σ C′(R⁻¹ − S⁻¹)C indefinite: no saddle point; the filter says so."""
    A, _, Q = setting(0.04)
    f = CentralizedMinimax(A, Q, [C] * N_SENSORS, [R] * N_SENSORS, 0.02 * np.eye(2), np.zeros(4), np.eye(4))
    f.step([np.zeros(2)] * N_SENSORS)
    assert not f.admissible
    g = CentralizedMinimax(A, Q, [C] * N_SENSORS, [R] * N_SENSORS, S, np.zeros(4), np.eye(4))
    g.step([np.zeros(2)] * N_SENSORS)
    assert g.admissible
    L = g.adversary_gain()                                            # (11), stacked
    assert L.shape == (4, 2 * N_SENSORS)
    np.testing.assert_allclose(L[:, :2], A @ g.Sigma @ C.T @ np.linalg.inv(S))
