"""Robust moving-horizon fusion: the sum-of-norms window of García Carrillo et al. with an arrival cost
and a tuning-free threshold.

The window problem
------------------
The paper's estimator (10) on the latest W measurements, in its Huber form (:mod:`son_problem`),

    min_x  ½‖L⁻¹([p_0; v_0] − x̄)‖²  +  Σᵢ huber_δ(rᵢ),     r = z − Hx  (whitened per (8)),

plus one term the paper's window lacks: the **arrival cost** on the oldest node (p_0, v_0) — the
summary of every measurement that has left the window, so the window keeps a Kalman filter's memory
(the paper's 15-measurement window forgets it, which is why the minimum-error Kalman filter beats it
at low outlier rates, docs/carrillo_table1.md). Its rows are quadratic, never Huber (``lsq`` rows of
:mod:`son_problem`), so the same solver family solves it: the compiled IPM with the chain
factorisation by default, the cvxpy reference in the tests.

The arrival cost: the robust Kalman prediction
----------------------------------------------
When the oldest node 0 leaves the window (the W + 1-st measurement arrives), its terms — the previous
arrival cost N(x̄_0, P_0), its GPS row (3) and its relative row (4) — are summarised by the minimiser
and Hessian of their Huber cost *on the active set of the last window solve* (a row with |rᵢ| ≥ δ has
curvature 0 and pulls with the constant force δ·sign rᵢ; :func:`riccati.information_update`):

    Λ⁺ = blkdiag(0, P_0⁻¹) + GᵀΘG,   y⁺ = Λ⁺⁻¹(Λ y_0 + GᵀΘz + Gᵀψ_L),   Θ = ψ′(r̂), ψ_L = ψ(r̂)·(1 − Θ)

over node 0's variables y = [u, p, v] (u: the measuring agent, eliminated by the marginal). The
posterior of (p, v) — mean y⁺_{pv}, covariance (Λ⁺⁻¹)_{pv} — is then predicted to the new oldest node
by the motion model (2), x̄ = F x⁺, P = F Σ⁺ Fᵀ + Q(Δt) (:func:`riccati.predict`): the robust
analogue of the Kalman prediction. The outlier decision about node 0 is the window's, made with the
W − 1 measurements after it (a robust Kalman filter decides on arrival, alone).

The tuning-free threshold
-------------------------
δ = c·σ̂ with the Huber constant c = 1.345 (95 % asymptotic efficiency at the Gaussian) and σ̂ a robust
scale of the whitened measurement residuals: σ̂ = 1.4826·median|ν̃| (the MAD about 0, consistent at the
Gaussian) over the last ``scale_window`` residuals (:class:`RobustScale`), where ν̃ is the relative
row's residual of each node leaving the window at its posterior y⁺, normalised by its own variance under
the model (÷√(1 − h) for an inlier row, ÷√(1 + h) for a rejected one, h = gΛ⁺⁻¹gᵀ): a whitened
one-step innovation, N(0, 1) when the noise model is right, so σ̂ ≈ 1 then and σ̂ tracks the actual
noise level otherwise. In the paper's parametrisation (9)–(10), with residuals divided by the scale
c_(10) before (10) is applied, the equivalent weight is the λ ∈ (0, 1) with

    δ = c_(10)·√2·λ²/(1 − λ)          (son_problem.delta_from_lambda; (10) with ℓ̄ eliminated),

so the online threshold is the paper's λ chosen per window (:attr:`lam`); at c_(10) = 1 and σ̂ = 1,
δ = 1.345 is λ ≈ 0.50 (the paper's λ = 0.0209 is δ = 0.036 at its implied c_(10) ≈ 57, Section IV-A).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .riccati import predict, white_noise_acceleration
from .relative_measurement import RelativeMeasurement
from .robust_window import HUBER_C, MAD_TO_SIGMA, ArrivalCost, RobustScale, fold_node
from .son_layout import time_order
from .spec import FusionSpec
from .sum_of_norms import Result, SumOfNormsEstimator, check_window_keys

__all__ = ["HUBER_C", "MAD_TO_SIGMA", "ArrivalCost", "RobustMHE", "RobustScale", "fold_node"]

class RobustMHE(SumOfNormsEstimator):
    """Robust moving-horizon fusion (module doc): the sum-of-norms window with an arrival cost and the
    online threshold δ = c·σ̂.

    Parameters (beyond :class:`SumOfNormsEstimator`'s W, q, solver, max_lateness, dt_floor, whitening,
    flag_sigma, solver_options):

    c:            Huber constant of the online threshold (default 1.345).
    delta:        a fixed δ instead of the online one (None: online).
    scale_window: residuals in the MAD (default 20 windows' worth: 20·W).
    sigma0:       σ̂ before 30 residuals have been seen.
    p0_sigma, v0_sigma: the initial arrival cost (before any node has left the window): the oldest
                  node's position ~ N(its measured position, p0_sigma²) — i.e. unknown — and its velocity
                  ~ N(0, v0_sigma²), the Kalman baselines' initial prior (``KalmanCV.v0_sigma`` = 20 m/s).
    """

    def __init__(self, W: int = 15, q: float = 1.0, c: float = HUBER_C, delta: float | None = None,
                 scale_window: int | None = None, sigma0: float = 1.0, p0_sigma: float = 1e3,
                 v0_sigma: float = 20.0, robust_motion: bool = True, reject: float = 3.0, **kw):
        if "lam" in kw:
            raise ValueError("the robust MHE sets λ online (give c, or a fixed delta)")
        super().__init__(W=W, q=q, delta=delta if delta is not None else c * sigma0, **kw)
        self.reject = float(reject)
        self.online = delta is None
        self.quad_motion = not robust_motion
        self.scale = RobustScale(int(scale_window or 20 * W), sigma0=sigma0, c=c)
        self.c = float(c)
        self.p0_sigma, self.v0_sigma = float(p0_sigma), float(v0_sigma)
        self._post: tuple[float, np.ndarray, np.ndarray] | None = None   # (t, mean, cov) of the last node out
        self._last: Result | None = None
        self._last_delta = self.delta
        self._dirty = True
        self._arr_key: tuple | None = None
        self._arr: ArrivalCost | None = None

    @property
    def lam(self) -> float:
        """λ of (10) at unit residual scale for the current δ (module doc)."""
        return super().lam

    # ------------------------------------------------------------------ stream
    def add(self, meas: RelativeMeasurement) -> None:
        """Insert one measurement; if it pushes the oldest node out, fold that node into the arrival cost
        (from the last solve of the window that still held it)."""
        w = self.window
        old = None
        if w.count == w.W:
            if self._dirty or self._last is None:
                self.solve()
            s0 = int(time_order(w.t, w.seq, w.count)[0])
            old = (w.meas[s0], w.Wr[s0].copy(), w.Wg[s0].copy())
        ev = w.stats["evicted"]
        st = w.add(meas)
        if st != "accepted":
            return
        self._dirty = True
        if old is not None and w.stats["evicted"] > ev:
            self._absorb(*old)

    def solve(self, delta: float | None = None) -> Result:
        """Solve the window (arrival cost + Huber rows); if some relative measurement's residual exceeds
        ``reject``·σ̂ (a gross outlier, |ℓ̄| > reject·σ̂ − δ), solve again without those measurements (their
        rows zeroed for that solve: a one-step hard-redescending refinement of the Huber estimate)."""
        r = super().solve(delta)
        d = self.delta if delta is None else float(delta)
        lim = self.reject * self.scale.sigma - d
        gross = np.flatnonzero(np.abs(r.ell).max(axis=1) > max(lim, 0.0)) if np.isfinite(lim) else []
        if len(gross):
            w = self.window
            slots = time_order(w.t, w.seq, w.count)[gross]
            keep = (w.wr[slots].copy(), w.Wr[slots].copy())
            w.wr[slots] = 0.0
            w.Wr[slots] = 0.0
            try:
                r2 = super().solve(delta)
            finally:
                w.wr[slots], w.Wr[slots] = keep
            r2.outliers[gross] = True
            r2.extra["rejected"] = int(len(gross))
            r = r2
        if delta is None:
            self._last, self._last_delta, self._dirty = r, self.delta, False
        return r

    # ------------------------------------------------------------------ arrival cost
    def arrival_cost(self) -> ArrivalCost | None:
        """The prior on the current oldest node: the last node out's posterior predicted to it."""
        w = self.window
        if w.count == 0:
            return None
        s0 = int(time_order(w.t, w.seq, w.count)[0])
        if self._post is None:
            key = ("initial", int(w.seq[s0]))
            if key != self._arr_key:
                self._arr_key, self._arr = key, self._initial(w.meas[s0].target_position)
            return self._arr
        return self._predicted_to(float(w.t[s0]))

    def _initial(self, position: np.ndarray) -> ArrivalCost:
        """The initial arrival cost (class doc) on a node measured at ``position``."""
        p2, v2 = self.p0_sigma ** 2, self.v0_sigma ** 2
        return ArrivalCost(np.array([position[0], position[1], 0.0, 0.0]), np.diag([p2, p2, v2, v2]))

    def _predicted_to(self, t: float) -> ArrivalCost:
        """The last node out's posterior predicted to time t (≥ its time) by the motion model (2); the last
        one is kept (a window is solved twice when it holds a gross outlier, and its leaving node folds
        against the prior its last solve had)."""
        key = self._arr_key
        if key is None or key[0] is not self._post or key[1] != float(t):   # (the posterior itself, not its time)
            t_a, x, S = self._post
            F, Q = white_noise_acceleration(max(t - t_a, 0.0), self.q, self.dt_floor)
            self._arr_key, self._arr = (self._post, float(t)), ArrivalCost(*predict(x, S, F, Q))
        return self._arr

    def _absorb(self, rec: RelativeMeasurement, Wr: np.ndarray, Wg: np.ndarray) -> None:
        """Node 0 of the last solve has left the window: its posterior (module doc) becomes the next
        arrival cost, and its normalised relative residual goes into the scale estimate."""
        res = self._last
        mean, cov, nu = fold_node(self._prior_at_oldest(rec), rec, Wr, Wg, res.target[0], res.uav[0],
                                  self._last_delta, self.reject * self.scale.sigma)
        self._post = (float(rec.t), mean, cov)
        self.scale.push(nu)
        if self.online:
            self.set_delta(self.scale.delta)

    def _prior_at_oldest(self, rec: RelativeMeasurement) -> ArrivalCost:
        """The arrival cost node 0 (measured by ``rec``) had in the last solve."""
        if self._post is not None:
            return self._predicted_to(rec.t)
        return self._initial(rec.target_position)


# ============================================================================= the fusion-role plug-in


@dataclass(frozen=True)
class RobustMHEParams:
    """``[fusion]`` keys of ``estimator = "robust_mhe"`` (scenarios/carrillo_robust.toml). ``delta``:
    a fixed threshold instead of the online one (leave it out: δ = c·σ̂)."""

    window: int = 15
    q: float = 3.0
    c: float = HUBER_C
    delta: float | None = None
    reject: float = 3.0
    scale_window: int = 300
    solver: Literal["ipm", "osqp", "cvxpy"] = "ipm"
    max_lateness: float = 1.0
    dt_floor: float = 0.02
    whitening: Literal["chol", "sym"] = "chol"
    flag_sigma: float = 3.0


def _check(source: str, p: RobustMHEParams) -> None:
    from ..schema import ScenarioError

    check_window_keys(source, p)
    if not (math.isfinite(p.c) and p.c > 0):
        raise ScenarioError(source, "fusion.c", f"must be a finite number > 0, got {p.c}",
                            "c = 1.345 (Huber's 95 %-efficiency constant)")
    if not p.reject > 0:
        raise ScenarioError(source, "fusion.reject", f"must be > 0, got {p.reject}",
                            "e.g. reject = 3.0 (σ̂ units; a large value turns the re-solve off)")
    if p.scale_window < 30:
        raise ScenarioError(source, "fusion.scale_window", f"must be ≥ 30 residuals, got {p.scale_window}",
                            "e.g. scale_window = 300 (20 windows of 15)")


def _build(p: RobustMHEParams) -> RobustMHE:
    return RobustMHE(W=p.window, q=p.q, c=p.c, delta=p.delta, reject=p.reject, scale_window=p.scale_window,
                     solver=p.solver, max_lateness=p.max_lateness, dt_floor=p.dt_floor, whitening=p.whitening,
                     flag_sigma=p.flag_sigma)


def _distributed_node(mhe: RobustMHE, i: int, records, iterations: int, rho: float, T: float):
    """UAV ``i``'s node of the distributed fusion (:mod:`agent.estimators.admm_fusion`): this estimator's
    window, motion and threshold settings, agreed with the other UAVs by consensus ADMM."""
    from .admm_fusion import AdmmFusionNode

    return AdmmFusionNode(i, records, W=mhe.W, q=mhe.q, iterations=iterations, rho=rho, c=mhe.c, reject=mhe.reject,
                          scale_window=mhe.scale.size, dt_floor=mhe.dt_floor, whitening=mhe.window.whitening,
                          robust_motion=not mhe.quad_motion, T=T)


FUSION_SPEC = FusionSpec(name="robust_mhe", params=RobustMHEParams, build=_build, check=_check,
                         distributed=_distributed_node,
                         doc="robust moving-horizon fusion: Huber window + arrival cost + online threshold")
