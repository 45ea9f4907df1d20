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
