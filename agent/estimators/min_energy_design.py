"""Offline design of Zamani & Ugrinovskii's distributed H∞ minimum-energy filters: the SDP (29).

Paper: M. Zamani, V. Ugrinovskii, "Cooperative robust estimation with local performance guarantees".
Notation follows the paper; nodes and edges are **0-based** here.

Problem data
------------
Plant ẋ = A x + B w (1); node i measures yᵢ = Cᵢ x + Dᵢ vᵢ (2), Eᵢ = DᵢDᵢᵀ > 0; node i receives from
each in-neighbour j ∈ Nᵢ the message cᵢⱼ = Wᵢⱼ x̂ⱼ + Fᵢⱼ εᵢⱼ (3), Gᵢⱼ = FᵢⱼFᵢⱼᵀ > 0. ``edges`` are
directed pairs (i, j): *node i receives from node j*. P ⪰ 0 (nN × nN) weighs the network error in (5).

Decision variables (one set per node i, per edge (i, j) ∈ E)
-------------------------------------------------------------
Ȳᵢ = Ȳᵢᵀ > 0,  gᵢ = γ̄ᵢ⁻² > 0,  Υᵢⱼ = Υᵢⱼᵀ with 0 < Υᵢⱼ < Gᵢⱼ⁻¹,  τᵢⱼ > 0,  s = γ⁻².

Constraints
-----------
* (16)  Σⱼ τᵢⱼ < 1.
* (26)  [[AᵀȲᵢ + ȲᵢA + (gᵢ + Σⱼτᵢⱼ)I − (CᵢᵀEᵢ⁻¹Cᵢ + ΣⱼWᵢⱼᵀΥᵢⱼWᵢⱼ),  ȲᵢB],
         [BᵀȲᵢ,  (Σⱼτᵢⱼ − 1)I]] < 0.
* (27)  Θ̄ > 0, with the diagonal blocks Θ̄ᵢᵢ = [[θ̄₀ⁱⁱ, θ̄₁ⁱⁱ … θ̄ₗⁱⁱ], [(θ̄ₖⁱⁱ)ᵀ, diag(Gᵢⱼₖ⁻¹)]],
        θ̄₀ⁱⁱ = ΣⱼWᵢⱼᵀΥᵢⱼWᵢⱼ + (gᵢ + Σⱼτᵢⱼ)I − s Pᵢᵢ,  θ̄ₖⁱⁱ = WᵢⱼₖᵀΥᵢⱼₖ (the printed (θ₁ⁱⁱ)′ lacks
        its bar), and the off-diagonal blocks Θ̄ᵢⱼ = [[Ψᵢⱼ − s Pᵢⱼ, 0], [0, 0]] (i < j), Θ̄ⱼᵢ = Θ̄ᵢⱼᵀ,
        Ψᵢⱼ = −[j ∈ Nᵢ] WᵢⱼᵀΥᵢⱼWᵢⱼ − [i ∈ Nⱼ] WⱼᵢᵀΥⱼᵢWⱼᵢ.
* optional  Z̄ᵢⱼ ⪰ z₀ I.  Matching (26) with the Riccati equation (20) through Ȳᵢ = Qᵢ⁻¹ gives
        Υᵢⱼ = Ūᵢⱼ⁻¹ = (Gᵢⱼ + τᵢⱼ⁻¹Z̄ᵢⱼ)⁻¹, hence **Z̄ᵢⱼ = τᵢⱼ(Υᵢⱼ⁻¹ − Gᵢⱼ)** (not printed in the paper).
        Z̄ᵢⱼ ⪰ z₀I ⟺ Υᵢⱼ ⪯ (Gᵢⱼ + (z₀/τᵢⱼ)I)⁻¹ ⟺ (Woodbury + Schur) the LMI
        [[Gᵢⱼ⁻¹ − Υᵢⱼ, Gᵢⱼ⁻¹], [Gᵢⱼ⁻¹, Gᵢⱼ⁻¹ + (τᵢⱼ/z₀)I]] ⪰ 0, linear in (Υᵢⱼ, τᵢⱼ).

Strict inequalities are imposed with a margin: ``X ⪰ margin·I`` (``margin`` default 1e-6).

Two steps (PAPER_NOTES 001)
---------------------------
1. **Supremum** — maximise s = γ⁻² subject to all of the above: γ*² = 1/s*. In the paper's example
   this reproduces Table I's γ² (0.2500 and 0.3116). The optimal point itself is *not* a usable filter:
   it sits on the boundary of the LMIs, where the Riccati solutions of (20) are ~1e5–1e6 and very
   stiff (and Theorem 2 asks γ² > γ*² anyway).
2. **Centring** (``gamma2_factor`` = f > 1) — fix γ² = f·γ*² and pick a well-centred feasible point:
   every strict constraint Xₖ ≻ 0 gets its own slack, Xₖ ⪰ tₖI, and Σₖ log tₖ is maximised
   (``centre="logmargin"``, default), or the analytic centre Σₖ log det Xₖ (``centre="logdet"``,
   much slower). The filter uses this point: its Riccati solution stays below Ȳᵢ⁻¹ (moderate) and
   every τᵢⱼ, Z̄ᵢⱼ keeps a margin. Its γ̄ᵢ² are larger than on the optimal face (the price of
   robustness). (A single common slack, max t s.t. Xₖ ⪰ t·σₖI, was tried and rejected: it leaves
   every non-binding constraint where the solver drops it, e.g. τᵢⱼ ≈ 1e-4 and Z̄ᵢⱼ ≈ 0.)

Only the SDP fixes γ*² (and, in Simulation 2, γ̄₄² = 9/31 and min λ(Z̄₄ⱼ) = 0.1); the other per-node
numbers lie on a non-unique optimal face, so different solvers return different, equally valid
points. :func:`node_ranges` computes the range of γ̄ᵢ² over that face.

A failed solve never returns numbers: :class:`DesignError` says whether the problem is infeasible,
the solve inaccurate (status ``*_inaccurate``, an iteration limit, or an a-posteriori check of the
returned point that fails), or the solver crashed.

Pure: numpy + cvxpy only; :meth:`MinEnergyDesign.to_dict` / :meth:`MinEnergyDesign.from_dict` give
plain lists for the caller to store.
"""

from __future__ import annotations

import logging
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent.estimators.riccati import sym

__all__ = [
    "DesignError", "NetworkProblem", "NodeDesign", "MinEnergyDesign", "make_problem",
    "consensus_weight", "design_network", "solve_supremum", "check_design", "check_point",
    "node_ranges", "table_row", "theta_matrix", "SUPREMUM_REL_TOL",
]


log = logging.getLogger(__name__)


class DesignError(RuntimeError):
    """The SDP (29) did not yield a trustworthy design.

    Attributes: ``status`` — ``"infeasible"``, ``"inaccurate"``, ``"unbounded"`` or
    ``"solver_error"``; ``stage`` — ``"supremum"``, ``"centring"`` or ``"feasibility"``;
    ``solver_status`` — the raw cvxpy status string (or the exception text).
    """

    def __init__(self, status: str, stage: str, solver: str, solver_status: str, detail: str = ""):
        self.status, self.stage, self.solver, self.solver_status = status, stage, solver, solver_status
        msg = f"SDP (29) {stage} step: {status} (solver {solver} returned status {solver_status!r})"
        if detail:
            msg += f": {detail}"
        super().__init__(msg)


# ------------------------------------------------------------------------------------- problem data

def _mat(M: Any, name: str) -> np.ndarray:
    a = np.asarray(M, dtype=float)
    if a.ndim == 1:
        a = a.reshape(1, -1)
    if a.ndim != 2 or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a finite matrix, got shape {a.shape}")
    return a


@dataclass(frozen=True, eq=False)
class NetworkProblem:
    """Validated problem data of (29). Nodes 0 … N−1; ``nbrs[i]`` = sorted in-neighbours Nᵢ."""

    A: np.ndarray
    B: np.ndarray
    C: tuple[np.ndarray, ...]
    D: tuple[np.ndarray, ...]
    W: Mapping[tuple[int, int], np.ndarray]
    F: Mapping[tuple[int, int], np.ndarray]
    edges: tuple[tuple[int, int], ...]
    P: np.ndarray
    N: int

    @property
    def n(self) -> int:
        return self.A.shape[0]

    @property
    def nbrs(self) -> tuple[tuple[int, ...], ...]:
        return tuple(tuple(sorted(j for (i, j) in self.edges if i == k)) for k in range(self.N))

    def E(self, i: int) -> np.ndarray:
        return self.D[i] @ self.D[i].T

    def G(self, i: int, j: int) -> np.ndarray:
        F = self.F[(i, j)]
        return F @ F.T

    def matches(self, other: "NetworkProblem", rtol: float = 1e-12) -> bool:
        """Same plant, nodes, edges and matrices (e.g. a stored design vs. the scenario it runs in)."""
        def close(a: np.ndarray, b: np.ndarray) -> bool:
            return a.shape == b.shape and bool(np.allclose(a, b, rtol=rtol, atol=rtol))

        return (self.N == other.N and self.edges == other.edges and close(self.A, other.A)
                and close(self.B, other.B) and close(self.P, other.P)
                and all(close(a, b) for a, b in zip(self.C + self.D, other.C + other.D))
                and all(close(self.W[e], other.W[e]) and close(self.F[e], other.F[e]) for e in self.edges))

    def to_dict(self) -> dict:
        return {"A": self.A.tolist(), "B": self.B.tolist(), "C": [c.tolist() for c in self.C],
                "D": [d.tolist() for d in self.D], "edges": [list(e) for e in self.edges],
                "W": [self.W[e].tolist() for e in self.edges], "F": [self.F[e].tolist() for e in self.edges],
                "P": self.P.tolist(), "N": self.N}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "NetworkProblem":
        edges = [tuple(e) for e in d["edges"]]
        return make_problem(d["A"], d["B"], d["C"], d["D"], dict(zip(edges, d["W"])),
                            dict(zip(edges, d["F"])), edges, P=d["P"], N=d["N"])


def consensus_weight(N: int, edges: Sequence[tuple[int, int]], n: int) -> np.ndarray:
    """P = ½(𝐋 + 𝐋_⊤) ⊗ Iₙ: the H∞-consensus weight that reproduces Table I.

    𝐋 is the Laplacian of the directed graph (row i: in-degree of i, −1 for each j ∈ Nᵢ) and 𝐋_⊤ that
    of the reversed graph, so ‖e‖²_P = ½ Σ_{(i,j)∈E} ‖x̂ᵢ − x̂ⱼ‖². The paper prints (𝐋 + 𝐋_⊤) ⊗ I,
    which doubles γ² exactly (PAPER_NOTES 001).
    """
    Adj = np.zeros((N, N))
    for (i, j) in edges:
        Adj[i, j] = 1.0
    L = np.diag(Adj.sum(axis=1)) - Adj
    Lr = np.diag(Adj.sum(axis=0)) - Adj.T
    return np.kron(0.5 * (L + Lr), np.eye(n))


def _as_array(X: Any) -> np.ndarray | None:
    try:
        return np.asarray(X, dtype=float)
    except (ValueError, TypeError):
        return None                                   # ragged: a list of differently shaped matrices


def _per_node(X: Any, N: int, name: str) -> tuple[np.ndarray, ...]:
    """One matrix for every node (a 1-D or 2-D array) or a list of N per-node matrices."""
    a = _as_array(X)
    if a is not None and a.ndim <= 2:
        M = _mat(a, name)
        return tuple(M for _ in range(N))
    if len(X) != N:
        raise ValueError(f"{name} must be one matrix or a list of {N} matrices (one per node), got {len(X)}")
    return tuple(_mat(X[i], f"{name}[{i}]") for i in range(N))


def _per_edge(X: Any, edges: Sequence[tuple[int, int]], name: str) -> dict[tuple[int, int], np.ndarray]:
    """One matrix for every edge, a mapping {(i, j): matrix}, or a list of matrices aligned with
    ``edges`` (in the order the caller gave them)."""
    if isinstance(X, Mapping):
        out = {}
        for e in edges:
            if tuple(e) not in X:
                raise ValueError(f"{name} has no matrix for edge {tuple(e)}")
            out[tuple(e)] = _mat(X[tuple(e)], f"{name}{tuple(e)}")
        return out
    a = _as_array(X)
    if a is None or a.ndim == 3:
        if len(X) != len(edges):
            raise ValueError(f"{name} must be one matrix, a mapping, or one matrix per edge ({len(edges)}), "
                             f"got {len(X)}")
        return {tuple(e): _mat(X[k], f"{name}[{k}]") for k, e in enumerate(edges)}
    M = _mat(a, name)
    return {tuple(e): M for e in edges}


def make_problem(A, B, C, D, W, F, edges, P=None, N: int | None = None) -> NetworkProblem:
    """Validate and normalise the data of (29).

    ``C``, ``D``: one matrix for every node, or a list of N per-node matrices. ``W``, ``F``: one
    matrix for every edge, a mapping {(i, j): matrix}, or a list of matrices aligned with ``edges``.
    ``P``: nN × nN, or None / ``"consensus"`` for :func:`consensus_weight`. ``N`` defaults to len(C) for a list of
    per-node matrices, else 1 + the largest node id in ``edges``.
    """
    A, B = _mat(A, "A"), _mat(B, "B")
    n = A.shape[0]
    if A.shape != (n, n):
        raise ValueError(f"A must be square, got {A.shape}")
    if B.shape[0] != n:
        raise ValueError(f"B must have {n} rows, got {B.shape}")
    given = [(int(i), int(j)) for (i, j) in edges]
    if len(set(given)) != len(given):
        raise ValueError("edges contain duplicates")
    edges = tuple(sorted(given))
    if N is None:
        a = _as_array(C)
        N = len(C) if a is None or a.ndim == 3 else 1 + max((max(e) for e in edges), default=0)
    N = int(N)
    for (i, j) in edges:
        if not (0 <= i < N and 0 <= j < N) or i == j:
            raise ValueError(f"edge {(i, j)} must join two different nodes in 0..{N - 1}")
    Cs, Ds = _per_node(C, N, "C"), _per_node(D, N, "D")
    for i in range(N):
        if Cs[i].shape[1] != n:
            raise ValueError(f"C[{i}] must have {n} columns, got {Cs[i].shape}")
        if Ds[i].shape[0] != Cs[i].shape[0]:
            raise ValueError(f"D[{i}] must have {Cs[i].shape[0]} rows (as C[{i}]), got {Ds[i].shape}")
        if np.linalg.eigvalsh(sym(Ds[i] @ Ds[i].T)).min() <= 0:
            raise ValueError(f"E[{i}] = D[{i}] D[{i}]ᵀ must be positive definite")
    Ws, Fs = _per_edge(W, given, "W"), _per_edge(F, given, "F")
    for e in edges:
        if Ws[e].shape[1] != n:
            raise ValueError(f"W{e} must have {n} columns, got {Ws[e].shape}")
        if Fs[e].shape[0] != Ws[e].shape[0]:
            raise ValueError(f"F{e} must have {Ws[e].shape[0]} rows (as W{e}), got {Fs[e].shape}")
        if np.linalg.eigvalsh(sym(Fs[e] @ Fs[e].T)).min() <= 0:
            raise ValueError(f"G{e} = F F ᵀ must be positive definite")
    if isinstance(P, str):
        if P != "consensus":
            raise ValueError(f"P must be a matrix, None or 'consensus', got {P!r}")
        P = None
    P = consensus_weight(N, edges, n) if P is None else _mat(P, "P")
    if P.shape != (n * N, n * N):
        raise ValueError(f"P must be {n * N}×{n * N}, got {P.shape}")
    if not np.allclose(P, P.T, atol=1e-12) or np.linalg.eigvalsh(sym(P)).min() < -1e-10:
        raise ValueError("P must be symmetric positive semidefinite")
    return NetworkProblem(A=A, B=B, C=Cs, D=Ds, W=Ws, F=Fs, edges=edges, P=sym(P), N=N)


# ------------------------------------------------------------------------------------------ result

@dataclass(frozen=True, eq=False)
class NodeDesign:
    """What node i's filter needs from the design (Theorem 2): γ̄ᵢ², τᵢⱼ, Υᵢⱼ = Ūᵢⱼ⁻¹, Ȳᵢ."""

    i: int
    gammabar2: float
    tau: Mapping[int, float]
    Upsilon: Mapping[int, np.ndarray]
    Y: np.ndarray

    @property
    def tau_sum(self) -> float:
        return float(sum(self.tau.values()))


@dataclass(frozen=True, eq=False)
class MinEnergyDesign:
    """Every quantity of Theorem 2 for one network, 0-based.

    ``gamma2`` is the γ² the point was designed for (= ``gamma2_star`` for the raw supremum point,
    ``gamma2_factor``·``gamma2_star`` for a centred design); ``gammabar2[i]``, ``tau[i][j]``,
    ``Upsilon[i][j]``, ``Zbar[i][j]`` = τᵢⱼ(Υᵢⱼ⁻¹ − Gᵢⱼ), ``Y[i]`` = Ȳᵢ.
    """

    problem: NetworkProblem
    gamma2: float
    gamma2_star: float
    gammabar2: tuple[float, ...]
    tau: Mapping[int, Mapping[int, float]]
    Upsilon: Mapping[int, Mapping[int, np.ndarray]]
    Zbar: Mapping[int, Mapping[int, np.ndarray]]
    Y: tuple[np.ndarray, ...]
    zbar_min: float = 0.0
    margin: float = 1e-6
    gamma2_factor: float | None = None
    centre: str | None = None
    solver: str = "CLARABEL"
    solver_status: str = "optimal"
    solve_time_s: float = 0.0
    info: Mapping[str, Any] = field(default_factory=dict)

    @property
    def N(self) -> int:
        return self.problem.N

    @property
    def edges(self) -> tuple[tuple[int, int], ...]:
        return self.problem.edges

    def node(self, i: int) -> NodeDesign:
        return NodeDesign(i=i, gammabar2=self.gammabar2[i], tau=dict(self.tau[i]),
                          Upsilon={j: U.copy() for j, U in self.Upsilon[i].items()}, Y=self.Y[i].copy())

    def zbar_min_eig(self, i: int) -> float:
        """minⱼ λ_min(Z̄ᵢⱼ) (Table I's second column); +inf for a node without in-neighbours."""
        vals = [float(np.linalg.eigvalsh(Z).min()) for Z in self.Zbar[i].values()]
        return min(vals) if vals else float("inf")

    def to_dict(self) -> dict:
        """Plain lists/floats/strings (JSON/TOML/msgpack-able). Per-edge lists follow ``edges``."""
        E = self.edges
        return {
            "kind": "zamani_min_energy_design", "version": 1,
            "problem": self.problem.to_dict(),
            "gamma2": self.gamma2, "gamma2_star": self.gamma2_star,
            "gammabar2": list(self.gammabar2),
            "tau": [self.tau[i][j] for (i, j) in E],
            "Upsilon": [self.Upsilon[i][j].tolist() for (i, j) in E],
            "Zbar": [self.Zbar[i][j].tolist() for (i, j) in E],
            "Y": [Y.tolist() for Y in self.Y],
            "zbar_min": self.zbar_min, "margin": self.margin, "gamma2_factor": self.gamma2_factor,
            "centre": self.centre, "solver": self.solver, "solver_status": self.solver_status,
            "solve_time_s": self.solve_time_s, "info": dict(self.info),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "MinEnergyDesign":
        if d.get("kind") != "zamani_min_energy_design":
            raise ValueError("not a stored Zamani min-energy design (missing kind = 'zamani_min_energy_design')")
        prob = NetworkProblem.from_dict(d["problem"])
        E = prob.edges
        stored_edges = [tuple(e) for e in d["problem"]["edges"]]
        order = {e: k for k, e in enumerate(stored_edges)}
        tau: dict[int, dict[int, float]] = {i: {} for i in range(prob.N)}
        Ups: dict[int, dict[int, np.ndarray]] = {i: {} for i in range(prob.N)}
        Zb: dict[int, dict[int, np.ndarray]] = {i: {} for i in range(prob.N)}
        for (i, j) in E:
            k = order[(i, j)]
            tau[i][j] = float(d["tau"][k])
            Ups[i][j] = np.array(d["Upsilon"][k], float)
            Zb[i][j] = np.array(d["Zbar"][k], float)
        return cls(problem=prob, gamma2=float(d["gamma2"]), gamma2_star=float(d["gamma2_star"]),
                   gammabar2=tuple(float(v) for v in d["gammabar2"]), tau=tau, Upsilon=Ups, Zbar=Zb,
                   Y=tuple(np.array(Y, float) for Y in d["Y"]), zbar_min=float(d["zbar_min"]),
                   margin=float(d["margin"]), gamma2_factor=d.get("gamma2_factor"),
                   centre=d.get("centre"), solver=d.get("solver", ""),
                   solver_status=d.get("solver_status", ""), solve_time_s=float(d.get("solve_time_s", 0.0)),
                   info=dict(d.get("info", {})))


# ---------------------------------------------------------------------------------------- the SDP

class _SDP:
    """cvxpy model of (16), (26), (27) [+ Z̄ ⪰ z₀I] for one problem; the objective is set per step.

    ``mode="margin"``: every strict constraint X ≻ 0 is X ⪰ margin·I. ``mode="logmargin"``: each
    strict constraint k gets its own slack variable tₖ with X ⪰ tₖI (``self.slacks``), for the
    centring objective Σₖ log tₖ. ``s_fixed``: γ⁻² fixed instead of a variable.
    """

    def __init__(self, prob: NetworkProblem, zbar_min: float, margin: float, s_fixed: float | None = None,
                 mode: str = "margin"):
        import cvxpy as cp

        self.cp = cp
        self.prob = prob
        n, N = prob.n, prob.N
        self.s = cp.Variable(name="s") if s_fixed is None else None
        self._s = self.s if s_fixed is None else float(s_fixed)
        self.g = cp.Variable(N, name="g")
        self.Y = [cp.Variable((n, n), symmetric=True, name=f"Y{i}") for i in range(N)]
        self.U = {e: cp.Variable((prob.W[e].shape[0],) * 2, symmetric=True, name=f"U{e}") for e in prob.edges}
        self.tau = {e: cp.Variable(name=f"tau{e}") for e in prob.edges}
        self.constraints: list[Any] = []
        self.strict: list[tuple[str, Any]] = []     # (kind, expression that must be ≻ 0)
        self.slacks: list[Any] = []
        self._mode, self._margin = mode, margin
        for i in range(N):
            self._node_constraints(i, zbar_min)
        self._strict("theta", self._theta())                                   # (27): Θ̄ ≻ 0
        if self.s is not None:
            self.constraints.append(self.s >= 0)

    def _strict(self, kind: str, X: Any) -> None:
        """X ≻ 0 as X ⪰ margin·I, or X ⪰ tₖI with a slack tₖ of its own (``mode="logmargin"``)."""
        cp = self.cp
        if self._mode == "logmargin":
            t = cp.Variable(name=f"t_{kind}_{len(self.slacks)}")
            self.slacks.append(t)
            lo: Any = t
        else:
            lo = self._margin
        if X.shape and X.shape[0] > 1:
            self.constraints.append(0.5 * (X + X.T) >> lo * np.eye(X.shape[0]))
        else:
            self.constraints.append(cp.reshape(X, (), order="F") >= lo if X.shape else X >= lo)
        self.strict.append((kind, X))

    def _tau_sum(self, i: int) -> Any:
        taus = [self.tau[(i, j)] for j in self.prob.nbrs[i]]
        return sum(taus) if taus else 0.0

    def _wuw(self, i: int) -> Any:
        """Σⱼ Wᵢⱼᵀ Uᵢⱼ Wᵢⱼ over node i's neighbours."""
        prob, n = self.prob, self.prob.n
        return sum((prob.W[(i, j)].T @ self.U[(i, j)] @ prob.W[(i, j)] for j in prob.nbrs[i]), np.zeros((n, n)))

    def _node_constraints(self, i: int, zbar_min: float) -> None:
        """Node i's LMI (26), Y, g ≻ 0, Σ τ < 1 (16), and per edge τ, U, G⁻¹ − U ≻ 0 [+ Z̄ᵢⱼ ≻ z₀I]."""
        cp, prob = self.cp, self.prob
        n, m, A, B = prob.n, prob.B.shape[1], prob.A, prob.B
        tsum = self._tau_sum(i)
        CEC = prob.C[i].T @ np.linalg.inv(prob.E(i)) @ prob.C[i]
        L11 = A.T @ self.Y[i] + self.Y[i] @ A + (self.g[i] + tsum) * np.eye(n) - CEC - self._wuw(i)
        L12 = self.Y[i] @ B
        L22 = (tsum - 1.0) * np.eye(m)
        self._strict("lmi26", -cp.bmat([[L11, L12], [L12.T, L22]]))            # (26)
        self._strict("Y", self.Y[i])
        self._strict("g", self.g[i])
        if prob.nbrs[i]:
            self._strict("sum_tau", 1.0 - tsum)                                  # (16)
        for j in prob.nbrs[i]:
            e = (i, j)
            G_inv = np.linalg.inv(prob.G(i, j))
            self._strict("tau", self.tau[e])
            self._strict("U", self.U[e])
            self._strict("Ginv_minus_U", G_inv - self.U[e])
            if zbar_min > 0:                                                     # Z̄ᵢⱼ ≻ z₀I
                p = G_inv.shape[0]
                self._strict("zbar_lmi", cp.bmat([[G_inv - self.U[e], G_inv],
                                                  [G_inv, G_inv + (self.tau[e] / zbar_min) * np.eye(p)]]))

    def _theta_diagonal(self, i: int) -> Any:
        """Θ̄'s diagonal block of node i (27)."""
        prob, n, s, nb = self.prob, self.prob.n, self._s, self.prob.nbrs
        th0 = self._wuw(i) + (self.g[i] + self._tau_sum(i)) * np.eye(n) - s * prob.P[i * n:(i + 1) * n, i * n:(i + 1) * n]
        rows = [[th0] + [prob.W[(i, j)].T @ self.U[(i, j)] for j in nb[i]]]
        for a, j in enumerate(nb[i]):
            r = [(prob.W[(i, j)].T @ self.U[(i, j)]).T]
            for b, k in enumerate(nb[i]):
                pa, pb = prob.W[(i, j)].shape[0], prob.W[(i, k)].shape[0]
                r.append(np.linalg.inv(prob.G(i, j)) if a == b else np.zeros((pa, pb)))
            rows.append(r)
        return self.cp.bmat(rows)

    def _theta_off_diagonal(self, i: int, j: int, sizes: list[int]) -> Any:
        """Θ̄'s block (i, j), i < j (27): the coupling −WᵀUW of the edges between i and j, and −s·Pᵢⱼ."""
        prob, n, nb = self.prob, self.prob.n, self.prob.nbrs
        Psi: Any = np.zeros((n, n))
        if j in nb[i]:
            Psi = Psi - prob.W[(i, j)].T @ self.U[(i, j)] @ prob.W[(i, j)]
        if i in nb[j]:
            Psi = Psi - prob.W[(j, i)].T @ self.U[(j, i)] @ prob.W[(j, i)]
        top = Psi - self._s * prob.P[i * n:(i + 1) * n, j * n:(j + 1) * n]
        Mi, Mj = sizes[i] - n, sizes[j] - n
        if isinstance(top, np.ndarray) and not np.any(top):
            return np.zeros((sizes[i], sizes[j]))
        return self.cp.bmat([[top, np.zeros((n, Mj))], [np.zeros((Mi, n)), np.zeros((Mi, Mj))]])

    def _theta(self) -> Any:
        """Θ̄ of (27), block by block."""
        prob, N = self.prob, self.prob.N
        sizes = [prob.n + sum(prob.W[(i, j)].shape[0] for j in prob.nbrs[i]) for i in range(N)]
        blocks: list[list[Any]] = [[None] * N for _ in range(N)]
        for i in range(N):
            blocks[i][i] = self._theta_diagonal(i)
        for i in range(N):
            for j in range(i + 1, N):
                blocks[i][j] = self._theta_off_diagonal(i, j, sizes)
                blocks[j][i] = blocks[i][j].T
        return self.cp.bmat(blocks)

    def solve(self, objective: Any, solver: str, stage: str,
              solver_opts: Mapping[str, Any] | None) -> tuple[Any, float]:
        return self.solve_problem(self.cp.Problem(objective, self.constraints), solver, stage, solver_opts)

    def solve_problem(self, problem: Any, solver: str, stage: str,
                      solver_opts: Mapping[str, Any] | None) -> tuple[Any, float]:
        cp = self.cp
        t0 = time.perf_counter()
        try:
            with warnings.catch_warnings():      # an inaccurate status becomes a DesignError below
                warnings.filterwarnings("ignore", message="Solution may be inaccurate")
                problem.solve(solver=solver, **dict(solver_opts or {}))
        except cp.error.SolverError as exc:
            raise DesignError("solver_error", stage, solver, "solver_error", str(exc).splitlines()[0]) from None
        dt = time.perf_counter() - t0
        st = problem.status
        stats = problem.solver_stats
        self.solver_time = float(stats.solve_time) if stats is not None and stats.solve_time is not None else dt
        self.wall_time = dt
        if st in (cp.INFEASIBLE, "infeasible"):
            raise DesignError("infeasible", stage, solver, st,
                              "no point satisfies (16), (26), (27) and the Z̄ bound with this margin")
        if st in (cp.UNBOUNDED, "unbounded"):
            raise DesignError("unbounded", stage, solver, st)
        if st != cp.OPTIMAL:
            # optimal_inaccurate, infeasible_inaccurate, unbounded_inaccurate, user_limit, ...
            raise DesignError("inaccurate", stage, solver, st,
                              "the solver stopped before reaching its tolerances; do not use its numbers")
        return problem, dt

    def point(self) -> dict:
        N, nb = self.prob.N, self.prob.nbrs
        return {
            "g": [float(self.g.value[i]) for i in range(N)],
            "Y": [sym(np.array(self.Y[i].value, float)) for i in range(N)],
            "U": {e: sym(np.array(self.U[e].value, float)) for e in self.prob.edges},
            "tau": {e: float(self.tau[e].value) for e in self.prob.edges},
            "nbrs": nb,
        }


# ------------------------------------------------------------------------------- a-posteriori check

def check_point(prob: NetworkProblem, s: float, g: Sequence[float], Y: Sequence[np.ndarray],
                U: Mapping[tuple[int, int], np.ndarray], tau: Mapping[tuple[int, int], float],
                zbar_min: float = 0.0) -> dict[str, float]:
    """Smallest eigenvalue of every strict constraint of (29) at a point (numpy only; positive = feasible).

    Returns {"lmi26": λ_min of −(26) over nodes, "theta": λ_min(Θ̄), "Y", "g", "tau", "sum_tau"
    (min of 1 − Σⱼτᵢⱼ), "U", "Ginv_minus_U", "zbar" (minᵢⱼ λ_min(Z̄ᵢⱼ) − z₀), "zbar_lmi" (λ_min of
    the LMI form of Z̄ᵢⱼ ⪰ z₀I; +inf when z₀ = 0), "relative": the
    worst of these divided by the size (max |entry|, ≥ 1) of the matrix it belongs to, and
    "scale_<key>": that size per key}.
    """
    n, N, m = prob.n, prob.N, prob.B.shape[1]
    A, B = prob.A, prob.B
    nb = prob.nbrs
    out = {k: np.inf for k in ("lmi26", "theta", "Y", "g", "tau", "sum_tau", "U", "Ginv_minus_U", "zbar",
                               "zbar_lmi")}
    rel = np.inf

    scales = {k: 1.0 for k in out}

    def upd(k: str, M: np.ndarray | float) -> None:
        nonlocal rel
        if np.ndim(M) == 0:
            lam, scale = float(M), 1.0
        else:
            M = sym(np.asarray(M, float))
            lam = float(np.linalg.eigvalsh(M).min())
            scale = max(1.0, float(np.abs(M).max()))
        out[k] = min(out[k], lam)
        scales[k] = max(scales[k], scale)
        rel = min(rel, lam / scale)

    for i in range(N):
        tsum = sum(tau[(i, j)] for j in nb[i])
        CEC = prob.C[i].T @ np.linalg.inv(prob.E(i)) @ prob.C[i]
        WUW = sum((prob.W[(i, j)].T @ U[(i, j)] @ prob.W[(i, j)] for j in nb[i]), np.zeros((n, n)))
        L11 = A.T @ Y[i] + Y[i] @ A + (g[i] + tsum) * np.eye(n) - CEC - WUW
        L = np.block([[L11, Y[i] @ B], [B.T @ Y[i], (tsum - 1.0) * np.eye(m)]])
        upd("lmi26", -L)
        upd("Y", Y[i])
        upd("g", g[i])
        if nb[i]:
            upd("sum_tau", 1.0 - tsum)
        for j in nb[i]:
            e = (i, j)
            Ginv = np.linalg.inv(prob.G(i, j))
            upd("tau", tau[e])
            upd("U", U[e])
            upd("Ginv_minus_U", Ginv - U[e])
            if zbar_min > 0:
                p = Ginv.shape[0]
                upd("zbar_lmi", np.block([[Ginv - U[e], Ginv], [Ginv, Ginv + (tau[e] / zbar_min) * np.eye(p)]]))
            try:
                Z = tau[e] * (np.linalg.inv(U[e]) - prob.G(i, j))
                lamz = float(np.linalg.eigvalsh(sym(Z)).min()) - zbar_min
            except np.linalg.LinAlgError:
                lamz = -np.inf
            out["zbar"] = min(out["zbar"], lamz)
    Th = theta_matrix(prob, s, g, U, tau)
    upd("theta", Th)
    out["relative"] = rel
    out.update({"scale_" + k: v for k, v in scales.items()})
    return out


def theta_matrix(prob: NetworkProblem, s: float, g: Sequence[float], U: Mapping[tuple[int, int], np.ndarray],
                 tau: Mapping[tuple[int, int], float]) -> np.ndarray:
    """Θ̄ of (27) at a numeric point."""
    n, N = prob.n, prob.N
    nb = prob.nbrs
    sizes = [n + sum(prob.W[(i, j)].shape[0] for j in nb[i]) for i in range(N)]
    off = np.concatenate([[0], np.cumsum(sizes)])
    Th = np.zeros((off[-1], off[-1]))
    P = prob.P
    for i in range(N):
        o = off[i]
        tsum = sum(tau[(i, j)] for j in nb[i])
        WUW = sum((prob.W[(i, j)].T @ U[(i, j)] @ prob.W[(i, j)] for j in nb[i]), np.zeros((n, n)))
        Th[o:o + n, o:o + n] = WUW + (g[i] + tsum) * np.eye(n) - s * P[i * n:(i + 1) * n, i * n:(i + 1) * n]
        c = o + n
        for j in nb[i]:
            p = prob.W[(i, j)].shape[0]
            WU = prob.W[(i, j)].T @ U[(i, j)]
            Th[o:o + n, c:c + p] = WU
            Th[c:c + p, o:o + n] = WU.T
            Th[c:c + p, c:c + p] = np.linalg.inv(prob.G(i, j))
            c += p
    for i in range(N):
        for j in range(i + 1, N):
            Psi = np.zeros((n, n))
            if j in nb[i]:
                Psi -= prob.W[(i, j)].T @ U[(i, j)] @ prob.W[(i, j)]
            if i in nb[j]:
                Psi -= prob.W[(j, i)].T @ U[(j, i)] @ prob.W[(j, i)]
            blk = Psi - s * P[i * n:(i + 1) * n, j * n:(j + 1) * n]
            Th[off[i]:off[i] + n, off[j]:off[j] + n] = blk
            Th[off[j]:off[j] + n, off[i]:off[i] + n] = blk.T
    return Th


def check_design(design: MinEnergyDesign) -> dict[str, float]:
    """:func:`check_point` at a design's own point and γ² (positive numbers = strictly feasible)."""
    prob = design.problem
    U = {(i, j): design.Upsilon[i][j] for (i, j) in prob.edges}
    tau = {(i, j): design.tau[i][j] for (i, j) in prob.edges}
    return check_point(prob, 1.0 / design.gamma2, [1.0 / v for v in design.gammabar2], design.Y, U, tau,
                       design.zbar_min)


def _verify(prob: NetworkProblem, pt: dict, s: float, zbar_min: float, stage: str, solver: str,
            status: str, rel_tol: float) -> dict[str, float]:
    """Re-check a returned point with numpy. ``rel_tol`` = 0: every strict constraint must hold
    strictly (λ_min > 0). ``rel_tol`` > 0 (the supremum point, which lies on the boundary by
    construction): λ_min ≥ −rel_tol·max(1, ‖X‖_max) — feasible to solver accuracy."""
    chk = check_point(prob, s, pt["g"], pt["Y"], pt["U"], pt["tau"], zbar_min)
    bad = []
    for k in ("lmi26", "theta", "Y", "g", "tau", "sum_tau", "U", "Ginv_minus_U"):
        lam, scale = chk[k], chk["scale_" + k]
        if not (lam > 0 if rel_tol == 0 else lam >= -rel_tol * scale):
            bad.append(k)
    if zbar_min > 0 and chk["zbar_lmi"] < -max(rel_tol, 1e-8) * chk["scale_zbar_lmi"]:
        bad.append("zbar")
    if bad:
        raise DesignError("inaccurate", stage, solver, status,
                          "the returned point violates the constraint(s) " + ", ".join(bad)
                          + (" strictly" if rel_tol == 0 else " beyond solver accuracy")
                          + " (try a tighter solver tolerance or a larger margin)")
    return chk


def _build_design(prob: NetworkProblem, pt: dict, gamma2: float, gamma2_star: float, **kw: Any) -> MinEnergyDesign:
    N, nb = prob.N, prob.nbrs
    tau = {i: {j: pt["tau"][(i, j)] for j in nb[i]} for i in range(N)}
    Ups = {i: {j: pt["U"][(i, j)] for j in nb[i]} for i in range(N)}
    Zb = {i: {j: sym(pt["tau"][(i, j)] * (np.linalg.inv(pt["U"][(i, j)]) - prob.G(i, j))) for j in nb[i]}
          for i in range(N)}
    return MinEnergyDesign(problem=prob, gamma2=float(gamma2), gamma2_star=float(gamma2_star),
                           gammabar2=tuple(1.0 / v for v in pt["g"]), tau=tau, Upsilon=Ups, Zbar=Zb,
                           Y=tuple(pt["Y"]), **kw)


_SOLVER_DEFAULTS: dict[str, dict[str, Any]] = {
    # The supremum of (29) lies on a degenerate face (in Table I Simulation 1, Υᵢⱼ → Gᵢⱼ⁻¹ at the
    # undetectable nodes 1 and 4): interior-point iterations stall at a relative duality gap of
    # 1e-6 … 2e-6 there and Clarabel's default 1e-8 reports "AlmostSolved" (cvxpy: optimal_inaccurate).
    # A 1e-5 relative gap on γ⁻² is 20× finer than Table I prints; the feasibility tolerances stay at
    # their defaults and every returned point is re-checked strictly with numpy (check_point).
    "CLARABEL": {"tol_gap_abs": 1e-6, "tol_gap_rel": 1e-5},
    # SCS (first order): 1e-6 leaves Θ̄ violated beyond SUPREMUM_REL_TOL in Simulation 1; 1e-7 reproduces
    # Clarabel's γ*² (≈1 s / ≈13 s for Simulations 1 / 2) and the centred point (≈40–55 s, which needs the
    # 200k iterations) with SCS 3.2. SCS 3.3 needs 1e-8 in Simulation 1 but does not converge at 1e-8 in
    # Simulation 2: the supremum step therefore tightens eps ×0.1 (to SCS_EPS_FLOOR) while the returned
    # point fails the numpy re-check, unless the caller fixed eps itself.
    "SCS": {"eps_abs": 1e-7, "eps_rel": 1e-7, "max_iters": 200_000},
}


#: The supremum point lies on the boundary of (29) by construction, so it is accepted when every
#: constraint holds to solver accuracy: λ_min ≥ −SUPREMUM_REL_TOL·max(1, ‖X‖_max). (Clarabel's points
#: violate Θ̄ ⪰ margin·I by ≈ 1e-7 relative at the 1e-5 gap.) Centred designs must hold strictly.
SUPREMUM_REL_TOL = 1e-6

#: The tightest eps the supremum step tries with SCS before it reports the point inaccurate.
SCS_EPS_FLOOR = 1e-9


def _opts(solver: str, solver_opts: Mapping[str, Any] | None) -> dict[str, Any]:
    o = dict(_SOLVER_DEFAULTS.get(solver.upper(), {}))
    o.update(solver_opts or {})
    return o


def solve_supremum(prob: NetworkProblem, zbar_min: float = 0.0, margin: float = 1e-6, solver: str = "CLARABEL",
                   solver_opts: Mapping[str, Any] | None = None) -> tuple[float, dict, dict]:
    """Step 1: sup γ⁻² s.t. (27), (16) [+ Z̄ ⪰ z₀I]. Returns (γ*², point, info) where info has the
    cvxpy status, the solver's own time and the wall time (cvxpy compilation included)."""
    opts = _opts(solver, solver_opts)
    tighten = solver.upper() == "SCS" and not {"eps_abs", "eps_rel"} & set(solver_opts or {})
    while True:
        sdp = _SDP(prob, zbar_min, margin)
        problem, _ = sdp.solve(sdp.cp.Maximize(sdp.s), solver, "supremum", opts)
        s = float(sdp.s.value)
        if not s > 0:
            raise DesignError("infeasible", "supremum", solver, problem.status,
                              "the optimal γ⁻² is not positive (no finite γ²)")
        pt = sdp.point()
        try:
            _verify(prob, pt, s, zbar_min, "supremum", solver, problem.status, SUPREMUM_REL_TOL)
            break
        except DesignError:
            if not tighten or opts["eps_abs"] * 0.1 < SCS_EPS_FLOOR * 0.99:
                raise
            opts = dict(opts, eps_abs=opts["eps_abs"] * 0.1, eps_rel=opts["eps_rel"] * 0.1)
            log.info("SCS supremum point fails the re-check: retrying with eps %.0e", opts["eps_abs"])
    return 1.0 / s, pt, {"status": problem.status, "solver_time_s": sdp.solver_time, "wall_time_s": sdp.wall_time,
                         "solver_opts": opts}


def design_network(A, B, C, D, W, F, edges, P=None, zbar_min: float = 0.0, margin: float = 1e-6,
                   solver: str = "CLARABEL", gamma2_factor: float | None = None, *, N: int | None = None,
                   centre: str = "logmargin", solver_opts: Mapping[str, Any] | None = None) -> MinEnergyDesign:
    """Design the network of Theorem 2 by the SDP (29).

    Parameters
    ----------
    A (n×n), B (n×m): plant (1).  C, D: per-node measurement matrices (2) (one matrix for all nodes
    or a list of N).  W, F: per-edge communication matrices (3) (one matrix or {(i, j): matrix}).
    edges: directed pairs (i, j), node i receives from node j (0-based).  P: nN×nN weight of (5),
    default ½(𝐋 + 𝐋_⊤) ⊗ Iₙ (:func:`consensus_weight`, Table I's choice).  zbar_min: z₀ > 0 adds
    Z̄ᵢⱼ ≻ z₀I (Table I Simulation 2: 0.1).  margin: strict inequalities become ⪰ margin·I.
    solver: ``"CLARABEL"`` (default) or ``"SCS"`` (any cvxpy SDP solver).
    gamma2_factor: None → return the supremum point itself (γ² = γ*², on the boundary: reproduces
    Table I but is a stiff, barely-bounded filter). f > 1 → also solve the centring step at
    γ² = f·γ*² and return that point (the one to run).
    centre: ``"logmargin"`` (default: each strict constraint Xₖ ≻ 0 gets its own slack tₖ,
    Xₖ ⪰ tₖI, and Σₖ log tₖ is maximised — as the geometric mean of the tₖ, an SDP plus second-order
    cones — so every constraint keeps a positive, balanced margin; ~25 ms of Clarabel time) or
    ``"logdet"`` (the analytic centre Σₖ log det Xₖ; ~100× slower because of Θ̄'s log-det).
    solver_opts: passed to cvxpy's ``solve`` (e.g. ``{"max_iter": 2}`` for Clarabel); merged over
    the defaults (Clarabel: relative gap 1e-5, see ``_SOLVER_DEFAULTS``; SCS: eps 1e-9).

    Raises :class:`DesignError` (status ``"infeasible"`` / ``"inaccurate"`` / ``"solver_error"``) —
    never returns numbers from a failed or inaccurate solve. The returned point is re-checked with
    numpy (:func:`check_point`): a centred point must satisfy every strict constraint strictly, the
    supremum point to solver accuracy (``SUPREMUM_REL_TOL``).
    """
    prob = make_problem(A, B, C, D, W, F, edges, P=P, N=N)
    zbar_min = float(zbar_min)
    if zbar_min < 0:
        raise ValueError("zbar_min must be ≥ 0")
    if not margin > 0:
        raise ValueError("margin must be > 0 (the LMIs of (29) are strict)")
    solver = solver.upper()
    g2star, pt, inf1 = solve_supremum(prob, zbar_min, margin, solver, solver_opts)
    common = dict(zbar_min=zbar_min, margin=float(margin), solver=solver)
    info = {"supremum_solver_time_s": inf1["solver_time_s"], "supremum_wall_time_s": inf1["wall_time_s"],
            "supremum_solver_opts": inf1["solver_opts"]}
    if gamma2_factor is None:
        return _build_design(prob, pt, g2star, g2star, gamma2_factor=None, centre=None,
                             solver_status=inf1["status"], solve_time_s=inf1["solver_time_s"], info=info, **common)
    f = float(gamma2_factor)
    if not f > 1.0:
        raise ValueError("gamma2_factor must be > 1 (Theorem 2 needs γ² > γ*²)")
    gamma2 = f * g2star
    pt2, inf2 = _centre(prob, 1.0 / gamma2, zbar_min, margin, solver, solver_opts, centre)
    info.update({"centring_solver_time_s": inf2["solver_time_s"], "centring_wall_time_s": inf2["wall_time_s"]})
    return _build_design(prob, pt2, gamma2, g2star, gamma2_factor=f, centre=centre, solver_status=inf2["status"],
                         solve_time_s=inf1["solver_time_s"] + inf2["solver_time_s"], info=info, **common)


def _centre(prob: NetworkProblem, s: float, zbar_min: float, margin: float, solver: str,
            solver_opts: Mapping[str, Any] | None, centre: str) -> tuple[dict, dict]:
    if centre == "logmargin":
        sdp = _SDP(prob, zbar_min, margin, s_fixed=s, mode="logmargin")
        cp = sdp.cp
        # geo_mean has the same maximiser as Σ log tₖ but is SOC-representable (no exponential
        # cones; cvxpy's dyadic approximation is exact here and warns about it): SCS converges too
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="geo_mean is being approximated")
            objective = cp.Maximize(cp.geo_mean(cp.hstack(sdp.slacks)))
    elif centre == "logdet":
        sdp = _SDP(prob, zbar_min, margin, s_fixed=s)
        cp = sdp.cp
        terms = []
        for _, X in sdp.strict:
            if X.shape and X.shape[0] > 1:
                terms.append(cp.log_det(0.5 * (X + X.T)))
            else:
                terms.append(cp.log(cp.reshape(X, (), order="F") if X.shape else X))
        objective = cp.Maximize(sum(terms))
    else:
        raise ValueError(f"unknown centre {centre!r}; use 'logmargin' or 'logdet'")
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="geo_mean is being approximated")
        problem, _ = sdp.solve(objective, solver, "centring", _opts(solver, solver_opts))
    pt = sdp.point()
    _verify(prob, pt, s, zbar_min, "centring", solver, problem.status, 0.0)
    return pt, {"status": problem.status, "solver_time_s": sdp.solver_time, "wall_time_s": sdp.wall_time}


# ------------------------------------------------------------------------------ face / table helpers

def node_ranges(prob: NetworkProblem, gamma2: float, zbar_min: float = 0.0, margin: float = 1e-6,
                solver: str = "CLARABEL", nodes: Sequence[int] | None = None,
                solver_opts: Mapping[str, Any] | None = None) -> dict[int, tuple[float, float]]:
    """Range of γ̄ᵢ² over the feasible set of (29) at a fixed γ² (just above γ*² it approximates the
    optimal face). Returns {i: (min γ̄ᵢ², max γ̄ᵢ²)}: 2 solves per node of one compiled problem
    (the objective ±gᵢ is a cvxpy Parameter). Raises :class:`DesignError` like :func:`design_network`."""
    import cvxpy as cp

    sdp = _SDP(prob, zbar_min, margin, s_fixed=1.0 / float(gamma2))
    c = cp.Parameter(prob.N)
    problem = cp.Problem(cp.Maximize(c @ sdp.g), sdp.constraints)
    out = {}
    opts = _opts(solver, solver_opts)
    for i in (range(prob.N) if nodes is None else nodes):
        vals = []
        for sign in (1.0, -1.0):                       # max gᵢ → min γ̄ᵢ²; min gᵢ → max γ̄ᵢ²
            e = np.zeros(prob.N)
            e[i] = sign
            c.value = e
            sdp.solve_problem(problem, solver, "feasibility", opts)
            vals.append(float(sdp.g.value[i]))
        out[i] = (1.0 / vals[0], 1.0 / vals[1])
    return out


def table_row(prob: NetworkProblem, gamma2: float, gammabar2: Sequence[float], zbar_mins: Sequence[float],
              margin: float = 1e-9, solver: str = "CLARABEL",
              solver_opts: Mapping[str, Any] | None = None) -> dict:
    """Is a published row (γ², γ̄ᵢ², minⱼ λ_min(Z̄ᵢⱼ)) jointly feasible for (29)?

    Fixes s = 1/γ² and gᵢ = 1/γ̄ᵢ², imposes Z̄ᵢⱼ ⪰ zbar_mins[i]·I for every j ∈ Nᵢ, and searches the
    remaining variables (Ȳᵢ, Υᵢⱼ, τᵢⱼ). Returns the feasible point's :func:`check_point`; raises
    :class:`DesignError` ("infeasible") if there is none.
    """
    import cvxpy as cp

    sdp = _SDP(prob, 0.0, margin, s_fixed=1.0 / float(gamma2))
    for i, gb in enumerate(gammabar2):
        sdp.constraints.append(sdp.g[i] == 1.0 / float(gb))
        z0 = float(zbar_mins[i])
        for j in prob.nbrs[i]:
            e = (i, j)
            Ginv = np.linalg.inv(prob.G(i, j))
            p = Ginv.shape[0]
            Z = cp.bmat([[Ginv - sdp.U[e], Ginv], [Ginv, Ginv + (sdp.tau[e] / z0) * np.eye(p)]])
            sdp.constraints.append(0.5 * (Z + Z.T) >> 0)
    problem, _ = sdp.solve(cp.Minimize(0), solver, "feasibility", _opts(solver, solver_opts))
    pt = sdp.point()
    return check_point(prob, 1.0 / float(gamma2), pt["g"], pt["Y"], pt["U"], pt["tau"])
