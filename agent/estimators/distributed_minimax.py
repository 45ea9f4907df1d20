"""Distributed minimax filter of Gu & Hu (2009), eqs. (18a)/(18b) and the update of Section III-B.

Each node i runs, at every tick t (b = ctx.b is the visibility weight; the paper has b = 1):

    χ⁰ᵢ = [χ¹, χ², χ³] = [b² C′R⁻¹C,  b C′R⁻¹ yᵢ,  b² C′(R⁻¹ − S⁻¹)C]                 (18a)
    χᵢ ← χᵢ + η Σ_{j∈Nᵢ} (χⱼ − χᵢ)          for R rounds (``rounds``)               (18b)
    Σᵢ⁻¹ = Pᵢ⁻¹ + N χ³ᵢ
    x̂ᵢ ← A x̂ᵢ + A Σᵢ (N χ²ᵢ − N χ¹ᵢ x̂ᵢ)      (Σᵢ, not Pᵢ: the typo of (18), PAPER_NOTES 000)
    Pᵢ ← A Σᵢ A′ + Q                           (Q = B Q_w B′ in state space)

N χᵢ approximates Σⱼ χⱼ (17); the consensus is re-initialised from the local χ every tick, and
η = consensus_rate(δ_max) is the same at every node so the network sum of χ is preserved.
With C, R, S equal at every node (and equal b), χ¹ and χ³ are identical everywhere, so every
node's P and Σ equal the centralized ones (:class:`agent.estimators.minimax.CentralizedMinimax`)
and, when all payloads arrive, **the mean of the node estimates equals the centralized estimate
exactly for any number of rounds** (the update is affine in x̂ᵢ and χ²ᵢ).

``resilient_f`` = f > 0 makes (18b) resilient to Byzantine neighbours: each round, the payloads that are
inconsistent with the node's own are discarded (:class:`agent.estimators.information_gate.InformationGate`),
and W-MSR trims what is left (:func:`agent.estimators.consensus.trimmed_disagreement`). The neighbours a
node discarded in a tick are published beside its estimate (``report()`` → ``aux["suspected"]``).

S → ∞ (``S=None``) gives the distributed Kalman filter (:class:`DistributedKalman`).

Exchange protocol (:class:`agent.estimators.base.Estimator`): ``start(ctx, y)``; for r < rounds:
``payload(r)`` = {"chi1", "chi2", "chi3"}, ``absorb(r, inbox)``; then ``finish()``. Only payloads
from ``ctx.neighbours`` that carry every key with the right shape and finite values are used; a
missing or malformed one counts as a dropped link for that round.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..schema import Matrix, ScenarioError, check_covariance
from .base import Estimator, Payload, TickContext, valid_inbox
from .consensus import consensus_rate, consensus_round
from .information_gate import InformationGate
from .minimax import information_update, inverse_or_zero, sensor_information
from .riccati import sym
from .spec import EstimatorSpec

_KEYS = ("chi1", "chi2", "chi3")


class DistributedMinimax(Estimator):
    """One node of the distributed minimax filter (18).

    Parameters
    ----------
    A :        state matrix (m×m).
    Q :        the filter's process-noise matrix in state space (B Q_w B′, m×m).
    C, R :     this node's measurement matrix (p×m) and noise covariance (p×p).
    S :        adversary noise covariance (p×p); ``None`` = S → ∞ (Kalman).
    n :        number of nodes N (used when the tick context gives none, i.e. ``ctx.n <= 0``).
    x0, P0 :   initial estimate and matrix.
    rounds :   consensus rounds per tick (0 = purely local χ).
    eta_rule : consensus rate rule passed to :func:`agent.estimators.consensus.consensus_rate`.
    resilient_f : W-MSR's f, with the consistency gate (0: plain consensus).
    beta_max :  the largest visibility weight b a sensor can have (the gate's bound on χ¹ = b² C′R⁻¹C).
    """

    def __init__(self, A: np.ndarray, Q: np.ndarray, C: np.ndarray, R: np.ndarray,
                 S: np.ndarray | None, n: int, x0: np.ndarray, P0: np.ndarray, rounds: int,
                 eta_rule: str = "1/(dmax+1)", resilient_f: int = 0, beta_max: float = 1.0):
        self.resilient_f = int(resilient_f)
        self.A = np.asarray(A, dtype=float)
        self.Q = np.asarray(Q, dtype=float)
        self.C = np.atleast_2d(np.asarray(C, dtype=float))
        self.R_inv = np.linalg.inv(np.atleast_2d(np.asarray(R, dtype=float)))
        self.S_inv = inverse_or_zero(S, self.C.shape[0])
        self.n = int(n)
        self.rounds = int(rounds)
        self.eta_rule = eta_rule
        self._x = np.array(x0, dtype=float)
        self._P = sym(np.array(P0, dtype=float))
        self.Sigma: np.ndarray | None = None
        self._ctx: TickContext | None = None
        self._chi: dict[str, np.ndarray] | None = None
        self.dropped = 0  # neighbour payloads missing or malformed (all ticks, all rounds)
        self.gate = (InformationGate(self.C, self.R_inv, self.S_inv, beta_max=max(1.0, beta_max) ** 2)
                     if self.resilient_f > 0 else None)
        self.suspected: set[int] = set()   # neighbours whose payload the gate discarded this tick
        self.suspicions = 0                # payloads the gate discarded (all ticks, all rounds)

    # --- Estimator interface ---------------------------------------------------------------------
    def start(self, ctx: TickContext, y: np.ndarray) -> None:
        c1, c2, c3 = sensor_information(self.C, self.R_inv, self.S_inv, y, ctx.b)   # (18a)
        self._ctx = ctx
        self._chi = {"chi1": c1, "chi2": c2, "chi3": c3}
        self.suspected = set()

    def payload(self, r: int) -> Payload:
        chi = self._require_chi()
        return {k: v.copy() for k, v in chi.items()}

    def absorb(self, r: int, inbox: Mapping[int, Payload]) -> None:
        chi = self._require_chi()
        ctx = self._ctx
        allowed = set(ctx.neighbours)
        from_neighbours = {j: p for j, p in inbox.items() if j in allowed}
        good = valid_inbox(from_neighbours, self.payload_shapes())
        self.dropped += len(allowed) - len(good)
        if self.gate is not None:
            lying = self.gate.suspects(chi, good, self._x, r)
            if lying:
                self.suspected.update(lying)
                self.suspicions += len(lying)
                good = {j: p for j, p in good.items() if j not in lying}
        eta = consensus_rate(ctx.delta_max, self.eta_rule)
        new = consensus_round(chi, good, eta, keys=_KEYS, trim=self.resilient_f)   # (18b), W-MSR if f > 0
        new["chi1"], new["chi3"] = sym(new["chi1"]), sym(new["chi3"])
        self._chi = new

    def finish(self) -> None:
        chi = self._require_chi()
        N = self._ctx.n if self._ctx.n > 0 else self.n
        self._x, self._P, self.Sigma = information_update(
            self._x, self._P, self.A, self.Q, N * chi["chi1"], N * chi["chi2"], N * chi["chi3"])
        self._chi = None
        self._ctx = None

    def report(self) -> dict[str, np.ndarray]:
        """With the gate on: ``suspected``, the neighbours whose payload it discarded in this tick."""
        if self.gate is None:
            return {}
        return {"suspected": np.array(sorted(self.suspected), dtype=float)}

    @property
    def x(self) -> np.ndarray:
        return self._x

    @property
    def P(self) -> np.ndarray:
        return self._P

    @property
    def chi(self) -> dict[str, np.ndarray] | None:
        """The node's current χ (between ``start`` and ``finish``), else None."""
        return self._chi

    def payload_shapes(self) -> dict[str, tuple[int, ...]]:
        m = self.A.shape[0]
        return {"chi1": (m, m), "chi2": (m,), "chi3": (m, m)}

    def _set_P(self, P: np.ndarray) -> None:
        self._P = sym(np.array(P, dtype=float))

    def _set_x(self, x: np.ndarray) -> None:
        x = np.asarray(x, dtype=float)
        if x.shape != self._x.shape:
            raise ValueError(f"state shape {x.shape} != {self._x.shape}")
        self._x = x.copy()

    def _require_chi(self) -> dict[str, np.ndarray]:
        if self._chi is None:
            raise RuntimeError("start(ctx, y) must be called before payload/absorb/finish")
        return self._chi


class DistributedKalman(DistributedMinimax):
    """Distributed Kalman filter: :class:`DistributedMinimax` with S → ∞ (S⁻¹ = 0), Section IV.

    ``DistributedKalman(A, Q, C, R, n, x0, P0, rounds, eta_rule="1/(dmax+1)")``.
    """

    def __init__(self, A: np.ndarray, Q: np.ndarray, C: np.ndarray, R: np.ndarray, n: int,
                 x0: np.ndarray, P0: np.ndarray, rounds: int, eta_rule: str = "1/(dmax+1)",
                 resilient_f: int = 0, beta_max: float = 1.0):
        super().__init__(A, Q, C, R, None, n, x0, P0, rounds, eta_rule, resilient_f, beta_max)


# ----------------------------------------------------------------------------- the runtime's specs

@dataclass(frozen=True)
class MinimaxParams:
    """``[estimator]`` keys of the minimax filter: S, the adversary noise covariance (q × q) of (13)."""

    S: Matrix | None = None


def _check_minimax(sc: Any, p: MinimaxParams) -> None:
    q = sc.C.shape[0]
    if p.S is None:
        raise ScenarioError(sc.source, "estimator.S", "the minimax filter needs S (q × q)",
                            "add S, or use name = \"kalman\" (the S → ∞ case)")
    check_covariance(sc.source, "estimator.S", p.S, q, f"q × q with q = {q}")


def _build_minimax(sc: Any, i: int, p: MinimaxParams, design: Mapping[str, Any]) -> DistributedMinimax:
    e = sc.estimator
    return DistributedMinimax(sc.A, sc.filter_Q(), sc.C, sc.R, np.array(p.S, float), sc.sensors.n,
                              sc.initial_estimates()[i], sc.initial_covariance(), e.rounds, e.eta, e.resilient_f,
                              _beta_max(sc))


def _build_kalman(sc: Any, i: int, p: Any, design: Mapping[str, Any]) -> DistributedKalman:
    e = sc.estimator
    return DistributedKalman(sc.A, sc.filter_Q(), sc.C, sc.R, sc.sensors.n, sc.initial_estimates()[i],
                             sc.initial_covariance(), e.rounds, e.eta, e.resilient_f, _beta_max(sc))


def _beta_max(sc: Any) -> float:
    """The largest visibility weight of the run: the sensors' β, or a scheduled graph's b."""
    bs = [b for g in sc.topology.graphs for b in g.b]
    return max([1.0, float(sc.sensors.beta), *map(float, bs)])


MINIMAX = EstimatorSpec(
    name="minimax", params=MinimaxParams, check=_check_minimax, build=_build_minimax, default=True,
    doc="Gu & Hu's distributed minimax filter (18a)/(18b)")

KALMAN = EstimatorSpec(
    name="kalman", build=_build_kalman,
    doc="the distributed Kalman filter: the minimax filter with S → ∞ (Gu & Hu, Section IV)")
