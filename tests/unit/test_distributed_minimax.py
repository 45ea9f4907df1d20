"""Distributed minimax / Kalman filter (Gu & Hu (18a), (18b) and update), driven by hand on fixed graphs."""

import numpy as np
import pytest

from agent.estimators.base import TickContext
from agent.estimators.distributed_minimax import DistributedKalman, DistributedMinimax
from agent.estimators.minimax import CentralizedMinimax
from agent.models import IntelligentTarget, LinearSensor, LinearTarget, double_integrator

N = 10
T = 0.04
C = np.hstack([np.eye(2), np.zeros((2, 2))])
R = 0.04 * np.eye(2)
S = 0.09 * np.eye(2)
X0_TARGET = np.array([0.0, 0.0, 1.0, 0.5])
A, B = double_integrator(T)
Q = B @ (0.01 * np.eye(2)) @ B.T


# --- tiny local graph helpers (the topology package is not imported here on purpose) ------------
def ring(n):
    adj = np.zeros((n, n), bool)
    for i in range(n):
        adj[i, (i + 1) % n] = adj[(i + 1) % n, i] = True
    return adj


def path(n):
    adj = np.zeros((n, n), bool)
    for i in range(n - 1):
        adj[i, i + 1] = adj[i + 1, i] = True
    return adj


def connected(adj):
    seen, todo = {0}, [0]
    while todo:
        i = todo.pop()
        for j in np.flatnonzero(adj[i]):
            if j not in seen:
                seen.add(int(j))
                todo.append(int(j))
    return len(seen) == adj.shape[0]


def random_geometric(n, radius, seed):
    rng = np.random.default_rng(seed)
    while True:
        pts = rng.uniform(0.0, 1.0, size=(n, 2))
        d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
        adj = (d <= radius) & ~np.eye(n, dtype=bool)
        if connected(adj) and not adj[~np.eye(n, dtype=bool)].all():
            return adj


GRAPHS = {"ring": ring(N), "path": path(N), "rgg": random_geometric(N, 0.45, 3)}


def contexts(adj, k, b=None):
    dmax = int(adj.sum(axis=1).max())
    b = np.ones(adj.shape[0]) if b is None else b
    return [TickContext(k=k, t=k * T, n=adj.shape[0], neighbours=tuple(int(j) for j in np.flatnonzero(adj[i])),
                        weights=tuple(1.0 for _ in np.flatnonzero(adj[i])), b=float(b[i]), delta_max=dmax, T=T)
            for i in range(adj.shape[0])]


def tick(nodes, adj, ys, k, b=None, drop=None):
    """One tick of the exchange protocol; ``drop(r, i, j)`` True drops j's payload to i."""
    ctxs = contexts(adj, k, b)
    for node, ctx, y in zip(nodes, ctxs, ys):
        node.start(ctx, y)
    for r in range(nodes[0].rounds):
        pl = [node.payload(r) for node in nodes]
        for i, (node, ctx) in enumerate(zip(nodes, ctxs)):
            node.absorb(r, {j: pl[j] for j in ctx.neighbours if drop is None or not drop(r, i, j)})
    for node in nodes:
        node.finish()


def make_nodes(rounds, S_=S, cls=DistributedMinimax):
    if cls is DistributedKalman:
        return [DistributedKalman(A, Q, C, R, N, np.zeros(4), np.eye(4), rounds) for _ in range(N)]
    return [cls(A, Q, C, R, S_, N, np.zeros(4), np.eye(4), rounds) for _ in range(N)]


def run_normal(adj, rounds, steps=150, seed=0, S_=S):
    """Normal target (1); returns (mean − centralized, max node deviation, P mismatch) per step."""
    rng = np.random.default_rng(seed)
    nodes = make_nodes(rounds, S_)
    central = CentralizedMinimax(A, Q, [C] * N, [R] * N, S_, np.zeros(4), np.eye(4))
    tgt = LinearTarget(A, B, 0.01 * np.eye(2), X0_TARGET, rng)
    sensor = LinearSensor(C, R)
    mean_err, dev, p_err = [], [], []
    for k in range(steps):
        ys = [sensor.measure(tgt.x, 1.0, rng) for _ in range(N)]
        tick(nodes, adj, ys, k)
        central.step(ys)
        tgt.step()
        xs = np.array([nd.x for nd in nodes])
        mean_err.append(np.abs(xs.mean(axis=0) - central.x).max())
        dev.append(np.linalg.norm(xs - central.x, axis=1).max())
        p_err.append(max(np.abs(nd.P - central.P).max() for nd in nodes))
    return np.array(mean_err), np.array(dev), np.array(p_err)


@pytest.mark.parametrize("graph", sorted(GRAPHS))
@pytest.mark.parametrize("rounds", [0, 1, 3, 10])
@pytest.mark.parametrize("S_", [S, None], ids=["minimax", "kalman"])
def test_mean_of_nodes_equals_centralized(graph, rounds, S_):
    mean_err, _, p_err = run_normal(GRAPHS[graph], rounds, steps=25, S_=S_)
    assert mean_err.max() < 1e-9
    assert p_err.max() < 1e-12       # χ¹, χ³ identical at every node → P, Σ are the centralized ones


@pytest.mark.parametrize("graph", sorted(GRAPHS))
def test_deviation_from_centralized_shrinks_with_rounds(graph):
    devs = [run_normal(GRAPHS[graph], r, steps=30)[1] for r in (1, 3, 10, 30)]
    peak = [d.max() for d in devs]                                    # worst node, worst step
    rms = [float(np.sqrt(np.mean(d[10:] ** 2))) for d in devs]        # after the P₀ = I transient
    for metric in (peak, rms):
        assert all(a > b for a, b in zip(metric, metric[1:])), metric
        assert metric[-1] < 0.3 * metric[0], metric


def run_intelligent(cls, rounds, steps=2000, seed=0, adj=None):
    adj = ring(N) if adj is None else adj
    rng = np.random.default_rng(seed)
    nodes = make_nodes(rounds, cls=cls)
    tgt = IntelligentTarget(A, 0.04, X0_TARGET)
    sensor = LinearSensor(C, R)
    err = np.empty(steps)
    for k in range(steps):
        x_hat = np.mean([nd.x for nd in nodes], axis=0)        # target reads the mean estimate
        err[k] = np.linalg.norm(tgt.x[:2] - x_hat[:2])
        tick(nodes, adj, [sensor.measure(tgt.x, 1.0, rng) for _ in range(N)], k)
        tgt.step(x_hat)
    return err


def test_intelligent_target_distributed_kalman_diverges_minimax_bounded():
    ek = run_intelligent(DistributedKalman, rounds=1, steps=1500)
    em = run_intelligent(DistributedMinimax, rounds=1, steps=1500)
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))
    assert rms(ek[-200:]) > 100 * rms(ek[:200])
    assert em.max() < 1.0


def test_dropped_payload_does_not_crash():
    adj = GRAPHS["rgg"]
    rng = np.random.default_rng(4)
    nodes = make_nodes(3)
    sensor = LinearSensor(C, R)
    x = X0_TARGET.copy()
    for k in range(30):
        ys = [sensor.measure(x, 1.0, rng) for _ in range(N)]
        tick(nodes, adj, ys, k, drop=lambda r, i, j, k=k: (r + i + j + k) % 4 == 0)
        x = A @ x
    assert all(np.all(np.isfinite(nd.x)) for nd in nodes)
    assert all(nd.dropped > 0 for nd in nodes if adj[nodes.index(nd)].sum() > 0)
    assert max(np.linalg.norm(nd.x[:2] - x[:2]) for nd in nodes) < 0.5


def _absorb_once(inbox_mod):
    adj = ring(N)
    ctx = contexts(adj, 0)
    rng = np.random.default_rng(5)
    ys = [rng.normal(size=2) for _ in range(N)]
    nodes = make_nodes(1)
    for nd, c, y in zip(nodes, ctx, ys):
        nd.start(c, y)
    pl = {j: nodes[j].payload(0) for j in ctx[0].neighbours}
    nodes[0].absorb(0, inbox_mod(pl))
    return nodes[0].chi


@pytest.mark.parametrize("bad", ["shape", "nan", "missing_key", "inf"])
def test_malformed_payload_is_ignored(bad):
    j_bad = 1                                                   # a neighbour of 0 on the ring

    def corrupt(pl):
        pl = {j: dict(p) for j, p in pl.items()}
        if bad == "shape":
            pl[j_bad]["chi1"] = np.zeros((3, 3))
        elif bad == "nan":
            pl[j_bad]["chi2"] = np.array([np.nan, 0.0, 0.0, 0.0])
        elif bad == "inf":
            pl[j_bad]["chi3"] = np.full((4, 4), np.inf)
        else:
            del pl[j_bad]["chi2"]
        return pl

    got = _absorb_once(corrupt)
    ref = _absorb_once(lambda pl: {j: p for j, p in pl.items() if j != j_bad})
    for key in ("chi1", "chi2", "chi3"):
        np.testing.assert_array_equal(got[key], ref[key])
        assert np.all(np.isfinite(got[key]))


def test_non_neighbour_payload_is_ignored():
    ref = _absorb_once(lambda pl: pl)
    got = _absorb_once(lambda pl: {**pl, 5: {"chi1": np.eye(4), "chi2": np.ones(4), "chi3": np.eye(4)}})
    for key in ("chi1", "chi2", "chi3"):
        np.testing.assert_array_equal(got[key], ref[key])


def test_visibility_weights_many_rounds_approach_centralized():
    """b_i = 0 at some nodes: with many rounds each node approaches the centralized filter with b."""
    adj = GRAPHS["rgg"]
    b = np.ones(N)
    b[[2, 7]] = 0.0
    b[4] = 0.5
    rng = np.random.default_rng(6)
    nodes = make_nodes(150)
    central = CentralizedMinimax(A, Q, [C] * N, [R] * N, S, np.zeros(4), np.eye(4))
    sensor = LinearSensor(C, R)
    x = X0_TARGET.copy()
    for k in range(8):
        ys = [sensor.measure(x, bi, rng) for bi in b]
        tick(nodes, adj, ys, k, b=b)
        central.step(ys, b)
        x = A @ x
    for nd in nodes:
        np.testing.assert_allclose(nd.x, central.x, rtol=0, atol=1e-6)
        np.testing.assert_allclose(nd.P, central.P, rtol=0, atol=1e-7)


def test_payload_shapes_and_set_x():
    nd = make_nodes(2)[0]
    assert nd.payload_shapes() == {"chi1": (4, 4), "chi2": (4,), "chi3": (4, 4)}
    nd.reinitialise({3: np.ones(4), 1: 3 * np.ones(4)})
    np.testing.assert_array_equal(nd.x, 2 * np.ones(4))
    with pytest.raises(RuntimeError):
        nd.payload(0)
    nd.start(contexts(ring(N), 0)[0], np.zeros(2))
    p = nd.payload(0)
    assert {k: v.shape for k, v in p.items()} == nd.payload_shapes()
    p["chi2"][:] = 99.0                                         # a payload is a copy
    assert not np.any(nd.chi["chi2"] == 99.0)
