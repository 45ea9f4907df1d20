"""The fusion role's data: one time-stamped relative measurement of the target by a UAV (García Carrillo
et al.'s (3)–(4)), and the whitening of its covariance (8) — shared by every fusion estimator
(:mod:`sum_of_norms`, :mod:`robust_mhe`, :mod:`admm_fusion`, :mod:`fusion_baselines`) and the UAV world
(:mod:`agent.models_uav`, :mod:`agent.roles.uav`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["RelativeMeasurement", "whitener"]


def _as_cov(M, name: str) -> np.ndarray:
    A = np.asarray(M, dtype=float)
    if A.shape != (2, 2) or not np.isfinite(A).all():
        raise ValueError(f"{name} must be a finite 2×2 covariance, got shape {A.shape}")
    if abs(A[0, 1] - A[1, 0]) > 1e-9 * max(1.0, abs(A).max()):
        raise ValueError(f"{name} must be symmetric")
    if A[0, 0] <= 0 or A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0] <= 0:
        raise ValueError(f"{name} must be positive definite")
    return A


def _as_vec2(v, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (2,) or not np.isfinite(a).all():
        raise ValueError(f"{name} must be a finite 2-vector")
    return a


@dataclass(frozen=True)
class RelativeMeasurement:
    """One time-stamped relative measurement of the target by an agent (the paper's (4)).

    agent:  id of the measuring agent; 0 is the reference agent, i.e. ``z`` is then an absolute
            measurement (3) of the target's position and ``gps`` must be None.
    t:      time stamp (s) at which the measurement was taken.
    z:      (2,) measured target position minus the agent's position (m).
    R:      (2, 2) covariance of ``z`` (m²).
    gps:    (2,) the agent's GPS position at ``t`` (required for agent ≥ 1).
    gps_R:  (2, 2) covariance of ``gps``.
    """

    agent: int
    t: float
    z: np.ndarray
    R: np.ndarray
    gps: np.ndarray | None = None
    gps_R: np.ndarray | None = None

    def __post_init__(self):
        object.__setattr__(self, "agent", int(self.agent))
        object.__setattr__(self, "t", float(self.t))
        if not math.isfinite(self.t):
            raise ValueError("t must be finite")
        object.__setattr__(self, "z", _as_vec2(self.z, "z"))
        object.__setattr__(self, "R", _as_cov(self.R, "R"))
        if self.agent < 0:
            raise ValueError("agent ids are ≥ 0 (0 = the reference agent)")
        if self.agent == 0:
            if self.gps is not None:
                raise ValueError("agent 0 is the reference agent (x₀ ≡ 0): it has no GPS")
        else:
            if self.gps is None or self.gps_R is None:
                raise ValueError("a measurement by agent ≥ 1 needs the agent's GPS position and covariance")
            object.__setattr__(self, "gps", _as_vec2(self.gps, "gps"))
            object.__setattr__(self, "gps_R", _as_cov(self.gps_R, "gps_R"))

    @property
    def target_position(self) -> np.ndarray:
        """The raw measured target position gps + z (what "measurement error" is computed from)."""
        return self.z if self.gps is None else self.gps + self.z

    @property
    def target_cov(self) -> np.ndarray:
        return self.R if self.gps_R is None else self.R + self.gps_R


def whitener(C: np.ndarray, mode: str = "chol") -> np.ndarray:
    """2×2 matrix W with W C Wᵀ = I: L⁻¹ (C = LLᵀ, L lower) for "chol", C^{-1/2} for "sym"."""
    C = np.asarray(C, float)
    if mode == "chol":
        return np.linalg.inv(np.linalg.cholesky(C))
    if mode == "sym":
        w, V = np.linalg.eigh(C)
        return (V / np.sqrt(w)) @ V.T
    raise ValueError("whitening must be 'chol' or 'sym'")
