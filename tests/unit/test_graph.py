"""topology.graph: range adjacency, Laplacian facts, connectivity, Chen's Hₚ and schedules."""

from __future__ import annotations

import numpy as np
import pytest

from topology.graph import (
    GraphSpec, PeriodicSchedule, algebraic_connectivity, chen_example_schedule, components,
    degrees, edge_weights, h_matrix, is_connected, lambda0, laplacian, max_degree,
    neighbour_lists, range_adjacency, target_connected,
)


def _path(n: int) -> np.ndarray:
    a = np.zeros((n, n))
    for i in range(n - 1):
        a[i, i + 1] = a[i + 1, i] = 1.0
    return a


def test_range_adjacency_boundary_is_an_edge():
    pos = np.array([[0.0, 0.0], [3.0, 4.0], [10.0, 0.0]])   # |p0 - p1| = 5 exactly
    adj = range_adjacency(pos, 5.0)
    assert adj[0, 1] == adj[1, 0] == 1.0
    assert adj[0, 2] == 0.0 and adj[1, 2] == 0.0
    assert np.all(np.diag(adj) == 0.0)
    assert np.array_equal(adj, adj.T)
    assert range_adjacency(pos, 5.0 - 1e-9)[0, 1] == 0.0
    assert range_adjacency(pos, 10.0)[0, 2] == 1.0


def test_range_adjacency_dead_node_has_no_edges():
    pos = np.zeros((4, 3))                                   # all co-located: complete graph
    adj = range_adjacency(pos, 1.0, alive=[True, False, True, True])
    assert adj[1].sum() == 0 and adj[:, 1].sum() == 0
    assert adj[0, 2] == adj[2, 3] == adj[0, 3] == 1.0
    with pytest.raises(ValueError):
        range_adjacency(pos, 1.0, alive=[True, False])
    with pytest.raises(ValueError):
        range_adjacency(pos, -1.0)


def test_laplacian_degrees_and_neighbour_lists():
    adj = np.array([[0, 2.0, 0, 0.5],
                    [2.0, 0, 1.0, 0],
                    [0, 1.0, 0, 0],
                    [0.5, 0, 0, 0]])
    L = laplacian(adj)
    assert np.allclose(L.sum(axis=1), 0.0)
    assert np.allclose(L, L.T)
    assert np.allclose(np.diag(L), [2.5, 3.0, 1.0, 0.5])
    assert np.allclose(degrees(adj), [2.5, 3.0, 1.0, 0.5])
    assert max_degree(adj) == 2
    assert neighbour_lists(adj) == [[1, 3], [0, 2], [1], [0]]
    assert edge_weights(adj) == [[2.0, 0.5], [2.0, 1.0], [1.0], [0.5]]
    assert np.all(np.linalg.eigvalsh(L) > -1e-12)


def test_components_and_connectivity():
    adj = np.zeros((5, 5))
    adj[0, 3] = adj[3, 0] = 1
    adj[1, 2] = adj[2, 1] = 1
    assert components(adj) == [[0, 3], [1, 2], [4]]
    assert not is_connected(adj)
    assert is_connected(_path(6))
    assert is_connected(np.zeros((1, 1)))
    assert components(_path(4)) == [[0, 1, 2, 3]]


@pytest.mark.parametrize("n", [2, 3, 5, 8])
def test_algebraic_connectivity_closed_forms(n):
    assert algebraic_connectivity(_path(n)) == pytest.approx(2 - 2 * np.cos(np.pi / n), abs=1e-12)
    complete = np.ones((n, n)) - np.eye(n)
    assert algebraic_connectivity(complete) == pytest.approx(float(n), abs=1e-12)


def test_algebraic_connectivity_degenerate():
    assert algebraic_connectivity(np.zeros((1, 1))) == 0.0
    assert algebraic_connectivity(np.zeros((3, 3))) == 0.0
    two_pairs = np.kron(np.eye(2), np.array([[0, 1.0], [1.0, 0]]))
    assert algebraic_connectivity(two_pairs) == 0.0


def test_h_matrix_and_target_connected():
    adj = _path(3)
    b = [0.0, 0.0, 2.0]
    H = h_matrix(adj, b)
    assert np.allclose(H, laplacian(adj) + np.diag(b))
    assert target_connected(adj, b)
    assert np.linalg.eigvalsh(H).min() > 0                  # Lemma 2.1 for one graph
    split = np.zeros((3, 3))
    split[0, 1] = split[1, 0] = 1
    assert not target_connected(split, [0, 0, 1])           # component {0, 1} never sees it
    assert lambda0([h_matrix(split, [0, 0, 1])]) == 0.0     # snapped to exactly 0
    assert target_connected(split, [0, 1, 1])
    with pytest.raises(ValueError):
        h_matrix(adj, [1.0, 1.0])


def test_graphspec_validation_and_matrices():
    g = GraphSpec(3, ((0, 1), (1, 2)), (0.0, 0.0, 1.0), weights=(2.0, 0.5))
    a = g.adjacency()
    assert a[0, 1] == a[1, 0] == 2.0 and a[1, 2] == a[2, 1] == 0.5 and a[0, 2] == 0
    assert np.allclose(g.H(), laplacian(a) + np.diag([0, 0, 1.0]))
    assert g.neighbour_lists() == [[1], [0, 2], [1]]
    assert g.target_connected()
    for bad in [dict(n=3, edges=((0, 3),), b=(1, 1, 1)),
                dict(n=3, edges=((1, 1),), b=(1, 1, 1)),
                dict(n=3, edges=((0, 1), (1, 0)), b=(1, 1, 1)),
                dict(n=3, edges=(), b=(1, 1)),
                dict(n=3, edges=(), b=(1, -1, 1)),
                dict(n=3, edges=((0, 1),), b=(1, 1, 1), weights=(1.0, 2.0)),
                dict(n=3, edges=((0, 1),), b=(1, 1, 1), weights=(0.0,)),
                dict(n=0, edges=(), b=())]:
        with pytest.raises(ValueError):
            GraphSpec(**bad)


def test_schedule_cycles_with_dwell():
    gs = tuple(GraphSpec(2, (), (float(i + 1), 0.0)) for i in range(4))
    s = PeriodicSchedule(gs, dwell_ticks=3)
    idx = [s.index_at(k) for k in range(14)]
    assert idx == [0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3, 0, 0]
    assert s.at(4) is gs[1]
    assert s.period_ticks == 12 and s.n == 2
    assert len(s.H_list()) == 4
    with pytest.raises(ValueError):
        s.at(-1)
    with pytest.raises(ValueError):
        PeriodicSchedule(gs, dwell_ticks=0)
    with pytest.raises(ValueError):
        PeriodicSchedule((gs[0], GraphSpec(3, (), (1, 1, 1))), dwell_ticks=1)
    with pytest.raises(ValueError):
        PeriodicSchedule((), dwell_ticks=1)


def test_chen_example_schedule():
    s = chen_example_schedule()
    assert s.dwell_ticks == 10 and len(s.graphs) == 4 and s.n == 3
    assert s.at(0).edges == () and s.at(0).b == (1.0, 1.0, 1.0)
    assert s.at(10).b == (1.0, 0.0, 0.0) and s.at(10).neighbour_lists() == [[1, 2], [0], [0]]
    assert s.at(25).b == (1.0, 1.0, 0.0) and s.at(25).neighbour_lists() == [[2], [2], [0, 1]]
    assert s.at(39).b == (0.0, 0.0, 1.0) and s.at(39).neighbour_lists() == [[1], [0, 2], [1]]
    assert s.at(40) is s.graphs[0]
    assert s.ever_sees_target() and s.all_target_connected()
    # λ₀ is G4's smallest eigenvalue: H = tridiag path with b on the end node = 2 − 2cos(π/7)
    assert s.lambda0() == pytest.approx(0.19806, abs=1e-5)
    assert lambda0(s.H_list()) == pytest.approx(2 - 2 * np.cos(np.pi / 7), abs=1e-12)
    assert chen_example_schedule(1).at(3) == chen_example_schedule(1).graphs[3]


def test_schedule_that_never_sees_the_target():
    blind = PeriodicSchedule((GraphSpec(3, ((0, 1), (1, 2)), (0, 0, 0)),
                              GraphSpec(3, (), (0, 0, 0))), dwell_ticks=5)
    assert not blind.ever_sees_target()
    assert not blind.all_target_connected()
    assert blind.lambda0() == 0.0
    partly = PeriodicSchedule((GraphSpec(3, ((0, 1),), (1, 0, 0)),
                               GraphSpec(3, (), (1, 1, 1))), dwell_ticks=1)
    assert partly.ever_sees_target() and not partly.all_target_connected()   # node 2 alone, b = 0
