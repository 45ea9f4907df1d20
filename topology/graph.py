"""Graph facts for the flock: range adjacency, Laplacians, connectivity, switching schedules.

Pure functions over numpy arrays (no transport, no file I/O). Conventions:

* An adjacency matrix ``adj`` is an ``(n, n)`` float array, symmetric, zero diagonal, with
  ``adj[i, j] = g_ij > 0`` the weight of the undirected edge (i, j) and 0 for "no edge"
  (Chen et al.: ``g_ij = α_ij`` when i and j are connected at k, else 0).
* ``b`` is the vector of target-visibility weights bᵢ ≥ 0 (Chen: ``bᵢ(k) = βᵢ`` if sensor i is
  connected to the target at k, else 0).
* Chen's Hₚ = Lₚ + Bₚ with Lₚ = D − G the weighted Laplacian and Bₚ = diag(b) (Section 2.A);
  Lemma 2.1: under Assumption 1 (every maximal connected component contains a node that sees the
  target), λ₀ = min over all graphs of the smallest eigenvalue of Hₚ is > 0.

Nodes are 0-based everywhere (the papers number them from 1).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "range_adjacency", "lists_adjacency", "degrees", "max_degree", "laplacian", "neighbour_lists", "edge_weights",
    "components", "is_connected", "algebraic_connectivity", "h_matrix", "target_connected",
    "lambda0", "GraphSpec", "PeriodicSchedule", "chen_example_schedule",
]


def _as_adj(adj: np.ndarray) -> np.ndarray:
    a = np.asarray(adj, dtype=float)
    if a.ndim != 2 or a.shape[0] != a.shape[1]:
        raise ValueError(f"adjacency must be a square (n, n) matrix, got shape {a.shape}")
    return a


def _as_b(b: Sequence[float] | np.ndarray, n: int) -> np.ndarray:
    bb = np.asarray(b, dtype=float).reshape(-1)
    if bb.shape != (n,):
        raise ValueError(f"b must have one entry per node (n = {n}), got {bb.shape[0]}")
    return bb


def range_adjacency(positions: np.ndarray, radius: float,
                    alive: Sequence[bool] | None = None) -> np.ndarray:
    """0/1 adjacency of a range graph: edge (i, j) iff ‖pᵢ − pⱼ‖ ≤ ``radius``.

    The inequality is inclusive (Gu & Hu: nodes are neighbours when their distance is
    "less than or equal to" the communication range E). A node with ``alive[i] == False`` has no
    edges. Returns an ``(n, n)`` float array, symmetric, zero diagonal.
    """
    p = np.asarray(positions, dtype=float)
    if p.ndim == 1:
        p = p.reshape(-1, 1)
    if p.ndim != 2:
        raise ValueError(f"positions must be an (n, d) array, got shape {p.shape}")
    n = p.shape[0]
    if not np.isfinite(radius) or radius < 0:
        raise ValueError(f"radius must be a finite number ≥ 0, got {radius!r}")
    diff = p[:, None, :] - p[None, :, :]
    dist = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))
    adj = (dist <= radius).astype(float)
    np.fill_diagonal(adj, 0.0)
    if alive is not None:
        live = np.asarray(alive, dtype=bool).reshape(-1)
        if live.shape != (n,):
            raise ValueError(f"alive must have one entry per node (n = {n}), got {live.shape[0]}")
        adj[~live, :] = 0.0
        adj[:, ~live] = 0.0
    return adj


def degrees(adj: np.ndarray) -> np.ndarray:
    """Weighted degrees dᵢ = Σⱼ gᵢⱼ (for a 0/1 adjacency: the number of neighbours)."""
    return _as_adj(adj).sum(axis=1)


def max_degree(adj: np.ndarray) -> int:
    """Maximum number of neighbours δ_max (unweighted; counts edges, not weights). 0 for n = 0."""
    a = _as_adj(adj)
    if a.shape[0] == 0:
        return 0
    return int((a > 0).sum(axis=1).max())


def laplacian(adj: np.ndarray) -> np.ndarray:
    """Weighted Laplacian L = D − G (rows sum to zero)."""
    a = _as_adj(adj)
    return np.diag(a.sum(axis=1)) - a


def lists_adjacency(links) -> np.ndarray:
    """The 0/1 adjacency (float) of neighbour lists: gᵢⱼ = 1 for each j in ``links[i]`` (a tick's link
    table, as the world sends it: the inverse of :func:`neighbour_lists`)."""
    n = len(links)
    adj = np.zeros((n, n))
    for i, nb in enumerate(links):
        adj[i, list(nb)] = 1.0
    return adj


def neighbour_lists(adj: np.ndarray) -> list[list[int]]:
    """For each node, the ascending list of its neighbours (gᵢⱼ > 0)."""
    a = _as_adj(adj)
    return [[int(j) for j in np.flatnonzero(a[i] > 0) if j != i] for i in range(a.shape[0])]


def edge_weights(adj: np.ndarray) -> list[list[float]]:
    """For each node, the weights gᵢⱼ aligned with :func:`neighbour_lists`."""
    a = _as_adj(adj)
    return [[float(a[i, j]) for j in nb] for i, nb in enumerate(neighbour_lists(a))]


def components(adj: np.ndarray) -> list[list[int]]:
    """Maximal connected components (Chen's "maximal connected branches"), each ascending,
    ordered by their smallest node (:func:`scipy.sparse.csgraph.connected_components`)."""
    from scipy.sparse.csgraph import connected_components

    a = _as_adj(adj)
    if a.shape[0] == 0:
        return []
    k, labels = connected_components(a > 0, directed=False)
    return [np.flatnonzero(labels == c).tolist() for c in range(k)]   # labels follow the smallest node


def is_connected(adj: np.ndarray) -> bool:
    """True iff the graph has at most one connected component (n ≤ 1 counts as connected)."""
    return len(components(adj)) <= 1


def algebraic_connectivity(adj: np.ndarray) -> float:
    """λ₂ of the Laplacian (Fiedler value). 0.0 for a disconnected graph and for n ≤ 1."""
    a = _as_adj(adj)
    if a.shape[0] <= 1 or not is_connected(a):
        return 0.0
    return float(np.linalg.eigvalsh(laplacian(a))[1])


def h_matrix(adj: np.ndarray, b: Sequence[float] | np.ndarray) -> np.ndarray:
    """Chen's Hₚ = Lₚ + Bₚ = L + diag(b) (Section 2.A)."""
    a = _as_adj(adj)
    return laplacian(a) + np.diag(_as_b(b, a.shape[0]))


def target_connected(adj: np.ndarray, b: Sequence[float] | np.ndarray) -> bool:
    """Chen's Assumption 1 for one graph: every maximal connected component contains at least one
    node with bᵢ > 0 (then Hₚ is positive definite)."""
    a = _as_adj(adj)
    bb = _as_b(b, a.shape[0])
    return all(any(bb[i] > 0 for i in comp) for comp in components(a))


def lambda0(H_list: Sequence[np.ndarray]) -> float:
    """λ₀ of Chen's Lemma 2.1: the smallest eigenvalue over all Hₚ in ``H_list``.

    Values within 1e-12·max(1, ‖Hₚ‖) of zero are returned as exactly 0.0 (a component that never
    sees the target gives a zero eigenvalue, which floating point may report as ±1e-17).
    """
    if len(H_list) == 0:
        raise ValueError("lambda0 needs at least one H matrix")
    vals = []
    for H in H_list:
        h = np.asarray(H, dtype=float)
        lam = float(np.linalg.eigvalsh(0.5 * (h + h.T)).min())
        scale = max(1.0, float(np.abs(h).max()) if h.size else 1.0)
        vals.append(0.0 if abs(lam) <= 1e-12 * scale else lam)
    return min(vals)


@dataclass(frozen=True)
class GraphSpec:
    """One fixed graph of n sensors plus the target: undirected edges, edge weights α (default 1),
    target weights b (Chen's βᵢ where the sensor sees the target, else 0)."""

    n: int
    edges: tuple[tuple[int, int], ...]
    b: tuple[float, ...]
    weights: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if int(self.n) != self.n or self.n < 1:
            raise ValueError(f"GraphSpec.n must be a positive integer, got {self.n!r}")
        object.__setattr__(self, "n", int(self.n))
        edges = tuple((int(i), int(j)) for i, j in self.edges)
        seen: set[frozenset[int]] = set()
        for i, j in edges:
            if not (0 <= i < self.n and 0 <= j < self.n):
                raise ValueError(f"GraphSpec edge ({i}, {j}) has a node outside 0..{self.n - 1}")
            if i == j:
                raise ValueError(f"GraphSpec edge ({i}, {j}) is a self-loop")
            key = frozenset((i, j))
            if key in seen:
                raise ValueError(f"GraphSpec edge ({i}, {j}) is listed twice")
            seen.add(key)
        object.__setattr__(self, "edges", edges)
        b = tuple(float(v) for v in self.b)
        if len(b) != self.n:
            raise ValueError(f"GraphSpec.b must have n = {self.n} entries, got {len(b)}")
        if not all(np.isfinite(v) and v >= 0 for v in b):
            raise ValueError(f"GraphSpec.b entries must be finite and ≥ 0, got {b}")
        object.__setattr__(self, "b", b)
        if self.weights is not None:
            w = tuple(float(v) for v in self.weights)
            if len(w) != len(edges):
                raise ValueError(f"GraphSpec.weights must have one entry per edge ({len(edges)}), "
                                 f"got {len(w)}")
            if not all(np.isfinite(v) and v > 0 for v in w):
                raise ValueError(f"GraphSpec.weights must be finite and > 0, got {w}")
            object.__setattr__(self, "weights", w)

    def adjacency(self) -> np.ndarray:
        """Weighted adjacency G (gᵢⱼ = gⱼᵢ = α of the edge)."""
        a = np.zeros((self.n, self.n))
        w = self.weights if self.weights is not None else (1.0,) * len(self.edges)
        for (i, j), g in zip(self.edges, w):
            a[i, j] = a[j, i] = g
        return a

    def H(self) -> np.ndarray:
        """Chen's Hₚ = Lₚ + Bₚ."""
        return h_matrix(self.adjacency(), self.b)

    def neighbour_lists(self) -> list[list[int]]:
        return neighbour_lists(self.adjacency())

    def edge_weights(self) -> list[list[float]]:
        return edge_weights(self.adjacency())

    def target_connected(self) -> bool:
        """Assumption 1 for this graph."""
        return target_connected(self.adjacency(), self.b)


@dataclass(frozen=True)
class PeriodicSchedule:
    """Periodic switching among ``graphs``, each held for ``dwell_ticks`` ticks:
    tick k uses ``graphs[(k // dwell_ticks) % len(graphs)]``."""

    graphs: tuple[GraphSpec, ...]
    dwell_ticks: int

    def __post_init__(self) -> None:
        graphs = tuple(self.graphs)
        if not graphs:
            raise ValueError("PeriodicSchedule needs at least one graph")
        if any(not isinstance(g, GraphSpec) for g in graphs):
            raise ValueError("PeriodicSchedule.graphs must be GraphSpec instances")
        ns = {g.n for g in graphs}
        if len(ns) != 1:
            raise ValueError(f"PeriodicSchedule graphs disagree on the number of nodes: {sorted(ns)}")
        if int(self.dwell_ticks) != self.dwell_ticks or self.dwell_ticks < 1:
            raise ValueError(f"dwell_ticks must be an integer ≥ 1, got {self.dwell_ticks!r}")
        object.__setattr__(self, "graphs", graphs)
        object.__setattr__(self, "dwell_ticks", int(self.dwell_ticks))

    @property
    def n(self) -> int:
        return self.graphs[0].n

    @property
    def period_ticks(self) -> int:
        return self.dwell_ticks * len(self.graphs)

    def index_at(self, k: int) -> int:
        """Index of the graph in force at tick k (k ≥ 0)."""
        if k < 0:
            raise ValueError(f"tick must be ≥ 0, got {k}")
        return (int(k) // self.dwell_ticks) % len(self.graphs)

    def at(self, k: int) -> GraphSpec:
        """The graph in force at tick k."""
        return self.graphs[self.index_at(k)]

    def H_list(self) -> list[np.ndarray]:
        """[Hₚ for each distinct graph p], the input of Lemma 2.1 / Theorem 3.3."""
        return [g.H() for g in self.graphs]

    def ever_sees_target(self) -> bool:
        """True iff some graph has some node with bᵢ > 0."""
        return any(v > 0 for g in self.graphs for v in g.b)

    def all_target_connected(self) -> bool:
        """Assumption 1 for every graph of the schedule (⇒ λ₀ > 0, Lemma 2.1)."""
        return all(g.target_connected() for g in self.graphs)

    def lambda0(self) -> float:
        """λ₀ of Lemma 2.1 over the schedule's graphs."""
        return lambda0(self.H_list())


def chen_example_schedule(dwell_ticks: int = 10) -> PeriodicSchedule:
    """The four switching graphs of Chen et al.'s Section 4 (0-based nodes, all α = β = 1).

    G1: no edges, b = (1, 1, 1);  G2: edges (0,1), (0,2), b = (1, 0, 0);
    G3: edges (0,2), (1,2), b = (1, 1, 0);  G4: edges (0,1), (1,2), b = (0, 0, 1).

    The paper's listing of bᵢ(k), gᵢⱼ(k) changes graph every tick T (k = 4nT, 4nT + T, …) while
    its text says "every 1 second"; ``dwell_ticks`` chooses. NOTE: with the paper's gain
    K = [0.9376, 0.5884]ᵀ the closed loop is stable for dwell 1, 2 or 3 but diverges for dwell ≥ 4
    (each of G2, G3, G4 alone is unstable under that gain; see agent.estimators.hinf_switching).
    """
    return PeriodicSchedule(
        graphs=(
            GraphSpec(3, (), (1.0, 1.0, 1.0)),
            GraphSpec(3, ((0, 1), (0, 2)), (1.0, 0.0, 0.0)),
            GraphSpec(3, ((0, 2), (1, 2)), (1.0, 1.0, 0.0)),
            GraphSpec(3, ((0, 1), (1, 2)), (0.0, 0.0, 1.0)),
        ),
        dwell_ticks=dwell_ticks,
    )
