"""r-robustness of a link graph: whether W-MSR can tolerate f Byzantine neighbours on it.

LeBlanc, Zhang, Koutsoukos & Sundaram, "Resilient asymptotic consensus in robust networks" (IEEE JSAC 31(4),
2013): a subset S of the nodes is *r-reachable* if some node of S has at least r neighbours outside S, and the
graph is *r-robust* if of every two disjoint non-empty subsets at least one is r-reachable (Definition 6).
W-MSR with parameter f reaches consensus among the honest nodes under an f-total Byzantine model when the
graph is (2f + 1)-robust (Theorem 2 for the f-local malicious model, and the Byzantine variant of Vaidya et al.).

Deciding r-robustness is coNP-complete in general; for a flock of up to ``EXACT_MAX`` sensors this module
decides it exactly over every subset (2ⁿ of them, a bitmask sweep in numpy), and beyond that it gives what the
degrees alone say: a graph with a node of degree < r is not r-robust, and one with minimum degree
≥ ⌊n/2⌋ + r − 1 is (LeBlanc et al., Lemma 7), in between it is unknown (None).
"""

from __future__ import annotations

import numpy as np

EXACT_MAX = 16   #: largest flock decided exactly (2¹⁶ subsets)


def _masks(adj: np.ndarray) -> np.ndarray:
    """Each node's neighbours as a bitmask (int64)."""
    A = np.asarray(adj, bool)
    return (A.astype(np.int64) << np.arange(A.shape[0], dtype=np.int64)[None, :]).sum(axis=1)


def _popcount(x: np.ndarray) -> np.ndarray:
    c = np.zeros(x.shape, np.int64)
    for b in range(int(x.max()).bit_length() if x.size else 0):
        c += (x >> b) & 1
    return c


def _unreachable(adj: np.ndarray, r: int) -> np.ndarray:
    """Bool over the 2ⁿ subsets (bit i = node i): non-empty and not r-reachable (no node of S has r
    neighbours outside S)."""
    n = adj.shape[0]
    nb = _masks(adj)
    S = np.arange(1 << n, dtype=np.int64)
    reach = np.zeros(S.shape, bool)
    full = (1 << n) - 1
    for i in range(n):
        inside = ((S >> i) & 1).astype(bool)
        outside = _popcount(nb[i] & (full & ~S))
        reach |= inside & (outside >= r)
    bad = ~reach
    bad[0] = False
    return bad


def is_r_robust(adj: np.ndarray, r: int) -> bool | None:
    """Whether the graph of the symmetric 0/1 adjacency ``adj`` is r-robust (None: undecided, beyond
    ``EXACT_MAX`` nodes when the degrees do not settle it)."""
    A = np.asarray(adj, bool)
    n = A.shape[0]
    if r <= 0:
        return True
    if n == 0:
        return False
    deg = A.sum(axis=1)
    if deg.min() < r:
        return False
    if deg.min() >= n // 2 + r - 1:
        return True
    if n > EXACT_MAX:
        return None
    return _exactly_r_robust(A, r)


def _exactly_r_robust(A: np.ndarray, r: int) -> bool:
    """Definition 6 over every pair of disjoint subsets: no unreachable subset whose complement holds another."""
    n = A.shape[0]
    bad = _unreachable(A, r)
    # has[m]: some non-empty subset of m is unreachable (a sum over subsets, bit by bit)
    has = bad.copy()
    S = np.arange(1 << n, dtype=np.int64)
    for i in range(n):
        with_i = ((S >> i) & 1).astype(bool)
        has[with_i] |= has[S[with_i] ^ (1 << i)]
    full = (1 << n) - 1
    return not bool(np.any(has[full & ~S[bad]]))


def robustness(adj: np.ndarray) -> int | None:
    """The largest r for which the graph is r-robust (0 for a graph with an isolated node; at most ⌈n/2⌉,
    the complete graph's); None when undecided."""
    A = np.asarray(adj, bool)
    n = A.shape[0]
    if n == 0:
        return 0
    best = 0
    for r in range(1, (n + 1) // 2 + 1):
        ok = is_r_robust(A, r)
        if ok is None:
            return None
        if not ok:
            break
        best = r
    return best
