"""Robust moving-horizon fusion: the arrival cost against the cvxpy reference, the least-squares
limit equal to the Kalman filter, the online threshold's scale, the robust Kalman filter, the outlier
models, the fusion plug-in, and a small-seed version of the table's ordering."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from agent.estimators.fusion_baselines import KalmanCV, RobustKalmanCV, rmse, score_stream
from agent.estimators.riccati import huber_irls_weight
from agent.estimators.robust_mhe import RobustMHE, RobustScale
from agent.estimators.son_ipm import solve_ipm
from agent.estimators.son_reference import CvxpyReference
from agent.estimators.sum_of_norms import RelativeMeasurement
from agent.models_uav import UavConfig, UavRelativeSim, config_from_tables, student_nu_for
from agent.schema import ScenarioError
from agent.scenario import parse_uav_scenario


def _stream(frac=0.10, model="uniform", dur=20.0, seed=0):
    return UavRelativeSim(UavConfig(outlier_fraction=frac, outlier_model=model)).generate(dur, np.random.default_rng(seed))


def _cv_stream(n, q, sigma, seed, dt=0.1):
    """Absolute measurements (agent 0) of a target that *is* the model: white-noise acceleration q."""
    rng = np.random.default_rng(seed)
    x = np.zeros(4)
    x[2:] = (3.0, -2.0)
    recs = []
    for k in range(n):
        if k:
            x[:2] += dt * x[2:]
            a = rng.normal(0.0, math.sqrt(q / dt), 2)  # ≈ white-noise acceleration of density q
            x[:2] += 0.5 * dt * dt * a
            x[2:] += dt * a
        recs.append(RelativeMeasurement(0, k * dt, x[:2] + rng.normal(0.0, sigma, 2), np.eye(2)))
    return recs


def test_arrival_cost_window_matches_cvxpy_reference():
    """With an arrival cost (quadratic rows), the default IPM — fused hot path and generic path — and the
    cvxpy reference agree on the objective to 1e-6."""
    st = _stream(0.15)
    est = RobustMHE(W=15, q=3.0)
    ref = CvxpyReference()
    checked = 0
    for i in range(60):
        est.add(st.record(i))
        r = est.solve()
        if i in (30, 45, 59):
            assert est.arrival_cost() is not None
            prob, _ = est.problem()
            assert prob.lsq is not None and prob.lsq.sum() == 2
            a = solve_ipm(prob)
            b = ref.solve(prob)
            f = max(1.0, abs(b.objective))
            assert abs(a.objective - b.objective) / f < 1e-6
            assert abs(b.extra["objective10_as_huber"] - b.objective) / f < 1e-6
            if "rejected" not in r.extra:  # the estimator's own (fused) solve is the same problem
                assert abs(r.objective - a.objective) / f < 1e-9
            checked += 1
    assert checked == 3


def test_least_squares_limit_is_the_kalman_filter():
    """δ = ∞ (no Huber, no rejection): the window with its arrival cost is exactly the Kalman filter —
    the newest node equals KalmanCV's estimate once the initial priors have been forgotten."""
    st = _stream(0.0, dur=30.0)
    kf = KalmanCV(q=1.0)
    m = RobustMHE(W=5, q=1.0, delta=1e9, reject=math.inf, dt_floor=0.0)
    diffs = []
    for i in range(len(st)):
        rec = st.record(i)
        kf.add(rec)
        m.add(rec)
        diffs.append(np.abs(kf.estimate() - m.solve().newest).max())
    assert max(diffs[-50:]) < 1e-3


@pytest.mark.parametrize("s", [1.0, 2.0])
def test_online_delta_recovers_the_noise_scale(s):
    """Gaussian data from the estimator's own model with noise σ = s × the nominal: σ̂ ≈ s (10 %), δ = 1.345σ̂."""
    est = RobustMHE(W=15, q=1.0)
    for rec in _cv_stream(700, 1.0, s, seed=int(10 * s)):
        est.add(rec)
        est.solve()
    assert est.scale.sigma == pytest.approx(s, rel=0.10)
    assert est.delta == pytest.approx(1.345 * est.scale.sigma)


def test_mad_scale():
    sc = RobustScale(size=2000)
    sc.push(np.random.default_rng(0).normal(0.0, 2.0, 2000))
    assert sc.sigma == pytest.approx(2.0, rel=0.05)
    # 20 % gross contamination moves the MAD by its known bias only (Φ⁻¹(0.8125)/Φ⁻¹(0.75) ≈ 1.32)
    sc.push(np.concatenate([np.random.default_rng(1).normal(0.0, 1.0, 1600), np.full(400, 50.0)]))
    assert 1.2 < sc.sigma < 1.45


def test_mad_scale_is_the_median_of_its_ring_exactly():
    """The scale keeps its values sorted (no sort per push): the same σ̂, bit for bit, as np.median."""
    rng = np.random.default_rng(4)
    sc, ring = RobustScale(size=37, min_count=1), []
    for n in range(300):
        r = rng.standard_t(2.0, size=int(rng.integers(1, 4)))
        r[rng.random(r.size) < 0.05] = np.nan            # non-finite residuals are skipped
        ring = (ring + [abs(v) for v in r if np.isfinite(v)])[-37:]
        assert sc.push(r) == 1.4826 * float(np.median(ring)), n


def test_robust_kalman_downweights_a_gross_outlier():
    recs = _cv_stream(200, 1.0, 1.0, seed=3)
    kf, rkf = KalmanCV(q=1.0), RobustKalmanCV(q=1.0)
    for r in recs:
        kf.add(r)
        rkf.add(r)
    x_kf, x_rkf = kf.estimate(), rkf.estimate()
    bad = RelativeMeasurement(0, recs[-1].t + 0.1, kf.predict(recs[-1].t + 0.1)[:2] + np.array([50.0, 0.0]), np.eye(2))
    kf.add(bad)
    rkf.add(bad)
    jump_kf = np.abs(kf.estimate()[:2] - x_kf[:2]).max()
    jump_rkf = np.abs(rkf.estimate()[:2] - x_rkf[:2]).max()
    assert jump_kf > 5.0 and jump_rkf < 0.2 * jump_kf
    assert huber_irls_weight(np.array([0.5, 10.0]), 1.345)[1] == pytest.approx(0.1345)


def test_robust_mhe_rejects_a_gross_outlier_and_forgets_it():
    recs = _cv_stream(120, 1.0, 1.0, seed=4)
    recs[80] = RelativeMeasurement(0, recs[80].t, recs[80].z + np.array([40.0, -30.0]), np.eye(2))
    est = RobustMHE(W=15, q=1.0)
    for i, r in enumerate(recs):
        est.add(r)
        res = est.solve()
        if i == 85:
            assert res.extra.get("rejected") == 1 and res.outliers.sum() == 1
    assert est.scale.sigma < 1.3   # the outlier's residual is one of 300


def test_outlier_models():
    assert student_nu_for(0.01, 5.5, 40.0) == pytest.approx(3.22, abs=0.01)
    nu = student_nu_for(0.20, 5.5, 40.0)
    assert (1 + (40 / 5.5) ** 2 / nu) ** (-nu / 2) == pytest.approx(0.20)
    st = _stream(0.10, "student_t", dur=200.0)
    assert st.outlier.mean() == pytest.approx(0.10, abs=0.03)
    b = _stream(0.10, "burst", dur=100.0)
    assert b.outlier.mean() == pytest.approx(0.10, abs=0.02)
    for i in (1, 2):  # runs of 5 consecutive measurements of one UAV
        o = b.outlier[b.agent == i].astype(int)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], o, [0]])))
        assert np.all((edges[1::2] - edges[0::2]) % 5 == 0)
    with pytest.raises(ValueError, match="outlier_model"):
        UavRelativeSim(UavConfig(outlier_model="cauchy"))


def test_fusion_plugin_selects_the_robust_mhe_with_precise_errors(scenario_path):
    data = tomllib.loads(scenario_path("carrillo_robust.toml").read_text())
    sc = parse_uav_scenario(data, "carrillo_robust.toml")
    est = sc.uav.make_estimators()
    assert isinstance(est["robust_mhe"], RobustMHE) and est["robust_mhe"].online and est["robust_mhe"].q == 3.0
    assert isinstance(est["robust_kalman_q3"], RobustKalmanCV)
    for fusion, key in (({"estimator": "robust_mh"}, "fusion.estimator"),
                        ({"estimator": "robust_mhe", "window": 0}, "fusion.window"),
                        ({"estimator": "robust_mhe", "thresh": 1.0}, "fusion.thresh"),
                        ({"estimator": "robust_mhe", "c": -1.0}, "fusion.c")):
        with pytest.raises(ScenarioError) as e:
            parse_uav_scenario(dict(data, fusion=fusion), "x.toml")
        assert e.value.key == key and e.value.source == "x.toml" and e.value.fix
    # the paper's scenario still selects the paper's window by default
    paper = config_from_tables(tomllib.loads(scenario_path("carrillo_uav.toml").read_text()))
    assert "sum_of_norms" in paper.make_estimators()


def test_small_table_ordering_at_ten_percent():
    """The table's claim on one rate, 2 seeds × 30 s: robust MHE ≥ 10 % better than the hindsight-best
    Kalman filter and no worse than the robust Kalman filter."""
    acc: dict[str, list] = {}
    for seed in range(2):
        st = _stream(0.10, dur=30.0, seed=seed)
        ests = {f"kf{q:g}": KalmanCV(q=q) for q in (0.3, 1.0, 3.0)}
        ests["rkf"] = RobustKalmanCV(q=3.0)
        ests["mhe"] = RobustMHE(W=15, q=3.0)
        for k, v in score_stream(st, ests).items():
            acc.setdefault(k, []).append(v)
    r = {k: rmse(np.concatenate(v)) for k, v in acc.items()}
    best_kf = min(r["kf0.3"], r["kf1"], r["kf3"])
    assert r["mhe"] <= 0.9 * best_kf
    assert r["mhe"] <= r["rkf"]
