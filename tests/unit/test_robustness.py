"""r-robustness (topology/robustness.py) against Definition 6 read literally, over every pair of disjoint subsets."""

import itertools

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from topology.robustness import EXACT_MAX, is_r_robust, robustness


def _by_definition(A: np.ndarray, r: int) -> bool:
    n = len(A)

    def reachable(S):
        return any(sum(A[i][j] for j in range(n) if j not in S) >= r for i in S)

    for labels in itertools.product(range(3), repeat=n):
        s1 = {i for i in range(n) if labels[i] == 1}
        s2 = {i for i in range(n) if labels[i] == 2}
        if s1 and s2 and not reachable(s1) and not reachable(s2):
            return False
    return True


@st.composite
def graphs(draw):
    n = draw(st.integers(2, 7))
    bits = draw(st.lists(st.booleans(), min_size=n * (n - 1) // 2, max_size=n * (n - 1) // 2))
    A = np.zeros((n, n), bool)
    A[np.triu_indices(n, 1)] = bits
    return A | A.T


@settings(max_examples=150, deadline=None)
@given(graphs(), st.integers(1, 4))
def test_the_bitmask_sweep_agrees_with_the_definition(A, r):
    assert is_r_robust(A, r) == _by_definition(A.astype(int), r)


def test_known_graphs():
    assert robustness(~np.eye(10, dtype=bool)) == 5          # K_n is ⌈n/2⌉-robust
    ring = np.roll(np.eye(8, dtype=bool), 1, axis=1)
    assert robustness(ring | ring.T) == 1                   # a cycle: 1-robust, never 2
    A = np.zeros((4, 4), bool)
    A[0, 1] = A[1, 0] = True                                 # an isolated node
    assert robustness(A) == 0


def test_beyond_the_exact_size_the_degrees_decide_or_nothing_does():
    n = EXACT_MAX + 4
    assert is_r_robust(~np.eye(n, dtype=bool), 3) is True     # min degree ≥ ⌊n/2⌋ + r − 1
    ring = np.roll(np.eye(n, dtype=bool), 1, axis=1)
    assert is_r_robust(ring | ring.T, 3) is False           # a sensor with fewer than r neighbours
    band = sum(np.roll(np.eye(n, dtype=bool), s, axis=1) for s in (1, 2, 3, n - 1, n - 2, n - 3)).astype(bool)
    assert is_r_robust(band, 3) is None                     # degree 6: neither test settles it
