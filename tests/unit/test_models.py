"""Motion and sensor models (agent/models.py): Gu & Hu (1), (3), (19) and the intelligent target."""

import numpy as np
import pytest

from agent.models import (DoubleIntegratorAgent, IntelligentTarget, LinearSensor, LinearTarget,
                          double_integrator, integrate_double_integrator)


def test_double_integrator_matrices_match_19():
    T = 0.04
    A, B = double_integrator(T)
    A_paper = np.array([[1, 0, T, 0], [0, 1, 0, T], [0, 0, 1, 0], [0, 0, 0, 1]], float)
    B_paper = np.array([[T * T / 2, 0], [0, T * T / 2], [T, 0], [0, T]], float)
    np.testing.assert_array_equal(A, A_paper)
    np.testing.assert_array_equal(B, B_paper)
    A3, B3 = double_integrator(0.5, dim=3)
    assert A3.shape == (6, 6) and B3.shape == (6, 3)


def test_double_integrator_is_exact_zoh_of_constant_acceleration():
    T, u = 0.1, np.array([0.3, -0.2])
    A, B = double_integrator(T)
    z = np.array([1.0, 2.0, -0.5, 0.25])
    q, p = z[:2].copy(), z[2:].copy()
    agent = DoubleIntegratorAgent(z[:2], z[2:], T)
    for _ in range(50):
        z = A @ z + B @ u
        q, p = integrate_double_integrator(q, p, u, T)
        agent.step(u)
    t = 50 * T
    exact_q = np.array([1.0, 2.0]) + np.array([-0.5, 0.25]) * t + 0.5 * u * t * t
    np.testing.assert_allclose(z[:2], exact_q, atol=1e-12)
    np.testing.assert_allclose(np.concatenate([q, p]), z, atol=1e-12)
    np.testing.assert_allclose(agent.z, z, atol=1e-12)


def test_integrate_double_integrator_vectorised_over_agents():
    rng = np.random.default_rng(0)
    q, p, u = rng.normal(size=(3, 10, 2))
    qn, pn = integrate_double_integrator(q, p, u, 0.04)
    for i in range(10):
        qi, pi = integrate_double_integrator(q[i], p[i], u[i], 0.04)
        np.testing.assert_allclose(qn[i], qi)
        np.testing.assert_allclose(pn[i], pi)


def test_sensor_noise_statistics():
    C = np.hstack([np.eye(2), np.zeros((2, 2))])
    R = np.array([[0.04, 0.01], [0.01, 0.09]])
    sensor = LinearSensor(C, R)
    x = np.array([3.0, -1.0, 1.0, 0.5])
    rng = np.random.default_rng(1)
    ys = np.array([sensor.measure(x, 1.0, rng) for _ in range(40_000)])
    np.testing.assert_allclose(ys.mean(axis=0), C @ x, atol=0.01)
    np.testing.assert_allclose(np.cov(ys.T), R, atol=0.004)


def test_sensor_b_zero_gives_pure_noise_and_same_stream():
    C = np.hstack([np.eye(2), np.zeros((2, 2))])
    R = 0.04 * np.eye(2)
    sensor = LinearSensor(C, R)
    x = np.array([100.0, 50.0, 1.0, 0.5])
    y0 = sensor.measure(x, 0.0, np.random.default_rng(7))
    y1 = sensor.measure(x, 1.0, np.random.default_rng(7))
    np.testing.assert_allclose(y1 - C @ x, y0, atol=1e-12)  # same draw whatever the visibility
    rng = np.random.default_rng(2)
    ys = np.array([sensor.measure(x, 0.0, rng) for _ in range(20_000)])
    np.testing.assert_allclose(ys.mean(axis=0), 0.0, atol=0.01)
    np.testing.assert_allclose(ys.var(axis=0), 0.04, rtol=0.05)
    y_half = sensor.measure(x, 0.5, np.random.default_rng(7))
    np.testing.assert_allclose(y_half, 0.5 * C @ x + y0, atol=1e-12)


def test_linear_target_noise_enters_through_B():
    T = 0.04
    A, B = double_integrator(T)
    rng = np.random.default_rng(3)
    x0 = np.array([0.0, 0.0, 1.0, 0.5])
    tgt = LinearTarget(A, B, 0.01 * np.eye(2), x0, rng)
    steps = np.array([tgt.x.copy()] + [tgt.step() for _ in range(2000)])
    incr = steps[1:] - steps[:-1] @ A.T           # = B w
    w = incr[:, 2:] / T
    np.testing.assert_allclose(incr[:, :2], 0.5 * T * T * w, atol=1e-12)
    np.testing.assert_allclose(np.cov(w.T), 0.01 * np.eye(2), atol=0.0015)


def test_intelligent_target_pushes_away_from_estimate():
    A, _ = double_integrator(0.04)
    x0 = np.array([0.0, 0.0, 1.0, 0.5])
    tgt = IntelligentTarget(A, 0.04, x0)
    np.testing.assert_allclose(tgt.step(x0), A @ x0)             # perfect estimate: plain motion
    x1 = tgt.x.copy()
    x_hat = x1 - np.array([1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(tgt.step(x_hat), A @ x1 + 0.04 * np.array([1.0, 0, 0, 0]))


def test_intelligent_target_noise_needs_rng():
    A, B = double_integrator(0.04)
    with pytest.raises(ValueError):
        IntelligentTarget(A, 0.04, np.zeros(4), B=B, Q=0.01 * np.eye(2))
    tgt = IntelligentTarget(A, 0.04, np.zeros(4), B=B, Q=0.01 * np.eye(2), rng=np.random.default_rng(0))
    assert np.all(np.isfinite(tgt.step(np.zeros(4))))
