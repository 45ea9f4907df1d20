"""Sum-of-norms estimation under impulsive noise on an asynchronous measurement graph
(García Carrillo, Russell, Hespanha & Collins; "the paper" below, equations (2)–(10)).

The measurement graph
---------------------
Nodes are agent states at measurement times plus the reference agent 0 (x₀ ≡ 0, never a variable):

* one **target node** (position p, velocity v; double integrator per axis) per measurement, at the
  measurement's time stamp — one node per measurement keeps the sparsity pattern of H fixed as the
  window slides (PAPER_NOTES 004);
* one **measuring-agent node** (position u) per measurement of an agent i ≥ 1. As in the paper's UAV
  experiment the agents' own motion constraints are *not* used (their GPS/IMU is good, their dynamics
  windy), so each agent node carries its GPS edge and its relative edge only.

Edges (rows of z = Hx + ε, each whitened per (8) so that ε has unit covariance):

* motion constraint (2) between consecutive target nodes (time order, any agent):
  [p_k; v_k] − Φ(Δt)[p_{k−1}; v_{k−1}] = d̄,  Φ = [[1, Δt], [0, 1]],  cov d̄ = q·[[Δt³/3, Δt²/2],
  [Δt²/2, Δt]] (white-noise acceleration of spectral density ``q`` m²/s³), with Δt floored at
  ``dt_floor`` in the covariance only (two UAVs measuring at nearly the same instant would otherwise
  make H ill-conditioned); no known input, so z = 0;
* relative measurement (4): z_k = p_k − u_k + n, cov ``R`` (agent 0: z_k = p_k + n, an absolute (3));
* GPS (3) of the measuring agent: gps_k = u_k + n, cov ``gps_R``.

Whitening: a 2×2 block with covariance C is multiplied by C^{-1/2}. ``whitening="chol"`` (default)
uses L⁻¹ with C = LLᵀ, L lower (motion blocks: position row first, then the velocity row conditioned
on it); ``"sym"`` uses the symmetric square root. They differ because the ℓ₁ term is not rotation
invariant (PAPER_NOTES 004); for diagonal measurement covariances they coincide.

If every covariance in the window is diagonal, the problem splits into an x- and a y-problem with one
sparsity pattern (variables per node [u, p, v] of that axis); otherwise one joint problem is solved
(variables per node [u_x, u_y, p_x, p_y, v_x, v_y]). Nodes are ordered by time, so HᵀH is banded.

The estimator and its robustness knob
-------------------------------------
(10):  min_{x,ℓ̄}  1/(2λ²)·‖(Hx − z)/c + ℓ̄‖² + √2/(1 − λ)·‖ℓ̄‖₁,  equivalently (ℓ̄ eliminated)

    min_x Σᵢ huber_δ(rᵢ),  r = z − Hx (unit-covariance whitened),  δ = c·√2·λ²/(1 − λ),

and ℓ̄ = soft_threshold(r, δ)/c. The knob is **δ**, the Huber threshold in units of the whitened noise
standard deviation: residuals below δ are treated as Gaussian, above it as impulsive. Give either
``delta`` or ``lam`` together with the residual scale ``scale`` (= c). The paper's λ values only make
sense with an undisclosed c ≈ 57 (its λ = 0.0209 is δ ≈ 0.036 at c = 57); with c = 1 the same δ is
λ ≈ 0.15. δ ≥ max|r_LS| gives least squares exactly (λ ≥ λ_max: no outlier detected).
All reported objective values are in the Huber form Σ huber_δ(r) (= λ²c² × objective (10)).

Sliding window and lateness
---------------------------
The window holds the latest ``W`` measurements by time stamp (any agent, any rate). A measurement
may arrive out of order:

* t ≥ t_newest − ``max_lateness``: inserted at its place in time; if the window then holds W + 1
  measurements the *oldest by time stamp* is evicted — which is the new one itself if it is older than
  the whole (full) window (counted as ``stale``);
* t < t_newest − ``max_lateness``: dropped and counted as ``too_late`` (its node would sit in the
  window's past with a stale estimate already published; reprocessing is bounded by the lateness);
* the same (agent, t) twice: dropped, counted as ``duplicate`` (at-least-once transports).

Estimates: ``newest`` is the target state at the newest node (the filtering estimate, what Table I
scores by default); ``midwindow`` the node in the middle of the window (index (k−1)//2 in time order
— a smoothed estimate with a lag of about half the window).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from .relative_measurement import RelativeMeasurement, whitener
from .son_banded import bandwidth
from .son_covariance import node_covariances
from .son_fused import fused_split_ipm
from .son_ipm import IPM_STATUS, solve_ipm
from .son_layout import (NO_ARRIVAL, ROW_ARRIVAL, ROW_GPS, ROW_PRIOR, ROW_REL, build_split, build_split_arrival,
                         motion_weights, quadratic_rows, time_order)
from .son_problem import HuberProblem, SolveOut, delta_from_lambda, lambda_from_delta
from .son_reference import CvxpyReference, OsqpSolver, solve_ls
from .spec import FusionSpec

__all__ = ["RelativeMeasurement", "Result", "SumOfNormsEstimator", "MeasurementWindow", "build_joint", "build_split",
           "delta_from_lambda", "lambda_from_delta", "whitener", "motion_whitener"]


# ============================================================================= whitening


def motion_whitener(dt: float, q: float, dt_floor: float = 0.02, mode: str = "chol") -> np.ndarray:
    return motion_weights(float(dt), float(q), float(dt_floor), 0 if mode == "chol" else 1)


# ============================================================================= graph builders


def build_joint(t, seq, kind, z, gps, Wr, Wg, count, q, dt_floor, mode, v_prior, arrival=None):
    """One joint problem (some covariance not diagonal). ``Wr``/``Wg`` (cap, 2, 2) whitening matrices.
    Node k has variables [u_x, u_y (kind 1 only), p_x, p_y, v_x, v_y]. ``arrival``: None, or the arrival
    cost (L⁻¹ (4, 4), L⁻¹x̄ (4,)) on [p_x, p_y, v_x, v_y] of the oldest node (four quadratic rows
    ``ROW_ARRIVAL`` first). Same returns as :func:`build_split`, with hv/zz of shape (1, ·) and
    uix/pix/vix of shape (count, 2)."""
    order = time_order(t, seq, count)
    uix = np.full((count, 2), -1, np.int64)
    pix = np.empty((count, 2), np.int64)
    vix = np.empty((count, 2), np.int64)
    n = 0
    for k in range(count):
        s = order[k]
        if kind[s] == 1:
            uix[k] = (n, n + 1)
            n += 2
        pix[k] = (n, n + 1)
        vix[k] = (n + 2, n + 3)
        n += 4
    rp, ci, hv, zz, rowtype, rownode = [0], [], [], [], [], []

    def add_row(cols, vals, zi, rt, k):
        ci.extend(cols)
        hv.extend(vals)
        rp.append(len(ci))
        zz.append(zi)
        rowtype.append(rt)
        rownode.append(k)

    if arrival is not None:
        Wa, za = arrival
        cols = [pix[0, 0], pix[0, 1], vix[0, 0], vix[0, 1]]
        for row in range(4):
            add_row(cols, list(Wa[row]), float(za[row]), ROW_ARRIVAL, 0)
    for k in range(count):
        s = order[k]
        if k > 0:
            dt = t[s] - t[order[k - 1]]
            W = motion_weights(dt, q, dt_floor, mode)
            for ax in range(2):
                for row in range(2):
                    a0, a1 = W[row, 0], W[row, 1]
                    add_row([pix[k - 1, ax], vix[k - 1, ax], pix[k, ax], vix[k, ax]],
                            [-a0, -(a0 * dt + a1), a0, a1], 0.0, row, k)
        if kind[s] == 1:
            Wgs = Wg[s]
            zg = Wgs @ gps[s]
            for row in range(2):
                add_row([uix[k, 0], uix[k, 1]], [Wgs[row, 0], Wgs[row, 1]], zg[row], ROW_GPS, k)
            Wrs = Wr[s]
            zr = Wrs @ z[s]
            for row in range(2):
                add_row([uix[k, 0], uix[k, 1], pix[k, 0], pix[k, 1]],
                        [-Wrs[row, 0], -Wrs[row, 1], Wrs[row, 0], Wrs[row, 1]], zr[row], ROW_REL, k)
        else:
            Wrs = Wr[s]
            zr = Wrs @ z[s]
            for row in range(2):
                add_row([pix[k, 0], pix[k, 1]], [Wrs[row, 0], Wrs[row, 1]], zr[row], ROW_REL, k)
    if count == 1 and arrival is None:
        for ax in range(2):
            add_row([vix[0, ax]], [1.0 / v_prior], 0.0, ROW_PRIOR, 0)
    return (order, np.array(rp, np.int64), np.array(ci, np.int64), np.array(hv, float)[None, :],
            np.array(zz, float)[None, :], n, uix, pix, vix, np.array(rowtype, np.int64), np.array(rownode, np.int64))


# ============================================================================= the window


class MeasurementWindow:
    """The latest W measurements by time stamp, stored in slots (unsorted; builders sort).

    ``add(meas)`` returns one of "accepted", "too_late", "stale", "duplicate"; ``stats`` counts them
    and the evictions. Invariant: ``count ≤ W``; once W measurements have been accepted, count == W.
    """

    def __init__(self, W: int = 15, max_lateness: float = 1.0, whitening: str = "chol"):
        if W < 1:
            raise ValueError("W must be ≥ 1")
        self.W = int(W)
        self.max_lateness = float(max_lateness)
        self.whitening = whitening
        cap = self.W
        self.t = np.zeros(cap)
        self.seq = np.zeros(cap, np.int64)
        self.kind = np.zeros(cap, np.int64)
        self.agent = np.zeros(cap, np.int64)
        self.z = np.zeros((cap, 2))
        self.gps = np.zeros((cap, 2))
        self.Wr = np.zeros((cap, 2, 2))
        self.Wg = np.zeros((cap, 2, 2))
        self.wr = np.zeros((cap, 2))
        self.wg = np.ones((cap, 2))
        self.diag = np.ones(cap, bool)
        self.meas: list[RelativeMeasurement | None] = [None] * cap
        self.count = 0
        self.t_newest = -math.inf
        self._seq = 0
        self.stats = {"received": 0, "accepted": 0, "too_late": 0, "stale": 0, "duplicate": 0, "evicted": 0}

    def add(self, meas: RelativeMeasurement) -> str:
        st = self.stats
        st["received"] += 1
        t = meas.t
        if t < self.t_newest - self.max_lateness:
            st["too_late"] += 1
            return "too_late"
        c = self.count
        tw = self.t[:c]
        for s in np.flatnonzero(tw == t):
            if self.agent[s] == meas.agent:
                st["duplicate"] += 1
                return "duplicate"
        if c == self.W:
            s = int(np.argmin(tw))  # oldest by (t, seq): argmin returns the first slot among ties …
            ties = np.flatnonzero(tw == tw[s])
            if ties.size > 1:
                s = int(ties[np.argmin(self.seq[ties])])
            if t < tw[s]:
                st["stale"] += 1
                return "stale"
            st["evicted"] += 1
        else:
            s = c
            self.count = c + 1
        self._store(s, meas)
        if t > self.t_newest:
            self.t_newest = t
        st["accepted"] += 1
        return "accepted"

    def _store(self, s: int, meas: RelativeMeasurement) -> None:
        self.t[s] = meas.t
        self.seq[s] = self._seq
        self._seq += 1
        self.agent[s] = meas.agent
        self.z[s] = meas.z
        R = meas.R
        diag = R[0, 1] == 0.0
        Wr = whitener(R, self.whitening) if not diag else np.diag(1.0 / np.sqrt(np.diag(R)))
        self.Wr[s] = Wr
        self.wr[s, 0] = Wr[0, 0]
        self.wr[s, 1] = Wr[1, 1]
        if meas.agent == 0:
            self.kind[s] = 0
            self.gps[s] = 0.0
            self.Wg[s] = np.eye(2)
            self.wg[s] = 1.0
        else:
            self.kind[s] = 1
            self.gps[s] = meas.gps
            G = meas.gps_R
            gdiag = G[0, 1] == 0.0
            Wg = whitener(G, self.whitening) if not gdiag else np.diag(1.0 / np.sqrt(np.diag(G)))
            self.Wg[s] = Wg
            self.wg[s, 0] = Wg[0, 0]
            self.wg[s, 1] = Wg[1, 1]
            diag = diag and gdiag
        self.diag[s] = diag
        self.meas[s] = meas

    def measurements(self) -> list[RelativeMeasurement]:
        """The window's measurements in time order."""
        order = time_order(self.t, self.seq, self.count)
        return [self.meas[s] for s in order]

    @property
    def split(self) -> bool:
        return bool(self.diag[: self.count].all())


# ============================================================================= results


@dataclass(slots=True)
class Result:
    """What :meth:`SumOfNormsEstimator.solve` returns.

    x:          (A, n) the solver's node vector(s) (A = 2 per-axis problems, or 1 joint problem).
    times:      (k,) node times in time order; ``agents`` (k,) measuring agent per node.
    target:     (k, 4) target state [p_x, p_y, v_x, v_y] at every node.
    uav:        (k, 2) estimated positions of the measuring agents (NaN for agent 0).
    ell:        (k, 2) ℓ̄ on each node's relative-measurement rows (whitened units, ÷c for (10)'s units);
    ell_rows:   (A, m) ℓ̄ on every row (motion, GPS, relative).
    outliers:   (k,) bool — measurement judged an outlier: ‖ℓ̄ of its relative rows‖ > ``flag_sigma``.
    objective:  Σ huber_δ(r) at x (Huber form; objective (10) = objective / (λ²c²)).
    kkt:        residuals (stationarity, stationarity_rel, gap, …; see son_problem).
    newest, midwindow: (4,) target state at the newest node / the middle node; t_newest, t_mid.
    """

    x: np.ndarray
    times: np.ndarray
    agents: np.ndarray
    target: np.ndarray
    uav: np.ndarray
    ell: np.ndarray
    ell_rows: np.ndarray
    outliers: np.ndarray
    objective: float
    kkt: dict
    newest: np.ndarray
    midwindow: np.ndarray
    t_newest: float
    t_mid: float
    solver: str
    iterations: int
    status: str
    extra: dict = field(default_factory=dict)


# ============================================================================= the estimator


class SumOfNormsEstimator:
    """Sliding-window sum-of-norms estimator (10) of the target position (and the agents').

    Parameters
    ----------
    W:            window length in measurements (the paper: 15).
    delta:        Huber threshold δ on unit-whitened residuals (the robustness knob; default 0.1).
    lam, scale:   alternatively λ of (10) and the residual scale c: δ = c·√2λ²/(1−λ).
    q:            the estimator's target motion model: white-noise acceleration density (m²/s³);
                  default 5000, the single loose tuning that reproduces the paper's Table I.
    solver:       "ipm" (default, numba), "osqp", "cvxpy" (cvxpy + Clarabel, the reference), "ls" (δ = ∞).
    max_lateness: out-of-order tolerance (s); older measurements are dropped and counted.
    dt_floor:     floor on Δt in the motion covariance (s).
    whitening:    "chol" or "sym" (see module doc).
    flag_sigma:   ‖ℓ̄‖ (whitened) above which a measurement is reported as an outlier.
    v_prior:      σ (m/s) of the zero-velocity prior used only while the window holds one node.
    solver_options: passed to the solver (ipm: tol, maxit, polish; osqp: settings; cvxpy: tol …).
    """

    def __init__(self, W: int = 15, delta: float | None = None, lam: float | None = None, scale: float = 1.0,
                 q: float = 5000.0, solver: str = "ipm", max_lateness: float = 1.0, dt_floor: float = 0.02,
                 whitening: str = "chol", flag_sigma: float = 3.0, v_prior: float = 1e3,
                 solver_options: dict | None = None):
        if delta is not None and lam is not None:
            raise ValueError("give either delta or (lam, scale), not both")
        if lam is not None:
            delta = delta_from_lambda(lam, scale)
        if delta is None:
            delta = 0.1
        if not delta > 0:
            raise ValueError("delta must be positive")
        if whitening not in ("chol", "sym"):
            raise ValueError("whitening must be 'chol' or 'sym'")
        if solver not in ("ipm", "osqp", "cvxpy", "ls"):
            raise ValueError(f"unknown solver {solver!r}")
        self.delta = float(delta)
        self.scale = float(scale)
        self.q = float(q)
        self.dt_floor = float(dt_floor)
        self.flag_sigma = float(flag_sigma)
        self.v_prior = float(v_prior)
        self.quad_motion = False   #: motion rows quadratic (never Huber); the paper: Huber on every row
        self.solver = solver
        self.solver_options = dict(solver_options or {})
        self.window = MeasurementWindow(W, max_lateness, whitening)
        self._mode = 0 if whitening == "chol" else 1
        self._osqp = OsqpSolver(**self.solver_options) if solver == "osqp" else None
        self._cvx = CvxpyReference(**self.solver_options) if solver == "cvxpy" else None

    # ------------------------------------------------------------------ knobs
    @property
    def W(self) -> int:
        return self.window.W

    @property
    def lam(self) -> float:
        """λ of (10) for the current δ and residual scale."""
        return lambda_from_delta(self.delta, self.scale)

    @property
    def stats(self) -> dict:
        return self.window.stats

    def set_delta(self, delta: float) -> None:
        self.delta = float(delta)

    # ------------------------------------------------------------------ stream
    def add(self, meas: RelativeMeasurement) -> None:
        """Insert one measurement (policy in the module doc); counters in :attr:`stats`."""
        self.window.add(meas)

    def update(self, meas: RelativeMeasurement) -> Result:
        self.add(meas)
        return self.solve()

    # ------------------------------------------------------------------ problem
    def problem(self, delta: float | None = None):
        """The window's Huber problem and its layout: (HuberProblem, layout dict)."""
        w = self.window
        if w.count == 0:
            raise RuntimeError("the window is empty")
        d = self.delta if delta is None else float(delta)
        arr = self.arrival_cost()
        split = self._split(arr)
        if split:
            aW, az = NO_ARRIVAL if arr is None else arr.per_axis()
            out = build_split_arrival(w.t, w.seq, w.kind, w.z, w.gps, w.wr, w.wg, w.count, self.q, self.dt_floor,
                                      self._mode, self.v_prior, aW, az, arr is not None)
            axes_map = (0, 1)
        else:
            out = build_joint(w.t, w.seq, w.kind, w.z, w.gps, w.Wr, w.Wg, w.count, self.q, self.dt_floor,
                              self._mode, self.v_prior, None if arr is None else arr.rows())
            axes_map = (0, 0)
        order, rp, ci, hv, zz, n, uix, pix, vix, rowtype, rownode = out
        chain = (rowtype, rownode, uix, pix, vix) if split else None
        lsq = quadratic_rows(rowtype, self.quad_motion)
        prob = HuberProblem(rp, ci, hv, zz, int(n), int(bandwidth(rp, ci)), d, chain, lsq if lsq.any() else None)
        layout = {"order": order, "uix": uix, "pix": pix, "vix": vix, "rowtype": rowtype, "rownode": rownode,
                  "split": split, "axes_map": axes_map}
        return prob, layout

    # ------------------------------------------------------------------ arrival cost (moving horizon)
    def arrival_cost(self):
        """The prior on the window's oldest node, or None (this estimator has none; the moving-horizon
        estimator :class:`agent.estimators.robust_mhe.RobustMHE` carries one: an object with ``rows()`` —
        (L⁻¹ (4, 4), L⁻¹x̄ (4,)) on [p_x, p_y, v_x, v_y] — ``per_axis()`` — the same split by axis, (2, 2, 2)
        and (2, 2) — and ``decoupled``, whether the axes are independent)."""
        return None

    def _split(self, arr) -> bool:
        return self.window.split and (arr is None or arr.decoupled)

    def _run_solver(self, prob: HuberProblem) -> SolveOut:
        if self.solver == "ipm":
            return solve_ipm(prob, **self.solver_options)
        if self.solver == "osqp":
            return self._osqp.solve(prob)
        if self.solver == "cvxpy":
            return self._cvx.solve(prob)
        return solve_ls(prob)

    def solve(self, delta: float | None = None) -> Result:
        """Solve (10) on the current window (optionally at another δ) and decode the estimates."""
        w = self.window
        if self.solver == "ipm" and w.count > 0 and self._split(self.arrival_cost()):
            return self._solve_fused(self.delta if delta is None else float(delta))
        prob, lay = self.problem(delta)
        out = self._run_solver(prob)
        return self._decode(prob, lay, out)

    def _solve_fused(self, delta: float) -> Result:
        w = self.window
        o = self.solver_options
        arr = self.arrival_cost()
        aW, az = NO_ARRIVAL if arr is None else arr.per_axis()
        order, times, X, target, uav, ellm, ell, sm = fused_split_ipm(
            w.t, w.seq, w.kind, w.z, w.gps, w.wr, w.wg, w.count, self.q, self.dt_floor, self._mode, self.v_prior,
            aW, az, arr is not None, self.quad_motion, delta, o.get("tol", 1e-9), o.get("maxit", 60), o.get("polish", True),
            o.get("polish_gap", 0.3))
        k = order.shape[0]
        mid = (k - 1) // 2
        obj, stat, stat_rel, rmax, gap, pres, iters, st, pol = sm.tolist()
        kkt = {"stationarity": stat, "stationarity_rel": stat_rel, "gap": gap, "max_abs_residual": rmax,
               "dual_infeasibility": pres}
        return Result(X, times, w.agent[order], target, uav, ellm, ell,
                      (ellm[:, 0] ** 2 + ellm[:, 1] ** 2) > self.flag_sigma ** 2, obj, kkt, target[k - 1],
                      target[mid], times[k - 1], times[mid], "ipm", int(iters),
                      IPM_STATUS[int(st)], {"polished_both": pol == 1.0})

    def solve_deltas(self, deltas) -> list[Result]:
        """Solve the same window for several δ (the problem is built once): the λ/δ sweep."""
        w = self.window
        if self.solver == "ipm" and w.count > 0 and self._split(self.arrival_cost()):
            return [self._solve_fused(float(d)) for d in deltas]
        prob, lay = self.problem()
        return [self._decode(prob, lay, self._run_solver(prob.with_delta(float(d)))) for d in deltas]

    def _decode(self, prob: HuberProblem, lay: dict, out: SolveOut) -> Result:
        w = self.window
        order = lay["order"]
        k = order.shape[0]
        X = out.x
        target = np.empty((k, 4))
        uav = np.full((k, 2), np.nan)
        pix, vix, uix = lay["pix"], lay["vix"], lay["uix"]
        if lay["split"]:
            for ax in range(2):
                target[:, ax] = X[ax, pix]
                target[:, 2 + ax] = X[ax, vix]
                has = uix >= 0
                uav[has, ax] = X[ax, uix[has]]
        else:
            for ax in range(2):
                target[:, ax] = X[0, pix[:, ax]]
                target[:, 2 + ax] = X[0, vix[:, ax]]
                has = uix[:, ax] >= 0
                uav[has, ax] = X[0, uix[has, ax]]
        # ℓ̄ on the relative rows, per node
        ell = np.zeros((k, 2))
        rel = np.flatnonzero(lay["rowtype"] == ROW_REL)
        if lay["split"]:
            ell[lay["rownode"][rel], 0] = out.ell[0, rel]
            ell[lay["rownode"][rel], 1] = out.ell[1, rel]
        else:
            nodes = lay["rownode"][rel]
            # two rows per node, in order
            ell[nodes[0::2], 0] = out.ell[0, rel[0::2]]
            ell[nodes[1::2], 1] = out.ell[0, rel[1::2]]
        outliers = np.hypot(ell[:, 0], ell[:, 1]) > self.flag_sigma
        times = w.t[order].copy()
        mid = (k - 1) // 2
        return Result(x=X, times=times, agents=w.agent[order].copy(), target=target, uav=uav, ell=ell,
                      ell_rows=out.ell, outliers=outliers, objective=out.objective, kkt=out.kkt,
                      newest=target[-1].copy(), midwindow=target[mid].copy(), t_newest=float(times[-1]),
                      t_mid=float(times[mid]), solver=out.solver, iterations=out.iterations, status=out.status,
                      extra=out.extra)

    def covariances(self, delta: float | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """The covariances of the target state at the window's newest and middle nodes (4 × 4 each, the order
        of :attr:`Result.newest` and :attr:`Result.midwindow`) that the window's own information implies
        (:func:`agent.estimators.son_covariance.node_covariances`); None for an empty or undetermined window."""
        if self.window.count == 0:
            return None
        prob, lay = self.problem(delta)
        k = lay["order"].shape[0]
        out = node_covariances(prob, lay, [k - 1, (k - 1) // 2])
        return None if out is None else (out[0], out[1])

    # ------------------------------------------------------------------ λ helpers
    def lambda_max(self) -> float:
        """λ_max (at the current residual scale): the smallest λ for which no outlier is detected,
        i.e. δ = max |r_LS| of the window's least-squares residuals."""
        prob, _ = self.problem()
        ls = solve_ls(prob)
        return lambda_from_delta(max(ls.kkt["max_abs_residual"], 1e-300), self.scale)


# ============================================================================= the fusion-role plug-in


@dataclass(frozen=True)
class SonParams:
    """``[fusion]`` keys of ``estimator = "sum_of_norms"`` (the paper's window, scenarios/carrillo_uav.toml)."""

    window: int = 15
    delta: float = 0.1
    q: float = 5000.0
    solver: Literal["ipm", "osqp", "cvxpy", "ls"] = "ipm"
    max_lateness: float = 1.0
    dt_floor: float = 0.02
    whitening: Literal["chol", "sym"] = "chol"
    flag_sigma: float = 3.0


def check_window_keys(source: str, p) -> None:
    """The window keys every sum-of-norms fusion estimator shares (window, q, max_lateness, dt_floor, and
    δ when given): positive, precise errors."""
    from ..schema import ScenarioError

    if p.window < 1:
        raise ScenarioError(source, "fusion.window", f"must be ≥ 1, got {p.window}", "e.g. window = 15")
    for key in ("q", "dt_floor", "max_lateness", "flag_sigma") + (("delta",) if p.delta is not None else ()):
        v = getattr(p, key)
        if not (math.isfinite(v) and v > 0):
            raise ScenarioError(source, f"fusion.{key}", f"must be a finite number > 0, got {v}",
                                f"e.g. {key} = {getattr(type(p), key, 1.0)}")


def _build_son(p: SonParams) -> SumOfNormsEstimator:
    return SumOfNormsEstimator(W=p.window, delta=p.delta, q=p.q, solver=p.solver, max_lateness=p.max_lateness,
                               dt_floor=p.dt_floor, whitening=p.whitening, flag_sigma=p.flag_sigma)


FUSION_SPEC = FusionSpec(name="sum_of_norms", params=SonParams, build=_build_son, check=check_window_keys,
                         default=True, doc="García Carrillo et al.'s sliding-window sum-of-norms estimator (10)")
