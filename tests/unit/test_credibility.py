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
from flocktrack.record.credibility import Reference, chi2_interval, consistency

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
