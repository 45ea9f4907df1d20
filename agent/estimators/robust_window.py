"""The robust pieces of the moving-horizon fusion, shared by the central window
(:mod:`agent.estimators.robust_mhe`, whose module doc states the model) and the distributed ADMM node
(:mod:`agent.estimators.admm_fusion`), and the robust Kalman baseline: Huber's constant, the online
scale σ̂ (MAD of the whitened residuals), the arrival cost N(x̄, P) on a window's oldest node, and the
fold of a node leaving the window into it (the robust Kalman prediction).
"""

from __future__ import annotations

import math
from bisect import bisect_left, insort
from dataclasses import dataclass

import numpy as np

from .son_fold import axis_whiteners, fold_kernel
from .relative_measurement import RelativeMeasurement, whitener

__all__ = ["HUBER_C", "MAD_TO_SIGMA", "ArrivalCost", "RobustScale", "fold_node"]

_NO_GPS = np.zeros(2)   # (the reference agent 0 has no GPS row)

HUBER_C = 1.345          #: Huber's constant: 95 % asymptotic efficiency at the Gaussian
MAD_TO_SIGMA = 1.4826    #: 1/Φ⁻¹(3/4): the MAD of a Gaussian times this is its σ


class RobustScale:
    """σ̂ = 1.4826·median|rᵢ| over the last ``size`` whitened residuals pushed (the MAD about 0);
    ``sigma0`` until ``min_count`` have been seen. ``delta`` = c·σ̂."""

    def __init__(self, size: int = 300, min_count: int = 30, sigma0: float = 1.0, c: float = HUBER_C):
        if size < 1 or min_count < 1 or not sigma0 > 0 or not c > 0:
            raise ValueError("size, min_count ≥ 1 and sigma0, c > 0")
        self.size, self.min_count, self.c = int(size), int(min_count), float(c)
        self._buf = [0.0] * self.size   # the last ``size`` values, in arrival order (a ring)
        self._sorted: list[float] = []  # the same values, sorted: the median without a sort per push
        self._n = 0          # values pushed so far
        self.sigma = float(sigma0)

    def push(self, r) -> float:
        """Add residuals; returns the updated σ̂ (the same number np.median of the ring gives)."""
        for v in np.abs(np.ravel(np.asarray(r, float))).tolist():
            if math.isfinite(v):
                slot = self._n % self.size
                if self._n >= self.size:
                    del self._sorted[bisect_left(self._sorted, self._buf[slot])]
                self._buf[slot] = v
                insort(self._sorted, v)
                self._n += 1
        if self._n >= self.min_count:
            s, m = self._sorted, len(self._sorted)
            med = s[m // 2] if m % 2 else (s[m // 2 - 1] + s[m // 2]) / 2
            if med > 0:
                self.sigma = MAD_TO_SIGMA * med
        return self.sigma

    @property
    def count(self) -> int:
        return self._n

    @property
    def delta(self) -> float:
        return self.c * self.sigma


@dataclass(frozen=True)
class ArrivalCost:
    """The prior N(x̄, P) on the oldest node's [p_x, p_y, v_x, v_y] (its rows are L⁻¹(x − x̄), P = LLᵀ)."""

    xbar: np.ndarray
    P: np.ndarray

    @property
    def decoupled(self) -> bool:
        """True if the x- and y-axis are independent (the split solver's per-axis layout)."""
        P = self.P
        return P[0, 1] == 0.0 and P[0, 3] == 0.0 and P[1, 2] == 0.0 and P[2, 3] == 0.0

    def rows(self) -> tuple[np.ndarray, np.ndarray]:
        """(L⁻¹ (4, 4), L⁻¹x̄ (4,)): the four quadratic rows of the joint problem."""
        Wa = whitener(self.P)
        return Wa, Wa @ self.xbar

    def per_axis(self) -> tuple[np.ndarray, np.ndarray]:
        """((2, 2, 2), (2, 2)): per axis a, L_a⁻¹ on [p_a, v_a] and L_a⁻¹x̄_a (requires ``decoupled``;
        computed once: a window is solved twice when it holds a gross outlier)."""
        if "_per_axis" not in self.__dict__:
            self.__dict__["_per_axis"] = axis_whiteners(self.P, self.xbar)   # a cache beside the frozen fields
        return self.__dict__["_per_axis"]


def fold_node(prior: ArrivalCost, rec: RelativeMeasurement, Wr: np.ndarray, Wg: np.ndarray, s_hat: np.ndarray,
              u_hat: np.ndarray, delta: float, gross: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The posterior of a node leaving the window (robust_mhe's module doc, "The arrival cost"): its prior ``prior``
    (the arrival cost it had), its relative row (4) and GPS row (3) (whitened by ``Wr``, ``Wg``) with their
    Huber curvature and force at the window solution (target state ``s_hat``, agent position ``u_hat``) for
    threshold ``delta``; rows beyond ``gross`` leave no trace. Returns (mean (4,), covariance (4, 4)) of
    [p, v], and the relative row's normalised residual ν̃ (2,) for the scale estimate."""
    has_u = rec.agent != 0
    return fold_kernel(prior.P, prior.xbar, np.asarray(Wr, float), np.asarray(Wg, float), rec.z,
                       rec.gps if has_u else _NO_GPS, has_u, np.asarray(s_hat, float),
                       np.asarray(u_hat, float) if has_u else _NO_GPS,
                       float(delta), float(gross))
