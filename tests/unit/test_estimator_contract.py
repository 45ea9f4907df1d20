"""Every registered estimator (and the toy of docs/adding_an_estimator.md) through the same contract: built
from a shipped scenario by its spec, it survives an empty inbox, NaN / huge / wrong-shape payloads and a
dropped round, re-initialises after a rejoin, and gives the same numbers twice. Adding the toy touches
no file of the runtime: the scenario loader, the CLI, the design and the metrics read its spec."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import toy_estimator
from agent.estimators import registry
from agent.estimators.base import Estimator, TickContext
from agent.scenario import ScenarioError, load_scenario
from flocktrack.engine.build import design
from flocktrack.cli import main

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = sorted((ROOT / "scenarios").glob("*.toml"))


@pytest.fixture(scope="module", autouse=True)
def toy_registered():
    registry.register(toy_estimator.SPEC)
    yield
    registry.unregister(toy_estimator.SPEC.name)


def _names() -> list[str]:
    return sorted({*registry.names(), toy_estimator.SPEC.name})


def _scenario_for(name: str):
    """The first shipped scenario (its own estimator first) that is valid with estimator ``name``."""
    for path in sorted(SHIPPED, key=lambda p: load_scenario(p).estimator.name != name):
        try:
            sc = load_scenario(path, **{"estimator.name": name, "run.ticks": 30})
        except ScenarioError:
            continue
        if sc.kind == "flock":
            return sc
    raise AssertionError(f"no shipped scenario runs estimator {name!r}")


_DESIGNS: dict[str, tuple] = {}


def _built(name: str, i: int = 0):
    if name not in _DESIGNS:
        sc = _scenario_for(name)
        _DESIGNS[name] = (sc, design(sc))
    sc, dsg = _DESIGNS[name]
    return sc, registry.make_estimator(sc, i, dsg)


def _ctx(sc, k: int, neighbours=(1, 2)) -> TickContext:
    return TickContext(k=k, t=k * sc.run.T, n=sc.sensors.n, neighbours=tuple(neighbours),
                       weights=(1.0,) * len(neighbours), b=1.0, delta_max=len(neighbours), T=sc.run.T)


def _tick(sc, est, k: int, y, inboxes) -> np.ndarray:
    """One tick: start, one absorb per round with ``inboxes(r)``, finish; the new estimate."""
    est.start(_ctx(sc, k), y)
    for r in range(est.rounds):
        est.payload(r)
        est.absorb(r, inboxes(r))
    est.finish()
    return np.array(est.x, float)


def _y(sc, k: int) -> np.ndarray:
    return np.random.default_rng(k).normal(size=sc.C_of(0).shape[0])


def _good_inbox(sc, name: str, k: int):
    """Neighbours 1 and 2's real round payloads at tick k (their own estimators, same measurements)."""
    nbrs = {j: _built(name, j)[1] for j in (1, 2)}
    for j, e in nbrs.items():
        e.start(_ctx(sc, k, neighbours=(0,)), _y(sc, k) + j)
    return {j: e.payload(0) for j, e in nbrs.items()}


@pytest.mark.parametrize("name", _names())
def test_empty_inbox_and_determinism(name):
    sc, a = _built(name)
    _, b = _built(name)
    xa = [_tick(sc, a, k, _y(sc, k), lambda r: {}) for k in range(5)]
    xb = [_tick(sc, b, k, _y(sc, k), lambda r: {}) for k in range(5)]
    assert all(np.isfinite(x).all() for x in xa)
    assert all(np.array_equal(p, q) for p, q in zip(xa, xb))   # bit for bit


@pytest.mark.parametrize("name", _names())
def test_malformed_payloads_are_dropped_links(name):
    sc, ref = _built(name)
    good = _good_inbox(sc, name, 0)
    x_dropped = _tick(sc, ref, 0, _y(sc, 0), lambda r: {})
    for bad in ("nan", "wrong_shape", "missing_key", "not_an_array"):
        _, est = _built(name)
        poisoned = {}
        for j, p in good.items():
            key = next(iter(p))
            q = dict(p)
            if bad == "nan":
                q[key] = np.full_like(p[key], np.nan)
            elif bad == "wrong_shape":
                q[key] = np.zeros(np.size(p[key]) + 1)
            elif bad == "missing_key":
                q.pop(key)
            else:
                q[key] = "x"
            poisoned[j] = q
        x = _tick(sc, est, 0, _y(sc, 0), lambda r, p=poisoned: p)
        np.testing.assert_array_equal(x, x_dropped, err_msg=f"{name}: a {bad} payload is not a dropped link")


@pytest.mark.parametrize("name", _names())
def test_huge_payloads_and_a_dropped_round_leave_a_finite_estimate(name):
    sc, est = _built(name)
    good = _good_inbox(sc, name, 0)
    huge = {j: {k: v * 1e6 for k, v in p.items()} for j, p in good.items()}
    x = _tick(sc, est, 0, _y(sc, 0), lambda r: huge)
    assert np.isfinite(x).all()
    _, est2 = _built(name)
    x = _tick(sc, est2, 0, _y(sc, 0), lambda r: good if r == 0 else {})   # later rounds dropped
    assert np.isfinite(x).all()


@pytest.mark.parametrize("name", _names())
def test_reinitialise_after_rejoin_takes_the_neighbours_mean(name):
    sc, est = _built(name)
    m = sc.m
    nb = {1: np.arange(m, dtype=float), 2: np.arange(m, dtype=float) + 2.0}
    est.reinitialise(nb, {j: np.eye(m) * (j + 1) for j in nb} if est.P is not None else None)
    np.testing.assert_allclose(est.x, np.arange(m) + 1.0)
    if type(est)._set_P is not Estimator._set_P:   # an estimator whose P is a covariance adopts theirs
        np.testing.assert_allclose(est.P, np.eye(m) * 2.5)
    assert np.isfinite(_tick(sc, est, 0, _y(sc, 0), lambda r: {})).all()


def test_the_toy_runs_through_the_cli_with_its_own_key(tmp_path, capsys):
    """Registered, the toy is a choice of --estimator, its key is part of the [estimator] schema (with the
    same precise errors), and a run scores it."""
    scen = str(ROOT / "scenarios" / "gu_hu_normal.toml")
    out = tmp_path / "toy"
    assert main(["run", scen, "--transport", "inproc", "--ticks", "60", "--estimator", "toy_average",
                 "--set", "estimator.gain=0.3", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["estimator"] == "toy_average" and np.isfinite(s["network_rmse"])
    assert main(["run", scen, "--transport", "inproc", "--ticks", "5", "--estimator", "toy_average",
                 "--set", "estimator.gain=3", "--out", str(tmp_path / "bad")]) == 2
    assert "[estimator.gain] must be in (0, 1], got 3.0" in capsys.readouterr().err
    with pytest.raises(ScenarioError, match=r"estimator\.gian.*did you mean `gain`"):
        load_scenario(scen, **{"estimator.name": "toy_average", "estimator.gian": 0.3})


# ============================================================================= the fusion role's estimators

def _fusion_records(n: int = 60):
    from agent.models_uav import UavRelativeSim

    stream = UavRelativeSim().generate(3.0, np.random.default_rng(7))
    return [stream.record(int(i)) for i in stream.arrival_order()[:n]]


def _fusion_built(name: str):
    from agent.estimators.registry import build_fusion

    return build_fusion({"estimator": name}, "contract.toml")[1]


@pytest.mark.parametrize("name", sorted(registry.fusion_specs()))
def test_every_fusion_estimator_streams_deterministically_and_survives_hostile_measurements(name):
    """Each ``[fusion] estimator`` from its spec's defaults: finite estimates over a real stream, bit for bit
    the same twice; a malformed measurement is refused where it is made (never reaches the window); a
    gross outlier and a measurement too late for the window leave the estimate finite; an empty window
    says so instead of returning numbers."""
    from agent.estimators.relative_measurement import RelativeMeasurement

    recs = _fusion_records()
    runs = []
    for _ in range(2):
        est = _fusion_built(name)
        with pytest.raises(RuntimeError):
            est.solve()                                   # nothing to estimate from yet
        runs.append([est.update(r).newest.copy() for r in recs])
    assert all(np.isfinite(x).all() for x in runs[0])
    assert all(np.array_equal(a, b) for a, b in zip(*runs))
    for bad in (dict(z=[np.nan, 0.0]), dict(z=[1.0, 2.0, 3.0]), dict(R=[[1.0, 0.0], [0.0, -1.0]]),
                dict(gps=None)):
        kw = dict(agent=1, t=recs[-1].t, z=[1.0, 2.0], R=np.eye(2), gps=[0.0, 0.0], gps_R=np.eye(2)) | bad
        with pytest.raises(ValueError):
            RelativeMeasurement(**kw)
    last = recs[-1]
    huge = RelativeMeasurement(agent=last.agent, t=last.t + 0.01, z=last.z + 1e6, R=last.R, gps=last.gps,
                               gps_R=last.gps_R)
    late = RelativeMeasurement(agent=last.agent, t=recs[0].t - 10.0, z=last.z, R=last.R, gps=last.gps,
                               gps_R=last.gps_R)
    for r in (huge, late):
        assert np.isfinite(est.update(r).newest).all()


@pytest.mark.parametrize("name", sorted(registry.fusion_specs()))
def test_every_fusion_estimator_refuses_a_bad_key_with_file_key_and_fix(name):
    from agent.estimators.registry import build_fusion

    spec = registry.fusion_specs()[name]
    with pytest.raises(ScenarioError) as e:
        build_fusion({"estimator": name, "no_such_key": 1}, "contract.toml")
    assert e.value.source == "contract.toml" and e.value.key == "fusion.no_such_key" and e.value.fix
    assert spec.param_names()        # its [fusion] keys are the schema the error lists
