"""Sparse-row and normal-matrix algebra of the sum-of-norms solvers (García Carrillo et al., (10)).

The Huber form of (10) (see :mod:`son_problem`) has one n×n linear system per Newton step, least
squares or active-set solve: the normal matrix HᵀΘH (Θ diagonal, weights of the rows of H) times y = b.
H is stored by rows (CSR: row pointers ``rp``, column indices ``ci``, values ``hv`` of one axis) and the
system is solved in one of two ways, chosen by the layout argument ``ch``:

* **chain** (``ch`` = (rowtype, rownode, uix, pix, vix) of :func:`son_layout.build_split`): the
  per-axis UAV graph, a chain of target nodes (p_k, v_k) in time order joined by the motion rows (2),
  each with an optional leaf u_k (the measuring agent, joined to p_k by the relative row (4) and
  carrying its GPS row (3)). The leaves are eliminated (Schur complement of a diagonal) and the
  block-tridiagonal 2×2 remainder is factored by the block Thomas recursion: O(W) per factorisation,
  closed-form 2×2 blocks;
* **banded** (``ch`` = :data:`NO_CHAIN`): any other pattern, e.g. the joint problem of correlated
  covariances. Nodes are ordered by time, so HᵀΘH is banded (half-bandwidth :func:`bandwidth`) and is
  Cholesky-factored in band storage, O(n·bw²).

A pivot that collapses is replaced by 1e128 in both (Wright's modified Cholesky for interior-point
methods: the direction is dropped instead of blowing up); the factorisations return how many were.
"""

from __future__ import annotations

import math

import numpy as np

from .son_jit import kernel
from .son_layout import ROW_ARRIVAL, ROW_GPS, ROW_MOTION_V, ROW_REL

__all__ = ["NO_CHAIN", "bandwidth", "factor_normal", "ls_solve_all", "matvec", "normal_workspace", "rmatvec",
           "solve_normal", "weighted_least_squares"]

_E = np.zeros(0, np.int64)
NO_CHAIN = (_E, _E, _E, _E, _E)  #: the layout argument ``ch`` of a problem without chain layout (banded path)


# ============================================================================= H by rows


@kernel
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


@kernel
def matvec(rp, ci, hv, x, out):
    """out = H x (one axis: values ``hv``)."""
    for r in range(rp.shape[0] - 1):
        s = 0.0
        for a in range(rp[r], rp[r + 1]):
            s += hv[a] * x[ci[a]]
        out[r] = s


@kernel
def rmatvec(rp, ci, hv, y, out):
    """out = Hᵀ y (one axis: values ``hv``)."""
    out[:] = 0.0
    for r in range(rp.shape[0] - 1):
        yr = y[r]
        if yr == 0.0:
            continue
        for a in range(rp[r], rp[r + 1]):
            out[ci[a]] += hv[a] * yr


@kernel
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


@kernel
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


@kernel
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


# ============================================================================= chain layout: block Thomas


@kernel
def _chain_factor(rp, hv, th, rt, rn, uix, K, Nuu, Nup, D, E, Sinv, G):
    """Normal matrix HᵀΘH of a *chain* problem (the per-axis UAV graph of
    :func:`son_layout.build_split`: target nodes (p_k, v_k) in time order joined by motion rows, each
    with an optional leaf u_k joined to p_k by the relative row), with the leaves eliminated (Schur
    complement of the diagonal N_uu) and the remaining block-tridiagonal 2×2 system factored by the
    block Thomas recursion S_k = D_k − E_k S_{k−1}⁻¹ E_kᵀ (closed-form 2×2 LDLᵀ; a collapsing pivot is
    replaced by 1e128 as in :func:`_chol`). Returns the number of replaced pivots."""
    Nrel = np.zeros((K, 2))
    _chain_normal(rp, hv, th, rt, rn, K, Nrel, Nuu, Nup, D, E)
    return _chain_thomas(uix, K, Nrel, Nuu, D, E, Sinv, G)


@kernel(inline=True)
def _chain_normal(rp, hv, th, rt, rn, K, Nrel, Nuu, Nup, D, E):
    """The blocks of HᵀΘH of a chain problem, row by row: D_k (2×2 [p_k, v_k] diagonal block, stored
    [00, 01, 11]), E_k (the [p_k, v_k] × [p_{k−1}, v_{k−1}] block, stored [00, 01, 10, 11]), N_uu (the
    GPS part of the leaf's diagonal), N_up (leaf × p_k) and Nrel (K, 2, zero on entry): the relative
    row's θh_u² and θh_p², which :func:`_chain_thomas` needs to eliminate the leaf. The arrival cost's
rows (``ROW_ARRIVAL``) add to D_0."""
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
        if typ <= ROW_MOTION_V:
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
        elif typ == ROW_GPS:
            h0 = hv[a]
            Nuu[k] += t * h0 * h0  # the GPS part of N_uu (the relative part is added below)
        elif typ == ROW_REL:
            if rp[r + 1] - a == 2:
                h0 = hv[a]
                h1 = hv[a + 1]
                Nrel[k, 0] = t * h0 * h0
                Nup[k] = t * h0 * h1
                Nrel[k, 1] = t * h1 * h1
            else:
                h0 = hv[a]
                D[k, 0] += t * h0 * h0
        elif typ == ROW_ARRIVAL:  # the arrival cost on [p_0, v_0]
            h0 = hv[a]
            h1 = hv[a + 1]
            D[k, 0] += t * h0 * h0
            D[k, 1] += t * h0 * h1
            D[k, 2] += t * h1 * h1
        else:  # ROW_PRIOR on v_0
            h0 = hv[a]
            D[k, 2] += t * h0 * h0


@kernel(inline=True)
def _chain_thomas(uix, K, Nrel, Nuu, D, E, Sinv, G):
    """Eliminate each leaf u_k into D_k, then the block Thomas recursion S_k = D_k − E_k S_{k−1}⁻¹ E_kᵀ:
    stores S_k⁻¹ ([00, 01, 11]) and G_k = E_k S_{k−1}⁻¹. Returns the number of replaced pivots."""
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


@kernel
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


# ============================================================================= the system, either way


@kernel
def factor_normal(rp, ci, hv, th, n, bw, ws, ch):
    """Factor HᵀΘH into the workspace ``ws`` (:func:`normal_workspace`): chain recursion if a chain
    layout ``ch`` is given (K > 0), else banded Cholesky. Returns the number of replaced pivots."""
    L, Nuu, Nup, D, E, Sinv, G, Y = ws
    rt, rn, uix, pix, vix = ch
    K = uix.shape[0]
    if K > 0:
        return _chain_factor(rp, hv, th, rt, rn, uix, K, Nuu, Nup, D, E, Sinv, G)
    _normal(rp, ci, hv, th, L)
    return _chol(L, n, bw)


@kernel
def solve_normal(b, n, bw, ws, ch):
    """Solve HᵀΘH y = b in place with the factors :func:`factor_normal` left in ``ws``."""
    L, Nuu, Nup, D, E, Sinv, G, Y = ws
    rt, rn, uix, pix, vix = ch
    K = uix.shape[0]
    if K > 0:
        _chain_solve(b, uix, pix, vix, K, Nuu, Nup, E, Sinv, G, Y)
    else:
        _chol_solve(L, n, bw, b)


@kernel
def normal_workspace(n, bw, K):
    """Workspace of :func:`factor_normal` / :func:`solve_normal`: (L, Nuu, Nup, D, E, Sinv, G, Y); the
    band L (n, bw + 1) for the banded path (K = 0), the chain's per-node blocks for K nodes otherwise."""
    if K > 0:
        L = np.empty((1, 1))
    else:
        L = np.empty((n, bw + 1))
    return (L, np.empty(K), np.empty(K), np.empty((K, 3)), np.empty((K, 4)), np.empty((K, 3)),
            np.empty((K, 4)), np.empty((K, 2)))


@kernel
def weighted_least_squares(rp, ci, hv, z, n, bw, theta, x, ws, ch):
    """x = argmin Σ θᵢ (zᵢ − hᵢx)² by one factorisation. Returns the count of replaced pivots."""
    bad = factor_normal(rp, ci, hv, theta, n, bw, ws, ch)
    tz = np.empty(z.shape[0])
    for i in range(z.shape[0]):
        tz[i] = theta[i] * z[i]
    rmatvec(rp, ci, hv, tz, x)
    solve_normal(x, n, bw, ws, ch)
    return bad


@kernel
def ls_solve_all(rp, ci, hv, z, n, bw, ch):
    """Least squares (all θ = 1) of every axis: X (A, n) and the total count of replaced pivots."""
    A = hv.shape[0]
    m = rp.shape[0] - 1
    X = np.empty((A, n))
    ws = normal_workspace(n, bw, ch[2].shape[0])
    th = np.ones(m)
    bad = 0
    for a in range(A):
        bad += weighted_least_squares(rp, ci, hv[a], z[a], n, bw, th, X[a], ws, ch)
    return X, bad
