"""The problem every sum-of-norms solver solves, and the one evaluation they are compared by.

The problem
-----------
Eliminating ℓ̄ from (10) of García Carrillo et al. row by row (PAPER_NOTES 004) leaves a Huber
regression on the whitened residuals r = z − Hx:

    min_x  P(x) = Σᵢ huber_δ(rᵢ),   huber_δ(r) = r²/2 (|r| ≤ δ),  δ|r| − δ²/2 (|r| > δ),

with ℓ̄ = soft_threshold(r, δ) at the optimum and, for (10) with parameter λ and residual scale c
(residuals divided by c before (10) is applied),

    δ = c·√2·λ²/(1 − λ),   objective(10) = P(x) / (λ²c²)        (:func:`delta_from_lambda`).

Problem data (:class:`HuberProblem`) are one or more independent problems ("axes") sharing one
sparsity pattern, rows stored CSR: ``rp`` (m+1), ``ci`` (nnz), values ``hv`` (A, nnz), ``z`` (A, m).
The x/y split of the UAV problem (:mod:`son_layout`) gives A = 2 problems with the same pattern; a
window with correlated (non-diagonal) covariances gives one joint problem (A = 1).

The common interface
--------------------
Every solver returns the same :class:`SolveOut`, made by :func:`evaluate_solution` from the solver's
own x: the objective P(x) evaluated by one common function (so solvers are compared on equal terms),
ℓ̄ per row and KKT residuals:

* ``stationarity``     ‖Hᵀψ(z − Hx)‖∞ with ψ = clip(·, −δ, δ) — the gradient of P (P is C¹), zero
                        exactly at an optimum;
* ``stationarity_rel`` the same divided by max_j Σᵢ|Hᵢⱼ|·δ (the largest value it could take);
* ``gap``               a duality-gap certificate P(x) − D(u) ≥ P(x) − P* where the solver supplies a
                        dual point u (the IPM does; NaN otherwise);
* solver-specific residuals (OSQP's prim/dual residuals, …).

Quadratic rows
--------------
Rows flagged in ``lsq`` (the moving-horizon estimator's arrival cost, :mod:`son_arrival`) are plain
least-squares rows, ½rᵢ², never Huber: δ = ∞ on them (no bound on uᵢ in the dual, ℓ̄ᵢ = 0).

The solvers: :func:`son_ipm.solve_ipm` (the default, a compiled interior-point method),
:class:`son_reference.OsqpSolver`, :class:`son_reference.CvxpyReference` (the literal (10), the tests'
independent reference) and :func:`son_reference.solve_ls` (least squares, δ = ∞).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .son_banded import NO_CHAIN, matvec, rmatvec
from .son_jit import kernel

__all__ = ["HuberProblem", "SolveOut", "delta_from_lambda", "evaluate_all", "evaluate_solution", "huber_sum",
           "lambda_from_delta"]


@dataclass
class HuberProblem:
    """A independent Huber regressions with a common CSR sparsity pattern.

    rp: (m+1,) int64 row pointers;  ci: (nnz,) int64 column indices;  hv: (A, nnz) values;
    z: (A, m) right-hand sides;  n: number of unknowns per problem;  bw: bandwidth of HᵀH
    (max |i − j| over the columns of any row);  delta: Huber threshold (whitened units).
    """

    rp: np.ndarray
    ci: np.ndarray
    hv: np.ndarray
    z: np.ndarray
    n: int
    bw: int
    delta: float
    chain: tuple | None = None  #: (rowtype, rownode, uix, pix, vix) when H has the UAV chain layout
    lsq: np.ndarray | None = None  #: (m,) bool, rows that are quadratic (δ = ∞: the arrival cost); None: none

    @property
    def m(self) -> int:
        return int(self.rp.shape[0] - 1)

    @property
    def axes(self) -> int:
        return int(self.hv.shape[0])

    def dense_H(self, a: int = 0) -> np.ndarray:
        """Dense H of problem ``a`` (tests and the reference)."""
        H = np.zeros((self.m, self.n))
        for r in range(self.m):
            for k in range(self.rp[r], self.rp[r + 1]):
                H[r, self.ci[k]] += self.hv[a, k]
        return H

    def shape_key(self) -> tuple:
        """Identity of the sparsity pattern and of the quadratic rows (what an OSQP/cvxpy set-up depends on)."""
        return (self.axes, self.n, self.rp.tobytes(), self.ci.tobytes(), self.lsq_mask().tobytes())

    def lsq_mask(self) -> np.ndarray:
        """(m,) bool: the quadratic rows (all False if none)."""
        return np.zeros(self.m, np.bool_) if self.lsq is None else np.asarray(self.lsq, np.bool_)

    def with_delta(self, delta: float) -> "HuberProblem":
        return HuberProblem(self.rp, self.ci, self.hv, self.z, self.n, self.bw, float(delta), self.chain, self.lsq)

    def without_chain(self) -> "HuberProblem":
        """The same problem for the generic banded path."""
        return HuberProblem(self.rp, self.ci, self.hv, self.z, self.n, self.bw, self.delta, None, self.lsq)

    def chain_arg(self) -> tuple:
        """The layout argument ``ch`` of the compiled kernels (:data:`son_banded.NO_CHAIN` if none)."""
        if self.chain is None:
            return NO_CHAIN
        return self.chain


@dataclass
class SolveOut:
    """What every solver returns. x: (A, n); ell: (A, m) = soft_threshold(z − Hx, δ);
    objective: Σ over axes of P(x) (Huber form, whitened units); kkt: residuals (see module doc)."""

    x: np.ndarray
    ell: np.ndarray
    objective: float
    kkt: dict[str, float]
    iterations: int = 0
    status: str = "solved"
    solver: str = ""
    extra: dict = field(default_factory=dict)


# ============================================================================= (10) ⇔ Huber


def delta_from_lambda(lam: float, scale: float = 1.0) -> float:
    """Huber threshold on unit-whitened residuals equivalent to (10) with λ and residual scale c."""
    lam = float(lam)
    if not 0.0 < lam < 1.0:
        raise ValueError("λ must lie in (0, 1)")
    return float(scale) * math.sqrt(2.0) * lam * lam / (1.0 - lam)


def lambda_from_delta(delta: float, scale: float = 1.0) -> float:
    """Inverse of :func:`delta_from_lambda`: the λ ∈ (0, 1) with c·√2λ²/(1−λ) = δ."""
    d = float(delta) / float(scale)
    if d <= 0.0:
        raise ValueError("δ must be positive")
    s2 = math.sqrt(2.0)
    return (-d + math.sqrt(d * d + 4.0 * s2 * d)) / (2.0 * s2)


# ============================================================================= the common evaluation


@kernel
def huber_sum(r, delta, lsq):
    """P = Σᵢ huber_δ(rᵢ) of the residuals r (½rᵢ² on the quadratic rows ``lsq``)."""
    s = 0.0
    for i in range(r.shape[0]):
        a = abs(r[i])
        if a <= delta or lsq[i]:
            s += 0.5 * a * a
        else:
            s += delta * a - 0.5 * delta * delta
    return s


@kernel
def evaluate_all(rp, ci, hv, z, n, delta, lsq, X):
    """Common evaluation: objective Σ P, ℓ̄ = soft(r, δ) (A, m), stationarity ‖Hᵀψ(r)‖∞ and its scale
    max_j Σᵢ|Hᵢⱼ|·δ, and max |r| (the quadratic rows ``lsq``: ψ = r, ℓ̄ = 0)."""
    A = hv.shape[0]
    m = rp.shape[0] - 1
    ell = np.empty((A, m))
    r = np.empty(m)
    psi = np.empty(m)
    g = np.empty(n)
    col = np.empty(n)
    obj = 0.0
    stat = 0.0
    scale = 0.0
    rmax = 0.0
    for a in range(A):
        matvec(rp, ci, hv[a], X[a], r)
        for i in range(m):
            ri = z[a, i] - r[i]
            r[i] = ri
            if lsq[i]:
                psi[i] = ri
                ell[a, i] = 0.0
            elif ri > delta:
                psi[i] = delta
                ell[a, i] = ri - delta
            elif ri < -delta:
                psi[i] = -delta
                ell[a, i] = ri + delta
            else:
                psi[i] = ri
                ell[a, i] = 0.0
            if abs(ri) > rmax:
                rmax = abs(ri)
        obj += huber_sum(r, delta, lsq)
        rmatvec(rp, ci, hv[a], psi, g)
        for j in range(n):
            if abs(g[j]) > stat:
                stat = abs(g[j])
        col[:] = 0.0
        for i in range(m):
            for k in range(rp[i], rp[i + 1]):
                col[ci[k]] += abs(hv[a, k])
        for j in range(n):
            if col[j] * delta > scale:
                scale = col[j] * delta
    return obj, ell, stat, scale, rmax


def evaluate_solution(prob: HuberProblem, X: np.ndarray, solver: str, iterations: int = 0, status: str = "solved",
                      kkt_extra: dict | None = None, extra: dict | None = None) -> SolveOut:
    """The :class:`SolveOut` of a solver's x (A, n): objective, ℓ̄ and KKT residuals by
    :func:`evaluate_all` (``gap`` NaN unless ``kkt_extra`` gives it), plus the solver's own data."""
    X = np.ascontiguousarray(X, dtype=float)
    obj, ell, stat, scale, rmax = evaluate_all(prob.rp, prob.ci, prob.hv, prob.z, prob.n, prob.delta,
                                               prob.lsq_mask(), X)
    kkt = {"stationarity": float(stat), "stationarity_rel": float(stat / scale) if scale > 0 else float(stat),
           "gap": float("nan"), "max_abs_residual": float(rmax)}
    if kkt_extra:
        kkt.update(kkt_extra)
    return SolveOut(X, ell, float(obj), kkt, iterations, status, solver, extra or {})
