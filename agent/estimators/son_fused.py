"""The sum-of-norms estimator's hot path: a split window built, solved and decoded in one compiled call.

For the default solver on a window whose covariances are all diagonal,
``SumOfNormsEstimator.solve`` makes one call to :func:`fused_split_ipm` instead of building the
:class:`son_problem.HuberProblem` in Python: :func:`son_layout.build_split` (the rows of (2)–(4),
whitened per (8)), :func:`son_ipm.ipm_solve_all` on both axes (the Huber form of (10)),
:func:`son_problem.evaluate_all` (the common objective and KKT residuals), and the decoding of the
node vector into target states, agent positions and ℓ̄ on the relative rows.
"""

from __future__ import annotations

import numpy as np

from .son_banded import bandwidth
from .son_ipm import ipm_solve_all
from .son_jit import kernel
from .son_layout import ROW_REL, build_split_arrival, quadratic_rows
from .son_problem import evaluate_all

__all__ = ["fused_split_ipm"]


@kernel
def fused_split_ipm(t, seq, kind, z, gps, wr, wg, count, q, dt_floor, mode, v_prior, aW, az, arrival, quad_motion,
                    delta, tol, maxit, polish, ptol):
    """Build (:func:`son_layout.build_split_arrival`; window slots, layout and arrival-cost arguments as
    there; the quadratic rows are the arrival rows, and the motion rows if ``quad_motion``), solve both
    axes (:func:`son_ipm.ipm_solve_all` with ``tol``, ``maxit``, ``polish``, polish gap ``ptol``),
    evaluate (:func:`son_problem.evaluate_all`) and decode, in one compiled call.

    Returns order (k,) slots in time order, times (k,), X (2, n), target (k, 4) [p_x, p_y, v_x, v_y],
    uav (k, 2) (NaN for agent 0), ellm (k, 2) ℓ̄ of each node's relative rows, ell (2, m) ℓ̄ of every
    row, and summary (9,): objective, stationarity, stationarity_rel, max |r|, gap (sum over axes),
    ‖Hᵀu‖∞, iterations, status and polish (per-axis worst)."""
    order, rp, ci, hv, zz, n, uix, pix, vix, rowtype, rownode = build_split_arrival(
        t, seq, kind, z, gps, wr, wg, count, q, dt_floor, mode, v_prior, aW, az, arrival)
    lsq = quadratic_rows(rowtype, quad_motion)
    X, U, info = ipm_solve_all(rp, ci, hv, zz, n, bandwidth(rp, ci), (rowtype, rownode, uix, pix, vix), delta, lsq,
                               tol, maxit, polish, ptol)
    obj, ell, stat, scale, rmax = evaluate_all(rp, ci, hv, zz, n, delta, lsq, X)
    k = count
    target = np.empty((k, 4))
    uav = np.full((k, 2), np.nan)
    ellm = np.zeros((k, 2))
    times = np.empty(k)
    for j in range(k):
        times[j] = t[order[j]]
        for ax in range(2):
            target[j, ax] = X[ax, pix[j]]
            target[j, 2 + ax] = X[ax, vix[j]]
            if uix[j] >= 0:
                uav[j, ax] = X[ax, uix[j]]
    for r in range(rowtype.shape[0]):
        if rowtype[r] == ROW_REL:
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
