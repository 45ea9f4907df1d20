"""The Foxglove views of a run's messages (flocktrack/record/foxglove.py), message by message: what each
message adds, when a tick's estimates and metrics are written, the log's levels and words, the ellipse."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from agent import wire
from agent.scenario import parse_scenario
from flocktrack.record.foxglove import LAG_TICKS, FoxgloveViews, ellipse_axes, log_line

from conftest import ROOT


@pytest.fixture
def views():
    sc = parse_scenario(tomllib.loads((ROOT / "scenarios" / "demo.toml").read_text()), "demo.toml")
    return FoxgloveViews(sc), sc


def _tick(sc, k: int) -> wire.Tick:
    n = sc.sensors.n
    links = [[j for j in (i - 1, i + 1) if 0 <= j < n] for i in range(n)]
    return wire.Tick(k=k, t=k * sc.run.T, n=n, links=links, weights=[[1.0] * len(nb) for nb in links], b=[1.0] * n,
                     alive=[True] * n, positions=np.column_stack([np.arange(n, dtype=float) + 0.1 * k, np.zeros(n)]))


def test_a_tick_draws_the_flock_at_once_and_its_estimates_and_metrics_two_ticks_later(views):
    v, sc = views
    T = round(sc.run.T * 1e9)
    topics = []
    for k in range(5):
        topics.append([t for t, _m, _ns in v.of("world/tick", _tick(sc, k), k * T)])
        v.of("target/truth", wire.Truth(k=k, t=k * sc.run.T, x=np.array([1.0, 2.0, 0.0, 0.0])), k * T)
        for i in range(sc.sensors.n):
            v.of(f"agent/{i}/estimate", wire.Estimate(src=i, k=k, x=np.array([1.0, 2.0 + i * 0.01, 0.0, 0.0]),
                                                      x_next=np.zeros(4), P=np.eye(4) * 0.1), k * T)
    assert topics[0][:2] == ["/tf", "/scene/sensors"]                        # the frame once, first
    assert all(t.count("/tf") == 0 for t in topics[1:])
    assert all({"/scene/sensors", "/scene/links", "/scene/ranges"} <= set(t) for t in topics)
    # tick k's estimates, target and metrics come with tick k + LAG_TICKS
    assert "/scene/estimates" not in topics[LAG_TICKS - 1] and "/scene/estimates" in topics[LAG_TICKS]
    rest = v.finish()
    metrics = [m for t, m, _ns in rest if t == "/metrics"]
    assert [m["k"] for m in metrics] == list(range(5 - LAG_TICKS, 5))
    assert all(ns == m["k"] * T for (t, m, ns) in rest if t == "/metrics")
    last = metrics[-1]
    errs = [abs(0.01 * i) for i in range(sc.sensors.n)]
    assert math.isclose(last["rmse"], math.sqrt(np.mean(np.square(errs))), rel_tol=1e-9)
    assert last["links"] == sc.sensors.n - 1 and last["messages"] == 2 + sc.sensors.n
    assert v.finish() == []                                                  # nothing twice


def test_the_log_says_what_happened_with_a_level_to_match():
    C = wire.Control
    assert log_line("world/event", C(k=5, verb="fault", args={"id": 0, "kind": "crash", "phase": "start",
                                                               "agents": [2.0]}))[:2] == \
        ("Warning", "k=5: fault 0 crash start (agent/2)")
    assert log_line("world/event", C(k=9, verb="fault", args={"id": 0, "kind": "crash", "phase": "heal"}))[0] == "Info"
    assert log_line("launcher/event", C(k=6, verb="process", args={"event": "exit", "name": "agent/2", "rc": -9})) == \
        ("Error", "k=6: agent/2 crashed (exit -9)", "launcher")
    assert log_line("launcher/event", C(k=9, verb="process", args={"event": "spawn", "name": "agent/2",
                                                                    "rejoin": True}))[:2] == \
        ("Warning", "k=9: agent/2 restarted, rejoining")
    assert log_line("world/event", C(k=3, verb="late", args={"missing": 2, "agents": [1.0, 4.0]}))[:2] == \
        ("Warning", "k=3: tick closed without the states of 2 sensors (agent/1, agent/4)")
    assert log_line("control/pause", C(k=4, verb="pause"))[:2] == ("Info", "k=4: pause")
    assert log_line("world/end", wire.End(k=100, reason="done"))[:2] == ("Info", "run over after 100 ticks (done)")


def test_the_ellipse_is_two_sigma_along_the_principal_axes():
    a, b, yaw = ellipse_axes(np.diag([4.0, 1.0]))
    assert (a, b) == pytest.approx((8.0, 4.0)) and math.sin(yaw) == pytest.approx(0.0, abs=1e-12)
    R = np.array([[math.cos(0.5), -math.sin(0.5)], [math.sin(0.5), math.cos(0.5)]])
    a, b, yaw = ellipse_axes(R @ np.diag([9.0, 0.25]) @ R.T)
    assert (a, b) == pytest.approx((12.0, 2.0)) and math.tan(yaw) == pytest.approx(math.tan(0.5))
    assert ellipse_axes(np.array([[1.0, 0.0], [0.0, -1.0]])) is None
    assert ellipse_axes(np.array([[np.nan, 0.0], [0.0, 1.0]])) is None


def test_the_ellipse_agrees_with_numpys_eigendecomposition():
    rng = np.random.default_rng(7)
    for _ in range(200):
        A = rng.normal(size=(2, 2)) * rng.uniform(0.01, 100)
        P = A @ A.T + 1e-6 * np.eye(2)
        w, V = np.linalg.eigh(P)
        a, b, yaw = ellipse_axes(P)
        assert (a, b) == pytest.approx((4 * math.sqrt(w[1]), 4 * math.sqrt(w[0])), rel=1e-7, abs=1e-9)
        assert abs(np.array([math.cos(yaw), math.sin(yaw)]) @ V[:, 1]) == pytest.approx(1.0)   # the major axis


def test_a_long_run_keeps_only_the_ticks_still_open(views):
    """What the views keep by tick is let go once the tick's views are written — and a message that comes
    after that (late) is not kept again: the recorder's memory does not grow with the run."""
    v, sc = views
    T = round(sc.run.T * 1e9)
    for k in range(300):
        v.of("world/tick", _tick(sc, k), k * T)
        v.of("target/truth", wire.Truth(k=k, t=k * sc.run.T, x=np.array([1.0, 2.0, 0.0, 0.0])), k * T)
        v.of("agent/0/estimate", wire.Estimate(src=0, k=k, x=np.zeros(4), x_next=np.zeros(4)), k * T)
        if k >= 10:   # an estimate of a tick whose views are written long ago
            v.of("agent/1/estimate", wire.Estimate(src=1, k=k - 10, x=np.zeros(4), x_next=np.zeros(4)), k * T)
    assert len(v._t_ns) <= LAG_TICKS + 1 and len(v._count) <= LAG_TICKS + 1 and len(v._pending) <= LAG_TICKS + 1
