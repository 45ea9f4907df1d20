"""Baselines of García Carrillo et al.'s Table I, on the same measurement stream as the sum-of-norms
estimator:

* :class:`KalmanCV` — a Kalman filter on *all* measurements: constant-velocity (white-noise
  acceleration) target model per axis with process-noise density ``q`` (m²/s³),
  Q(Δt) = q·[[Δt³/3, Δt²/2], [Δt²/2, Δt]], measurement of the target position gps + z with covariance
  R + gps_R (agent 0: z with R). The paper does not give its tuning; q ≈ 5000 reproduces its Kalman
  rows ("loose"), q ≈ 1 is the minimum-error tuning (PAPER_NOTES 004) — both are just values of q.
  Out-of-order measurements within ``max_lateness`` are handled exactly: the filter rolls back to the
  state before the late time stamp and re-applies the later measurements; older ones are dropped
  and counted (``stats["too_late"]``).
* :class:`RobustKalmanCV` — the baseline a user would pick instead of a window: the same filter with a
  Huber M-estimation measurement update (iteratively reweighted, :func:`riccati.information_update`
  with weights ψ(r)/r on the whitened innovation) and the same tuning-free threshold as the robust
  moving-horizon estimator (δ = 1.345·σ̂, σ̂ the MAD of its whitened innovations,
  :class:`robust_window.RobustScale`).
* :class:`BatchLeastSquares` — least squares (δ = ∞) on the sum-of-norms estimator's own window and
  graph (same W, motion model, whitening), i.e. the paper's BLS on the same 15-measurement window.
"""

from __future__ import annotations

import bisect
import math

import numpy as np

from .riccati import huber_irls_weight, information_update, predict, white_noise_acceleration
from .relative_measurement import RelativeMeasurement, whitener
from .sum_of_norms import Result, SumOfNormsEstimator


class KalmanCV:
    """Kalman filter, state [p_x, p_y, v_x, v_y], on every measurement (see module doc).

    ``add(meas)`` updates; ``estimate()`` returns the filtered state at the latest time stamp
    (``t``); ``predict(t)`` extrapolates to time t without changing the filter.
    """

    def __init__(self, q: float = 1.0, max_lateness: float = 1.0, v0_sigma: float = 20.0):
        self.q = float(q)
        self.max_lateness = float(max_lateness)
        self.v0_sigma = float(v0_sigma)
        self.x: np.ndarray | None = None
        self.P: np.ndarray | None = None
        self.t = -math.inf
        # history for exact out-of-order handling: (t, seq, meas, x_after, P_after), time order
        self._hist: list[tuple] = []
        self._keys: list[tuple[float, int]] = []
        self._seq = 0
        self.stats = {"received": 0, "accepted": 0, "too_late": 0}

    # ------------------------------------------------------------------ model
    def _FQ(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return white_noise_acceleration(dt, self.q)

    def _step(self, x, P, t_prev, meas: RelativeMeasurement):
        y = meas.target_position
        R = meas.target_cov
        if x is None:
            x = np.array([y[0], y[1], 0.0, 0.0])
            P = np.zeros((4, 4))
            P[:2, :2] = R
            P[2, 2] = P[3, 3] = self.v0_sigma ** 2
            return x, P
        x, P = predict(x, P, *self._FQ(meas.t - t_prev))
        return self._correct(x, P, y, R)

    def _correct(self, x, P, y, R):
        """The measurement update of the predicted (x, P) by the target position y with covariance R."""
        S = P[:2, :2] + R
        K = np.linalg.solve(S, P[:2, :]).T  # P Hᵀ S⁻¹ with H = [I 0]
        x = x + K @ (y - x[:2])
        P = P - K @ P[:2, :]
        P = 0.5 * (P + P.T)
        return x, P

    # ------------------------------------------------------------------ stream
    def add(self, meas: RelativeMeasurement) -> None:
        st = self.stats
        st["received"] += 1
        if meas.t < self.t - self.max_lateness:
            st["too_late"] += 1
            return
        key = (meas.t, self._seq)
        self._seq += 1
        pos = bisect.bisect_right(self._keys, key)
        if pos == len(self._keys):
            x, P = self._step(self.x, self.P, self.t, meas)
            self._hist.append((meas.t, meas, x, P))
            self._keys.append(key)
            self.x, self.P, self.t = x, P, meas.t
        else:
            # roll back to the state before position `pos`, insert, re-apply
            self._hist.insert(pos, (meas.t, meas, None, None))
            self._keys.insert(pos, key)
            if pos == 0:
                x, P, tp = None, None, -math.inf
            else:
                tp, _, x, P = self._hist[pos - 1]
            for j in range(pos, len(self._hist)):
                tj, mj, _, _ = self._hist[j]
                x, P = self._step(x, P, tp, mj)
                self._hist[j] = (tj, mj, x, P)
                tp = tj
            self.x, self.P, self.t = x, P, tp
        st["accepted"] += 1
        # forget history older than the lateness horizon (keep one entry before it as the anchor)
        horizon = self.t - self.max_lateness
        cut = bisect.bisect_left(self._keys, (horizon, -1)) - 1
        if cut > 0:
            del self._hist[:cut]
            del self._keys[:cut]

    def update(self, meas: RelativeMeasurement) -> np.ndarray:
        self.add(meas)
        return self.estimate()

    def estimate(self) -> np.ndarray:
        if self.x is None:
            raise RuntimeError("no measurement yet")
        return self.x.copy()

    def predict(self, t: float) -> np.ndarray:
        F, _ = self._FQ(t - self.t)
        return F @ self.x


class RobustKalmanCV(KalmanCV):
    """:class:`KalmanCV` with a Huber M-estimation measurement update (module doc): the whitened
    innovation rows r = W(y − p) (W R Wᵀ = I) get IRLS weights ψ(r)/r, iterated (at most ``irls_iter``
    times) to the Huber estimate argmin ½‖x − x⁻‖²_{P⁻¹} + Σ huber_δ(rᵢ); the covariance is the
    reweighted one, (P⁻¹ + GᵀWG)⁻¹. δ = c·σ̂ online (``delta`` fixes it instead)."""

    def __init__(self, q: float = 1.0, max_lateness: float = 1.0, v0_sigma: float = 20.0, c: float = 1.345,
                 delta: float | None = None, scale_window: int = 300, irls_iter: int = 10):
        from .robust_window import RobustScale

        super().__init__(q=q, max_lateness=max_lateness, v0_sigma=v0_sigma)
        self.scale = RobustScale(scale_window, c=c)
        self.fixed_delta = delta
        self.irls_iter = int(irls_iter)

    @property
    def delta(self) -> float:
        return self.scale.delta if self.fixed_delta is None else float(self.fixed_delta)

    def _correct(self, x, P, y, R):
        Wt = whitener(R)
        G = np.zeros((2, 4))
        G[:, :2] = Wt
        zw = Wt @ y
        S = G @ P @ G.T + np.eye(2)           # innovation covariance, whitened units
        nu = np.linalg.solve(np.linalg.cholesky(S), zw - G @ x)
        d = self.delta
        self.scale.push(nu)
        Lam = np.linalg.inv(P)
        xs = x
        for _ in range(self.irls_iter):
            xn, Lp = information_update(x, Lam, G, zw, huber_irls_weight(zw - G @ xs, d))
            done = np.max(np.abs(xn - xs)) < 1e-9 * (1.0 + np.max(np.abs(xn)))
            xs = xn
            if done:
                break
        return xs, np.linalg.inv(Lp)


class BatchLeastSquares(SumOfNormsEstimator):
    """Batched least squares on the sum-of-norms window (same graph and whitening, δ = ∞)."""

    def __init__(self, W: int = 15, q: float = 5000.0, max_lateness: float = 1.0, dt_floor: float = 0.02,
                 whitening: str = "chol", v_prior: float = 1e3):
        super().__init__(W=W, delta=math.inf, q=q, solver="ls", max_lateness=max_lateness, dt_floor=dt_floor,
                         whitening=whitening, v_prior=v_prior)

    def solve(self, delta: float | None = None) -> Result:  # δ is irrelevant for least squares
        return super().solve()


# ----------------------------------------------------------------------------- Table I harness


def run_comparison(stream, *, W: int = 15, q_son: float = 5000.0, deltas=(0.1,), kalman_qs=(5000.0, 1.0),
                   q_bls: float | None = None, whitening: str = "chol", solver: str = "ipm",
                   in_arrival_order: bool = False, max_lateness: float = 1.0) -> dict[str, np.ndarray]:
    """Run the sum-of-norms estimator (one window, every δ in ``deltas`` solved on the same built
    problem), BLS on the same window and a Kalman filter per q in ``kalman_qs`` over one simulated
    stream (:class:`agent.models_uav.UavStream`). After every measurement each estimator's estimate of
    the target position is scored against the truth:

    * ``measurement``: the raw measured position gps + z at its time;
    * ``kalman_q<q>``: the filtered estimate at the newest time stamp;
    * ``bls``, ``son_d<δ>``: the newest node; ``son_d<δ>_mid``: the mid-window node (at its own time).

    Returns name → squared position errors (one per processed measurement), so RMSEs pool over seeds.
    """
    order = stream.arrival_order() if in_arrival_order else np.arange(len(stream))
    son = SumOfNormsEstimator(W=W, delta=float(deltas[0]), q=q_son, solver=solver, whitening=whitening,
                              max_lateness=max_lateness)
    bls = BatchLeastSquares(W=W, q=q_son if q_bls is None else q_bls, whitening=whitening,
                            max_lateness=max_lateness)
    kfs = {q: KalmanCV(q=q, max_lateness=max_lateness) for q in kalman_qs}
    dense_t = stream.dense["t"]
    dense_p = stream.dense["pos"]

    def truth(t):
        return np.array([np.interp(t, dense_t, dense_p[:, 0]), np.interp(t, dense_t, dense_p[:, 1])])

    out: dict[str, list] = {"measurement": [], "bls": []}
    for q in kalman_qs:
        out[f"kalman_q{q:g}"] = []
    for d in deltas:
        out[f"son_d{d:g}"] = []
        out[f"son_d{d:g}_mid"] = []
    for i in order:
        m = stream.record(int(i))
        son.add(m)
        bls.add(m)
        for kf in kfs.values():
            kf.add(m)
        if son.window.count == 0:
            continue
        tp = stream.truth_pos[i]
        e = m.target_position - tp
        out["measurement"].append(e @ e)
        rb = bls.solve()
        tn = truth(rb.t_newest)
        e = rb.newest[:2] - tn
        out["bls"].append(e @ e)
        for q, kf in kfs.items():
            e = kf.estimate()[:2] - truth(kf.t)
            out[f"kalman_q{q:g}"].append(e @ e)
        for d, r in zip(deltas, son.solve_deltas(deltas)):
            e = r.newest[:2] - tn
            out[f"son_d{d:g}"].append(e @ e)
            e = r.midwindow[:2] - truth(r.t_mid)
            out[f"son_d{d:g}_mid"].append(e @ e)
    return {k: np.asarray(v) for k, v in out.items()}


def rmse(sq: np.ndarray) -> float:
    """Root of the mean of squared errors (pooled)."""
    return float(np.sqrt(np.mean(sq)))


def score_stream(stream, estimators: dict, in_arrival_order: bool = False) -> dict[str, np.ndarray]:
    """Feed one simulated stream to every estimator (name → a window estimator with ``add``/``solve``, or a
    Kalman filter with ``add``/``estimate``) and score, after every measurement, its newest estimate of the
    target position against the truth at that estimate's time (the window's newest node, the filter's
    latest time stamp). Returns name → squared position errors (pool over seeds with :func:`rmse`)."""
    order = stream.arrival_order() if in_arrival_order else np.arange(len(stream))
    dense_t, dense_p = stream.dense["t"], stream.dense["pos"]
    out: dict[str, list] = {k: [] for k in estimators}
    for i in order:
        m = stream.record(int(i))
        for name, est in estimators.items():
            est.add(m)
            if hasattr(est, "solve"):
                r = est.solve()
                p, t = r.newest[:2], r.t_newest
            else:
                p, t = est.estimate()[:2], est.t
            e = p - np.array([np.interp(t, dense_t, dense_p[:, 0]), np.interp(t, dense_t, dense_p[:, 1])])
            out[name].append(e @ e)
    return {k: np.asarray(v) for k, v in out.items()}
