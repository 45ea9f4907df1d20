"""García Carrillo et al., Table I and the λ (δ) sweep, reproduced over 10 seeds per outlier rate
(scenarios/carrillo_uav.toml; docs/carrillo_table1.md has the full table).

Scored estimate: the *newest node* of the window (a filtering estimate, like the Kalman filter's); the
mid-window (smoothed) node is checked beside it.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from agent.estimators.fusion_baselines import rmse, run_comparison
from agent.models_uav import config_from_tables

SCENARIOS = Path(__file__).resolve().parents[2] / "scenarios"

pytestmark = pytest.mark.slow

FRACTIONS = (0.01, 0.05, 0.10, 0.15, 0.20)
PUBLISHED = {
    "measurement": (9.7330, 15.4845, 20.5564, 22.9942, 35.2351),
    "kalman": (6.8656, 10.6555, 14.3670, 15.9173, 23.8675),
    "bls": (7.0527, 10.6061, 14.3661, 15.8792, 23.5845),
}
SEEDS = 10
SWEEP = (0.01, 0.03, 0.1, 0.3, 1.0, 1000.0)


@pytest.fixture(scope="module")
def table():
    sc = config_from_tables(tomllib.loads((SCENARIOS / "carrillo_uav.toml").read_text()))
    f = sc.fusion
    paper, minerr = {}, {}
    for frac in FRACTIONS:
        acc, acc_min = {}, {}
        for seed in range(SEEDS):
            stream = sc.sim(outlier_fraction=frac).generate(sc.duration, np.random.default_rng(seed))
            res = run_comparison(stream, W=int(f["window"]), q_son=float(f["q"]), deltas=SWEEP,
                                 kalman_qs=(5000.0, 1.0))
            for k, v in res.items():
                acc.setdefault(k, []).append(v)
            res = run_comparison(stream, W=int(f["window"]), q_son=30.0, deltas=(1.0,), kalman_qs=())
            for k, v in res.items():
                acc_min.setdefault(k, []).append(v)
        paper[frac] = {k: rmse(np.concatenate(v)) for k, v in acc.items()}
        minerr[frac] = {k: rmse(np.concatenate(v)) for k, v in acc_min.items()}
    assert float(f["delta"]) == 0.1
    return paper, minerr


def test_measurement_kalman_bls_rows_match_the_paper(table):
    paper, _ = table
    for i, frac in enumerate(FRACTIONS[:4]):  # 1–15 %; the published 20 % column is not reachable
        for key, name in (("measurement", "measurement"), ("kalman_q5000", "kalman"), ("bls", "bls")):
            got, pub = paper[frac][key], PUBLISHED[name][i]
            assert abs(got - pub) <= 0.10 * pub, (frac, name, got, pub)
    # 20 %: 40–70 m outliers cap the measurement RMS far below the published 35.24 m
    assert paper[0.20]["measurement"] < 0.8 * PUBLISHED["measurement"][4]


def test_sum_of_norms_beats_kalman_and_bls_at_every_rate(table):
    paper, _ = table
    ratios = []
    for frac in FRACTIONS:
        r = paper[frac]
        son, mid = r["son_d0.1"], r["son_d0.1_mid"]
        assert son < r["kalman_q5000"] and son < r["bls"], frac
        assert mid < son, frac
        ratios.append(son / r["kalman_q5000"])
    # the advantage grows with the outlier rate (from ≈ 0.85 at 1 %)
    assert ratios[0] > 0.78 and ratios[-1] < ratios[0] - 0.15
    # SoN/Kalman at 20 %: ≈ 0.64 for the newest node (published 0.375), much lower mid-window
    r20 = paper[0.20]
    assert 0.55 < ratios[-1] < 0.75
    assert r20["son_d0.1_mid"] / r20["kalman_q5000"] < 0.45


def test_minimum_error_tuning(table):
    """Reported honestly in docs/carrillo_table1.md; asserted here is only what holds robustly."""
    paper, minerr = table
    for frac in FRACTIONS:
        k_min, k_loose = paper[frac]["kalman_q1"], paper[frac]["kalman_q5000"]
        assert k_min < 0.6 * k_loose
        # the minimum-error Kalman filter beats the paper-tuned sum-of-norms estimator at every rate
        assert k_min < paper[frac]["son_d0.1"]
    # against a sum-of-norms estimator with an equally tight model: Kalman wins at 1 %, SoN at 20 %
    assert paper[0.01]["kalman_q1"] < minerr[0.01]["son_d1"]
    assert minerr[0.20]["son_d1"] < paper[0.20]["kalman_q1"]


def test_delta_sweep_flat_near_minimum_and_least_squares_beyond_residuals(table):
    paper, _ = table
    for frac in FRACTIONS:
        r = paper[frac]
        curve = {d: r[f"son_d{d:g}"] for d in SWEEP}
        best = min(curve.values())
        # flat: a decade and a half of δ around the paper's choice within 5 % of the best
        for d in (0.01, 0.03, 0.1, 0.3):
            assert curve[d] <= 1.05 * best, (frac, d, curve)
        # δ beyond every whitened residual: exactly batched least squares on the same window
        assert curve[1000.0] == pytest.approx(r["bls"], rel=1e-9)
        assert curve[1000.0] > 1.1 * best
