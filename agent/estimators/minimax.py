"""Centralized minimax filter of Gu & Hu (2009), eqs. (10)-(13) and the information form of III-A.

Model (1)-(4): x_{t+1} = A x_t + B w_t + d_t,  y_t^j = C^j x_t + v_t^j  (j = 1..N sensors),
with w ~ N(0, Q), v^j ~ N(0, R^j) and an adversary d_t = L(C(x_t − x̂_t) + n_t), n ~ N(0, S).
The saddle point of the zero-sum game (7)-(9) gives the one-step *predictor*

    Σ_t⁻¹   = P_t⁻¹ + Σ_j C^j′ (R^j⁻¹ − S⁻¹) C^j                          (12), information form
    K*      = A Σ_t C′ R⁻¹                                                   (10)
    x̂_{t+1} = A x̂_t + K* (y_t − C x̂_t)                                      (13)
            = A x̂_t + A Σ_t ( Σ_j C^j′R^j⁻¹ y_t^j − Σ_j C^j′R^j⁻¹C^j x̂_t )  (III-A)
    P_{t+1} = A Σ_t A′ + B Q B′                                              (13)

with C, R the stacked sensor matrices of (4). S⁻¹ is subtracted **once per sensor**
(blockdiag(S, …, S) in the stacked form; PAPER_NOTES 000). S → ∞ (``S=None``, S⁻¹ = 0) is the
Kalman filter (:mod:`agent.estimators.kalman`). The worst-case adversary gain is L* = A Σ C′ S⁻¹ (11).

The game has a saddle point only if Σ_t ≻ 0, i.e. P_t⁻¹ + Ω ≻ 0; :attr:`CentralizedMinimax.admissible`
records whether that held at the last step (nothing is hidden or clipped).

Visibility weights b_j scale each sensor's model, C^j → b_j C^j (the sensor then measures
y^j = b_j C^j x + v^j, :class:`agent.models.LinearSensor`), so a sensor with b_j = 0 contributes
nothing -- neither information nor the S⁻¹ term. This is exactly the per-node χ of (18a) with b.

Two numerically independent implementations are provided (``form=``):

* ``"information"`` -- the Section III-A form above (the one the distributed filter (18) sums);
* ``"covariance"``  -- gains (10)-(12) on the stacked model, with Σ obtained without inverting P by
  the matrix-inversion lemma Σ = P − P C′ (C P C′ + M⁻¹)⁻¹ C P, M = blockdiag(R^j⁻¹ − S⁻¹); needs
  every R^j⁻¹ − S⁻¹ invertible.

The module also exports the pieces the distributed filter reuses: :func:`sensor_information`
(one sensor's χ = [χ¹, χ², χ³] of (18a)) and :func:`information_update` (the update given summed χ).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.linalg import block_diag as _blockdiag

from .riccati import information_posterior, is_positive_definite, sym


def inverse_or_zero(S: np.ndarray | None, dim: int) -> np.ndarray:
    """S⁻¹, or the dim×dim zero matrix for S = None (S → ∞, the Kalman limit)."""
    if S is None:
        return np.zeros((dim, dim))
    return np.linalg.inv(np.atleast_2d(np.asarray(S, dtype=float)))


def sensor_information(C: np.ndarray, R_inv: np.ndarray, S_inv: np.ndarray,
                       y: np.ndarray | None, b: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One sensor's information triple of (18a) with visibility weight b (C → b C):

        χ¹ = b² C′R⁻¹C,   χ² = b C′R⁻¹ y,   χ³ = b² C′(R⁻¹ − S⁻¹)C.

    ``y = None`` (no measurement) gives χ² = 0.
    """
    b = float(b)
    CtRi = C.T @ R_inv
    chi1 = sym(b * b * (CtRi @ C))
    chi2 = np.zeros(C.shape[1]) if y is None else b * (CtRi @ np.asarray(y, dtype=float))
    chi3 = sym(b * b * (C.T @ (R_inv - S_inv) @ C))
    return chi1, chi2, chi3


def information_update(x: np.ndarray, P: np.ndarray, A: np.ndarray, Q: np.ndarray,
                       I1: np.ndarray, i2: np.ndarray, I3: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The update of III-A / (18) given (summed) information I1 = Σχ¹, i2 = Σχ², I3 = Σχ³:

        Σ = (P⁻¹ + I3)⁻¹,  x⁺ = A x + A Σ (i2 − I1 x),  P⁺ = A Σ A′ + Q.

    (The state update uses Σ, not P: the typo of (18), PAPER_NOTES 000.) Returns (x⁺, P⁺, Σ).
    """
    Sigma = information_posterior(P, I3)
    x_next = A @ x + A @ (Sigma @ (i2 - I1 @ x))
    P_next = sym(A @ Sigma @ A.T + Q)
    return x_next, P_next, Sigma


def _per_sensor(value, n: int, name: str) -> list:
    """Broadcast a single matrix (or None) to n sensors, or check a list has length n."""
    if value is None:
        return [None] * n
    try:
        single = np.ndim(value) <= 2          # one matrix (array or nested list) for every sensor
    except ValueError:                        # ragged list of per-sensor matrices
        single = False
    if single:
        return [value] * n
    if len(value) != n:
        raise ValueError(f"{name}: expected {n} entries, got {len(value)}")
    return list(value)


class CentralizedMinimax:
    """Centralized minimax filter (13) for N sensors (one-step predictor form).

    Parameters
    ----------
    A :      state matrix (m×m).
    Q :      the filter's process-noise matrix already in state space (B Q B′, m×m).
    Cs, Rs : per-sensor measurement matrices C^j (p_j×m) and noise covariances R^j (p_j×p_j).
    S :      covariance of the adversary's noise n_t (p×p; or a per-sensor list); ``None`` is
             S → ∞, i.e. the Kalman filter.
    x0, P0 : initial estimate x̂₀ and matrix P₀.
    form :   ``"information"`` (III-A, default) or ``"covariance"`` ((10)-(12), stacked).

    Attributes
    ----------
    x :      x̂_t, the prediction of the state at the current step (from data up to t−1).
    P :      P_t.
    Sigma :  Σ of the last step (None before the first step).
    K :      the stacked gain K* = A Σ C′R⁻¹ of the last step (covariance form only).
    admissible : whether Σ ≻ 0 held at the last step (saddle-point condition).
    """

    def __init__(self, A: np.ndarray, Q: np.ndarray, Cs: Sequence[np.ndarray], Rs: Sequence[np.ndarray],
                 S: np.ndarray | Sequence[np.ndarray] | None, x0: np.ndarray, P0: np.ndarray,
                 form: str = "information"):
        if form not in ("information", "covariance"):
            raise ValueError(f"unknown form {form!r}")
        self.A = np.asarray(A, dtype=float)
        self.Q = np.asarray(Q, dtype=float)
        self.Cs = [np.atleast_2d(np.asarray(C, dtype=float)) for C in Cs]
        n = len(self.Cs)
        self.Rs = [np.atleast_2d(np.asarray(R, dtype=float)) for R in _per_sensor(Rs, n, "Rs")]
        self.R_invs = [np.linalg.inv(R) for R in self.Rs]
        self.S_invs = [inverse_or_zero(Sj, C.shape[0]) for Sj, C in zip(_per_sensor(S, n, "S"), self.Cs)]
        self.form = form
        self._x = np.array(x0, dtype=float)
        self._P = sym(np.array(P0, dtype=float))
        self.Sigma: np.ndarray | None = None
        self.K: np.ndarray | None = None
        self.admissible = True

    @property
    def x(self) -> np.ndarray:
        return self._x

    @property
    def P(self) -> np.ndarray:
        return self._P

    @property
    def n_sensors(self) -> int:
        return len(self.Cs)

    def step(self, ys: Sequence[np.ndarray | None], b: Sequence[float] | None = None) -> np.ndarray:
        """Absorb the measurements y_t^j (one per sensor; ``None`` = missing) and predict x̂_{t+1}."""
        if len(ys) != self.n_sensors:
            raise ValueError(f"expected {self.n_sensors} measurements, got {len(ys)}")
        b = np.ones(self.n_sensors) if b is None else np.asarray(b, dtype=float)
        if self.form == "information":
            self._step_information(ys, b)
        else:
            self._step_covariance(ys, b)
        self.admissible = is_positive_definite(self.Sigma)
        return self._x

    # --- Section III-A ------------------------------------------------------------------------
    def _step_information(self, ys, b) -> None:
        m = self.A.shape[0]
        I1, i2, I3 = np.zeros((m, m)), np.zeros(m), np.zeros((m, m))
        for C, Ri, Si, y, bj in zip(self.Cs, self.R_invs, self.S_invs, ys, b):
            if bj == 0.0 or y is None:
                continue
            c1, c2, c3 = sensor_information(C, Ri, Si, y, bj)
            I1, i2, I3 = I1 + c1, i2 + c2, I3 + c3
        self._x, self._P, self.Sigma = information_update(self._x, self._P, self.A, self.Q, I1, i2, I3)
        self.K = None

    # --- (10)-(12), stacked ---------------------------------------------------------------------
    def _step_covariance(self, ys, b) -> None:
        used = [j for j in range(self.n_sensors) if b[j] != 0.0 and ys[j] is not None]
        A, P, x = self.A, self._P, self._x
        if not used:
            Sigma = P.copy()
            self.K = np.zeros((A.shape[0], 0))
            x_next = A @ x
        else:
            C = np.vstack([b[j] * self.Cs[j] for j in used])
            R_inv = _blockdiag(*[self.R_invs[j] for j in used])
            M_inv = _blockdiag(*[np.linalg.inv(self.R_invs[j] - self.S_invs[j]) for j in used])
            y = np.concatenate([np.asarray(ys[j], dtype=float) for j in used])
            # Σ = (P⁻¹ + C′MC)⁻¹ by the matrix-inversion lemma (no inverse of P)
            PCt = P @ C.T
            Sigma = sym(P - PCt @ np.linalg.solve(C @ PCt + M_inv, PCt.T))
            K = A @ Sigma @ C.T @ R_inv                                     # (10)
            x_next = A @ x + K @ (y - C @ x)                                # (13)
            self.K = K
        self.Sigma = Sigma
        self._x = x_next
        self._P = sym(A @ Sigma @ A.T + self.Q)                             # (13)

    def adversary_gain(self) -> np.ndarray:
        """L* = A Σ C′ S⁻¹ of (11) (stacked over all sensors, b = 1), for the last Σ."""
        if self.Sigma is None:
            raise RuntimeError("no step taken yet")
        C = np.vstack(self.Cs)
        S_inv = _blockdiag(*self.S_invs)
        return self.A @ self.Sigma @ C.T @ S_inv
