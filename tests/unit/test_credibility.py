"""Honest uncertainty (flocktrack/record/credibility.py): the NEES test tells a consistent covariance from
an optimistic and a conservative one; the centralized reference is the Kalman predictor of the true model,
and its errors match its covariance over independent runs; a real run's summary carries the section."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.stats import chi2

from agent.estimators.kalman import KalmanPredictor
from flocktrack.cli import main
from flocktrack.record.credibility import Reference, chi2_interval, consistency, settled

from conftest import ROOT

P = np.array([[2.0, 0.3, 0.0, 0.1], [0.3, 1.0, 0.0, 0.0], [0.0, 0.0, 0.5, 0.0], [0.1, 0.0, 0.0, 0.25]])


def _errors(scale: float, K: int = 4000, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return scale * rng.multivariate_normal(np.zeros(4), P, size=K)


def test_the_nees_verdict_follows_the_scale_of_the_errors():
    Ps = np.repeat(P[None], 4000, axis=0)
    assert consistency(_errors(1.0), Ps)["verdict"] == "consistent"
    assert consistency(_errors(2.0), Ps)["verdict"] == "optimistic"
    c = consistency(_errors(0.5), Ps)
    assert c["verdict"] == "conservative" and c["coin"] < 1
    assert c["anees"] == pytest.approx(4 * 0.25, rel=0.1)
    # the interval is χ²(K·m)/K at 2.5 % and 97.5 %
    lo, hi = chi2_interval(4 * 4000, 4000)
    assert lo == pytest.approx(chi2.ppf(0.025, 16000) / 4000) and lo < 4 < hi
    # a covariance that is not one is left out, not divided by
    bad = Ps.copy()
    bad[0] = -np.eye(4)
    assert consistency(_errors(1.0), bad)["samples"] == 3999


def _simulate(ref: Reference, ticks: int, seed: int, b: float = 1.0):
    rng = np.random.default_rng(seed)
    x = rng.multivariate_normal(ref.x0, ref.P0)
    truth, meas = {}, {}
    for k in range(ticks):
        truth[k] = x.copy()
        meas[k] = {i: (b, b * C @ x + rng.multivariate_normal(np.zeros(C.shape[0]), R))
                   for i, (C, R) in enumerate(zip(ref.Cs, ref.Rs))}
        x = ref.A @ x + rng.multivariate_normal(np.zeros(4), ref.Q)
    return truth, meas


def test_the_centralized_reference_is_the_stacked_kalman_predictor_and_its_covariance_is_honest():
    T = 0.1
    A = np.array([[1, 0, T, 0], [0, 1, 0, T], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    B = np.array([[T * T / 2, 0], [0, T * T / 2], [T, 0], [0, T]])
    C = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
    ref = Reference(A, B @ (0.5 * np.eye(2)) @ B.T, (C, C, C), (0.2 * np.eye(2), 0.1 * np.eye(2), 0.4 * np.eye(2)),
                    np.zeros(4), np.eye(4))
    truth, meas = _simulate(ref, 60, seed=0)
    out = ref.run(meas, 60)
    kp = KalmanPredictor.stacked(A, ref.Q, ref.Cs, ref.Rs, ref.x0, ref.P0)   # written independently
    for k in range(60):
        assert np.allclose(out[k][0], kp.x) and np.allclose(out[k][1], kp.P)
        kp.step(np.concatenate([meas[k][i][1] for i in range(3)]))
    # over independent runs the reference's errors at a fixed tick match its covariance (χ² at 95 %)
    E, Ps = [], []
    for seed in range(300):
        truth, meas = _simulate(ref, 30, seed=seed + 10)
        x, Pk = ref.run(meas, 30)[29]
        E.append(x - truth[29])
        Ps.append(Pk)
    assert consistency(np.array(E), np.array(Ps))["consistent"]


def test_the_start_up_transient_is_left_out_of_the_bound():
    """A prior far wider than the start's real error (x₀ known, P₀ = I) makes the first ticks' traces dwarf
    the steady state: the comparison starts once the reference has settled, and there the reference's own
    errors match its bound."""
    T = 0.04
    A = np.array([[1, 0, T, 0], [0, 1, 0, T], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    B = np.array([[T * T / 2, 0], [0, T * T / 2], [T, 0], [0, T]])
    C = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
    ref = Reference(A, B @ (0.01 * np.eye(2)) @ B.T, (C,) * 10, (0.04 * np.eye(2),) * 10, np.zeros(4), np.eye(4))
    rng = np.random.default_rng(3)
    mse, tr = [], []
    for _seed in range(40):
        truth, meas = _simulate(Reference(ref.A, ref.Q, ref.Cs, ref.Rs, np.zeros(4), 1e-12 * np.eye(4)), 300,
                                seed=int(rng.integers(1 << 30)))
        out = ref.run(meas, 300)
        ks = settled(list(range(300)), out)
        assert 0 < ks[0] < 100 and ks == list(range(ks[0], 300))
        mse += [np.sum((out[k][0] - truth[k]) ** 2) for k in ks]
        tr += [np.trace(out[k][1]) for k in ks]
        # from tick 0 the mean trace is several times the errors: the prior, not the filter
        assert np.mean([np.trace(out[k][1]) for k in range(300)]) > 2 * np.mean(tr[-len(ks):])
    assert np.mean(mse) / np.mean(tr) == pytest.approx(1.0, abs=0.15)
    assert settled([1, 2, 3], None) == [1, 2, 3]


def test_a_run_summary_says_how_honest_and_how_efficient_each_node_is(tmp_path):
    out = tmp_path / "run"
    assert main(["run", str(ROOT / "scenarios" / "gu_hu_normal.toml"), "--transport", "inproc", "--ticks", "400",
                 "--quiet", "--out", str(out)]) == 0
    cred = json.loads((out / "summary.json").read_text())["credibility"]
    assert set(cred["nees"]) == {str(i) for i in range(10)}
    net = cred["network"]
    lo, hi = net["interval"]
    assert net["dof"] == 4 and lo < 4 < hi and net["verdict"] in ("consistent", "conservative", "optimistic")
    assert net["consistent"] == (lo <= net["anees"] <= hi)
    eff = cred["efficiency"]
    # the distributed filter does no better than the centralized one on the same measurements
    assert eff["network_vs_central_mse"] >= 0.95, eff
    assert eff["central_trace_P_mean"] > 0 and len(eff["per_node"]) == 10
    # after the start-up transient the reference's own errors match its bound, and no node beats it
    assert cred["from_tick"] > 0 and 0.7 < eff["central_mse_over_trace"] < 1.4, eff
    assert eff["network"] >= 0.9, eff
    # each node's innovations against its own covariance (no truth needed): q = 2 degrees of freedom
    assert set(cred["nis"]) == {str(i) for i in range(10)}
    assert all(c["dof"] == 2 and c["verdict"] in ("consistent", "conservative", "optimistic")
               for c in cred["nis"].values())


def test_the_innovation_test_needs_no_truth_and_tells_honest_from_optimistic():
    """NIS of a node's own measurement against bCPC′ + R: a centralized predictor with the true model passes;
    the same estimates reported with a covariance ten times too small fail as optimistic."""
    from flocktrack.record.credibility import innovation_consistency

    T = 0.1
    A = np.array([[1, 0, T, 0], [0, 1, 0, T], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    B = np.array([[T * T / 2, 0], [0, T * T / 2], [T, 0], [0, T]])
    C = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
    ref = Reference(A, B @ (0.5 * np.eye(2)) @ B.T, (C,), (0.2 * np.eye(2),), np.zeros(4), 1e-9 * np.eye(4))
    truth, meas = _simulate(ref, 3000, seed=5)
    out = ref.run(meas, 3000)
    est = {k: {0: out[k][0]} for k in out}
    ks = list(range(50, 3000))
    honest = innovation_consistency(est, {k: {0: out[k][1]} for k in out}, meas, ref, ks)["0"]
    assert honest["verdict"] == "consistent" and honest["dof"] == 2, honest
    tight = innovation_consistency(est, {k: {0: 0.1 * out[k][1]} for k in out}, meas,
                                   Reference(A, ref.Q, (C,), (0.05 * np.eye(2),), ref.x0, ref.P0), ks)["0"]
    assert tight["verdict"] == "optimistic"
