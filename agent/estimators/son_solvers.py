"""Solvers for the sum-of-norms estimator (10) of García Carrillo et al., behind one interface.

The problem
-----------
Eliminating ℓ̄ from (10) row by row (PAPER_NOTES 004) leaves a Huber regression on the whitened
residuals r = z − Hx:

    min_x  P(x) = Σᵢ huber_δ(rᵢ),   huber_δ(r) = r²/2 (|r| ≤ δ),  δ|r| − δ²/2 (|r| > δ),

with ℓ̄ = soft_threshold(r, δ) at the optimum and, for (10) with parameter λ and residual scale c
(residuals divided by c before (10) is applied),

    δ = c·√2·λ²/(1 − λ),   objective(10) = P(x) / (λ²c²).

Every solver here returns the same :class:`SolveOut`: x, the objective P(x) evaluated by one common
function at the solver's own x (so solvers are compared on equal terms), ℓ̄ per row and KKT residuals:

* ``stationarity``     ‖Hᵀψ(z − Hx)‖∞ with ψ = clip(·, −δ, δ) — the gradient of P (P is C¹), zero
                        exactly at an optimum;
* ``stationarity_rel`` the same divided by max_j Σᵢ|Hᵢⱼ|·δ (the largest value it could take);
* ``gap``               a duality-gap certificate P(x) − D(u) ≥ P(x) − P* where the solver supplies a
                        dual point u (the IPM does; NaN otherwise);
* solver-specific residuals (OSQP's prim/dual residuals, …).

Problem data (:class:`HuberProblem`) are one or more independent problems ("axes") sharing one
sparsity pattern, rows stored CSR: ``rp`` (m+1), ``ci`` (nnz), values ``hv`` (A, nnz), ``z`` (A, m).
The x/y split of the UAV problem gives A = 2 problems with the same pattern; a window with correlated
(non-diagonal) covariances gives one joint problem (A = 1).

Solvers
-------
* :func:`solve_ipm` — the default: a primal–dual Mehrotra predictor–corrector interior-point method
  on the Huber dual  max_u zᵀu − ½‖u‖²  s.t. Hᵀu = 0, −δ ≤ u ≤ δ  (x is the multiplier of Hᵀu = 0),
  compiled with numba. Its Newton system reduces to the n×n normal matrix HᵀΘH (Θ diagonal, ≤ 1):

  - for the per-axis UAV graph (a *chain* of target nodes (p, v) in time order, each with a leaf u
    for the measuring agent) the leaves are eliminated (Schur complement of a diagonal) and the
    block-tridiagonal 2×2 remainder is factored by the block Thomas recursion: O(W) per iteration
    with closed-form 2×2 blocks;
  - for any other pattern (the joint problem of correlated covariances) HᵀΘH is *banded* because
    nodes are ordered by time, and is Cholesky-factored in band storage (O(n·bw²)).

  Start: the least-squares x, u = 0 and multipliers that make both linear residuals exactly zero (a
  feasible start that Newton steps keep), so only complementarity is driven down. Stop: the certified
  relative gap P(x) − D(u) ≤ ``tol``·max(1, P). *Polish*: whenever the gap is below
  ``polish_gap``·max(1, P) and the active set read from the residuals changed, the piecewise-quadratic
  stationarity equation H_QᵀH_Q x = H_Qᵀz_Q + δ·H_Lᵀsign (Q: rows with |rᵢ| < δ, L: the others) is
  solved exactly; if the new residuals fall in the assumed pieces, Hᵀψ(z − Hx) = 0 holds to rounding:
  an exact optimum, returned at once (this typically halves the iterations). After the IPM the active
  set is read from the primal, then from the dual, then with near-kink rows taken quadratic. Both axes
  are solved in one compiled call; no Python runs inside the iteration.
* :class:`OsqpSolver` — (10) as the QP  min ½‖w‖² + δ·1ᵀ(a + b)  s.t. Hx + w + a − b = z,  a, b ≥ 0
  (ℓ̄ = a − b; this is (10) scaled by λ²c² with the quadratic term carried by w = r − ℓ̄). The OSQP
  object is set up once per window *shape* (sparsity pattern) and afterwards only updated
  (``Ax``, ``l``, ``u``, ``q``).
* :class:`CvxpyReference` — the literal (10) in x and ℓ̄ (c = 1, λ = λ(δ)) with cvxpy + Clarabel, a
  DPP-parametrised problem compiled once per shape; the independent reference of the tests.
* :func:`solve_ls` — least squares (δ = ∞), the batched-least-squares baseline, by one banded solve.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
from numba import njit


# ============================================================================= data


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
        """Identity of the sparsity pattern (what an OSQP/cvxpy set-up depends on)."""
        return (self.axes, self.n, self.rp.tobytes(), self.ci.tobytes())

    def with_delta(self, delta: float) -> "HuberProblem":
        return HuberProblem(self.rp, self.ci, self.hv, self.z, self.n, self.bw, float(delta), self.chain)

    def without_chain(self) -> "HuberProblem":
        """The same problem for the generic banded path."""
        return HuberProblem(self.rp, self.ci, self.hv, self.z, self.n, self.bw, self.delta, None)

    def chain_arg(self) -> tuple:
        if self.chain is None:
            return _NO_CHAIN
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


# ============================================================================= numba kernels


@njit(cache=True, error_model="numpy")
def bandwidth(rp, ci):
    """Max |i − j| over pairs of columns sharing a row (the half-bandwidth of HᵀH)."""
    bw = 0
    for r in range(rp.shape[0] - 1):
        if rp[r + 1] == rp[r]:
            continue
        lo = ci[rp[r]]
        hi = lo
        for a in range(rp[r], rp[r + 1]):
            c = ci[a]
            if c < lo:
                lo = c
            if c > hi:
                hi = c
        if hi - lo > bw:
            bw = hi - lo
    return bw


@njit(cache=True, error_model="numpy")
def _matvec(rp, ci, hv, x, out):
    for r in range(rp.shape[0] - 1):
        s = 0.0
        for a in range(rp[r], rp[r + 1]):
            s += hv[a] * x[ci[a]]
        out[r] = s


@njit(cache=True, error_model="numpy")
def _rmatvec(rp, ci, hv, y, out):
    out[:] = 0.0
    for r in range(rp.shape[0] - 1):
        yr = y[r]
        if yr == 0.0:
            continue
        for a in range(rp[r], rp[r + 1]):
            out[ci[a]] += hv[a] * yr


@njit(cache=True, error_model="numpy")
def _normal(rp, ci, hv, theta, L):
    """Band storage of HᵀΘH: L[i, d] = N[i, i − d] (lower band)."""
    L[:, :] = 0.0
    for r in range(rp.shape[0] - 1):
        th = theta[r]
        if th == 0.0:
            continue
        for a in range(rp[r], rp[r + 1]):
            i = ci[a]
            hia = hv[a] * th
            for b in range(rp[r], rp[r + 1]):
                j = ci[b]
                if j <= i:
                    L[i, i - j] += hia * hv[b]


@njit(cache=True, error_model="numpy")
def _chol(L, n, bw):
    """In-place banded Cholesky. A pivot that collapses below 1e-13 of its original value is replaced
    by 1e128 (Wright's modified Cholesky for interior-point methods: the corresponding direction is
    dropped instead of blowing up). Returns the number of such pivots."""
    bad = 0
    for j in range(n):
        d0 = L[j, 0]
        s = d0
        k0 = j - bw
        if k0 < 0:
            k0 = 0
        for k in range(k0, j):
            v = L[j, j - k]
            s -= v * v
        if s <= 1e-13 * abs(d0) or s <= 1e-300:
            s = 1e128
            bad += 1
        dj = math.sqrt(s)
        L[j, 0] = dj
        i1 = j + bw + 1
        if i1 > n:
            i1 = n
        for i in range(j + 1, i1):
            s2 = L[i, i - j]
            k0 = i - bw
            if k0 < 0:
                k0 = 0
            for k in range(k0, j):
                s2 -= L[i, i - k] * L[j, j - k]
            L[i, i - j] = s2 / dj
    return bad


@njit(cache=True, error_model="numpy")
def _chol_solve(L, n, bw, b):
    """Solve (LLᵀ) y = b in place."""
    for i in range(n):
        s = b[i]
        k0 = i - bw
        if k0 < 0:
            k0 = 0
        for k in range(k0, i):
            s -= L[i, i - k] * b[k]
        b[i] = s / L[i, 0]
    for i in range(n - 1, -1, -1):
        s = b[i]
        k1 = i + bw + 1
        if k1 > n:
            k1 = n
        for k in range(i + 1, k1):
            s -= L[k, k - i] * b[k]
        b[i] = s / L[i, 0]


@njit(cache=True, error_model="numpy")
def _huber_sum(r, delta):
    s = 0.0
    for i in range(r.shape[0]):
        a = abs(r[i])
        if a <= delta:
            s += 0.5 * a * a
        else:
            s += delta * a - 0.5 * delta * delta
    return s


@njit(cache=True, error_model="numpy")
def _chain_factor(rp, hv, th, rt, rn, uix, K, Nuu, Nup, D, E, Sinv, G):
    """Normal matrix HᵀΘH of a *chain* problem (the per-axis UAV graph of sum_of_norms.build_split:
    target nodes (p_k, v_k) in time order joined by motion rows, each with an optional leaf u_k joined
    to p_k by the relative row), with the leaves eliminated (Schur complement of the diagonal N_uu)
    and the remaining block-tridiagonal 2×2 system factored by the block Thomas recursion
    S_k = D_k − E_k S_{k−1}⁻¹ E_kᵀ (closed-form 2×2 LDLᵀ; a collapsing pivot is replaced by 1e128 as
    in :func:`_chol`). Returns the number of replaced pivots."""
    Nrel = np.zeros((K, 2))
    for k in range(K):
        Nuu[k] = 0.0
        Nup[k] = 0.0
        for j in range(3):
            D[k, j] = 0.0
        for j in range(4):
            E[k, j] = 0.0
    for r in range(rp.shape[0] - 1):
        t = th[r]
        a = rp[r]
        k = rn[r]
        typ = rt[r]
        if typ <= 1:
            h0 = hv[a]
            h1 = hv[a + 1]
            h2 = hv[a + 2]
            h3 = hv[a + 3]
            t0 = t * h0
            t1 = t * h1
            t2 = t * h2
            t3 = t * h3
            D[k - 1, 0] += t0 * h0
            D[k - 1, 1] += t0 * h1
            D[k - 1, 2] += t1 * h1
            D[k, 0] += t2 * h2
            D[k, 1] += t2 * h3
            D[k, 2] += t3 * h3
            E[k, 0] += t2 * h0
            E[k, 1] += t2 * h1
            E[k, 2] += t3 * h0
            E[k, 3] += t3 * h1
        elif typ == 2:
            h0 = hv[a]
            Nuu[k] += t * h0 * h0  # the GPS part of N_uu (the relative part is added below)
        elif typ == 3:
            if rp[r + 1] - a == 2:
                h0 = hv[a]
                h1 = hv[a + 1]
                Nrel[k, 0] = t * h0 * h0
                Nup[k] = t * h0 * h1
                Nrel[k, 1] = t * h1 * h1
            else:
                h0 = hv[a]
                D[k, 0] += t * h0 * h0
        else:
            h0 = hv[a]
            D[k, 2] += t * h0 * h0
    bad = 0
    for k in range(K):
        if uix[k] >= 0:
            # eliminate the leaf u_k: D_pp += a − b²/c with a = θ_r h_p², b = θ_r h_u h_p,
            # c = θ_g h_g² + θ_r h_u², written without cancellation as a·(θ_g h_g²)/c
            ng = Nuu[k]
            c = ng + Nrel[k, 0]
            if c <= 1e-300:
                c = 1e-300
                bad += 1
            D[k, 0] += Nrel[k, 1] * (ng / c)
            Nuu[k] = c
        s00 = D[k, 0]
        s01 = D[k, 1]
        s11 = D[k, 2]
        if k > 0:
            e0 = E[k, 0]
            e1 = E[k, 1]
            e2 = E[k, 2]
            e3 = E[k, 3]
            i0 = Sinv[k - 1, 0]
            i1 = Sinv[k - 1, 1]
            i2 = Sinv[k - 1, 2]
            g00 = e0 * i0 + e1 * i1
            g01 = e0 * i1 + e1 * i2
            g10 = e2 * i0 + e3 * i1
            g11 = e2 * i1 + e3 * i2
            G[k, 0] = g00
            G[k, 1] = g01
            G[k, 2] = g10
            G[k, 3] = g11
            s00 -= g00 * e0 + g01 * e1
            s01 -= g00 * e2 + g01 * e3
            s11 -= g10 * e2 + g11 * e3
        p1 = s00
        if p1 <= 1e-13 * abs(D[k, 0]) or p1 <= 1e-300:
            p1 = 1e128
            bad += 1
        lf = s01 / p1
        p2 = s11 - lf * s01
        if p2 <= 1e-13 * abs(D[k, 2]) or p2 <= 1e-300:
            p2 = 1e128
            bad += 1
        ip2 = 1.0 / p2
        Sinv[k, 0] = 1.0 / p1 + lf * lf * ip2
        Sinv[k, 1] = -lf * ip2
        Sinv[k, 2] = ip2
    return bad


@njit(cache=True, error_model="numpy")
def _chain_solve(b, uix, pix, vix, K, Nuu, Nup, E, Sinv, G, Y):
    """Solve HᵀΘH y = b in place with the factors of :func:`_chain_factor`."""
    for k in range(K):
        b0 = b[pix[k]]
        b1 = b[vix[k]]
        if uix[k] >= 0:
            b0 -= Nup[k] / Nuu[k] * b[uix[k]]
        if k > 0:
            y0 = Y[k - 1, 0]
            y1 = Y[k - 1, 1]
            b0 -= G[k, 0] * y0 + G[k, 1] * y1
            b1 -= G[k, 2] * y0 + G[k, 3] * y1
        Y[k, 0] = b0
        Y[k, 1] = b1
    xp = 0.0
    xv = 0.0
    for k in range(K - 1, -1, -1):
        c0 = Y[k, 0]
        c1 = Y[k, 1]
        if k < K - 1:
            c0 -= E[k + 1, 0] * xp + E[k + 1, 2] * xv
            c1 -= E[k + 1, 1] * xp + E[k + 1, 3] * xv
        xp = Sinv[k, 0] * c0 + Sinv[k, 1] * c1
        xv = Sinv[k, 1] * c0 + Sinv[k, 2] * c1
        if uix[k] >= 0:
            b[uix[k]] = (b[uix[k]] - Nup[k] * xp) / Nuu[k]
        b[pix[k]] = xp
        b[vix[k]] = xv


@njit(cache=True, error_model="numpy")
def _factor(rp, ci, hv, th, n, bw, ws, ch):
    """Factor HᵀΘH: chain recursion if a chain layout is given (K > 0), else banded Cholesky."""
    L, Nuu, Nup, D, E, Sinv, G, Y = ws
    rt, rn, uix, pix, vix = ch
    K = uix.shape[0]
    if K > 0:
        return _chain_factor(rp, hv, th, rt, rn, uix, K, Nuu, Nup, D, E, Sinv, G)
    _normal(rp, ci, hv, th, L)
    return _chol(L, n, bw)


@njit(cache=True, error_model="numpy")
def _solve(b, n, bw, ws, ch):
    L, Nuu, Nup, D, E, Sinv, G, Y = ws
    rt, rn, uix, pix, vix = ch
    K = uix.shape[0]
    if K > 0:
        _chain_solve(b, uix, pix, vix, K, Nuu, Nup, E, Sinv, G, Y)
    else:
        _chol_solve(L, n, bw, b)


@njit(cache=True, error_model="numpy")
def _workspace(n, bw, K):
    if K > 0:
        L = np.empty((1, 1))
    else:
        L = np.empty((n, bw + 1))
    return (L, np.empty(K), np.empty(K), np.empty((K, 3)), np.empty((K, 4)), np.empty((K, 3)),
            np.empty((K, 4)), np.empty((K, 2)))


@njit(cache=True, error_model="numpy")
def _ls_solve(rp, ci, hv, z, n, bw, theta, x, ws, ch):
    """x = argmin Σ θᵢ (zᵢ − hᵢx)² by one factorisation. Returns the count of replaced pivots."""
    bad = _factor(rp, ci, hv, theta, n, bw, ws, ch)
    tz = np.empty(z.shape[0])
    for i in range(z.shape[0]):
        tz[i] = theta[i] * z[i]
    _rmatvec(rp, ci, hv, tz, x)
    _solve(x, n, bw, ws, ch)
    return bad


@njit(cache=True, error_model="numpy")
def _polish(rp, ci, hv, z, n, bw, delta, quad, sgn, ws, ch, Pcur, xn, r):
    """Active-set solve: rows with ``quad`` are taken as quadratic, the others as linear with sign
    ``sgn``, and the piecewise-quadratic stationarity H_QᵀH_Q x = H_Qᵀz_Q + δ·H_Lᵀsign is solved into xn.
    Returns (P(xn), consistent, improved): *consistent* means the new residuals fall in the assumed
    pieces (then Hᵀψ(z − H xn) = 0 up to rounding: xn is an exact optimum); *improved* that P(xn) ≤ Pcur
    (for a consistent point: up to rounding)."""
    m = rp.shape[0] - 1
    th = np.empty(m)
    w = np.empty(m)  # right-hand side: z on quadratic rows, δ·sign on linear rows (θ = 0 there)
    nq = 0
    for i in range(m):
        if quad[i]:
            th[i] = 1.0
            w[i] = z[i]
            nq += 1
        else:
            th[i] = 0.0
            w[i] = delta * sgn[i]
    if nq == 0:
        return Pcur, False, False
    bad = _factor(rp, ci, hv, th, n, bw, ws, ch)
    if bad > 0:
        return Pcur, False, False
    _rmatvec(rp, ci, hv, w, xn)
    _solve(xn, n, bw, ws, ch)
    _matvec(rp, ci, hv, xn, r)
    consistent = True
    lo = delta * (1.0 - 1e-11)
    hi = delta * (1.0 + 1e-11)
    for i in range(m):
        ri = z[i] - r[i]
        r[i] = ri
        if quad[i]:
            if abs(ri) > hi:
                consistent = False
        elif ri * sgn[i] < lo:
            consistent = False
    Pn = _huber_sum(r, delta)
    # a consistent point is an exact optimum: P may exceed Pcur only by rounding
    improved = Pn <= Pcur or (consistent and Pn <= Pcur + 1e-10 * max(1.0, abs(Pcur)))
    return Pn, consistent, improved


@njit(cache=True, error_model="numpy")
def _partition_primal(r, delta, quad, sgn):
    """Active set read from the residuals: quadratic iff |r| < δ."""
    for i in range(r.shape[0]):
        quad[i] = abs(r[i]) < delta
        sgn[i] = 1.0 if r[i] > 0 else -1.0


@njit(cache=True, error_model="numpy")
def _partition_dual(u, ya, yb, delta, quad, sgn):
    """Active set read from the IPM's dual iterate: linear iff a bound multiplier dominates its slack
    (ya/(δ − u) + yb/(δ + u) ≥ 1, i.e. Θ ≤ ½), with the sign of u."""
    for i in range(u.shape[0]):
        quad[i] = ya[i] / (delta - u[i]) + yb[i] / (delta + u[i]) < 1.0
        sgn[i] = 1.0 if u[i] > 0 else -1.0


@njit(cache=True, error_model="numpy")
def _step_limit(sa, sb, ya, yb, du, dya, dyb):
    """Largest α ≤ 1 keeping sa − α du, sb + α du, ya + α dya, yb + α dyb ≥ 0."""
    amax = 1.0
    for i in range(sa.shape[0]):
        d = du[i]
        if d * amax > sa[i]:
            amax = sa[i] / d
        elif -d * amax > sb[i]:
            amax = -sb[i] / d
        if -dya[i] * amax > ya[i]:
            amax = -ya[i] / dya[i]
        if -dyb[i] * amax > yb[i]:
            amax = -yb[i] / dyb[i]
    return amax


@njit(cache=True, error_model="numpy")
def _ipm_one(rp, ci, hv, z, n, bw, ch, delta, tol, maxit, do_polish, ptol, x, u):
    """Mehrotra predictor–corrector IPM on the Huber dual for one problem.

    Variables: x (n; the primal estimate, multiplier of Hᵀu = 0), u (m, dual), ya, yb (m, multipliers
    of u ≤ δ and −u ≤ δ) with slacks sa = δ − u, sb = δ + u. The start is feasible for both linear
    equations (Hᵀu = 0, u − r + ya − yb = 0); Newton steps keep them (their residuals are still carried,
    scaled by (1 − step), and the final certificate is recomputed exactly). Returns (iterations,
    certified gap P(x) − D(u), P(x), ‖Hᵀu‖∞, polish (1 exact active-set optimum, 0.5 improved only,
    0 none), status (0 converged / exact, 1 iteration limit, 2 stalled, 3 numerical breakdown))."""
    m = rp.shape[0] - 1
    ws = _workspace(n, bw, ch[2].shape[0])
    th = np.ones(m)
    # -- start: least-squares x, u = 0 and multipliers that zero both linear residuals
    _ls_solve(rp, ci, hv, z, n, bw, th, x, ws, ch)
    r = np.empty(m)
    _matvec(rp, ci, hv, x, r)
    amean = 0.0
    for i in range(m):
        r[i] = z[i] - r[i]
        amean += abs(r[i])
    amean /= m
    tau = max(delta, 0.5 * amean)
    ya = np.empty(m)
    yb = np.empty(m)
    rd = np.zeros(m)
    for i in range(m):
        u[i] = 0.0
        ya[i] = max(r[i], 0.0) + tau
        yb[i] = max(-r[i], 0.0) + tau
        rd[i] = u[i] - r[i] + ya[i] - yb[i]
    rpv = np.zeros(n)
    sa = np.empty(m)
    sb = np.empty(m)
    g = np.empty(m)
    dx = np.empty(n)
    du = np.empty(m)
    dya = np.empty(m)
    dyb = np.empty(m)
    hdx = np.empty(m)
    tmp = np.empty(m)
    isa = np.empty(m)
    isb = np.empty(m)
    xp = np.empty(n)
    xbest = np.empty(n)
    rtmp = np.empty(m)
    quad = np.empty(m, np.bool_)
    sgn = np.empty(m)
    inexact = False
    best_gap = 1e300
    stall = 0
    last_sig = -1.2345e300
    polished = False
    it = 0
    status = 1
    P = 0.0
    gap = 0.0
    scale_p = 1.0
    while True:
        # complementarity, the certificate P(x) − D(u) and the active-set signature
        mu = 0.0
        D = 0.0
        P = 0.0
        sig_ = 0.0
        for i in range(m):
            ui = u[i]
            ri = r[i]
            sa[i] = max(delta - ui, 1e-300)  # > 0 in exact arithmetic; guard against rounding
            sb[i] = max(delta + ui, 1e-300)
            mu += ya[i] * sa[i] + yb[i] * sb[i]
            D += z[i] * ui - 0.5 * ui * ui
            a_ = abs(ri)
            if a_ <= delta:
                P += 0.5 * a_ * a_
            else:
                P += delta * a_ - 0.5 * delta * delta
                sig_ += (i + 1.0) if ri > 0 else -1.618 * (i + 1.0)
        mu /= 2.0 * m
        gap = P - D
        scale_p = max(1.0, abs(P))
        if gap <= tol * scale_p or not mu > 0.0:
            status = 0
            break
        # stagnation at the precision limit of an ill-conditioned problem: stop, then polish
        if gap < 0.7 * best_gap:
            best_gap = gap
            stall = 0
        else:
            stall += 1
            if stall >= 3:
                status = 2
                break
        if do_polish and gap <= ptol * scale_p and sig_ != last_sig:
            # the active set has probably been identified: try the exact piecewise-quadratic solve
            last_sig = sig_
            _partition_primal(r, delta, quad, sgn)
            Pn, cons, impr = _polish(rp, ci, hv, z, n, bw, delta, quad, sgn, ws, ch, P, xp, rtmp)
            if cons and impr:
                for j in range(n):
                    x[j] = xp[j]
                P = Pn
                polished = True
                status = 0
                break
        if it >= maxit:
            break
        it += 1
        # normal matrix HᵀΘH, Θ = 1/(1 + ya/sa + yb/sb); predictor right-hand side (targets 0)
        for i in range(m):
            ia = 1.0 / sa[i]
            ib = 1.0 / sb[i]
            isa[i] = ia
            isb[i] = ib
            t_ = 1.0 / (1.0 + ya[i] * ia + yb[i] * ib)
            th[i] = t_
            gi = -rd[i] + ya[i] - yb[i]
            g[i] = gi
            tmp[i] = gi * t_
        _factor(rp, ci, hv, th, n, bw, ws, ch)
        _rmatvec(rp, ci, hv, tmp, dx)
        for j in range(n):
            dx[j] += rpv[j]
        _solve(dx, n, bw, ws, ch)
        _matvec(rp, ci, hv, dx, hdx)
        amax = 1.0
        for i in range(m):
            d = (g[i] - hdx[i]) * th[i]
            da = ya[i] * (d * isa[i] - 1.0)
            db = -yb[i] * (d * isb[i] + 1.0)
            du[i] = d
            dya[i] = da
            dyb[i] = db
            if d * amax > sa[i]:
                amax = sa[i] / d
            elif -d * amax > sb[i]:
                amax = -sb[i] / d
            if -da * amax > ya[i]:
                amax = -ya[i] / da
            if -db * amax > yb[i]:
                amax = -yb[i] / db
        mua = 0.0
        for i in range(m):
            mua += (ya[i] + amax * dya[i]) * (sa[i] - amax * du[i]) + (yb[i] + amax * dyb[i]) * (sb[i] + amax * du[i])
        mua /= 2.0 * m
        sig = mua / mu
        sig = sig * sig * sig
        if sig > 1.0:
            sig = 1.0
        smu = sig * mu
        # --- corrector: targets ta = σμ + Δya·Δu, tb = σμ − Δyb·Δu (second-order terms)
        for i in range(m):
            ta = smu + dya[i] * du[i]
            tb = smu - dyb[i] * du[i]
            gi = -rd[i] - ta * isa[i] + ya[i] + tb * isb[i] - yb[i]
            g[i] = gi
            tmp[i] = gi * th[i]
            dya[i] = ta  # kept for the multiplier update below
            dyb[i] = tb
        _rmatvec(rp, ci, hv, tmp, dx)
        for j in range(n):
            dx[j] += rpv[j]
        _solve(dx, n, bw, ws, ch)
        _matvec(rp, ci, hv, dx, hdx)
        amax = 1.0
        for i in range(m):
            d = (g[i] - hdx[i]) * th[i]
            da = -ya[i] + (dya[i] + ya[i] * d) * isa[i]
            db = -yb[i] + (dyb[i] - yb[i] * d) * isb[i]
            du[i] = d
            dya[i] = da
            dyb[i] = db
            if d * amax > sa[i]:
                amax = sa[i] / d
            elif -d * amax > sb[i]:
                amax = -sb[i] / d
            if -da * amax > ya[i]:
                amax = -ya[i] / da
            if -db * amax > yb[i]:
                amax = -yb[i] / db
        step = 0.995 * amax
        if step > 1.0:
            step = 1.0
        fin = step
        for j in range(n):
            fin += 0.0 * dx[j]
        for i in range(m):
            fin += 0.0 * (du[i] + dya[i] + dyb[i])
        if not math.isfinite(fin):  # numerical breakdown: keep the last finite iterate
            status = 3
            break
        for j in range(n):
            x[j] += step * dx[j]
            rpv[j] *= 1.0 - step  # Hᵀ(u + step·du) = (1 − step)·Hᵀu for an exact Newton step
        for i in range(m):
            u[i] += step * du[i]
            ya[i] += step * dya[i]
            yb[i] += step * dyb[i]
            r[i] -= step * hdx[i]
            rd[i] *= 1.0 - step
    if do_polish and not polished:
        # exact active-set solve from the primal, then from the dual reading of the active set; keep the
        # first consistent (exactly optimal) point, else any improvement
        _matvec(rp, ci, hv, x, r)
        for i in range(m):
            r[i] = z[i] - r[i]
        best = P
        for attempt in range(3):
            if attempt == 0:
                _partition_primal(r, delta, quad, sgn)
            elif attempt == 1:
                _partition_dual(u, ya, yb, delta, quad, sgn)
            else:
                # rows within 1e-3·δ of the kink are ambiguous at the IPM's tolerance: take them quadratic
                _partition_primal(r, delta * (1.0 + 1e-3), quad, sgn)
            Pn, cons, impr = _polish(rp, ci, hv, z, n, bw, delta, quad, sgn, ws, ch, P, xp, rtmp)
            if cons and impr:
                for j in range(n):
                    x[j] = xp[j]
                polished = True
                status = 0  # an exact optimum, whatever stopped the IPM
                break
            if impr and Pn < best:
                best = Pn
                for j in range(n):
                    xbest[j] = xp[j]
        if not polished and best < P:
            for j in range(n):
                x[j] = xbest[j]
            inexact = True
    # exact certificate at the returned point
    _matvec(rp, ci, hv, x, r)
    for i in range(m):
        r[i] = z[i] - r[i]
    P = _huber_sum(r, delta)
    if polished:
        # u = ψ(z − Hx) is box-feasible; at an exact optimum Hᵀu = 0 and P(x) − D(u) = 0
        for i in range(m):
            ri = r[i]
            if ri > delta:
                ri = delta
            elif ri < -delta:
                ri = -delta
            u[i] = ri
    D = 0.0
    for i in range(m):
        D += z[i] * u[i] - 0.5 * u[i] * u[i]
    _rmatvec(rp, ci, hv, u, rpv)
    pres = 0.0
    for j in range(n):
        if abs(rpv[j]) > pres:
            pres = abs(rpv[j])
    gap = P - D
    return it, gap, P, pres, 1.0 if polished else (0.5 if inexact else 0.0), status


@njit(cache=True, error_model="numpy")
def ipm_solve_all(rp, ci, hv, z, n, bw, ch, delta, tol, maxit, do_polish, ptol):
    """Solve every axis of a :class:`HuberProblem` (one compiled call). ``ch`` = (rowtype, rownode,
    uix, pix, vix) of a chain layout, or empty arrays for the banded path. Returns X (A, n),
    U (A, m), info (A, 6): iterations, certified gap, P, ‖Hᵀu‖∞, polish (1 exact active-set optimum,
    0.5 improved but not proven exact, 0 none), status (0 converged or exact active-set optimum,
    1 iteration limit, 2 stalled at the precision limit, 3 numerical breakdown)."""
    A = hv.shape[0]
    m = rp.shape[0] - 1
    X = np.empty((A, n))
    U = np.empty((A, m))
    info = np.empty((A, 6))
    for a in range(A):
        it, gap, P, pres, pol, st = _ipm_one(rp, ci, hv[a], z[a], n, bw, ch, delta, tol, maxit, do_polish, ptol,
                                             X[a], U[a])
        info[a, 0] = it
        info[a, 1] = gap
        info[a, 2] = P
        info[a, 3] = pres
        info[a, 4] = pol
        info[a, 5] = st
    return X, U, info


@njit(cache=True, error_model="numpy")
def ls_solve_all(rp, ci, hv, z, n, bw, ch):
    A = hv.shape[0]
    m = rp.shape[0] - 1
    X = np.empty((A, n))
    ws = _workspace(n, bw, ch[2].shape[0])
    th = np.ones(m)
    bad = 0
    for a in range(A):
        bad += _ls_solve(rp, ci, hv[a], z[a], n, bw, th, X[a], ws, ch)
    return X, bad


@njit(cache=True, error_model="numpy")
def evaluate_all(rp, ci, hv, z, n, delta, X):
    """Common evaluation: objective Σ P, ℓ̄ = soft(r, δ) (A, m), stationarity ‖Hᵀψ(r)‖∞ and its scale
    max_j Σᵢ|Hᵢⱼ|·δ, and max |r|."""
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
        _matvec(rp, ci, hv[a], X[a], r)
        for i in range(m):
            ri = z[a, i] - r[i]
            r[i] = ri
            if ri > delta:
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
        obj += _huber_sum(r, delta)
        _rmatvec(rp, ci, hv[a], psi, g)
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


# ============================================================================= the UAV graph (compiled)
# The builder of sum_of_norms' per-axis problem and its fused build+solve path live here, beside the
# kernels they call: numba's on-disk cache tracks one source file per function, so a cached caller in
# another file could otherwise keep running stale callees after an edit.


@njit(cache=True, error_model="numpy")
def _motion_w(dt, q, dt_floor, mode):
    """Whitening (2×2) of the motion residual [e_p, e_v] over Δt (per axis), mode 0 chol / 1 sym."""
    d = dt if dt > dt_floor else dt_floor
    c00 = q * d * d * d / 3.0
    c01 = q * d * d / 2.0
    c11 = q * d
    W = np.zeros((2, 2))
    if mode == 0:
        a = math.sqrt(c00)
        b = c01 / a
        c = math.sqrt(c11 - b * b)
        W[0, 0] = 1.0 / a
        W[1, 0] = -b / (a * c)
        W[1, 1] = 1.0 / c
    else:
        s = math.sqrt(c00 * c11 - c01 * c01)
        tt = math.sqrt(c00 + c11 + 2.0 * s)
        # C^{1/2} = (C + sI)/tt ; invert the 2×2
        s00 = (c00 + s) / tt
        s01 = c01 / tt
        s11 = (c11 + s) / tt
        det = s00 * s11 - s01 * s01
        W[0, 0] = s11 / det
        W[0, 1] = -s01 / det
        W[1, 0] = -s01 / det
        W[1, 1] = s00 / det
    return W


@njit(cache=True, error_model="numpy")
def _order(t, seq, count):
    """Indices of the first ``count`` slots sorted by (t, seq) (insertion sort: count is small)."""
    idx = np.empty(count, np.int64)
    for i in range(count):
        idx[i] = i
    for i in range(1, count):
        k = idx[i]
        j = i - 1
        while j >= 0 and (t[idx[j]] > t[k] or (t[idx[j]] == t[k] and seq[idx[j]] > seq[k])):
            idx[j + 1] = idx[j]
            j -= 1
        idx[j + 1] = k
    return idx


@njit(cache=True, error_model="numpy")
def build_split(t, seq, kind, z, gps, wr, wg, count, q, dt_floor, mode, v_prior):
    """Per-axis problems (all covariances diagonal). Slots are unsorted; ``wr``/``wg`` (cap, 2) hold the
    per-axis whitening scales 1/σ. Node k (time order) has variables [u_k (kind 1 only), p_k, v_k].

    Rows, per node in time order: the two motion rows from the previous node (entries [p_{k−1}, v_{k−1},
    p_k, v_k]), the GPS row ([u_k]), the relative row ([u_k, p_k], or [p_k] for agent 0); a single-node
    window adds a weak zero-velocity prior row ([v_0]). ``rowtype``: 0/1 motion (position/velocity
    row), 2 GPS, 3 relative, 4 prior; ``rownode``: node index. The chain solver relies on this layout.

    Returns order, rp, ci, hv (2, nnz), zz (2, m), n, uix, pix, vix, rowtype, rownode."""
    order = _order(t, seq, count)
    uix = np.full(count, -1, np.int64)
    pix = np.empty(count, np.int64)
    vix = np.empty(count, np.int64)
    n = 0
    for k in range(count):
        s = order[k]
        if kind[s] == 1:
            uix[k] = n
            n += 1
        pix[k] = n
        vix[k] = n + 1
        n += 2
    mmax = 4 * count + 2
    nnzmax = 11 * count + 4
    rp = np.zeros(mmax + 1, np.int64)
    ci = np.empty(nnzmax, np.int64)
    hv = np.empty((2, nnzmax))
    zz = np.zeros((2, mmax))
    rowtype = np.empty(mmax, np.int64)
    rownode = np.empty(mmax, np.int64)
    m = 0
    nz = 0
    for k in range(count):
        s = order[k]
        if k > 0:
            sp = order[k - 1]
            dt = t[s] - t[sp]
            W = _motion_w(dt, q, dt_floor, mode)
            for row in range(2):
                a0 = W[row, 0]
                a1 = W[row, 1]
                # a0 e_p + a1 e_v, e_p = p_k − p_{k−1} − Δt v_{k−1}, e_v = v_k − v_{k−1}
                ci[nz] = pix[k - 1]
                ci[nz + 1] = vix[k - 1]
                ci[nz + 2] = pix[k]
                ci[nz + 3] = vix[k]
                for ax in range(2):
                    hv[ax, nz] = -a0
                    hv[ax, nz + 1] = -(a0 * dt + a1)
                    hv[ax, nz + 2] = a0
                    hv[ax, nz + 3] = a1
                    zz[ax, m] = 0.0
                nz += 4
                rowtype[m] = row  # ROW_MOTION_P / ROW_MOTION_V
                rownode[m] = k
                m += 1
                rp[m] = nz
        if kind[s] == 1:
            # GPS row: gps = u
            ci[nz] = uix[k]
            for ax in range(2):
                hv[ax, nz] = wg[s, ax]
                zz[ax, m] = wg[s, ax] * gps[s, ax]
            nz += 1
            rowtype[m] = 2
            rownode[m] = k
            m += 1
            rp[m] = nz
            # relative row: z = p − u
            ci[nz] = uix[k]
            ci[nz + 1] = pix[k]
            for ax in range(2):
                hv[ax, nz] = -wr[s, ax]
                hv[ax, nz + 1] = wr[s, ax]
                zz[ax, m] = wr[s, ax] * z[s, ax]
            nz += 2
        else:
            ci[nz] = pix[k]
            for ax in range(2):
                hv[ax, nz] = wr[s, ax]
                zz[ax, m] = wr[s, ax] * z[s, ax]
            nz += 1
        rowtype[m] = 3
        rownode[m] = k
        m += 1
        rp[m] = nz
    if count == 1:
        # a single node: weak zero-velocity prior so that the problem has a unique solution
        ci[nz] = vix[0]
        for ax in range(2):
            hv[ax, nz] = 1.0 / v_prior
            zz[ax, m] = 0.0
        nz += 1
        rowtype[m] = 4
        rownode[m] = 0
        m += 1
        rp[m] = nz
    return (order, rp[: m + 1].copy(), ci[:nz].copy(), hv[:, :nz].copy(), zz[:, :m].copy(), n, uix, pix, vix,
            rowtype[:m].copy(), rownode[:m].copy())


@njit(cache=True, error_model="numpy")
def _fused_split_ipm(t, seq, kind, z, gps, wr, wg, count, q, dt_floor, mode, v_prior, delta, tol, maxit, polish,
                     ptol):
    """The hot path of :meth:`SumOfNormsEstimator.solve` for the default solver on a split window:
    build (:func:`build_split`), solve both axes (:func:`son_solvers.ipm_solve_all`), evaluate
    (:func:`son_solvers.evaluate_all`) and decode, in one compiled call."""
    order, rp, ci, hv, zz, n, uix, pix, vix, rowtype, rownode = build_split(
        t, seq, kind, z, gps, wr, wg, count, q, dt_floor, mode, v_prior)
    X, U, info = ipm_solve_all(rp, ci, hv, zz, n, bandwidth(rp, ci), (rowtype, rownode, uix, pix, vix), delta, tol,
                               maxit, polish, ptol)
    obj, ell, stat, scale, rmax = evaluate_all(rp, ci, hv, zz, n, delta, X)
    k = count
    target = np.empty((k, 4))
    uav = np.full((k, 2), np.nan)
    ellm = np.zeros((k, 2))
    times = np.empty(k)
    agents = np.empty(k, np.int64)
    for j in range(k):
        times[j] = t[order[j]]
        for ax in range(2):
            target[j, ax] = X[ax, pix[j]]
            target[j, 2 + ax] = X[ax, vix[j]]
            if uix[j] >= 0:
                uav[j, ax] = X[ax, uix[j]]
    for r in range(rowtype.shape[0]):
        if rowtype[r] == 3:
            ellm[rownode[r], 0] = ell[0, r]
            ellm[rownode[r], 1] = ell[1, r]
    summary = np.empty(9)
    summary[0] = obj
    summary[1] = stat
    summary[2] = stat / scale if scale > 0 else stat
    summary[3] = rmax
    summary[4] = info[0, 1] + info[1, 1]
    summary[5] = max(info[0, 3], info[1, 3])
    summary[6] = max(info[0, 0], info[1, 0])
    summary[7] = max(info[0, 5], info[1, 5])
    summary[8] = min(info[0, 4], info[1, 4])
    return order, times, X, target, uav, ellm, ell, summary


# ============================================================================= python interface

_E = np.zeros(0, np.int64)
_NO_CHAIN = (_E, _E, _E, _E, _E)
IPM_STATUS = ("solved", "max_iter", "stalled", "numerical_error")


def _finish(prob: HuberProblem, X: np.ndarray, solver: str, iterations: int = 0, status: str = "solved",
            kkt_extra: dict | None = None, extra: dict | None = None) -> SolveOut:
    X = np.ascontiguousarray(X, dtype=float)
    obj, ell, stat, scale, rmax = evaluate_all(prob.rp, prob.ci, prob.hv, prob.z, prob.n, prob.delta, X)
    kkt = {"stationarity": float(stat), "stationarity_rel": float(stat / scale) if scale > 0 else float(stat),
           "gap": float("nan"), "max_abs_residual": float(rmax)}
    if kkt_extra:
        kkt.update(kkt_extra)
    return SolveOut(X, ell, float(obj), kkt, iterations, status, solver, extra or {})


def solve_ipm(prob: HuberProblem, tol: float = 1e-9, maxit: int = 60, polish: bool = True,
              polish_gap: float = 0.3) -> SolveOut:
    """The default solver (see module doc). ``tol``: certified relative duality gap at which the IPM
    stops; ``polish_gap``: relative gap below which the exact active-set solve is attempted (whenever
    the active set changes) — accepted only if its residuals fall in the assumed pieces."""
    X, U, info = ipm_solve_all(prob.rp, prob.ci, prob.hv, prob.z, prob.n, prob.bw, prob.chain_arg(),
                               float(prob.delta), float(tol), int(maxit), bool(polish), float(polish_gap))
    status = IPM_STATUS[int(info[:, 5].max())]
    gap = float(info[:, 1].sum())
    return _finish(prob, X, "ipm", int(info[:, 0].max()), status,
                   {"gap": gap, "dual_infeasibility": float(info[:, 3].max())},
                   {"U": U, "polished": info[:, 4] == 1.0})


def ipm_raw(prob: HuberProblem, tol: float = 1e-9, maxit: int = 60, polish: bool = True,
            polish_gap: float = 0.3):
    """The compiled call alone (for benchmarks): returns (X, U, info)."""
    return ipm_solve_all(prob.rp, prob.ci, prob.hv, prob.z, prob.n, prob.bw, prob.chain_arg(),
                         float(prob.delta), float(tol), int(maxit), bool(polish), float(polish_gap))


def solve_ls(prob: HuberProblem) -> SolveOut:
    """Least squares on the same rows (δ = ∞): the batched-least-squares baseline."""
    X, bad = ls_solve_all(prob.rp, prob.ci, prob.hv, prob.z, prob.n, prob.bw, prob.chain_arg())
    return _finish(prob, X, "ls", 1, "solved" if bad == 0 else "rank_deficient")


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


# ----------------------------------------------------------------------------- OSQP


class OsqpSolver:
    """(10) as a QP for OSQP, set up once per window shape and then updated.

    Variables per axis (stacked over axes, block-diagonal): [x (n), w (m), a (m), b (m)];
    min ½‖w‖² + δ·1ᵀ(a + b)  s.t.  Hx + w + a − b = z  (l = u = z),  a ≥ 0,  b ≥ 0.
    """

    def __init__(self, eps_abs: float = 1e-8, eps_rel: float = 1e-8, max_iter: int = 50000,
                 polish: bool = True, warm_start: bool = True, cache_size: int = 8, **settings):
        self.settings = dict(eps_abs=eps_abs, eps_rel=eps_rel, max_iter=max_iter, polishing=polish,
                             warm_starting=warm_start, verbose=False, **settings)
        self._cache: OrderedDict = OrderedDict()
        self.cache_size = cache_size
        self.setups = 0

    def _setup(self, prob: HuberProblem):
        import osqp
        import scipy.sparse as sp

        A_, n, m = prob.axes, prob.n, prob.m
        nv = n + 3 * m
        rows, cols, ids = [], [], []
        # H block entries (ids = position in hv.ravel())
        rr = np.repeat(np.arange(m), np.diff(prob.rp))
        nnz = prob.ci.shape[0]
        for a in range(A_):
            rows.append(a * m + rr)
            cols.append(a * nv + prob.ci)
            ids.append(a * nnz + np.arange(nnz))
        base = A_ * nnz
        # identity blocks: w, a, −b  (equality rows), then a ≥ 0, b ≥ 0 rows
        const_vals = []
        k = 0
        for a in range(A_):
            ar = np.arange(m)
            for off, val in ((n, 1.0), (n + m, 1.0), (n + 2 * m, -1.0)):
                rows.append(a * m + ar)
                cols.append(a * nv + off + ar)
                ids.append(base + k + ar)
                const_vals.append(np.full(m, val))
                k += m
        neq = A_ * m
        for a in range(A_):
            ar = np.arange(2 * m)
            rows.append(neq + a * 2 * m + ar)
            cols.append(a * nv + n + m + ar)
            ids.append(base + k + ar)
            const_vals.append(np.ones(2 * m))
            k += 2 * m
        rows = np.concatenate(rows)
        cols = np.concatenate(cols)
        ids = np.concatenate(ids)
        const = np.concatenate(const_vals)
        nrow = neq + A_ * 2 * m
        M = sp.coo_matrix((ids.astype(float) + 1.0, (rows, cols)), shape=(nrow, A_ * nv)).tocsc()
        M.sort_indices()
        perm = M.data.astype(np.int64) - 1  # CSC slot -> entry id
        Pdiag = np.zeros(A_ * nv)
        for a in range(A_):
            Pdiag[a * nv + n: a * nv + n + m] = 1.0
        P = sp.diags(Pdiag).tocsc()
        P = sp.triu(P, format="csc")
        q = np.zeros(A_ * nv)
        l = np.concatenate([prob.z.ravel(), np.zeros(A_ * 2 * m)])
        u = np.concatenate([prob.z.ravel(), np.full(A_ * 2 * m, np.inf)])
        vals = np.concatenate([prob.hv.ravel(), const])
        M.data = vals[perm]
        solver = osqp.OSQP()
        self._fill_q(q, prob)
        solver.setup(P=P, q=q, A=M, l=l, u=u, **self.settings)
        self.setups += 1
        return {"solver": solver, "perm": perm, "const": const, "q": q, "l": l, "u": u, "delta": prob.delta,
                "nv": nv}

    @staticmethod
    def _fill_q(q, prob):
        n, m = prob.n, prob.m
        nv = n + 3 * m
        for a in range(prob.axes):
            q[a * nv + n + m: a * nv + n + 3 * m] = prob.delta

    def solve(self, prob: HuberProblem) -> SolveOut:
        key = prob.shape_key()
        ent = self._cache.get(key)
        if ent is None:
            ent = self._setup(prob)
            self._cache[key] = ent
            if len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(key)
            vals = np.concatenate([prob.hv.ravel(), ent["const"]])
            neq = prob.axes * prob.m
            ent["l"][:neq] = prob.z.ravel()
            ent["u"][:neq] = prob.z.ravel()
            kw = {"Ax": vals[ent["perm"]], "l": ent["l"], "u": ent["u"]}
            if prob.delta != ent["delta"]:
                self._fill_q(ent["q"], prob)
                ent["delta"] = prob.delta
                kw["q"] = ent["q"]
            ent["solver"].update(**kw)
        res = ent["solver"].solve(raise_error=False)
        nv = ent["nv"]
        X = np.stack([res.x[a * nv: a * nv + prob.n] for a in range(prob.axes)])
        info = res.info
        st = str(getattr(info, "status", ""))
        return _finish(prob, X, "osqp", int(info.iter), st,
                       {"osqp_prim_res": float(info.prim_res), "osqp_dual_res": float(info.dual_res)},
                       {"polished": int(getattr(info, "status_polish", 0)) == 1})


# ----------------------------------------------------------------------------- cvxpy + Clarabel


class CvxpyReference:
    """The literal sum-of-norms problem (10) (c = 1, λ = λ(δ)) in cvxpy, solved by Clarabel.

    min over x, ℓ̄:  1/(2λ²)·‖Hx − z + ℓ̄‖² + √2/(1−λ)·‖ℓ̄‖₁, all axes in one problem. The problem is
    DPP-parametrised in the nonzeros of H, in z and in λ's two weights, and compiled once per shape.
    Its optimal value times λ² is the Huber objective P* (reported as ``objective10`` in ``extra``);
    ``objective`` is P evaluated at its x like every other solver.
    """

    def __init__(self, solver: str = "CLARABEL", tol: float = 1e-10, cache_size: int = 8, **solver_kwargs):
        self.solver = solver
        if solver == "CLARABEL":
            kw = dict(tol_gap_abs=tol, tol_gap_rel=tol, tol_feas=tol, tol_ktratio=1e-8, max_iter=200)
        else:
            kw = {}
        kw.update(solver_kwargs)
        self.kwargs = kw
        self._cache: OrderedDict = OrderedDict()
        self.cache_size = cache_size

    def _setup(self, prob: HuberProblem):
        import cvxpy as cp
        import scipy.sparse as sp

        A_, n, m = prob.axes, prob.n, prob.m
        nnz = prob.ci.shape[0]
        rr = np.repeat(np.arange(m), np.diff(prob.rp))
        # block-diagonal selection matrices over axes: (Hx)_rows = Sr · (hv ∘ (Sc x))
        rows_c = np.arange(A_ * nnz)
        cols_c = np.concatenate([a * n + prob.ci for a in range(A_)])
        Sc = sp.csr_matrix((np.ones(A_ * nnz), (rows_c, cols_c)), shape=(A_ * nnz, A_ * n))
        rows_r = np.concatenate([a * m + rr for a in range(A_)])
        Sr = sp.csr_matrix((np.ones(A_ * nnz), (rows_r, np.arange(A_ * nnz))), shape=(A_ * m, A_ * nnz))
        x = cp.Variable(A_ * n)
        ell = cp.Variable(A_ * m)
        hv = cp.Parameter(A_ * nnz)
        z = cp.Parameter(A_ * m)
        lam = lambda_from_delta(prob.delta)
        wq = 1.0 / (2.0 * lam * lam)  # constants (a parameter times the parametrised Hx is not DPP):
        wl = math.sqrt(2.0) / (1.0 - lam)  # δ is part of the cache key
        Hx = Sr @ cp.multiply(hv, Sc @ x)
        obj = wq * cp.sum_squares(Hx - z + ell) + wl * cp.norm1(ell)
        problem = cp.Problem(cp.Minimize(obj))
        return {"problem": problem, "x": x, "ell": ell, "hv": hv, "z": z, "lam": lam}

    def solve(self, prob: HuberProblem) -> SolveOut:
        key = prob.shape_key() + (float(prob.delta),)
        ent = self._cache.get(key)
        if ent is None:
            ent = self._setup(prob)
            self._cache[key] = ent
            if len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(key)
        lam = ent["lam"]
        ent["hv"].value = prob.hv.ravel()
        ent["z"].value = prob.z.ravel()
        problem = ent["problem"]
        problem.solve(solver=self.solver, **self.kwargs)
        X = np.asarray(ent["x"].value, float).reshape(prob.axes, prob.n)
        stats = problem.solver_stats
        out = _finish(prob, X, "cvxpy-" + self.solver.lower(), int(stats.num_iters or 0), str(problem.status),
                      None, {"objective10": float(problem.value),
                             "objective10_as_huber": float(problem.value) * lam * lam,
                             "lambda": lam, "solve_time": float(stats.solve_time or float("nan"))})
        return out


SOLVERS = ("ipm", "osqp", "cvxpy", "ls")
