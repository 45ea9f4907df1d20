"""Centralized Kalman filter: the S → ∞ case of Gu & Hu's minimax filter (13).

Model: x_{t+1} = A x_t + w̃_t, w̃ ~ N(0, Q) (Q = B Q_w B′ in state space), y_t^j = C^j x_t + v_t^j,
v^j ~ N(0, R^j). With S⁻¹ = 0 the minimax recursion (12)-(13) becomes the information-form Kalman
one-step predictor

    Σ_t⁻¹ = P_t⁻¹ + Σ_j C^j′R^j⁻¹C^j,  x̂_{t+1} = A x̂_t + A Σ_t Σ_j C^j′R^j⁻¹(y^j − C^j x̂_t),
    P_{t+1} = A Σ_t A′ + Q,

which is how Gu & Hu obtain their Kalman baseline ("taking S → ∞", Section IV).

* :class:`CentralizedKalman` -- that filter, a thin subclass of
  :class:`agent.estimators.minimax.CentralizedMinimax` with ``S=None``.
* :class:`KalmanPredictor` -- the textbook covariance-form one-step predictor, written
  independently for cross-checking:

      Λ = C P C′ + R,  K = A P C′ Λ⁻¹,  x̂⁺ = A x̂ + K (y − C x̂),  P⁺ = A P A′ − K Λ K′ + Q.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.linalg import block_diag

from .minimax import CentralizedMinimax
from .riccati import sym


class CentralizedKalman(CentralizedMinimax):
    """Centralized Kalman predictor = :class:`CentralizedMinimax` with S → ∞ (S⁻¹ = 0).

    ``CentralizedKalman(A, Q, Cs, Rs, x0, P0, form="information")``; ``step(ys, b=None)``.
    """

    def __init__(self, A: np.ndarray, Q: np.ndarray, Cs: Sequence[np.ndarray], Rs: Sequence[np.ndarray],
                 x0: np.ndarray, P0: np.ndarray, form: str = "information"):
        super().__init__(A, Q, Cs, Rs, None, x0, P0, form=form)


class KalmanPredictor:
    """Textbook covariance-form Kalman one-step predictor on a stacked measurement y = C x + v.

    Parameters: A (m×m), Q (m×m, state space), C (p×m), R (p×p), x0, P0.
    ``step(y)`` returns x̂_{t+1}; attributes ``x``, ``P``, ``K`` (gain of the last step).
    """

    def __init__(self, A: np.ndarray, Q: np.ndarray, C: np.ndarray, R: np.ndarray,
                 x0: np.ndarray, P0: np.ndarray):
        self.A = np.asarray(A, dtype=float)
        self.Q = np.asarray(Q, dtype=float)
        self.C = np.atleast_2d(np.asarray(C, dtype=float))
        self.R = np.atleast_2d(np.asarray(R, dtype=float))
        self.x = np.array(x0, dtype=float)
        self.P = np.array(P0, dtype=float)
        self.K: np.ndarray | None = None

    @classmethod
    def stacked(cls, A, Q, Cs: Sequence[np.ndarray], Rs: Sequence[np.ndarray], x0, P0) -> "KalmanPredictor":
        """Build from per-sensor C^j, R^j (stacked as in Gu & Hu (4))."""
        return cls(A, Q, np.vstack(Cs), block_diag(*Rs), x0, P0)

    def step(self, y: np.ndarray) -> np.ndarray:
        A, C, P = self.A, self.C, self.P
        Lam = C @ P @ C.T + self.R
        K = A @ P @ C.T @ np.linalg.inv(Lam)
        self.x = A @ self.x + K @ (np.asarray(y, dtype=float) - C @ self.x)
        self.P = sym(A @ P @ A.T - K @ Lam @ K.T + self.Q)
        self.K = K
        return self.x
