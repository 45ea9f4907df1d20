"""Shared Riccati pieces for the minimax (Gu & Hu) and H∞ (Chen et al.) filters.

Both papers iterate the same information-form step

    P⁺ = A (P⁻¹ + Ω)⁻¹ Aᵀ + Q                                              (*)

with a different "information gain" Ω:

* Gu & Hu (13):   Ω = Σⱼ Cⱼᵀ (Rⱼ⁻¹ − S⁻¹) Cⱼ     (Σ = (P⁻¹ + Ω)⁻¹, Q → BQBᵀ); S → ∞ is Kalman.
* Chen (9):       Ω = Cᵀ R⁻¹ C − γ I.

Nothing here hides an indefinite result: the caller decides whether it is admissible.
"""

from __future__ import annotations

import numpy as np


def sym(M: np.ndarray) -> np.ndarray:
    """Symmetric part (keeps iterated covariances exactly symmetric)."""
    return 0.5 * (M + M.T)


def information_posterior(P: np.ndarray, Omega: np.ndarray) -> np.ndarray:
    """Σ = (P⁻¹ + Ω)⁻¹, the measurement-updated matrix of (*) (Gu & Hu (12); Chen (9) inner term)."""
    return sym(np.linalg.inv(np.linalg.inv(P) + Omega))


def information_step(P: np.ndarray, Omega: np.ndarray, A: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """One step of (*): P⁺ = A (P⁻¹ + Ω)⁻¹ Aᵀ + Q."""
    return sym(A @ information_posterior(P, Omega) @ A.T + Q)


def iterate_to_fixed_point(P0: np.ndarray, Omega: np.ndarray, A: np.ndarray, Q: np.ndarray,
                           tol: float = 1e-13, max_iter: int = 100_000) -> tuple[np.ndarray, int, bool]:
    """Iterate (*) from P0 until ‖P⁺ − P‖_max ≤ tol·max(1, ‖P‖_max).

    Returns (P, iterations, converged). The limit is returned whatever its inertia.
    """
    P = np.array(P0, dtype=float)
    for it in range(1, max_iter + 1):
        Pn = information_step(P, Omega, A, Q)
        if not np.all(np.isfinite(Pn)):
            return Pn, it, False
        if np.max(np.abs(Pn - P)) <= tol * max(1.0, float(np.max(np.abs(Pn)))):
            return Pn, it, True
        P = Pn
    return P, max_iter, False


def is_positive_definite(M: np.ndarray, tol: float = 0.0) -> bool:
    """True iff the symmetric part of M has all eigenvalues > tol."""
    if not np.all(np.isfinite(M)):
        return False
    return bool(np.linalg.eigvalsh(sym(np.asarray(M, float))).min() > tol)


# ============================================================================= robust fusion pieces
# Shared by the robust Kalman filter (fusion_baselines.RobustKalmanCV) and the moving-horizon
# estimator's arrival cost (son_arrival): the white-noise-acceleration prediction and the Huber
# information update, in whitened rows (unit-covariance residuals r = z − Gx).


def white_noise_acceleration(dt: float, q: float, dt_floor: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """F, Q of the planar constant-velocity model, state [p_x, p_y, v_x, v_y] (García Carrillo (2)):
    F = [[I, Δt I], [0, I]],  Q = q·[[Δt³/3 I, Δt²/2 I], [Δt²/2 I, Δt I]] with Δt floored at ``dt_floor``
    in Q only (as in the sum-of-norms graph's motion rows)."""
    F = np.eye(4)
    F[0, 2] = F[1, 3] = dt
    d = max(float(dt), float(dt_floor))
    Q = np.zeros((4, 4))
    Q[0, 0] = Q[1, 1] = q * d ** 3 / 3.0
    Q[0, 2] = Q[2, 0] = Q[1, 3] = Q[3, 1] = q * d ** 2 / 2.0
    Q[2, 2] = Q[3, 3] = q * d
    return F, Q


def predict(x: np.ndarray, P: np.ndarray, F: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Kalman prediction x⁺ = F x,  P⁺ = F P Fᵀ + Q."""
    return F @ x, sym(F @ P @ F.T + Q)


def huber_psi(r: np.ndarray, delta: float) -> np.ndarray:
    """ψ(r) = clip(r, −δ, δ), the derivative of huber_δ (the influence of a whitened residual)."""
    return np.clip(r, -delta, delta)


def huber_curvature(r: np.ndarray, delta: float) -> np.ndarray:
    """ψ′(r) = 1 on |r| < δ, 0 beyond: the curvature of huber_δ (the Hessian's row weights)."""
    return (np.abs(r) < delta).astype(float)


def huber_irls_weight(r: np.ndarray, delta: float) -> np.ndarray:
    """ψ(r)/r = min(1, δ/|r|): the iteratively-reweighted-least-squares weight of a whitened residual."""
    a = np.abs(r)
    return np.where(a > delta, delta / np.maximum(a, 1e-300), 1.0)


def information_update(x: np.ndarray, Lam: np.ndarray, G: np.ndarray, z: np.ndarray, theta: np.ndarray,
                       force: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Minimiser and Hessian of ½(y − x)ᵀΛ(y − x) + Σᵢ θᵢ·½(zᵢ − gᵢy)² − Σᵢ fᵢ·(zᵢ − gᵢy):

        Λ⁺ = Λ + GᵀΘG,   y⁺ = Λ⁺⁻¹(Λx + GᵀΘz + Gᵀf).

    With θ = IRLS weights and f = 0 it is one reweighted Kalman measurement update (information form);
    with θ = ψ′ (the Huber curvature at a point) and f = ψ on the rows beyond δ it is the exact minimiser
    of the Huber cost on that active set (a row beyond δ pulls with the constant force δ·sign r)."""
    Lp = sym(Lam + G.T @ (theta[:, None] * G))
    rhs = Lam @ x + G.T @ (theta * z)
    if force is not None:
        rhs = rhs + G.T @ force
    return np.linalg.solve(Lp, rhs), Lp
