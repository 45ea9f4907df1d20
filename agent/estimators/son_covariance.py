"""The covariance a sum-of-norms window implies for its estimates, from its own (local) information.

The window's problem is a Huber regression on whitened residuals r = z − Hx (:mod:`son_problem`): every row
is a measurement, motion or prior term divided by its standard deviation, so under the model each rᵢ is
N(0, 1). The M-estimator x̂ = argmin Σ huber_δ(rᵢ) then has the asymptotic covariance (Huber, *Robust
Statistics*, 1981, §7.6; the sandwich of an M-estimator)

    Cov x̂ = J⁻¹ K J⁻¹,   J = H′ diag(E ψ′(rᵢ)) H,   K = H′ diag(E ψ(rᵢ)²) H,

with ψ = clip(·, −δ, δ) the Huber influence function and the expectations taken at the Gaussian model:

    E ψ′ = 2Φ(δ) − 1,   E ψ² = (2Φ(δ) − 1) − 2δφ(δ) + 2δ²(1 − Φ(δ)),

and E ψ′ = E ψ² = 1 on the quadratic rows (δ = ∞: the arrival cost, a Gaussian motion model). For δ → ∞
this is the least-squares (H′H)⁻¹; for the paper's small δ it tends to the least-absolute-deviations
estimator's (π/2)(H′H)⁻¹. What it leaves out is what the model leaves out: an outlier the window
did not discard, or a target that moves otherwise than the motion rows say — which is what the run's NEES
then shows.
"""

from __future__ import annotations

import math

import numpy as np

from .son_problem import HuberProblem


def huber_moments(delta: float) -> tuple[float, float]:
    """(E ψ′(r), E ψ(r)²) for r ~ N(0, 1) and ψ = clip(·, −δ, δ)."""
    if not math.isfinite(delta):
        return 1.0, 1.0
    Phi = 0.5 * (1.0 + math.erf(delta / math.sqrt(2.0)))
    phi = math.exp(-0.5 * delta * delta) / math.sqrt(2.0 * math.pi)
    p = 2.0 * Phi - 1.0
    return p, p - 2.0 * delta * phi + 2.0 * delta * delta * (1.0 - Phi)


def _dense(prob: HuberProblem, a: int) -> np.ndarray:
    rows = np.repeat(np.arange(prob.m), np.diff(prob.rp))
    H = np.zeros((prob.m, prob.n))
    np.add.at(H, (rows, prob.ci), prob.hv[a])
    return H


def sandwich(prob: HuberProblem, a: int = 0, cols: list[int] | None = None) -> np.ndarray | None:
    """Cov x̂ = J⁻¹ K J⁻¹ of problem ``a``'s variables, or of those in ``cols`` only (J⁻¹ applied to those
    columns alone: Y = J⁻¹E, Cov = (HY)′ diag(E ψ²) (HY)); None when J is singular (too few rows for the
    variables)."""
    H = _dense(prob, a)
    d1, d2 = huber_moments(prob.delta)
    lsq = prob.lsq_mask()
    w1 = np.where(lsq, 1.0, d1)
    w2 = np.where(lsq, 1.0, d2)
    J = H.T @ (w1[:, None] * H)
    E = np.eye(prob.n) if cols is None else np.eye(prob.n)[:, cols]
    try:
        Y = np.linalg.solve(J, E)
    except np.linalg.LinAlgError:
        return None
    HY = H @ Y
    C = HY.T @ (w2[:, None] * HY)
    C = 0.5 * (C + C.T)
    return C if np.all(np.isfinite(C)) else None


def node_covariances(prob: HuberProblem, layout: dict, nodes: list[int]) -> list[np.ndarray] | None:
    """The 4 × 4 covariance of the target state [p_x, p_y, v_x, v_y] at each window node in ``nodes``
    (indices in time order, as :class:`~agent.estimators.sum_of_norms.Result`'s rows); None when the
    window does not determine it."""
    pix, vix = layout["pix"], layout["vix"]
    out = [np.zeros((4, 4)) for _ in nodes]
    if layout["split"]:                       # one problem per axis: no cross-axis covariance
        for ax in range(2):
            C = sandwich(prob, ax, [int(i) for k in nodes for i in (pix[k], vix[k])])
            if C is None:
                return None
            for j, P in enumerate(out):
                P[np.ix_([ax, 2 + ax], [ax, 2 + ax])] = C[2 * j:2 * j + 2, 2 * j:2 * j + 2]
    else:
        C = sandwich(prob, 0, [int(i) for k in nodes for i in (pix[k, 0], pix[k, 1], vix[k, 0], vix[k, 1])])
        if C is None:
            return None
        for j, P in enumerate(out):
            P[:] = C[4 * j:4 * j + 4, 4 * j:4 * j + 4]
    return out
