"""Target, sensor and plant motion models (pure numpy; Gu & Hu, 2009).

Models
------
* :func:`double_integrator` -- the sampled double integrator (19)::

      z_{t+1} = A z_t + B u_t,   z = [q, q̇],   A = [[I, T I], [0, I]],   B = [[T²/2 I], [T I]]

  used both for the target (state [px, py, vx, vy]) and for each mobile sensor's own motion.
* :class:`LinearTarget` -- the "normal target" (1) with d_t = 0:  x_{t+1} = A x_t + B w_t,
  w_t ~ N(0, Q).
* :class:`IntelligentTarget` -- the "intelligent target" of Section IV:
  x_{t+1} = A x_t + k_e (x_t − x̂_t) [+ B w_t], where x̂_t is the trackers' one-step prediction of
  x_t (the estimate made from data up to t−1). It pushes the state away from where the trackers
  believe it is.
* :class:`LinearSensor` -- the measurement (3) with a visibility weight: y = b C x + v, v ~ N(0, R).
* :func:`integrate_double_integrator` -- (19) applied to positions / velocities arrays of any
  number of agents at once.

Every random draw comes from a caller-supplied ``numpy.random.Generator`` (determinism: DESIGN.md).
"""

from __future__ import annotations

import numpy as np


def double_integrator(T: float, dim: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Matrices (A, B) of the sampled double integrator (19) in ``dim`` dimensions.

    State ordering is [q (dim), q̇ (dim)], so A is 2dim×2dim and B is 2dim×dim:
    A = [[I, T·I], [0, I]],  B = [[T²/2·I], [T·I]]  (exact zero-order hold of q̈ = u).
    """
    eye = np.eye(dim)
    zero = np.zeros((dim, dim))
    A = np.block([[eye, T * eye], [zero, eye]])
    B = np.vstack([0.5 * T * T * eye, T * eye])
    return A, B


def integrate_double_integrator(q: np.ndarray, p: np.ndarray, u: np.ndarray,
                                T: float) -> tuple[np.ndarray, np.ndarray]:
    """One step of (19) for positions ``q``, velocities ``p`` and accelerations ``u``.

    Works element-wise on arrays of equal shape, e.g. (dim,) for one agent or (n, dim) for a flock:
    q⁺ = q + T p + T²/2 u,  p⁺ = p + T u.  Returns new arrays (q⁺, p⁺).
    """
    q = np.asarray(q, dtype=float)
    p = np.asarray(p, dtype=float)
    u = np.asarray(u, dtype=float)
    return q + T * p + 0.5 * T * T * u, p + T * u


class DoubleIntegratorAgent:
    """A mobile sensor's own motion (19): position ``q``, velocity ``p``; ``step(u)`` advances T."""

    def __init__(self, q0: np.ndarray, p0: np.ndarray | None = None, T: float = 1.0):
        self.q = np.array(q0, dtype=float)
        self.p = np.zeros_like(self.q) if p0 is None else np.array(p0, dtype=float)
        self.T = float(T)

    @property
    def z(self) -> np.ndarray:
        """State z = [q, q̇] of (19)."""
        return np.concatenate([self.q, self.p])

    def step(self, u: np.ndarray) -> np.ndarray:
        self.q, self.p = integrate_double_integrator(self.q, self.p, u, self.T)
        return self.z


class LinearTarget:
    """The 'normal target' (1) without adversary: x_{t+1} = A x_t + B w_t, w_t ~ N(0, Q).

    Parameters
    ----------
    A, B : system matrices (m×m, m×p).
    Q :    process-noise covariance of w (p×p), Q ≥ 0 (Gu & Hu use 0.01·I₂).
    x0 :   initial state.
    rng :  numpy Generator used for w.
    """

    def __init__(self, A: np.ndarray, B: np.ndarray, Q: np.ndarray, x0: np.ndarray,
                 rng: np.random.Generator):
        self.A = np.asarray(A, dtype=float)
        self.B = np.asarray(B, dtype=float)
        self.Q = np.asarray(Q, dtype=float)
        self.x = np.array(x0, dtype=float)
        self.rng = rng

    def step(self) -> np.ndarray:
        w = self.rng.multivariate_normal(np.zeros(self.Q.shape[0]), self.Q)
        self.last_w = w  # the disturbance applied (recorded: H∞ ratios need it)
        self.x = self.A @ self.x + self.B @ w
        return self.x.copy()


class IntelligentTarget:
    """The 'intelligent target' of Gu & Hu, Section IV: x_{t+1} = A x_t + k_e (x_t − x̂_t) [+ B w_t].

    ``x_hat`` passed to :meth:`step` is the trackers' one-step prediction of x_t (computed from
    data up to t−1) -- e.g. a centralized filter's x before its update, or the mean of the nodes'
    estimates. The adversary term k_e e_t is the disturbance d_t of (1)-(2) acting on the full state
    error. Gu & Hu use k_e = 0.04 and no noise; the sample time T matters (PAPER_NOTES 000:
    Kalman diverges and minimax stays bounded for T ≈ 0.029–0.046 at k_e = 0.04).

    Parameters
    ----------
    A :    system matrix.
    ke :   adversary gain k_e (scalar or m×m matrix).
    x0 :   initial state.
    B, Q : optional process noise B w, w ~ N(0, Q) (omitted when Q is None).
    rng :  numpy Generator (required only when Q is given).
    """

    def __init__(self, A: np.ndarray, ke: float | np.ndarray, x0: np.ndarray,
                 B: np.ndarray | None = None, Q: np.ndarray | None = None,
                 rng: np.random.Generator | None = None):
        self.A = np.asarray(A, dtype=float)
        self.ke = np.asarray(ke, dtype=float)
        self.x = np.array(x0, dtype=float)
        self.B = None if B is None else np.asarray(B, dtype=float)
        self.Q = None if Q is None else np.asarray(Q, dtype=float)
        if self.Q is not None and (self.B is None or rng is None):
            raise ValueError("IntelligentTarget with noise Q needs B and rng")
        self.rng = rng

    def step(self, x_hat: np.ndarray) -> np.ndarray:
        e = self.x - np.asarray(x_hat, dtype=float)
        push = self.ke * e if self.ke.ndim == 0 else self.ke @ e
        x_next = self.A @ self.x + push
        if self.Q is not None:
            x_next = x_next + self.B @ self.rng.multivariate_normal(np.zeros(self.Q.shape[0]), self.Q)
        self.x = x_next
        return self.x.copy()


class DisturbedSensor:
    """Measurement (2) of Zamani & Ugrinovskii: yᵢ = b·Cᵢ x + Dᵢ vᵢ, vᵢ ~ N(0, v_std² I) held over a tick.

    Keeps the drawn disturbance in :attr:`last_v` (all of its components count in the H∞ ratios (5), (6),
    also those that Dᵢ does not pass)."""

    def __init__(self, C: np.ndarray, D: np.ndarray, v_std: float = 1.0):
        self.C = np.atleast_2d(np.asarray(C, dtype=float))
        self.D = np.atleast_2d(np.asarray(D, dtype=float))
        self.v_std = float(v_std)
        self.last_v: np.ndarray | None = None

    def measure(self, x: np.ndarray, b: float, rng: np.random.Generator) -> np.ndarray:
        v = self.v_std * rng.standard_normal(self.D.shape[1])
        self.last_v = v
        return float(b) * (self.C @ np.asarray(x, dtype=float)) + self.D @ v


class LinearSensor:
    """Measurement (3) with visibility weight b: y = b·C x + v, v ~ N(0, R).

    The noise v is drawn even when b = 0, so the random stream (and hence every later draw) does not
    depend on visibility; a sensor with b = 0 returns pure noise (and its filter weights it by b). The
    drawn v is kept in :attr:`last_v`.
    """

    def __init__(self, C: np.ndarray, R: np.ndarray):
        self.C = np.atleast_2d(np.asarray(C, dtype=float))
        self.R = np.atleast_2d(np.asarray(R, dtype=float))
        self._L = np.linalg.cholesky(self.R)
        self.last_v: np.ndarray | None = None   # the noise of the last measurement

    def measure(self, x: np.ndarray, b: float, rng: np.random.Generator) -> np.ndarray:
        v = self._L @ rng.standard_normal(self.C.shape[0])
        self.last_v = v  # the noise drawn (recorded: the H∞ energy ratios need it)
        return float(b) * (self.C @ np.asarray(x, dtype=float)) + v
