"""The covariance a sum-of-norms window implies (agent/estimators/son_covariance.py): the Huber moments
against numerical integration, the sandwich against least squares and against the spread of real IPM
solutions over noise draws."""

import math

import numpy as np
import pytest
from scipy import integrate, stats

from agent.estimators.son_covariance import huber_moments, sandwich
from agent.estimators.son_ipm import solve_ipm
from agent.estimators.son_problem import HuberProblem


@pytest.mark.parametrize("delta", [0.1, 0.5, 1.345, 3.0])
def test_the_huber_moments_are_the_gaussian_expectations(delta):
    d1, d2 = huber_moments(delta)
    e1 = stats.norm.cdf(delta) - stats.norm.cdf(-delta)
    e2 = integrate.quad(lambda r: min(r * r, delta * delta) * stats.norm.pdf(r), -np.inf, np.inf)[0]
    assert (d1, d2) == pytest.approx((e1, e2), rel=1e-7)
    assert huber_moments(math.inf) == (1.0, 1.0)
    d1, d2 = huber_moments(1e-4)
    assert d2 / d1 ** 2 == pytest.approx(math.pi / 2, rel=1e-3)     # least absolute deviations' efficiency


def _problem(H: np.ndarray, z: np.ndarray, delta: float) -> HuberProblem:
    m, n = H.shape
    rp = np.arange(0, m * n + 1, n, dtype=np.int64)
    ci = np.tile(np.arange(n, dtype=np.int64), m)
    return HuberProblem(rp, ci, H.reshape(1, -1).copy(), z.reshape(1, -1).copy(), n, n, float(delta), None, None)


def test_least_squares_gives_the_inverse_information():
    H = np.random.default_rng(0).normal(size=(40, 3))
    C = sandwich(_problem(H, np.zeros(40), math.inf))
    assert C == pytest.approx(np.linalg.inv(H.T @ H), rel=1e-10)


@pytest.mark.parametrize("delta", [0.1, 1.345])
def test_the_sandwich_is_the_spread_of_the_solutions_over_noise(delta):
    """500 noise draws of one 80-row regression, each solved by the IPM: the empirical covariance of x̂
    agrees with the sandwich within 20 % in trace (a sample of 500 has a ~6 % standard error)."""
    rng = np.random.default_rng(1)
    H = rng.normal(size=(80, 3))
    x0 = np.array([1.0, -2.0, 0.5])
    xs = np.array([solve_ipm(_problem(H, H @ x0 + rng.normal(size=80), delta)).x[0] for _ in range(500)])
    emp = np.cov(xs.T)
    C = sandwich(_problem(H, np.zeros(80), delta))
    assert np.trace(emp) / np.trace(C) == pytest.approx(1.0, abs=0.2)
    assert np.allclose(xs.mean(axis=0), x0, atol=4 * np.sqrt(np.diag(C) / 500))
