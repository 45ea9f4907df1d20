"""The one small interface every distributed estimator implements.

A sensor role hosts any estimator through this interface (DESIGN.md, "tick protocol"):

1. ``start(ctx, y)``          -- the tick begins: the node's measurement ``y`` and the tick's graph facts.
2. for ``r`` in ``range(rounds)``:
   ``payload(r)``              -- what this node sends to its neighbours in exchange round ``r``;
   ``absorb(r, inbox)``        -- the neighbours' round-``r`` payloads that arrived, keyed by sender id
                                  (iterated in ascending id order; a missing neighbour is a dropped link).
3. ``finish()``               -- the update; afterwards :attr:`x` is the estimate for the next tick.

:attr:`x` read *before* ``start`` is the node's estimate of the target state at the current tick
(for the predictor-form filters of the papers, x̂ₖ computed from data up to k-1).

The core never touches a transport: payloads are plain ``dict[str, np.ndarray]``.
"""

from __future__ import annotations

import math

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

Payload = dict[str, np.ndarray]


@dataclass(frozen=True)
class TickContext:
    """Graph facts for one node at one tick, as the world's tick message states them.

    Attributes
    ----------
    k, t:        tick index and time (s).
    n:           number of sensors in the network (N of Gu & Hu's consensus, n of Chen).
    neighbours:  ids of this node's neighbours at tick k, ascending.
    weights:     edge weights g_ij(k) aligned with ``neighbours`` (1.0 for range links).
    b:           target visibility weight b_i(k) (0 = the node does not see the target).
    delta_max:   maximum degree of the tick's graph (every node gets the same value, so the
                 consensus rate eta = 1/(delta_max + 1) is common and the network sum is preserved).
    T:           sample time (s).
    """

    k: int
    t: float
    n: int
    neighbours: tuple[int, ...] = ()
    weights: tuple[float, ...] = ()
    b: float = 1.0
    delta_max: int = 0
    T: float = 1.0
    extra: Mapping[str, float] = field(default_factory=dict)

    def weight_of(self, j: int) -> float:
        return self.weights[self.neighbours.index(j)]


class Estimator(ABC):
    """One node's distributed estimator. Subclasses document their model and cite equations."""

    #: number of exchange rounds per tick (0 = no communication)
    rounds: int = 1

    @abstractmethod
    def start(self, ctx: TickContext, y: np.ndarray) -> None:
        """Begin tick ``ctx.k`` with this node's measurement ``y``."""

    @abstractmethod
    def payload(self, r: int) -> Payload:
        """Payload this node publishes in exchange round ``r``."""

    @abstractmethod
    def absorb(self, r: int, inbox: Mapping[int, Payload]) -> None:
        """Neighbour payloads of round ``r`` that arrived (sender id -> payload)."""

    @abstractmethod
    def finish(self) -> None:
        """Update the estimate; afterwards :attr:`x` is the estimate for tick k+1."""

    def predict_only(self, ctx: TickContext, q: int) -> None:
        """A tick without information (the node's tick or truth lost, or the world marks it dead): the
        estimator's rounds with b = 0, no measurement (``q`` zeros) and no neighbours — its prediction."""
        self.start(ctx, np.zeros(q))
        for r in range(self.rounds):
            self.absorb(r, {})
        self.finish()

    @property
    @abstractmethod
    def x(self) -> np.ndarray:
        """Current state estimate."""

    @property
    def P(self) -> np.ndarray | None:
        """Current error covariance (or Riccati matrix) if the estimator has one."""
        return None

    def report(self) -> dict[str, np.ndarray]:
        """Vectors published beside the estimate (``Estimate.aux``) after :meth:`finish` (default none)."""
        return {}

    def payload_shapes(self) -> dict[str, tuple[int, ...]]:
        """Expected shape of each payload entry (used to drop malformed neighbour payloads)."""
        return {}

    def reinitialise(self, neighbour_estimates: Mapping[int, np.ndarray],
                     neighbour_covariances: Mapping[int, np.ndarray] | None = None) -> None:
        """Re-start from neighbours' estimates (a restarted node rejoining): the mean of their x̂
        (and of their P, where the estimator carries one), instead of the prior x̂₀."""
        if neighbour_estimates:
            xs = [np.asarray(neighbour_estimates[j], float) for j in sorted(neighbour_estimates)]
            self._set_x(np.mean(xs, axis=0))
        Ps = [np.asarray(neighbour_covariances[j], float) for j in sorted(neighbour_covariances or {})]
        Ps = [P for P in Ps if is_covariance(P)]    # (a peer's P that is no covariance is not taken up)
        if Ps:
            self._set_P(np.mean(Ps, axis=0))

    def _set_x(self, x: np.ndarray) -> None:  # pragma: no cover - overridden where supported
        raise NotImplementedError

    def _set_P(self, P: np.ndarray) -> None:  # noqa: B027 - a no-op on purpose: estimators without a covariance ignore it
        """Overwrite the covariance/Riccati matrix (only estimators that have one)."""


def is_covariance(P: np.ndarray) -> bool:
    """A square, finite, symmetric (to rounding) and positive-definite matrix: Cholesky succeeds."""
    if P.ndim != 2 or P.shape[0] != P.shape[1] or not all_finite(P):
        return False
    scale = max(float(np.abs(P).max()), 1e-300)
    if float(np.abs(P - P.T).max()) > 1e-9 * scale:
        return False
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return False
    return True


def all_finite(a: np.ndarray) -> bool:
    """No NaN or inf in ``a``: a finite sum proves it (NaN and inf propagate), and costs a third of
    ``np.isfinite(a).all()``; only a non-finite sum (also what an overflow of huge finite values gives) is
    checked element-wise. (Every neighbour payload of every round passes here.)"""
    return math.isfinite(np.add.reduce(a, axis=None)) or bool(np.isfinite(a).all())


def valid_inbox(inbox: Mapping[int, Payload], shapes: Mapping[str, tuple[int, ...]]) -> dict[int, Payload]:
    """Keep only payloads that carry every expected key with the expected shape and finite values,
    in ascending sender order. A malformed neighbour payload is treated as a dropped link."""
    out: dict[int, Payload] = {}
    for j in sorted(inbox):
        p = inbox[j]
        ok = True
        for key, shape in shapes.items():
            v = p.get(key)
            if not isinstance(v, np.ndarray) or v.shape != tuple(shape) or not all_finite(v):
                ok = False
                break
        if ok:
            out[j] = p
    return out
