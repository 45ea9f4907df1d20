"""Flocking controller (Gu & Hu (20) plus velocity damping) with double-integrator sensors (19)."""

import numpy as np
import pytest

from agent.control.flocking import FlockingController, jittered_grid
from agent.models import double_integrator, integrate_double_integrator

T = 0.04
E = 12.0
N = 10
REF = dict(kc=1.0, kr=30.0, kd=2.0, h1=100.0, h2=220.0)
V_TARGET = np.array([1.0, 0.5])


def connected(adj):
    seen, todo = {0}, [0]
    while todo:
        i = todo.pop()
        for j in np.flatnonzero(adj[i]):
            if j not in seen:
                seen.add(int(j))
                todo.append(int(j))
    return len(seen) == adj.shape[0]


def simulate(kd, seed, steps=2000):
    """10 sensors from a jittered 2×5 grid (spacing 8) follow a constant-velocity target, using the
    true target position / velocity as the estimate; neighbours are those within range E."""
    rng = np.random.default_rng(seed)
    ctrl = FlockingController(**{**REF, "kd": kd})
    q = jittered_grid(N, rows=2, spacing=8.0, jitter=1.0, rng=rng, origin=(0.0, 0.0))
    p = np.zeros_like(q)
    target = np.zeros(2)
    off = ~np.eye(N, dtype=bool)
    out = dict(connected=[], min_dist=[], centroid_err=[], rel_kinetic=[], max_degree=[])
    for _ in range(steps):
        d = np.linalg.norm(q[:, None] - q[None], axis=2)
        adj = (d <= E) & off
        out["connected"].append(connected(adj))
        out["min_dist"].append(d[off].min())
        out["max_degree"].append(adj.sum(axis=1).max())
        u = np.array([ctrl.control(q[i], p[i], target, V_TARGET, q[adj[i]]) for i in range(N)])
        q, p = integrate_double_integrator(q, p, u, T)
        target = target + T * V_TARGET
        out["centroid_err"].append(np.linalg.norm(q.mean(axis=0) - target))
        out["rel_kinetic"].append(0.5 * np.sum((p - V_TARGET) ** 2))
    return {k: np.array(v) for k, v in out.items()}


@pytest.mark.parametrize("seed", [0, 1])
def test_flock_follows_target_connected_without_collisions(seed):
    r = simulate(kd=2.0, seed=seed)
    assert r["connected"].all()                  # the range-E graph stays connected at every step
    assert r["min_dist"].min() > 3.0             # measured ≈ 3.97 (seed 0), 4.06 (seed 1)
    assert r["max_degree"][-1] < N - 1           # not a complete graph: consensus is not trivial
    assert r["centroid_err"][-1] < 0.5           # the flock is centred on the target
    assert r["rel_kinetic"][-200:].max() < 1e-3  # and moves with it


@pytest.mark.parametrize("seed", [0, 1])
def test_printed_law_without_damping_misbehaves(seed):
    """(20) as printed (k_d = 0): the oscillation about the target grows instead of settling, the
    flock breaks up (graph disconnects) and sensors nearly collide -- why the damping was added."""
    r = simulate(kd=0.0, seed=seed)
    ke = r["rel_kinetic"]
    assert ke[-200:].mean() > 5 * ke[:200].mean()                       # energy grows (≈ 15×)
    # the centroid is an undamped ZOH oscillator (pair terms cancel): amplitude × (1 + k_c T²/2)^(k/2),
    # ≈ 1.82 over the 1500 steps between the first and the last 500-step windows
    assert r["centroid_err"][-500:].max() > 1.5 * r["centroid_err"][:500].max()
    assert not r["connected"].all()
    assert r["min_dist"].min() < 1.0


def test_zoh_undamped_oscillator_is_unstable():
    """Single sensor, target at rest at 0: z⁺ = (A − B K) z with K = [k_c I, k_d I].
    det = 1 + k_c T²/2 − k_d T: > 1 (unstable) for k_d = 0, < 1 for k_d = 2."""
    A, B = double_integrator(T)
    for kd, unstable in ((0.0, True), (2.0, False)):
        K = np.hstack([REF["kc"] * np.eye(2), kd * np.eye(2)])
        M = A - B @ K
        rho = np.abs(np.linalg.eigvals(M)).max()
        assert (rho > 1.0) == unstable
        np.testing.assert_allclose(np.linalg.det(M[[0, 2]][:, [0, 2]]), 1 + REF["kc"] * T * T / 2 - kd * T)


def test_separation_force_profile():
    ctrl = FlockingController(**REF)
    d_star = ctrl.equilibrium_distance()
    assert d_star == pytest.approx(np.log(100 * 60 / (220 * 20)) / (1 / 20 - 1 / 60))
    assert 9.0 < d_star < 9.5
    assert abs(ctrl.separation_force(d_star)) < 1e-12
    assert ctrl.separation_force(2.0) > 0 and ctrl.separation_force(20.0) < 0   # repel / attract
    # force = −dH_s/dd, checked by finite differences
    for d in (1.0, 5.0, 15.0):
        fd = -(ctrl.separation_potential(d + 1e-6) - ctrl.separation_potential(d - 1e-6)) / 2e-6
        assert ctrl.separation_force(d) == pytest.approx(fd, rel=1e-6)


def test_control_terms():
    ctrl = FlockingController(**REF)
    q, p = np.array([1.0, 2.0]), np.array([0.5, 0.0])
    # no neighbours: pure cohesion + damping
    u = ctrl.control(q, p, np.zeros(2), np.array([1.0, 0.0]), [])
    np.testing.assert_allclose(u, -1.0 * q - 2.0 * (p - np.array([1.0, 0.0])))
    # one neighbour at the equilibrium distance adds nothing
    nb = q + ctrl.equilibrium_distance() * np.array([0.6, 0.8])
    np.testing.assert_allclose(ctrl.control(q, p, np.zeros(2), np.array([1.0, 0.0]), [nb]), u, atol=1e-12)
    # a close neighbour pushes away along the line between them, with magnitude k_r·force
    nb = q + np.array([3.0, 0.0])
    u2 = ctrl.control(q, p, q, p, np.array([nb]))
    np.testing.assert_allclose(u2, [-30.0 * ctrl.separation_force(3.0), 0.0], atol=1e-12)
    # pairwise terms are antisymmetric, so they cancel in the flock's centroid
    a = ctrl.control(q, np.zeros(2), np.zeros(2), np.zeros(2), [nb]) + ctrl.kc * q
    b = ctrl.control(nb, np.zeros(2), np.zeros(2), np.zeros(2), [q]) + ctrl.kc * nb
    np.testing.assert_allclose(a + b, 0.0, atol=1e-12)
    # coincident neighbour: no NaN
    assert np.all(np.isfinite(ctrl.control(q, p, np.zeros(2), None, [q.copy()])))


def test_u_max_bounds_control():
    ctrl = FlockingController(**REF, u_max=2.0)
    u = ctrl.control(np.array([100.0, 0.0]), np.zeros(2), np.zeros(2), np.zeros(2), [])
    assert np.linalg.norm(u) == pytest.approx(2.0)
    np.testing.assert_allclose(u / np.linalg.norm(u), [-1.0, 0.0])


def test_jittered_grid():
    q0 = jittered_grid(10, rows=2, spacing=8.0, jitter=0.0, rng=np.random.default_rng(0), origin=(5.0, -3.0))
    assert q0.shape == (10, 2)
    np.testing.assert_allclose(q0.mean(axis=0), [5.0, -3.0])
    assert sorted(set(np.round(q0[:, 1], 9))) == [-7.0, 1.0]
    np.testing.assert_allclose(np.diff(q0[:5, 0]), 8.0)
    q1 = jittered_grid(10, rows=2, spacing=8.0, jitter=1.0, rng=np.random.default_rng(0), origin=(5.0, -3.0))
    assert np.abs(q1 - q0).max() <= 1.0 and np.abs(q1 - q0).max() > 0
    q2 = jittered_grid(10, rows=2, spacing=8.0, jitter=1.0, rng=np.random.default_rng(0), origin=(5.0, -3.0))
    np.testing.assert_array_equal(q1, q2)
