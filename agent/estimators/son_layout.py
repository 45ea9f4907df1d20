"""The per-axis UAV measurement graph of García Carrillo et al. as a compiled row layout.

:func:`build_split` writes the rows of z = Hx + ε for a window whose covariances are all diagonal, so
that the x- and y-problems share one sparsity pattern (A = 2 axes; the joint problem of correlated
covariances is built in Python by ``sum_of_norms.build_joint``). Nodes are the window's measurements
in time order (:func:`time_order`); node k has the variables [u_k (measuring agent i ≥ 1 only), p_k,
v_k] of one axis, and contributes, in this order:

* the two motion rows (2) from node k − 1 (``ROW_MOTION_P``, ``ROW_MOTION_V``; entries [p_{k−1},
  v_{k−1}, p_k, v_k]): the residual [e_p, e_v] = [p_k − p_{k−1} − Δt v_{k−1}, v_k − v_{k−1}] whitened
  per (8) by :func:`motion_weights` (cov q·[[Δt³/3, Δt²/2], [Δt²/2, Δt]], Δt floored), z = 0;
* the agent's GPS row (3) (``ROW_GPS``, entry [u_k]): gps_k = u_k;
* the relative row (4) (``ROW_REL``, entries [u_k, p_k]): z_k = p_k − u_k, or the absolute row (3)
  [p_k] of the reference agent 0;

and a window of one node adds a weak zero-velocity prior row (``ROW_PRIOR``, entry [v_0]). A
moving-horizon window (:mod:`son_arrival`) puts its **arrival cost** first: two rows
(``ROW_ARRIVAL``, entries [p_0, v_0] of the oldest node) L⁻¹([p_0; v_0] − x̄) with P = LLᵀ the prior's
covariance per axis — quadratic rows (never Huber), and no zero-velocity row then. The chain solver
of :mod:`son_banded` relies on this layout (``rowtype``, ``rownode``, ``uix``/``pix``/``vix``).
"""

from __future__ import annotations

import math

import numpy as np

from .son_jit import kernel

__all__ = ["NO_ARRIVAL", "ROW_ARRIVAL", "ROW_GPS", "ROW_MOTION_P", "ROW_MOTION_V", "ROW_PRIOR", "ROW_REL",
           "build_split", "build_split_arrival", "motion_weights", "quadratic_rows", "time_order"]

# row types (the ``rowtype`` array of a layout)
ROW_MOTION_P, ROW_MOTION_V, ROW_GPS, ROW_REL, ROW_PRIOR, ROW_ARRIVAL = 0, 1, 2, 3, 4, 5
#: the arrival-cost argument (whitener (2, 2, 2), right-hand side (2, 2)) of a window without one
NO_ARRIVAL = (np.zeros((2, 2, 2)), np.zeros((2, 2)))


@kernel
def motion_weights(dt, q, dt_floor, mode):
    """Whitening W (2×2, W C Wᵀ = I) of the motion residual [e_p, e_v] of (2) over Δt, per axis:
    C = q·[[d³/3, d²/2], [d²/2, d]] with d = max(Δt, ``dt_floor``); ``mode`` 0: W = L⁻¹ with C = LLᵀ, L
    lower ("chol"), 1: W = C^{-1/2} ("sym")."""
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


@kernel
def quadratic_rows(rowtype, quad_motion):
    """The ``lsq`` mask of a layout: the arrival cost's rows, and the motion rows (2) if ``quad_motion``
    (a Gaussian motion model instead of the paper's impulsive disturbances)."""
    lsq = np.empty(rowtype.shape[0], np.bool_)
    for i in range(rowtype.shape[0]):
        lsq[i] = rowtype[i] == ROW_ARRIVAL or (quad_motion and rowtype[i] <= ROW_MOTION_V)
    return lsq


@kernel
def time_order(t, seq, count):
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


@kernel
def _node_variables(order, kind, count):
    """Variable indices per node in time order: uix (−1 for agent 0), pix, vix, and n."""
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
    return uix, pix, vix, n


@kernel
def _motion_rows(rp, ci, hv, zz, rowtype, rownode, m, nz, k, dt, W, pix, vix):
    """The two whitened motion rows (2) from node k − 1 to node k. Returns (m, nz)."""
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
        rowtype[m] = ROW_MOTION_P + row
        rownode[m] = k
        m += 1
        rp[m] = nz
    return m, nz


@kernel
def _agent_rows(rp, ci, hv, zz, rowtype, rownode, m, nz, k, s, z, gps, wr, wg, uix, pix):
    """Node k's (slot s, an agent i ≥ 1) GPS row (3) and relative row (4). Returns (m, nz)."""
    # GPS row: gps = u
    ci[nz] = uix[k]
    for ax in range(2):
        hv[ax, nz] = wg[s, ax]
        zz[ax, m] = wg[s, ax] * gps[s, ax]
    nz += 1
    rowtype[m] = ROW_GPS
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
    rowtype[m] = ROW_REL
    rownode[m] = k
    m += 1
    rp[m] = nz
    return m, nz


@kernel
def _absolute_row(rp, ci, hv, zz, rowtype, rownode, m, nz, k, s, z, wr, pix):
    """Node k's (slot s, the reference agent 0) absolute row (3): z = p. Returns (m, nz)."""
    ci[nz] = pix[k]
    for ax in range(2):
        hv[ax, nz] = wr[s, ax]
        zz[ax, m] = wr[s, ax] * z[s, ax]
    nz += 1
    rowtype[m] = ROW_REL
    rownode[m] = k
    m += 1
    rp[m] = nz
    return m, nz


@kernel
def build_split(t, seq, kind, z, gps, wr, wg, count, q, dt_floor, mode, v_prior):
    """Per-axis problems (all covariances diagonal; layout in the module doc). Slots are unsorted;
    ``kind`` is 1 for a measurement by an agent i ≥ 1 (0 for agent 0); ``wr``/``wg`` (cap, 2) hold the
    per-axis whitening scales 1/σ of the relative and GPS measurements; ``mode`` 0 chol / 1 sym.

    Returns order, rp, ci, hv (2, nnz), zz (2, m), n, uix, pix, vix, rowtype, rownode."""
    aW, az = NO_ARRIVAL
    return build_split_arrival(t, seq, kind, z, gps, wr, wg, count, q, dt_floor, mode, v_prior, aW, az, False)


@kernel
def _arrival_rows(rp, ci, hv, zz, rowtype, rownode, m, nz, aW, az, pix, vix):
    """The arrival cost's two quadratic rows on [p_0, v_0] (per axis a: whitener aW[a] (2×2, lower),
    right-hand side az[a] = aW[a]·x̄). Returns (m, nz)."""
    for row in range(2):
        ci[nz] = pix[0]
        ci[nz + 1] = vix[0]
        for ax in range(2):
            hv[ax, nz] = aW[ax, row, 0]
            hv[ax, nz + 1] = aW[ax, row, 1]
            zz[ax, m] = az[ax, row]
        nz += 2
        rowtype[m] = ROW_ARRIVAL
        rownode[m] = 0
        m += 1
        rp[m] = nz
    return m, nz


@kernel
def build_split_arrival(t, seq, kind, z, gps, wr, wg, count, q, dt_floor, mode, v_prior, aW, az, arrival):
    """:func:`build_split` with, if ``arrival``, the arrival cost's rows first (module doc; ``aW`` (2, 2, 2)
    the per-axis whiteners, ``az`` (2, 2) their right-hand sides). Same returns."""
    order = time_order(t, seq, count)
    uix, pix, vix, n = _node_variables(order, kind, count)
    mmax = 4 * count + 4
    nnzmax = 11 * count + 8
    rp = np.zeros(mmax + 1, np.int64)
    ci = np.empty(nnzmax, np.int64)
    hv = np.empty((2, nnzmax))
    zz = np.zeros((2, mmax))
    rowtype = np.empty(mmax, np.int64)
    rownode = np.empty(mmax, np.int64)
    m = 0
    nz = 0
    if arrival:
        m, nz = _arrival_rows(rp, ci, hv, zz, rowtype, rownode, m, nz, aW, az, pix, vix)
    for k in range(count):
        s = order[k]
        if k > 0:
            dt = t[s] - t[order[k - 1]]
            W = motion_weights(dt, q, dt_floor, mode)
            m, nz = _motion_rows(rp, ci, hv, zz, rowtype, rownode, m, nz, k, dt, W, pix, vix)
        if kind[s] == 1:
            m, nz = _agent_rows(rp, ci, hv, zz, rowtype, rownode, m, nz, k, s, z, gps, wr, wg, uix, pix)
        else:
            m, nz = _absolute_row(rp, ci, hv, zz, rowtype, rownode, m, nz, k, s, z, wr, pix)
    if count == 1 and not arrival:
        # a single node: weak zero-velocity prior so that the problem has a unique solution
        ci[nz] = vix[0]
        for ax in range(2):
            hv[ax, nz] = 1.0 / v_prior
            zz[ax, m] = 0.0
        nz += 1
        rowtype[m] = ROW_PRIOR
        rownode[m] = 0
        m += 1
        rp[m] = nz
    return (order, rp[: m + 1].copy(), ci[:nz].copy(), hv[:, :nz].copy(), zz[:, :m].copy(), n, uix, pix, vix,
            rowtype[:m].copy(), rownode[:m].copy())
