"""Zamani & Ugrinovskii's distributed H∞ minimum-energy filter, one node (Riccati (20), filter (21)).

The offline design (the SDP (29)) lives in :mod:`agent.estimators.min_energy_design` and is
re-exported here. This module holds the run-time node :class:`MinEnergyNode` and the run-time checks
of (5) and (6) (:func:`performance_report`).

The node (continuous time, paper Section III)
---------------------------------------------
With the design quantities of node i — γ̄ᵢ², τᵢⱼ, Υᵢⱼ = Ūᵢⱼ⁻¹ (so Z̄ᵢⱼ never enters the filter),
Ȳᵢ — and Rᵢ = (γ/γ̄ᵢ)² I (Theorem 2), so γ⁻²Rᵢ = γ̄ᵢ⁻² I and γ enters only through the design:

    Q̇ᵢ = AQᵢ + QᵢAᵀ − Qᵢ Mᵢ Qᵢ + Sᵢ,   Qᵢ(0) = 𝒳ᵢ⁻¹                                       (20)
    Mᵢ = Hᵢ − (γ̄ᵢ⁻² + Σⱼτᵢⱼ) I,   Hᵢ = CᵢᵀEᵢ⁻¹Cᵢ + Σⱼ WᵢⱼᵀΥᵢⱼWᵢⱼ,   Sᵢ = (1 − Σⱼτᵢⱼ)⁻¹BBᵀ
    x̂̇ᵢ = Ax̂ᵢ + Qᵢ (CᵢᵀEᵢ⁻¹(yᵢ − Cᵢx̂ᵢ) + Σⱼ WᵢⱼᵀΥᵢⱼ(cᵢⱼ − Wᵢⱼx̂ᵢ)),   x̂ᵢ(0) = ξᵢ           (21)

Initial weight: 𝒳ᵢ = Ȳᵢ by default. (26) says Ȳᵢ is a strict sub-solution of the information form
of (20), so by the comparison theorem Qᵢ(t) ⪯ Ȳᵢ⁻¹ for all t whenever 𝒳ᵢ ⪰ Ȳᵢ (PAPER_NOTES 001:
𝒳ᵢ = I lets some Riccati solutions blow up). A larger 𝒳ᵢ also works but loosens the bounds (5),
(6), whose right-hand sides contain ‖x(0) − ξᵢ‖²_𝒳ᵢ.

Integration inside a tick (why not plain RK4)
---------------------------------------------
The design's measurement noise is small (Dᵢ = 0.025 → Eᵢ⁻¹ = 1600), so Hᵢ is ~1e4 in the measured
directions and QᵢHᵢ can be very stiff: at the SDP's optimal point Qᵢ reaches ~5e5 and
|λ(QᵢHᵢ)| ~ 2e6 s⁻¹ (explicit RK4 would need substeps below 1e-6 s). A well-centred design is
benign (|λ| ≤ ~170 s⁻¹ even at t = 0), but the integrator must not depend on that. The default
``method="expm"`` is stiff-safe, and exact where it can be:

* (20) has constant coefficients, so it is propagated **exactly** through its Hamiltonian:
  with Q = Z X⁻¹, d/dt [X; Z] = [[−Aᵀ, M], [S, A]] [X; Z], hence
  Q(t+τ) = (Φ₂₁ + Φ₂₂Q)(Φ₁₁ + Φ₁₂Q)⁻¹ with Φ = exp(τ·Ham) — precomputed once for the 2J
  half-substep offsets of a tick, applied to the tick's initial Q in one batched solve.
* (21) is linear in x̂ with held data; on each of the J substeps it is solved exactly for Q frozen at
  the substep's midpoint (exponential midpoint rule: 2nd order in the substep, A-stable, no step
  limit from stiffness), all J (2n)×(2n) exponentials of a tick in one batched call
  (:func:`expm_batched`). Once Q has converged to round-off the whole tick is one cached affine map.

``method="rk4"`` (classic RK4 on (Q, x̂), ``substeps`` steps per tick) is kept as a reference for
tests; it is only stable when the substep is well below 1/|λ(QH)|.

Sample and hold (documented approximation)
------------------------------------------
The runtime is discrete: node i gets yᵢ(tₖ) at the start of tick k and the neighbours' x̂ⱼ(tₖ) once
per tick. Both are **held constant over the tick** [tₖ, tₖ + T). What they are compared against is
set by ``hold``:

* ``hold="model"`` (default): the held samples are compared with the node's estimate pulled back to
  the sample instant, zᵢ(s) = e^{−As} x̂ᵢ(tₖ + s):  innovations yᵢ(tₖ) − Cᵢzᵢ(s) and
  cᵢⱼ(tₖ) − Wᵢⱼzᵢ(s). With w = 0 the plant obeys x(tₖ) = e^{−As}x(tₖ + s), so the innovations are
  exact functions of the errors and the error dynamics do not depend on x. This matters: the Chua
  plant is **unstable** (eigenvalues 0.23 ± 3.19j), and with a plain hold the hold error
  Cᵢ(x(tₖ) − x(t)) ≈ −CᵢAx·s grows with x — the estimation error then grows like T‖x(t)‖ and P1
  fails (tests/unit/test_min_energy.py shows both). In z the filter reads ż = e^{−As}Q(h − Hz),
  x̂(tₖ + T) = e^{AT}z(T).
* ``hold="zoh"``: plain (21) with yᵢ and cᵢⱼ held constant. Correct as T → 0; biased on an
  unstable plant.

Both tend to (21) as T → 0. The guarantees (5), (6) are for the continuous filter; the run-time
checks measure how the sampled implementation does.

Exchange (one round per tick)
-----------------------------
``payload(0) = {"x": x̂ᵢ(tₖ)}``. ``absorb(0, inbox)`` takes, from every design in-neighbour
j ∈ Nᵢ that arrived (well-formed, ``valid_inbox``), cᵢⱼ = Wᵢⱼx̂ⱼ + Fᵢⱼεᵢⱼ with channel noise
εᵢⱼ ~ N(0, σ²I) drawn in ``start`` for every j ∈ Nᵢ every tick (so the node's random stream does not
depend on which links dropped). **A neighbour that did not arrive**: its last received x̂ⱼ is held —
under ``hold="model"`` propagated by the model to the current tick, e^{A(tₖ − tₖ′)}x̂ⱼ(tₖ′) — and
counted in ``counters["held"]``; a neighbour never heard from so far contributes nothing that tick
(its terms leave Hᵢ and the innovation; ``counters["missing"]``). The Riccati equation (20) is
data-independent and always uses the design's full Nᵢ. Senders outside the design's Nᵢ are ignored
(they have no Υᵢⱼ). Realised εᵢⱼ are exposed in :attr:`MinEnergyNode.last_channel_noise` for the
run-time checks.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import scipy.linalg

from agent.estimators.base import Estimator, Payload, TickContext, valid_inbox
from agent.estimators.min_energy_design import (
    DesignError, MinEnergyDesign, NetworkProblem, NodeDesign, check_design, check_point, consensus_weight,
    design_network, make_problem, node_ranges, solve_supremum, table_row,
)
from agent.estimators.riccati import sym
from agent.estimators.spec import EstimatorSpec, GraphFacts, RunTrace
from agent.schema import Matrices, Matrix, Pairs, ScenarioError
from agent.seeding import rng_for

__all__ = [
    "MinEnergyNode", "riccati_hamiltonian", "riccati_step", "expm_batched", "l2_energy", "iqc_offset",
    "performance_report",
    "DesignError", "MinEnergyDesign", "NetworkProblem", "NodeDesign", "check_design", "check_point",
    "consensus_weight", "design_network", "make_problem", "node_ranges", "solve_supremum", "table_row",
]


def _mat(M: Any, name: str) -> np.ndarray:
    a = np.asarray(M, dtype=float)
    if a.ndim == 1:
        a = a.reshape(1, -1)
    if a.ndim != 2 or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a finite matrix, got shape {a.shape}")
    return a


def riccati_hamiltonian(A: np.ndarray, M: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Ham = [[−Aᵀ, M], [S, A]] of Q̇ = AQ + QAᵀ − QMQ + S (Q = Z X⁻¹, d/dt[X; Z] = Ham [X; Z])."""
    return np.block([[-A.T, M], [S, A]])


def riccati_step(Q: np.ndarray, Phi: np.ndarray) -> np.ndarray:
    """Exact Riccati propagation Q ↦ (Φ₂₁ + Φ₂₂Q)(Φ₁₁ + Φ₁₂Q)⁻¹ for Φ = exp(h·Ham)."""
    n = Q.shape[0]
    X = Phi[:n, :n] + Phi[:n, n:] @ Q
    Z = Phi[n:, :n] + Phi[n:, n:] @ Q
    return sym(np.linalg.solve(X.T, Z.T).T)


def expm_batched(M: np.ndarray, order: int = 13, target: float = 0.5) -> np.ndarray:
    """exp of a stack of small matrices (…, k, k) by scaling and squaring a degree-``order`` Taylor
    polynomial (1-norm scaled to ≤ ``target``: truncation ≤ 0.5¹⁴/14! ≈ 7e-16 relative).

    Only matrix products — no LAPACK calls: for the 6×6 matrices of one tick it is ~5× faster than
    ``scipy.linalg.expm`` and, unlike it, does not slow down by 10–100× on a loaded machine
    (scipy's Padé solve goes through multi-threaded OpenBLAS even for tiny matrices).
    """
    M = np.asarray(M, dtype=float)
    nrm = float(np.max(np.sum(np.abs(M), axis=-2))) if M.size else 0.0
    sq = int(np.ceil(np.log2(nrm / target))) if nrm > target else 0
    X = M / (2.0 ** sq)
    eye = np.broadcast_to(np.eye(M.shape[-1]), M.shape)
    E = eye + X / order
    for k in range(order - 1, 0, -1):
        E = eye + (X @ E) / k
    for _ in range(sq):
        E = E @ E
    return E


class MinEnergyNode(Estimator):
    """Node i of the distributed H∞ minimum-energy filter (20)–(21), behind :class:`Estimator`.

    Parameters
    ----------
    A (n×n), B (n×m): plant (1).  C (pᵢ×n), D (pᵢ×mᵢ): this node's measurement (2).
    W, F: {j: Wᵢⱼ}, {j: Fᵢⱼ} for every in-neighbour j ∈ Nᵢ of the design.
    node: this node's :class:`NodeDesign` (γ̄ᵢ², τᵢⱼ, Υᵢⱼ, Ȳᵢ) — ``design.node(i)``.
    x0: ξᵢ = x̂ᵢ(0).
    substeps: integration substeps per tick (≥ 1).
    rng: seeded generator for the channel noise εᵢⱼ (required when ``channel_noise_std`` > 0).
    channel_noise_std: σ of εᵢⱼ ~ N(0, σ²I) in cᵢⱼ = Wᵢⱼx̂ⱼ + Fᵢⱼεᵢⱼ (0: none).
    X0: initial weight 𝒳ᵢ (default Ȳᵢ; Q(0) = 𝒳ᵢ⁻¹).
    method: ``"expm"`` (default; stiff-safe) or ``"rk4"`` (reference). hold: ``"model"`` or ``"zoh"``
    (module docstring). record_substeps: keep x̂ at every substep of the last tick in
    :attr:`substep_x` (for accurate error integrals in tests).
    """

    rounds = 1

    def __init__(self, A, B, C, D, W: Mapping[int, Any], F: Mapping[int, Any], node: NodeDesign, x0,
                 substeps: int = 10, rng: np.random.Generator | None = None, channel_noise_std: float = 0.0,
                 X0=None, method: str = "expm", hold: str = "model", record_substeps: bool = False) -> None:
        self._A = _mat(A, "A")
        n = self._A.shape[0]
        if self._A.shape != (n, n):
            raise ValueError(f"A must be square, got {self._A.shape}")
        self._B = _mat(B, "B")
        if self._B.shape[0] != n:
            raise ValueError(f"B must have {n} rows, got {self._B.shape}")
        self._C, self._D = _mat(C, "C"), _mat(D, "D")
        if self._C.shape[1] != n or self._D.shape[0] != self._C.shape[0]:
            raise ValueError(f"C must be p×{n} and D p×m, got {self._C.shape} and {self._D.shape}")
        if method not in ("expm", "rk4"):
            raise ValueError(f"method must be 'expm' or 'rk4', got {method!r}")
        if hold not in ("model", "zoh"):
            raise ValueError(f"hold must be 'model' or 'zoh', got {hold!r}")
        if int(substeps) < 1:
            raise ValueError("substeps must be ≥ 1")
        self.i = node.i
        self.method, self.hold, self.substeps = method, hold, int(substeps)
        self._n, self._p = n, self._C.shape[0]
        self._nbrs = tuple(sorted(node.tau))
        self._W = {j: _mat(W[j], f"W[{j}]") for j in self._nbrs}
        self._F = {j: _mat(F[j], f"F[{j}]") for j in self._nbrs}
        self._Ups = {j: sym(_mat(node.Upsilon[j], f"Upsilon[{j}]")) for j in self._nbrs}
        for j in self._nbrs:
            if self._W[j].shape[1] != n or self._Ups[j].shape != (self._W[j].shape[0],) * 2:
                raise ValueError(f"W[{j}] must be p×{n} with Upsilon[{j}] p×p")
        self.node = node
        Einv = np.linalg.inv(sym(self._D @ self._D.T))
        self._CtEinv = self._C.T @ Einv                                 # CᵢᵀEᵢ⁻¹
        self._H_meas = sym(self._CtEinv @ self._C)
        self._WtU = {j: self._W[j].T @ self._Ups[j] for j in self._nbrs}  # WᵢⱼᵀΥᵢⱼ
        self._WUW = {j: sym(self._WtU[j] @ self._W[j]) for j in self._nbrs}
        tsum = node.tau_sum
        if not 0 <= tsum < 1:
            raise ValueError(f"Σⱼτᵢⱼ = {tsum} violates (16) (must be < 1)")
        self._H_design = self._H_meas + sum(self._WUW.values(), np.zeros((n, n)))
        self._M = self._H_design - (1.0 / node.gammabar2 + tsum) * np.eye(n)
        self._S = (self._B @ self._B.T) / (1.0 - tsum)
        self._Ham = riccati_hamiltonian(self._A, self._M, self._S)
        X0 = node.Y if X0 is None else X0
        self.X0 = sym(_mat(X0, "X0"))
        self._Q = sym(np.linalg.inv(self.X0))
        self._x = np.asarray(x0, dtype=float).reshape(-1).copy()
        if self._x.shape != (n,):
            raise ValueError(f"x0 must have {n} entries")
        self._sigma = float(channel_noise_std)
        if self._sigma < 0:
            raise ValueError("channel_noise_std must be ≥ 0")
        if self._sigma > 0 and rng is None:
            raise ValueError("channel noise needs a seeded rng (np.random.Generator)")
        self._rng = rng
        self.record_substeps = bool(record_substeps)
        self.substep_x: np.ndarray | None = None
        self.counters: Counter = Counter()
        self.last_channel_noise: dict[int, np.ndarray] = {}
        self._last_x: dict[int, np.ndarray] = {}
        self._last_t: dict[int, float] = {}
        self._ctx: TickContext | None = None
        self._y = np.zeros(self._p)
        self._c: dict[int, np.ndarray] = {}
        self._t = 0.0
        self._cache: dict[Any, Any] = {}
        self._Q_converged = False

    @classmethod
    def from_design(cls, design: MinEnergyDesign, i: int, x0, **kw: Any) -> "MinEnergyNode":
        """Node i with the matrices stored in ``design.problem`` (kw: substeps, rng, …)."""
        pr = design.problem
        nd = design.node(i)
        W = {j: pr.W[(i, j)] for j in nd.tau}
        F = {j: pr.F[(i, j)] for j in nd.tau}
        return cls(pr.A, pr.B, pr.C[i], pr.D[i], W, F, nd, x0, **kw)

    # ------------------------------------------------------------------ Estimator interface
    def start(self, ctx: TickContext, y: np.ndarray) -> None:
        y = np.asarray(y, dtype=float).reshape(-1)
        if y.shape != (self._p,):
            raise ValueError(f"y must have {self._p} entries, got {y.shape}")
        self._ctx = ctx
        self._y = y.copy()
        self._t = float(ctx.t)
        eps = {}
        for j in self._nbrs:
            m = self._F[j].shape[1]
            eps[j] = self._sigma * self._rng.standard_normal(m) if self._sigma > 0 else np.zeros(m)
        self.last_channel_noise = eps
        self._c = {}

    def payload(self, r: int) -> Payload:
        if r != 0:
            raise ValueError(f"MinEnergyNode has one exchange round, got r = {r}")
        return {"x": self._x.copy()}

    def absorb(self, r: int, inbox: Mapping[int, Payload]) -> None:
        if r != 0:
            raise ValueError(f"MinEnergyNode has one exchange round, got r = {r}")
        if self._ctx is None:
            raise RuntimeError("absorb() before start()")
        good = valid_inbox(inbox, self.payload_shapes())
        t = self._t
        for j in self._nbrs:
            if j in good:
                xj = np.asarray(good[j]["x"], dtype=float).copy()
                self._last_x[j], self._last_t[j] = xj, t
            elif j in self._last_x:
                self.counters["held"] += 1
                xj = self._last_x[j]
                age = t - self._last_t[j]
                if self.hold == "model" and age > 0:
                    key = ("age", round(age, 12))
                    if key not in self._cache:
                        self._cache[key] = scipy.linalg.expm(self._A * age)
                    xj = self._cache[key] @ xj
            else:
                self.counters["missing"] += 1
                continue
            self._c[j] = self._W[j] @ xj + self._F[j] @ self.last_channel_noise[j]

    def finish(self) -> None:
        if self._ctx is None:
            raise RuntimeError("finish() before start()")
        T = float(self._ctx.T)
        present = tuple(j for j in self._nbrs if j in self._c)
        H = self._H_meas + sum((self._WUW[j] for j in present), np.zeros((self._n, self._n)))
        hv = self._CtEinv @ self._y + sum((self._WtU[j] @ self._c[j] for j in present), np.zeros(self._n))
        if self.method == "expm":
            self._tick_expm(T, H, hv, present)
        else:
            self._tick_rk4(T, H, hv)
        self._ctx = None

    @property
    def x(self) -> np.ndarray:
        return self._x.copy()

    @property
    def P(self) -> np.ndarray:
        """The Riccati matrix Qᵢ of (20) at the current time."""
        return self._Q.copy()

    @property
    def Q(self) -> np.ndarray:
        return self._Q.copy()

    @property
    def H(self) -> np.ndarray:
        """Hᵢ = CᵢᵀEᵢ⁻¹Cᵢ + Σ_{j∈Nᵢ} WᵢⱼᵀΥᵢⱼWᵢⱼ (all design neighbours): QᵢHᵢ sets the filter's speed."""
        return self._H_design.copy()

    @property
    def riccati_converged(self) -> bool:
        """True once Qᵢ stopped changing (to round-off) over a tick; ticks are then one cached map."""
        return self._Q_converged

    @property
    def neighbours(self) -> tuple[int, ...]:
        """The design's in-neighbours Nᵢ."""
        return self._nbrs

    def payload_shapes(self) -> dict[str, tuple[int, ...]]:
        return {"x": (self._n,)}

    def _set_x(self, x: np.ndarray) -> None:
        x = np.asarray(x, dtype=float).reshape(-1)
        if x.shape != (self._n,):
            raise ValueError(f"x must have {self._n} entries")
        self._x = x.copy()

    # ------------------------------------------------------------------ integration
    def _riccati_table(self, T: float, J: int) -> tuple[np.ndarray, int]:
        """Stacked Φ(m·h/2) = exp(m·h/2·Ham), m = 1 … 2J, for one tick (h = T/J), and the number of
        sequential chunks: Davison–Maki from the tick start is used only while exp(ρT) (ρ the
        spectral abscissa of Ham) stays moderate; otherwise the tick is split into substeps."""
        key = ("ric", T, J)
        if key not in self._cache:
            rho = float(np.max(np.abs(np.linalg.eigvals(self._Ham).real)))
            chunks = 1 if rho * T <= 5.0 else J
            per = 2 * J // chunks
            hh = 0.5 * T / J
            Phis = np.stack([scipy.linalg.expm(self._Ham * (m * hh)) for m in range(1, per + 1)])
            self._cache[key] = (Phis, chunks)
        return self._cache[key]

    def _riccati_traj(self, Q0: np.ndarray, T: float, J: int) -> np.ndarray:
        """Q at s = m·h/2, m = 0 … 2J (exact Riccati propagation, batched)."""
        Phis, chunks = self._riccati_table(T, J)
        n = self._n
        out = [Q0[None]]
        Q = Q0
        for _ in range(chunks):
            X = Phis[:, :n, :n] + Phis[:, :n, n:] @ Q
            Z = Phis[:, n:, :n] + Phis[:, n:, n:] @ Q
            Qs = np.linalg.solve(np.swapaxes(X, 1, 2), np.swapaxes(Z, 1, 2))   # (Z X⁻¹)ᵀ
            Qs = 0.5 * (Qs + np.swapaxes(Qs, 1, 2))
            out.append(Qs)
            Q = Qs[-1]
        return np.concatenate(out)

    def _tick_geometry(self, T: float, J: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """e^{−A s} at the substep midpoints (J, n, n), e^{A s} at the substep ends (J, n, n), e^{AT}."""
        key = ("geo", T, J)
        if key not in self._cache:
            h = T / J
            mids = np.stack([scipy.linalg.expm(-self._A * ((j + 0.5) * h)) for j in range(J)])
            ends = np.stack([scipy.linalg.expm(self._A * ((j + 1) * h)) for j in range(J)])
            self._cache[key] = (mids, ends, ends[-1])
        return self._cache[key]

    def _tick_expm(self, T: float, H: np.ndarray, hv: np.ndarray, present: tuple[int, ...]) -> None:
        J = self.substeps
        h = T / J
        n = self._n
        model = self.hold == "model"
        key = ("tick", T, J, present)
        if self._Q_converged and key in self._cache and not self.record_substeps:
            Psi, Lam = self._cache[key]
            self._x = Psi @ self._x + Lam @ hv
            return
        Q0 = self._Q
        Qs = self._riccati_traj(Q0, T, J)
        Qm = Qs[1::2]                                          # midpoints, (J, n, n)
        mids, ends, eAT = self._tick_geometry(T, J)
        if model:                                              # u = z: F = −e^{−As}QH, K = e^{−As}Q
            K = mids @ Qm
            Fm = -(K @ H)
        else:                                                  # u = x̂: F = A − QH, K = Q
            K = Qm
            Fm = self._A[None] - Qm @ H
        aug = np.zeros((J, 2 * n, 2 * n))
        aug[:, :n, :n] = Fm * h
        aug[:, :n, n:] = K * h
        E = expm_batched(aug)                                  # all substeps of the tick at once
        Phi_j, Gam_j = E[:, :n, :n], E[:, :n, n:]
        u = self._x.copy()                                     # z(0) = x̂(tₖ) for both holds
        rec = [self._x.copy()] if self.record_substeps else None
        for j in range(J):
            u = Phi_j[j] @ u + Gam_j[j] @ hv
            if rec is not None:
                rec.append(ends[j] @ u if model else u.copy())
        self._x = eAT @ u if model else u
        if rec is not None:
            self.substep_x = np.array(rec)
        Q = Qs[-1]
        if not np.all(np.isfinite(Q)):
            raise FloatingPointError("Riccati (20) solution is not finite (is the design feasible?)")
        if np.max(np.abs(Q - Q0)) <= 1e-13 * max(1.0, float(np.max(np.abs(Q)))):
            self._Q_converged = True
            Ptot, Gtot = np.eye(n), np.zeros((n, n))
            for j in range(J):
                Ptot, Gtot = Phi_j[j] @ Ptot, Phi_j[j] @ Gtot + Gam_j[j]
            self._cache[key] = (eAT @ Ptot, eAT @ Gtot) if model else (Ptot, Gtot)
        self._Q = Q

    def _tick_rk4(self, T: float, H: np.ndarray, hv: np.ndarray) -> None:
        J = self.substeps
        h = T / J
        A, M, S = self._A, self._M, self._S
        model = self.hold == "model"
        key = ("rk4pull", T, J)
        if model and key not in self._cache:
            self._cache[key] = [scipy.linalg.expm(-A * (k * h / 2)) for k in range(2 * J + 1)]
        pulls = self._cache.get(key)

        def f(Q: np.ndarray, u: np.ndarray, k2: int) -> tuple[np.ndarray, np.ndarray]:
            dQ = A @ Q + Q @ A.T - Q @ M @ Q + S
            if model:
                du = pulls[k2] @ Q @ (hv - H @ u)
            else:
                du = A @ u + Q @ (hv - H @ u)
            return dQ, du

        _, ends, eAT = self._tick_geometry(T, J)
        Q, u = self._Q, self._x.copy()
        rec = [self._x.copy()] if self.record_substeps else None
        for j in range(J):
            k1 = f(Q, u, 2 * j)
            k2 = f(Q + 0.5 * h * k1[0], u + 0.5 * h * k1[1], 2 * j + 1)
            k3 = f(Q + 0.5 * h * k2[0], u + 0.5 * h * k2[1], 2 * j + 1)
            k4 = f(Q + h * k3[0], u + h * k3[1], 2 * j + 2)
            Q = sym(Q + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]))
            u = u + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
            if rec is not None:
                rec.append(ends[j] @ u if model else u.copy())
        self._x = eAT @ u if model else u
        if rec is not None:
            self.substep_x = np.array(rec)
        self._Q = Q


# ------------------------------------------------------------------------------ run-time checks

def l2_energy(signal: np.ndarray, dt: float, kind: str = "hold", weight: np.ndarray | None = None) -> np.ndarray:
    """Cumulative ∫‖s‖²_weight dt of a sampled signal, one value per grid point (starts at 0).

    ``kind="hold"``: ``signal`` (K, d) is piecewise constant on K intervals (disturbances held over a
    tick) — exact. ``kind="trapz"``: ``signal`` (K+1, d) samples a continuous signal (errors) —
    trapezoid rule. Returns an array of K+1 cumulative values.
    """
    s = np.asarray(signal, dtype=float)
    s = s.reshape(s.shape[0], -1)
    q = np.einsum("ki,ij,kj->k", s, weight, s) if weight is not None else np.einsum("ki,ki->k", s, s)
    if kind == "hold":
        inc = q * dt
    elif kind == "trapz":
        inc = 0.5 * (q[1:] + q[:-1]) * dt
    else:
        raise ValueError(f"kind must be 'hold' or 'trapz', got {kind!r}")
    return np.concatenate([[0.0], np.cumsum(inc)])


def iqc_offset(e_i: np.ndarray, e_j: np.ndarray, w: np.ndarray, Zbar: np.ndarray, W: np.ndarray,
               dt: float) -> float:
    """Smallest dᵢⱼ ≥ 0 for which the run satisfies the IQC of Section II-B,
    ∫₀ᵗ‖ηᵢⱼ‖²_{Z̄ᵢⱼ⁻¹} ≤ ∫₀ᵗ(‖eᵢ‖² + ‖w‖²) + dᵢⱼ for every t, with ηᵢⱼ = −Wᵢⱼeⱼ.
    ``e_i``, ``e_j``: (K+1, n) error samples; ``w``: (K, m) held disturbance."""
    eta = -np.asarray(e_j, float) @ np.asarray(W, float).T
    lhs = l2_energy(eta, dt, "trapz", np.linalg.inv(sym(np.asarray(Zbar, float))))
    rhs = l2_energy(e_i, dt, "trapz") + l2_energy(w, dt, "hold")
    return float(max(0.0, np.max(lhs - rhs)))


def _ratio(lhs: float, rhs: float) -> float:
    """lhs/rhs; NaN when nothing disturbed the run (rhs = 0): the ratio is then undefined."""
    return lhs / rhs if rhs > 0 else float("nan")


def performance_report(design: MinEnergyDesign, errors: np.ndarray, x0_errors: np.ndarray, w: np.ndarray,
                       v: Sequence[np.ndarray], eps: Mapping[tuple[int, int], np.ndarray], dt: float,
                       X0: Sequence[np.ndarray] | None = None) -> dict:
    """Measured H∞ ratios of a run, beside the designed bounds.

    Inputs on one uniform grid of K intervals of length ``dt`` (a tick, or a substep):
    ``errors`` (K+1, N, n): eᵢ = x̂ᵢ − x at the grid points; ``x0_errors`` (N, n): x(0) − ξᵢ;
    ``w`` (K, m), ``v[i]`` (K, mᵢ), ``eps[(i, j)]`` (K, mᵢⱼ): the disturbances, held on each interval
    (a missing edge counts as zero channel noise). ``X0[i]``: 𝒳ᵢ (default Ȳᵢ, as the filter).

    Returns {"network": {"lhs": ∫‖e‖²_P, "rhs": bracket of (5), "ratio", "bound": γ²},
    "nodes": [{"lhs": ∫‖eᵢ‖², "rhs": bracket of (6) with βᵢ = 0, "ratio",
    "d": {j: dᵢⱼ (iqc_offset)}, "beta": Σⱼτᵢⱼdᵢⱼ, "ratio_beta": lhs/(βᵢ + rhs), "iqc_holds": all dᵢⱼ = 0,
    "bound": γ̄ᵢ²}]}. P3 claims ``ratio_beta`` ≤ γ̄ᵢ² (it presumes the IQC, with the measured dᵢⱼ);
    ``ratio`` ≤ γ̄ᵢ² is the stronger statement with βᵢ = 0. P2 claims network ratio ≤ γ². A ratio
    is NaN when its right-hand side is 0 (no initial error, no disturbance: nothing to bound).
    Integrals of the errors use the trapezoid rule on the given grid: sample finely enough (the
    filter's fast initial transient lasts milliseconds).
    """
    pr = design.problem
    N, n = pr.N, pr.n
    E = np.asarray(errors, dtype=float)
    K = E.shape[0] - 1
    if E.shape != (K + 1, N, n):
        raise ValueError(f"errors must be (K+1, {N}, {n}), got {E.shape}")
    w = np.asarray(w, dtype=float).reshape(K, -1)
    X0 = design.Y if X0 is None else X0
    x0e = np.asarray(x0_errors, dtype=float).reshape(N, n)
    Ew = float(l2_energy(w, dt)[-1])
    Ev = [float(l2_energy(np.asarray(v[i], float).reshape(K, -1), dt)[-1]) for i in range(N)]
    Eeps = {e: (float(l2_energy(np.asarray(eps[e], float).reshape(K, -1), dt)[-1]) if e in eps else 0.0)
            for e in pr.edges}
    init = [float(x0e[i] @ np.asarray(X0[i], float) @ x0e[i]) for i in range(N)]
    nodes = []
    for i in range(N):
        nb = pr.nbrs[i]
        lhs = float(l2_energy(E[:, i, :], dt, "trapz")[-1])
        rhs = init[i] + Ew + Ev[i] + sum(Eeps[(i, j)] for j in nb)
        d = {j: iqc_offset(E[:, i, :], E[:, j, :], w, design.Zbar[i][j], pr.W[(i, j)], dt) for j in nb}
        beta = float(sum(design.tau[i][j] * d[j] for j in nb))
        nodes.append({"lhs": lhs, "rhs": rhs, "ratio": _ratio(lhs, rhs),
                      "d": d, "beta": beta, "ratio_beta": _ratio(lhs, beta + rhs),
                      "iqc_holds": all(v_ == 0.0 for v_ in d.values()), "bound": design.gammabar2[i]})
    stacked = E.reshape(K + 1, N * n)
    lhs_net = float(l2_energy(stacked, dt, "trapz", pr.P)[-1])
    rhs_net = sum(init) + N * Ew + sum(Ev) + sum(Eeps.values())
    network = {"lhs": lhs_net, "rhs": rhs_net, "ratio": _ratio(lhs_net, rhs_net),
               "bound": design.gamma2}
    return {"network": network, "nodes": nodes}


# ----------------------------------------------------------------------------- the runtime's spec

@dataclass(frozen=True)
class MinEnergyParams:
    """``[estimator]`` keys of Zamani & Ugrinovskii's filters: the directed design edges [i, j] (node i
    receives from node j) with their W, F (one matrix, or one per edge), the SDP (29) options (P, zbar_min,
    margin, gamma2_factor, centre, solver) or a stored design_file, and the sampled filter's method,
    substeps, hold and channel noise."""

    edges: Pairs | None = None
    W: Matrix | Matrices | None = None
    F: Matrix | Matrices | None = None
    P: str = "consensus"                 #: "consensus" = ½(𝐋 + 𝐋ᵀ) ⊗ I (reproduces Table I)
    zbar_min: float = 0.0
    margin: float = 1e-6
    gamma2_factor: float = 1.1
    centre: Literal["logmargin", "logdet"] = "logmargin"
    solver: Literal["CLARABEL", "SCS"] = "CLARABEL"
    design_file: str | None = None
    method: Literal["expm", "rk4"] = "expm"
    substeps: int = 10
    hold: Literal["model", "zoh"] = "model"
    channel_noise_std: float = 0.0


def _check(sc: Any, p: MinEnergyParams) -> None:
    src, n = sc.source, sc.sensors.n
    if sc.estimator.rounds != 1:
        raise ScenarioError(src, "estimator.rounds", "the min_energy filter exchanges once per tick", "rounds = 1")
    if not p.edges:
        raise ScenarioError(src, "estimator.edges", "the min_energy design needs the directed edge set",
                            "edges = [[i, j], …] (node i receives from node j)")
    for ei, (a, b) in enumerate(p.edges):
        if not (0 <= a < n and 0 <= b < n) or a == b:
            raise ScenarioError(src, f"estimator.edges[{ei}]", f"[{a}, {b}] must join two different sensors",
                                f"use ids 0 … {n - 1}")
    if p.W is None or p.F is None:
        raise ScenarioError(src, "estimator.W" if p.W is None else "estimator.F", "is required by min_energy")
    if p.P != "consensus":
        raise ScenarioError(src, "estimator.P", f"only \"consensus\" is supported, got {p.P!r}")
    if not p.gamma2_factor > 1:
        raise ScenarioError(src, "estimator.gamma2_factor", "Theorem 2 needs γ² > γ*²", "e.g. 1.1")
    if p.substeps < 1:
        raise ScenarioError(src, "estimator.substeps", "must be ≥ 1")
    if p.zbar_min < 0 or not p.margin > 0 or p.channel_noise_std < 0:
        raise ScenarioError(src, "estimator.zbar_min", "zbar_min ≥ 0, margin > 0 and channel_noise_std ≥ 0")
    if sc.target.model != "continuous":
        raise ScenarioError(src, "target.model", "the min_energy filter runs on a continuous-time plant",
                            "model = \"continuous\"")


def _design(sc: Any, p: MinEnergyParams, facts: GraphFacts) -> dict[str, Any]:
    """The SDP (29) design for the scenario: loaded from ``design_file`` (checked against the scenario's
    problem data) or solved now (supremum γ*², then a well-centred point at γ² = gamma2_factor·γ*² that
    the filters run on)."""
    n = sc.sensors.n
    Cs, Ds = [sc.C_of(i) for i in range(n)], [sc.D_of(i) for i in range(n)]
    edges = [tuple(x) for x in p.edges]
    Ac, Bc = np.array(sc.target.A, float), np.array(sc.target.B, float)
    W, F = np.array(p.W, float), np.array(p.F, float)
    W = list(W) if W.ndim == 3 else W
    F = list(F) if F.ndim == 3 else F
    if not p.design_file:
        dsg = design_network(Ac, Bc, Cs, Ds, W, F, edges, P=p.P, zbar_min=p.zbar_min, margin=p.margin,
                             solver=p.solver, gamma2_factor=p.gamma2_factor, centre=p.centre)
        return {"min_energy": dsg.to_dict()}
    stored = facts.stored(p.design_file)
    dsg = MinEnergyDesign.from_dict(dict(stored.get("min_energy", stored)))
    if not dsg.problem.matches(make_problem(Ac, Bc, Cs, Ds, W, F, edges, P=p.P)):
        raise ScenarioError(sc.source, "estimator.design_file", f"{p.design_file} was designed for other problem "
                            "data", "re-run `flocktrack design` for this scenario")
    return {"min_energy": dsg.to_dict()}


def _build(sc: Any, i: int, p: MinEnergyParams, design: Mapping[str, Any]) -> MinEnergyNode:
    if "min_energy" not in design:
        raise ValueError("min_energy needs the SDP design (29), computed by the runtime before the run")
    return MinEnergyNode.from_design(MinEnergyDesign.from_dict(design["min_energy"]), i,
                                     x0=sc.initial_estimates()[i], substeps=p.substeps, method=p.method,
                                     hold=p.hold, rng=rng_for(sc.run.seed, "agent", i, "channel_noise"),
                                     channel_noise_std=p.channel_noise_std)


def _summary(design: Mapping[str, Any], trace: RunTrace | None) -> dict[str, Any]:
    """``"hinf"``: the local H∞ ratios (6) per node and the network ratio (5) measured on the run
    (disturbances w, vᵢ, εᵢⱼ as recorded, tick grid), beside the designed γ̄ᵢ² and γ² (None when the run
    has fewer than two complete ticks)."""
    if trace is None or len(trace.errors) < 2:
        return {"hinf": None}
    dsg = MinEnergyDesign.from_dict(design["min_energy"])
    E = trace.errors
    K = len(E) - 1
    eps: dict[tuple[int, int], np.ndarray] = {}
    for (i, j) in dsg.problem.edges:
        rows = [trace.extra(k, i, f"eps_{j}") for k in range(K)]
        if all(r is not None for r in rows):
            eps[(i, j)] = np.array(rows)
    rep = performance_report(dsg, E, -E[0], trace.w, list(trace.v), eps, trace.T)
    return {"hinf": {"gamma2_design": float(dsg.gamma2), "gamma2_star": float(dsg.gamma2_star),
                     "network_ratio": rep["network"]["ratio"], "network_bound": rep["network"]["bound"],
                     "node_ratio": [nd["ratio"] for nd in rep["nodes"]],
                     "node_ratio_beta": [nd["ratio_beta"] for nd in rep["nodes"]],
                     "node_bound": [nd["bound"] for nd in rep["nodes"]],
                     "iqc_holds": [bool(nd["iqc_holds"]) for nd in rep["nodes"]]}}


def _report_design(design: dict[str, Any]) -> tuple[dict[str, Any], str]:
    out = design["min_energy"]
    return out, f"γ*² = {out.get('gamma2_star'):.6g} (supremum), filters designed at γ² = {out.get('gamma2'):.6g}"


SPEC = EstimatorSpec(name="min_energy", params=MinEnergyParams, check=_check, design=_design, build=_build,
                     summary=_summary, report_design=_report_design, per_sensor_C=True,
                     doc="Zamani & Ugrinovskii's minimum-energy filters (20)/(21) with the SDP (29) design")
