"""The default solver of the sum-of-norms estimator (10): a compiled primal–dual interior-point method.

Mehrotra's predictor–corrector method on the dual of the Huber form of (10) (:mod:`son_problem`):

    max_u  D(u) = zᵀu − ½‖u‖²   s.t.  Hᵀu = 0,  −δ ≤ u ≤ δ,

whose multiplier of Hᵀu = 0 is the primal estimate x. The quadratic rows ``lsq`` (the arrival cost of
:mod:`son_arrival`) have no bound on uᵢ: their multipliers stay 0 and their slacks ∞ (Θᵢ = 1), and they
take no part in the complementarity μ or the step-length rule. Variables: x (n), u (m), ya, yb (m; multipliers
of u ≤ δ and −u ≤ δ) with slacks sa = δ − u, sb = δ + u. Every Newton system reduces to the n×n
normal matrix HᵀΘH with Θ = 1/(1 + ya/sa + yb/sb) ≤ 1, factored and solved by :mod:`son_banded`
(chain recursion for the per-axis UAV graph, banded Cholesky otherwise).

* **Start** (:func:`_start`): the least-squares x, u = 0 and multipliers that make both linear
  residuals (Hᵀu = 0, u − r + ya − yb = 0) exactly zero; Newton steps keep them (their residuals are
  still carried, scaled by (1 − step)), so only complementarity is driven down.
* **Iteration** (:func:`_iterate`): the predictor (:func:`_scaling`: Θ and the right-hand side for
  complementarity 0; :func:`_newton_solve`; :func:`_affine_direction`; :func:`_centring`:
  σ = (μ_aff/μ)³ from the complementarity that direction would reach), the corrector (the same
  factors, targets σμ plus the predictor's second-order terms: :func:`_corrector_rhs`,
  :func:`_newton_solve`, :func:`_corrector_direction`) and the step (:func:`_step_length`: 0.995 of the largest feasible
  step, at most 1; :func:`_take_step`).
  Both directions fold the one step-length rule :func:`_step_limit` over their rows.
* **Stop**: the certified relative gap P(x) − D(u) ≤ ``tol``·max(1, P); or stagnation (three
  iterations without reducing the gap by 30 %) at the precision limit of an ill-conditioned problem.
* **Polish** (:func:`_polish`): whenever the gap is below ``polish_gap``·max(1, P) and the active set
  read from the residuals changed, the piecewise-quadratic stationarity equation
  H_QᵀH_Q x = H_Qᵀz_Q + δ·H_Lᵀsign (Q: rows with |rᵢ| < δ, L: the others) is solved exactly; if the
  new residuals fall in the assumed pieces, Hᵀψ(z − Hx) = 0 holds to rounding: an exact optimum,
  returned at once (this typically halves the iterations). After the IPM (:func:`_polish_final`) the
  active set is read from the primal, then from the dual, then with near-kink rows taken quadratic.
* **Certificate** (:func:`_certificate`): P, the gap and ‖Hᵀu‖∞ recomputed exactly at the returned x.

Both axes are solved in one compiled call (:func:`ipm_solve_all`); no Python runs inside the
iteration, and the per-iteration pieces are compiled into :func:`_iterate` (``@kernel(inline=True)``,
see :mod:`son_jit`). The pieces share one naming of their arrays: ``rp, ci, hv`` (H of one axis),
``ws``/``ch`` (factor workspace and layout, :mod:`son_banded`), the iterate x, u, ya, yb and
r = z − Hx, the carried residuals rd of u − r + ya − yb = 0 (m) and rpv of Hᵀu = 0 (n), the slacks
sa, sb and their inverses isa, isb, Θ ``th``, the right-hand side g (and ``tmp`` = Θg), and the
direction dx, du, dya, dyb with hdx = H·dx.
"""

from __future__ import annotations

import math

import numpy as np

from .son_banded import factor_normal, matvec, normal_workspace, rmatvec, solve_normal, weighted_least_squares
from .son_jit import kernel
from .son_problem import HuberProblem, SolveOut, evaluate_solution, huber_sum

__all__ = ["IPM_STATUS", "ipm_raw", "ipm_solve_all", "solve_ipm"]

IPM_STATUS = ("solved", "max_iter", "stalled", "numerical_error")  #: status codes 0–3 of :func:`ipm_solve_all`


# ============================================================================= start and measurement


@kernel
def _start(rp, ci, hv, z, n, bw, ws, ch, delta, lsq, th, x, u, r, ya, yb, rd):
    """The feasible start: x = least squares (θ = 1), r = z − Hx, u = 0, ya = max(r, 0) + τ,
    yb = max(−r, 0) + τ with τ = max(δ, ½·mean|r|), so that rd = u − r + ya − yb = 0 and Hᵀu = 0
    (quadratic rows: ya = yb = 0, rd = −r, carried like every linear residual)."""
    m = z.shape[0]
    weighted_least_squares(rp, ci, hv, z, n, bw, th, x, ws, ch)
    matvec(rp, ci, hv, x, r)
    amean = 0.0
    for i in range(m):
        r[i] = z[i] - r[i]
        amean += abs(r[i])
    amean /= m
    tau = max(delta, 0.5 * amean)
    for i in range(m):
        u[i] = 0.0
        if lsq[i]:
            ya[i] = 0.0
            yb[i] = 0.0
        else:
            ya[i] = max(r[i], 0.0) + tau
            yb[i] = max(-r[i], 0.0) + tau
        rd[i] = u[i] - r[i] + ya[i] - yb[i]


@kernel(inline=True)
def _measure(z, delta, lsq, u, r, ya, yb, sa, sb):
    """The slacks sa = δ − u, sb = δ + u (kept > 0 against rounding), the mean complementarity μ, P(x),
    the certificate P(x) − D(u) and a signature of the active set read from r (quadratic rows: slacks
    ∞, outside μ). Returns (μ, P, gap, signature)."""
    m = z.shape[0]
    mu = 0.0
    D = 0.0
    P = 0.0
    sig = 0.0
    nb = 0
    for i in range(m):
        ui = u[i]
        ri = r[i]
        if lsq[i]:
            sa[i] = math.inf
            sb[i] = math.inf
            D += z[i] * ui - 0.5 * ui * ui
            P += 0.5 * ri * ri
            continue
        nb += 1
        sa[i] = max(delta - ui, 1e-300)  # > 0 in exact arithmetic; guard against rounding
        sb[i] = max(delta + ui, 1e-300)
        mu += ya[i] * sa[i] + yb[i] * sb[i]
        D += z[i] * ui - 0.5 * ui * ui
        a_ = abs(ri)
        if a_ <= delta:
            P += 0.5 * a_ * a_
        else:
            P += delta * a_ - 0.5 * delta * delta
            sig += (i + 1.0) if ri > 0 else -1.618 * (i + 1.0)
    mu /= 2.0 * max(nb, 1)
    return mu, P, P - D, sig


# ============================================================================= one Mehrotra iteration


@kernel
def _step_limit(amax, sa, sb, ya, yb, du, dya, dyb):
    """The step-length rule, one row at a time: the largest α ≤ ``amax`` keeping sa − α du, sb + α du,
    ya + α dya, yb + α dyb ≥ 0 (the predictor's and the corrector's direction loops fold it over the
    rows, starting from 1)."""
    if du * amax > sa:
        amax = sa / du
    elif -du * amax > sb:
        amax = -sb / du
    if -dya * amax > ya:
        amax = -ya / dya
    if -dyb * amax > yb:
        amax = -yb / dyb
    return amax


@kernel(inline=True)
def _scaling(sa, sb, ya, yb, rd, isa, isb, th, g, tmp):
    """Θ = 1/(1 + ya/sa + yb/sb) (the weights of the normal matrix HᵀΘH), the inverse slacks, the
    predictor's right-hand side g = −rd + ya − yb (complementarity targets 0) and Θg."""
    for i in range(sa.shape[0]):
        ia = 1.0 / sa[i]
        ib = 1.0 / sb[i]
        isa[i] = ia
        isb[i] = ib
        t_ = 1.0 / (1.0 + ya[i] * ia + yb[i] * ib)
        th[i] = t_
        gi = -rd[i] + ya[i] - yb[i]
        g[i] = gi
        tmp[i] = gi * t_


@kernel(inline=True)
def _newton_solve(rp, ci, hv, n, bw, ws, ch, tmp, rpv, dx, hdx):
    """The Newton solve of both directions: dx = (HᵀΘH)⁻¹(Hᵀ``tmp`` + rpv) with the factors in ``ws``
    (``tmp`` = Θg), and hdx = H dx."""
    rmatvec(rp, ci, hv, tmp, dx)
    for j in range(n):
        dx[j] += rpv[j]
    solve_normal(dx, n, bw, ws, ch)
    matvec(rp, ci, hv, dx, hdx)


@kernel(inline=True)
def _affine_direction(g, hdx, th, sa, sb, ya, yb, isa, isb, du, dya, dyb):
    """The predictor's (affine-scaling) direction of u, ya, yb from its Newton solve (hdx = H dx).
    Returns its largest feasible step (:func:`_step_limit`)."""
    amax = 1.0
    for i in range(g.shape[0]):
        d = (g[i] - hdx[i]) * th[i]
        da = ya[i] * (d * isa[i] - 1.0)
        db = -yb[i] * (d * isb[i] + 1.0)
        du[i] = d
        dya[i] = da
        dyb[i] = db
        amax = _step_limit(amax, sa[i], sb[i], ya[i], yb[i], d, da, db)
    return amax


@kernel(inline=True)
def _centring(mu, amax, lsq, sa, sb, ya, yb, du, dya, dyb):
    """Mehrotra's centring: the complementarity μ_aff (over the bounded rows) after the affine step of
    length ``amax`` gives σ = min(1, (μ_aff/μ)³). Returns σμ."""
    m = sa.shape[0]
    mua = 0.0
    nb = 0
    for i in range(m):
        if lsq[i]:
            continue
        nb += 1
        mua += (ya[i] + amax * dya[i]) * (sa[i] - amax * du[i]) + (yb[i] + amax * dyb[i]) * (sb[i] + amax * du[i])
    mua /= 2.0 * max(nb, 1)
    sig = mua / mu
    sig = sig * sig * sig
    if sig > 1.0:
        sig = 1.0
    return sig * mu


@kernel(inline=True)
def _corrector_rhs(smu, rd, ya, yb, isa, isb, th, du, dya, dyb, g, tmp):
    """The corrector's right-hand side g (and Θg) for the complementarity targets ta = σμ + Δya·Δu,
    tb = σμ − Δyb·Δu (Δ: the predictor's direction, its second-order terms); ta, tb are left in dya, dyb
    for :func:`_corrector_direction`."""
    for i in range(g.shape[0]):
        ta = smu + dya[i] * du[i]
        tb = smu - dyb[i] * du[i]
        gi = -rd[i] - ta * isa[i] + ya[i] + tb * isb[i] - yb[i]
        g[i] = gi
        tmp[i] = gi * th[i]
        dya[i] = ta
        dyb[i] = tb


@kernel(inline=True)
def _corrector_direction(g, hdx, th, sa, sb, ya, yb, isa, isb, du, dya, dyb):
    """The corrector's direction of u, ya, yb from its Newton solve (dya, dyb hold the targets ta, tb).
    Returns its largest feasible step (:func:`_step_limit`)."""
    amax = 1.0
    for i in range(g.shape[0]):
        d = (g[i] - hdx[i]) * th[i]
        da = -ya[i] + (dya[i] + ya[i] * d) * isa[i]
        db = -yb[i] + (dyb[i] - yb[i] * d) * isb[i]
        du[i] = d
        dya[i] = da
        dyb[i] = db
        amax = _step_limit(amax, sa[i], sb[i], ya[i], yb[i], d, da, db)
    return amax


@kernel(inline=True)
def _step_length(amax, dx, du, dya, dyb):
    """The step min(1, 0.995·``amax``) along the direction, or NaN if the direction is not finite
    (numerical breakdown)."""
    step = 0.995 * amax
    if step > 1.0:
        step = 1.0
    fin = step
    for j in range(dx.shape[0]):
        fin += 0.0 * dx[j]
    for i in range(du.shape[0]):
        fin += 0.0 * (du[i] + dya[i] + dyb[i])
    return step if math.isfinite(fin) else math.nan


@kernel(inline=True)
def _take_step(step, x, u, ya, yb, r, rd, rpv, dx, du, dya, dyb, hdx):
    """Move the iterate by ``step`` along the direction. The linear residuals rd and rpv shrink by
    (1 − step) (Hᵀ(u + step·du) = (1 − step)·Hᵀu for an exact Newton step)."""
    for j in range(x.shape[0]):
        x[j] += step * dx[j]
        rpv[j] *= 1.0 - step
    for i in range(u.shape[0]):
        u[i] += step * du[i]
        ya[i] += step * dya[i]
        yb[i] += step * dyb[i]
        r[i] -= step * hdx[i]
        rd[i] *= 1.0 - step


# ============================================================================= polish: exact active-set solve


@kernel
def _polish(rp, ci, hv, z, n, bw, delta, lsq, quad, sgn, ws, ch, Pcur, xn, r):
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
    bad = factor_normal(rp, ci, hv, th, n, bw, ws, ch)
    if bad > 0:
        return Pcur, False, False
    rmatvec(rp, ci, hv, w, xn)
    solve_normal(xn, n, bw, ws, ch)
    matvec(rp, ci, hv, xn, r)
    consistent = True
    lo = delta * (1.0 - 1e-11)
    hi = delta * (1.0 + 1e-11)
    for i in range(m):
        ri = z[i] - r[i]
        r[i] = ri
        if lsq[i]:
            continue
        if quad[i]:
            if abs(ri) > hi:
                consistent = False
        elif ri * sgn[i] < lo:
            consistent = False
    Pn = huber_sum(r, delta, lsq)
    # a consistent point is an exact optimum: P may exceed Pcur only by rounding
    improved = Pn <= Pcur or (consistent and Pn <= Pcur + 1e-10 * max(1.0, abs(Pcur)))
    return Pn, consistent, improved


@kernel
def _partition_primal(r, delta, lsq, quad, sgn):
    """Active set read from the residuals: quadratic iff |r| < δ (or a quadratic row)."""
    for i in range(r.shape[0]):
        quad[i] = abs(r[i]) < delta or lsq[i]
        sgn[i] = 1.0 if r[i] > 0 else -1.0


@kernel
def _partition_dual(u, ya, yb, delta, lsq, quad, sgn):
    """Active set read from the IPM's dual iterate: linear iff a bound multiplier dominates its slack
    (ya/(δ − u) + yb/(δ + u) ≥ 1, i.e. Θ ≤ ½), with the sign of u (quadratic rows: always quadratic)."""
    for i in range(u.shape[0]):
        quad[i] = lsq[i] or ya[i] / (delta - u[i]) + yb[i] / (delta + u[i]) < 1.0
        sgn[i] = 1.0 if u[i] > 0 else -1.0


@kernel
def _polish_final(rp, ci, hv, z, n, bw, ws, ch, delta, lsq, P, x, u, ya, yb):
    """The exact active-set solve after the IPM: from the primal, then from the dual reading of the
    active set, then with rows within 1e-3·δ of the kink (ambiguous at the IPM's tolerance) taken
    quadratic. Keeps the first consistent (exactly optimal) point, else the best improvement on P(x).
    Returns (polished: x is an exact optimum, inexact: x improved only)."""
    m = z.shape[0]
    r = np.empty(m)
    rtmp = np.empty(m)
    quad = np.empty(m, np.bool_)
    sgn = np.empty(m)
    xp = np.empty(n)
    xbest = np.empty(n)
    matvec(rp, ci, hv, x, r)
    for i in range(m):
        r[i] = z[i] - r[i]
    best = P
    for attempt in range(3):
        if attempt == 0:
            _partition_primal(r, delta, lsq, quad, sgn)
        elif attempt == 1:
            _partition_dual(u, ya, yb, delta, lsq, quad, sgn)
        else:
            _partition_primal(r, delta * (1.0 + 1e-3), lsq, quad, sgn)
        Pn, cons, impr = _polish(rp, ci, hv, z, n, bw, delta, lsq, quad, sgn, ws, ch, P, xp, rtmp)
        if cons and impr:
            x[:] = xp
            return True, False
        if impr and Pn < best:
            best = Pn
            xbest[:] = xp
    if best < P:
        x[:] = xbest
        return False, True
    return False, False


# ============================================================================= the loop and the certificate


@kernel
def _iterate(rp, ci, hv, z, n, bw, ws, ch, delta, lsq, tol, maxit, do_polish, ptol, x, u, ya, yb):
    """From the start, predictor–corrector iterations until a stopping rule (module doc) holds, trying
    the polish whenever the gap is below ``ptol``·max(1, P) and the active set changed. Returns
    (iterations, status (0 converged or exact, 1 iteration limit, 2 stalled, 3 numerical breakdown), P,
    polished)."""
    m = z.shape[0]
    r, rd, th, sa, sb = np.empty(m), np.empty(m), np.ones(m), np.empty(m), np.empty(m)
    isa, isb, g, tmp, hdx = np.empty(m), np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    du, dya, dyb, rtmp, sgn = np.empty(m), np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    quad = np.empty(m, np.bool_)
    rpv, dx, xp = np.zeros(n), np.empty(n), np.empty(n)
    _start(rp, ci, hv, z, n, bw, ws, ch, delta, lsq, th, x, u, r, ya, yb, rd)
    it = 0
    best_gap = 1e300
    stall = 0
    last_sig = -1.2345e300
    while True:
        mu, P, gap, sig = _measure(z, delta, lsq, u, r, ya, yb, sa, sb)
        scale_p = max(1.0, abs(P))
        if gap <= tol * scale_p or not mu > 0.0:
            return it, 0, P, False
        # stagnation at the precision limit of an ill-conditioned problem: stop, then polish
        if gap < 0.7 * best_gap:
            best_gap = gap
            stall = 0
        else:
            stall += 1
            if stall >= 3:
                return it, 2, P, False
        if do_polish and gap <= ptol * scale_p and sig != last_sig:
            # the active set has probably been identified: try the exact piecewise-quadratic solve
            last_sig = sig
            _partition_primal(r, delta, lsq, quad, sgn)
            Pn, cons, impr = _polish(rp, ci, hv, z, n, bw, delta, lsq, quad, sgn, ws, ch, P, xp, rtmp)
            if cons and impr:
                x[:] = xp
                return it, 0, Pn, True
        if it >= maxit:
            return it, 1, P, False
        it += 1
        # predictor: Θ, the affine direction (Newton solve, complementarity → 0), the centring σμ
        _scaling(sa, sb, ya, yb, rd, isa, isb, th, g, tmp)
        factor_normal(rp, ci, hv, th, n, bw, ws, ch)
        _newton_solve(rp, ci, hv, n, bw, ws, ch, tmp, rpv, dx, hdx)
        amax = _affine_direction(g, hdx, th, sa, sb, ya, yb, isa, isb, du, dya, dyb)
        smu = _centring(mu, amax, lsq, sa, sb, ya, yb, du, dya, dyb)
        # corrector: the same factors, targets σμ plus the predictor's second-order terms
        _corrector_rhs(smu, rd, ya, yb, isa, isb, th, du, dya, dyb, g, tmp)
        _newton_solve(rp, ci, hv, n, bw, ws, ch, tmp, rpv, dx, hdx)
        amax = _corrector_direction(g, hdx, th, sa, sb, ya, yb, isa, isb, du, dya, dyb)
        step = _step_length(amax, dx, du, dya, dyb)
        if math.isnan(step):
            return it, 3, P, False  # numerical breakdown: keep the last finite iterate
        _take_step(step, x, u, ya, yb, r, rd, rpv, dx, du, dya, dyb, hdx)


@kernel
def _certificate(rp, ci, hv, z, n, delta, lsq, polished, x, u):
    """The exact certificate at the returned x: (gap P(x) − D(u), P(x), ‖Hᵀu‖∞). After an exact polish
    u = ψ(z − Hx) (box-feasible; at an exact optimum Hᵀu = 0 and the gap is 0)."""
    m = z.shape[0]
    r = np.empty(m)
    hu = np.empty(n)
    matvec(rp, ci, hv, x, r)
    for i in range(m):
        r[i] = z[i] - r[i]
    P = huber_sum(r, delta, lsq)
    if polished:
        for i in range(m):
            ri = r[i]
            if lsq[i]:
                pass
            elif ri > delta:
                ri = delta
            elif ri < -delta:
                ri = -delta
            u[i] = ri
    D = 0.0
    for i in range(m):
        D += z[i] * u[i] - 0.5 * u[i] * u[i]
    rmatvec(rp, ci, hv, u, hu)
    pres = 0.0
    for j in range(n):
        if abs(hu[j]) > pres:
            pres = abs(hu[j])
    return P - D, P, pres


@kernel
def _ipm_one(rp, ci, hv, z, n, bw, ch, delta, lsq, tol, maxit, do_polish, ptol, x, u):
    """The IPM (module doc) on one problem, x and u written in place. Returns (iterations, certified
    gap P(x) − D(u), P(x), ‖Hᵀu‖∞, polish (1 exact active-set optimum, 0.5 improved only, 0 none),
    status (0 converged / exact, 1 iteration limit, 2 stalled, 3 numerical breakdown))."""
    m = rp.shape[0] - 1
    ws = normal_workspace(n, bw, ch[2].shape[0])
    ya = np.empty(m)
    yb = np.empty(m)
    it, status, P, polished = _iterate(rp, ci, hv, z, n, bw, ws, ch, delta, lsq, tol, maxit, do_polish, ptol, x, u,
                                       ya, yb)
    inexact = False
    if do_polish and not polished:
        polished, inexact = _polish_final(rp, ci, hv, z, n, bw, ws, ch, delta, lsq, P, x, u, ya, yb)
        if polished:
            status = 0  # an exact optimum, whatever stopped the IPM
    gap, P, pres = _certificate(rp, ci, hv, z, n, delta, lsq, polished, x, u)
    return it, gap, P, pres, 1.0 if polished else (0.5 if inexact else 0.0), status


@kernel
def ipm_solve_all(rp, ci, hv, z, n, bw, ch, delta, lsq, tol, maxit, do_polish, ptol):
    """Solve every axis of a :class:`HuberProblem` (one compiled call). ``ch`` = (rowtype, rownode,
    uix, pix, vix) of a chain layout, or :data:`son_banded.NO_CHAIN` for the banded path; ``lsq`` (m,)
    the quadratic rows. Returns
    X (A, n), U (A, m), info (A, 6): iterations, certified gap, P, ‖Hᵀu‖∞, polish (1 exact active-set
    optimum, 0.5 improved but not proven exact, 0 none), status (0 converged or exact active-set
    optimum, 1 iteration limit, 2 stalled at the precision limit, 3 numerical breakdown)."""
    A = hv.shape[0]
    m = rp.shape[0] - 1
    X = np.empty((A, n))
    U = np.empty((A, m))
    info = np.empty((A, 6))
    for a in range(A):
        it, gap, P, pres, pol, st = _ipm_one(rp, ci, hv[a], z[a], n, bw, ch, delta, lsq, tol, maxit, do_polish,
                                             ptol, X[a], U[a])
        info[a, 0] = it
        info[a, 1] = gap
        info[a, 2] = P
        info[a, 3] = pres
        info[a, 4] = pol
        info[a, 5] = st
    return X, U, info


# ============================================================================= python interface


def solve_ipm(prob: HuberProblem, tol: float = 1e-9, maxit: int = 60, polish: bool = True,
              polish_gap: float = 0.3) -> SolveOut:
    """The default solver (see module doc). ``tol``: certified relative duality gap at which the IPM
    stops; ``polish_gap``: relative gap below which the exact active-set solve is attempted (whenever
    the active set changes) — accepted only if its residuals fall in the assumed pieces."""
    X, U, info = ipm_raw(prob, tol, maxit, polish, polish_gap)
    status = IPM_STATUS[int(info[:, 5].max())]
    gap = float(info[:, 1].sum())
    return evaluate_solution(prob, X, "ipm", int(info[:, 0].max()), status,
                             {"gap": gap, "dual_infeasibility": float(info[:, 3].max())},
                             {"U": U, "polished": info[:, 4] == 1.0})


def ipm_raw(prob: HuberProblem, tol: float = 1e-9, maxit: int = 60, polish: bool = True,
            polish_gap: float = 0.3):
    """The compiled call alone (for benchmarks): returns (X, U, info) of :func:`ipm_solve_all`."""
    return ipm_solve_all(prob.rp, prob.ci, prob.hv, prob.z, prob.n, prob.bw, prob.chain_arg(),
                         float(prob.delta), prob.lsq_mask(), float(tol), int(maxit), bool(polish), float(polish_gap))
