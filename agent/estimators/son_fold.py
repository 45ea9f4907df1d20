"""Compiled pieces of the robust moving-horizon fusion's per-measurement bookkeeping
(:mod:`agent.estimators.robust_window`): the fold of a node leaving the window into the arrival cost, and
the per-axis whitening of that cost. Both were ~30 small numpy calls each per fused measurement (≈ 100 µs of
the robust MHE's ≈ 260 µs); here they are one compiled call each, same algebra.

:func:`fold_kernel` is robust_window.fold_node's body (robust_mhe's module doc, "The arrival cost"):

    Λ⁺ = Λ + GᵀΘG,   y⁺ = Λ⁺⁻¹(Λy₀ + GᵀΘz + Gᵀψ_L),   Θ = ψ′(r̂), ψ_L = ψ(r̂)·(1 − Θ)

over node 0's variables y = [u, p, v] (u only for a measuring agent ≠ 0), then the posterior covariance
Σ⁺ = Λ⁺⁻¹ of [p, v] and the relative row's residual normalised by its variance under the model.
"""

from __future__ import annotations

import numpy as np

from .son_jit import kernel

__all__ = ["axis_whiteners", "fold_kernel"]


@kernel
def _chol_whitener_2(a: float, b: float, d: float, out: np.ndarray) -> None:
    """``out`` = L⁻¹ for the 2×2 covariance [[a, b], [b, d]] = LLᵀ (L lower): W C Wᵀ = I."""
    l11 = np.sqrt(a)
    l21 = b / l11
    l22 = np.sqrt(d - l21 * l21)
    out[0, 0] = 1.0 / l11
    out[0, 1] = 0.0
    out[1, 0] = -l21 / (l11 * l22)
    out[1, 1] = 1.0 / l22


@kernel
def axis_whiteners(P: np.ndarray, xbar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per axis a ∈ {x, y}: L_a⁻¹ of P restricted to [p_a, v_a] (indices a, 2 + a) and L_a⁻¹ x̄_a —
    the arrival cost's rows in the split solver's per-axis layout ((2, 2, 2), (2, 2))."""
    aW = np.empty((2, 2, 2))
    az = np.empty((2, 2))
    for a in range(2):
        _chol_whitener_2(P[a, a], P[2 + a, a], P[2 + a, 2 + a], aW[a])
        az[a, 0] = aW[a, 0, 0] * xbar[a]
        az[a, 1] = aW[a, 1, 0] * xbar[a] + aW[a, 1, 1] * xbar[2 + a]
    return aW, az


@kernel
def fold_kernel(P: np.ndarray, xbar: np.ndarray, Wr: np.ndarray, Wg: np.ndarray, z: np.ndarray, gps: np.ndarray,
                has_u: bool, s_hat: np.ndarray, u_hat: np.ndarray, delta: float,
                gross: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean (4,), covariance (4, 4), ν̃ (2,)) of a node leaving the window (module doc): prior N(``xbar``,
    ``P``) on [p, v], relative row ``Wr``(p − u) = ``Wr z``, GPS row ``Wg u`` = ``Wg gps`` (when ``has_u``),
    at the window solution (``s_hat``, ``u_hat``) with threshold ``delta``; rows beyond ``gross`` leave no
    trace."""
    nv = 6 if has_u else 4
    nr = 4 if has_u else 2
    o = nv - 4
    Lam = np.zeros((nv, nv))
    y0 = np.zeros(nv)
    Lam[o:, o:] = np.linalg.inv(P)
    y0[o:] = xbar
    G = np.zeros((nr, nv))
    zz = np.empty(nr)
    G[0:2, o:o + 2] = Wr
    zz[0:2] = Wr @ z
    y_hat = np.empty(nv)
    y_hat[o:] = s_hat
    if has_u:
        G[0:2, 0:2] = -Wr
        G[2:4, 0:2] = Wg
        zz[2:4] = Wg @ gps
        Lam[0, 0] = 1e-12        # u has no prior (keeps Λ⁺ regular if both rows are rejected)
        Lam[1, 1] = 1e-12
        y0[0:2] = u_hat
        y_hat[0:2] = u_hat
    r = zz - G @ y_hat
    theta = np.empty(nr)
    force = np.empty(nr)
    for i in range(nr):
        ai = abs(r[i])
        theta[i] = 1.0 if ai < delta else 0.0
        force[i] = 0.0 if (ai > gross or theta[i] == 1.0) else min(max(r[i], -delta), delta)
    GtT = G.T * theta
    Lp = Lam + GtT @ G
    Lp = 0.5 * (Lp + Lp.T)
    yp = np.linalg.solve(Lp, Lam @ y0 + GtT @ zz + G.T @ force)
    Sp = np.linalg.inv(Lp)
    nu = np.empty(2)
    for i in range(2):
        gi = G[i]
        h = gi @ Sp @ gi
        rf = zz[i] - gi @ yp + h * force[i]        # a rejected row: its residual without its own pull
        var = 1.0 - h if theta[i] > 0 else 1.0 + h
        nu[i] = rf / np.sqrt(max(var, 1e-6))
    S = Sp[o:, o:]
    return yp[o:].copy(), 0.5 * (S + S.T), nu
