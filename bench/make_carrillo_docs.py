"""Reproduce García Carrillo et al.'s Table I and Fig. 4 (the λ/δ sweep), and compare the robust
moving-horizon fusion with every baseline over three outlier models; write
docs/carrillo_table1.md, docs/carrillo_table1.png and docs/carrillo_lambda_sweep.png.

    python bench/make_carrillo_docs.py [--seeds 10] [--quick]

Everything comes from scenarios/carrillo_uav.toml; the estimators are agent.estimators.*; the runs
are deterministic (seed s of outlier rate f uses numpy's default_rng(s): the same target path and
noise at every rate, only the outliers differ).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent.estimators.fusion_baselines import KalmanCV, RobustKalmanCV, rmse, run_comparison, score_stream
from agent.estimators.robust_mhe import RobustMHE
from agent.estimators.sum_of_norms import SumOfNormsEstimator
from agent.estimators.son_problem import lambda_from_delta
from agent.models_uav import config_from_tables

PUBLISHED = {
    "fractions": [0.01, 0.05, 0.10, 0.15, 0.20],
    "measurement": [9.7330, 15.4845, 20.5564, 22.9942, 35.2351],
    "kalman": [6.8656, 10.6555, 14.3670, 15.9173, 23.8675],
    "bls": [7.0527, 10.6061, 14.3661, 15.8792, 23.5845],
    # the bold (best-λ) entry of each column
    "son_best": [5.8470, 6.4056, 7.5963, 8.2533, 8.9530],
    "son_best_lambda": [0.0276, 0.0240, 0.0209, 0.0182, 0.0170],
}
SWEEP = (0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 2.0, 4.0, 8.0, 16.0, 1e3)
PAPER_SCALE = 57.0  # the residual scale the paper's λ values imply (PAPER_NOTES 004)
MIN_Q_KALMAN = (0.3, 1.0, 3.0)
MIN_Q_SON = 30.0
MIN_DELTAS = (0.3, 1.0, 3.0)
# beyond the paper: the robust comparison
MODELS = ("uniform", "student_t", "burst")
MODEL_TEXT = {"uniform": "the paper's outliers (40–70 m, uniform direction)",
              "student_t": "heavy-tailed Student-t noise on every measurement, ν such that P(‖n‖ > 40 m) = rate",
              "burst": "bursts of 5 consecutive outliers of one UAV, one 40–70 m offset per burst"}
SWEEP_Q_KALMAN = (0.1, 0.3, 1.0, 3.0, 10.0)
MHE_Q = 3.0                 # the one setting of the robust MHE (and of the robust KF beside it)
MHE_Q_DECADE = (1.0, 3.0, 10.0)
TUNED_SON = (30.0, 1.0)     # q, δ: the best tight sum-of-norms window of the minimum-error section


def robust_estimators(W: int, with_decade: bool) -> dict:
    """Every estimator of the robust comparison, fresh (names are the table's keys)."""
    e = {"son_paper": SumOfNormsEstimator(W=W, q=5000.0, delta=0.1),
         "son_tuned": SumOfNormsEstimator(W=W, q=TUNED_SON[0], delta=TUNED_SON[1])}
    for q in SWEEP_Q_KALMAN + (5000.0,):
        e[f"kalman_q{q:g}"] = KalmanCV(q=q)
    e[f"rkf_q{MHE_Q:g}"] = RobustKalmanCV(q=MHE_Q)
    e["rkf_q1"] = RobustKalmanCV(q=1.0)
    for q in (MHE_Q_DECADE if with_decade else (MHE_Q,)):
        e[f"mhe_q{q:g}"] = RobustMHE(W=W, q=q)
    return e


def run_robust(seeds: int, fractions, duration: float | None = None):
    """name → RMSE per (model, rate), pooled over seeds; plus the robust MHE's final σ̂ per (model, rate)."""
    sc = config_from_tables(tomllib.loads((ROOT / "scenarios" / "carrillo_uav.toml").read_text()))
    W = int(sc.fusion["window"])
    dur = sc.duration if duration is None else duration
    pooled: dict[tuple, dict[str, float]] = {}
    sigma: dict[tuple, float] = {}
    for model in MODELS:
        for frac in fractions:
            acc: dict[str, list] = {}
            sig = []
            for seed in range(seeds):
                stream = sc.sim(outlier_fraction=frac, outlier_model=model).generate(dur, np.random.default_rng(seed))
                ests = robust_estimators(W, model == "uniform")
                for k, v in score_stream(stream, ests).items():
                    acc.setdefault(k, []).append(v)
                e = stream.measured_target() - stream.truth_pos
                acc.setdefault("measurement", []).append(np.sum(e * e, axis=1))
                sig.append(ests[f"mhe_q{MHE_Q:g}"].scale.sigma)
            pooled[model, frac] = {k: rmse(np.concatenate(v)) for k, v in acc.items()}
            sigma[model, frac] = float(np.mean(sig))
            print(model, frac, {k: round(v, 2) for k, v in pooled[model, frac].items()}, flush=True)
    return pooled, sigma


def run_all(seeds: int, fractions, duration: float | None = None):
    sc = config_from_tables(tomllib.loads((ROOT / "scenarios" / "carrillo_uav.toml").read_text()))
    f = sc.fusion
    W, q, delta = int(f["window"]), float(f["q"]), float(f["delta"])
    dur = sc.duration if duration is None else duration
    deltas = tuple(sorted(set(SWEEP) | {delta}))
    kq = tuple(float(v) for v in sc.baselines["kalman_q"])
    paper: dict[float, dict[str, list]] = {}
    minerr: dict[float, dict[str, list]] = {}
    for frac in fractions:
        paper[frac], minerr[frac] = {}, {}
        for seed in range(seeds):
            stream = sc.sim(outlier_fraction=frac).generate(dur, np.random.default_rng(seed))
            res = run_comparison(stream, W=W, q_son=q, deltas=deltas, kalman_qs=kq,
                                 whitening=f.get("whitening", "chol"), max_lateness=f.get("max_lateness", 1.0))
            for k, v in res.items():
                paper[frac].setdefault(k, []).append(v)
            res = run_comparison(stream, W=W, q_son=MIN_Q_SON, deltas=MIN_DELTAS, kalman_qs=MIN_Q_KALMAN)
            for k, v in res.items():
                minerr[frac].setdefault(k, []).append(v)
    pooled = {fr: {k: rmse(np.concatenate(v)) for k, v in d.items()} for fr, d in paper.items()}
    pooled_min = {fr: {k: rmse(np.concatenate(v)) for k, v in d.items()} for fr, d in minerr.items()}
    return sc, pooled, pooled_min, deltas


def mid_lag(sc) -> float:
    """Mean time between the newest and the mid-window node (s), from one run."""
    from agent.estimators.sum_of_norms import SumOfNormsEstimator

    stream = sc.sim().generate(sc.duration, np.random.default_rng(0))
    est = SumOfNormsEstimator(W=int(sc.fusion["window"]), delta=float(sc.fusion["delta"]), q=float(sc.fusion["q"]))
    lag = []
    for m in stream.records():
        est.add(m)
        if est.window.count == est.W:
            r = est.solve()
            lag.append(r.t_newest - r.t_mid)
    return float(np.mean(lag))


def pct(a, b):
    return 100.0 * (a - b) / b


def write_markdown(path: Path, sc, pooled, pooled_min, deltas, seeds, lag, elapsed, robust=None):
    """docs/carrillo_table1.md: Table I at the paper's tuning, at minimum-error tuning, the δ sweep, the
    robust comparison and the settings the paper leaves unstated."""
    L = []
    _md_header(L.append, sc, seeds, lag, elapsed)
    _md_paper_tuning(L.append, sc, pooled)
    _md_minimum_error(L.append, sc, pooled, pooled_min)
    _md_robustness_knob(L.append, pooled, deltas)
    if robust is not None:
        _md_robust(L.append, *robust, seeds)
    _md_settings(L.append)
    path.write_text("\n".join(L) + "\n")


def _row(w, name, vals, pub=None):
    """One table row: values to 2 decimals, with the deviation from the published ``pub`` if given."""
    cells = []
    for i, v in enumerate(vals):
        c = f"{v:.2f}"
        if pub is not None:
            c += f" ({pct(v, pub[i]):+.0f} %)"
        cells.append(c)
    w(f"| {name} | " + " | ".join(cells) + " |")


def _md_header(w, sc, seeds, lag, elapsed):
    w("# García Carrillo et al., Table I — reproduced")
    w("")
    w("Generated by `bench/make_carrillo_docs.py` from `scenarios/carrillo_uav.toml` "
      f"({seeds} seeds per outlier rate, {sc.duration:g} s each, pooled RMSE of the 2-D position error over "
      f"every measurement time; {elapsed:.0f} s). Figures: `carrillo_table1.png`, `carrillo_lambda_sweep.png`.")
    w("")
    w("**Scored estimate.** *newest node* — the sum-of-norms and BLS estimates of the target at the newest "
      "measurement time of the window, i.e. filtering estimates comparable with the Kalman filter's. The "
      f"*mid-window* node (index ⌊(W−1)/2⌋ of the 15-measurement window, a smoothed estimate lagging ≈ {lag:.2f} s) "
      "is reported beside it and is much lower; the paper does not say which it scored.")
    w("")


def _md_paper_tuning(w, sc, pooled):
    fr = PUBLISHED["fractions"]
    d0 = float(sc.fusion["delta"])
    sk = f"son_d{d0:g}"
    w("## Paper tuning (one loose motion model for all three estimators)")
    w("")
    u = sc.uav
    w(f"Setting: two UAVs at ≈ {u.rate_hz:g} Hz each (≈ {2 * u.rate_hz:g} Hz fused), "
      f"relative noise σ = {u.sigma_rel:g} m "
      f"and GPS noise σ = {u.sigma_gps:g} m per axis, outliers replace the noise by a "
      f"{u.outlier_range[0]:g}–{u.outlier_range[1]:g} m vector in a random direction ({u.outlier_mode} fraction). "
      f"Kalman filter, BLS and the sum-of-norms graph all use q = {float(sc.fusion['q']):g} m²/s³ (white-noise "
      f"acceleration); window W = {int(sc.fusion['window'])}; sum-of-norms δ = {d0:g} "
      f"(λ = {lambda_from_delta(d0):.3f} at c = 1, λ = {lambda_from_delta(d0, PAPER_SCALE):.4f} at the paper's "
      f"implied c ≈ {PAPER_SCALE:g}).")
    w("")
    w("| RMSE (m) | " + " | ".join(f"{100 * f:g} % outliers" for f in fr) + " |")
    w("|---|" + "---|" * len(fr))
    _row(w, "measurement — published", PUBLISHED["measurement"])
    _row(w, "measurement — reproduced", [pooled[f]["measurement"] for f in fr], PUBLISHED["measurement"])
    _row(w, "Kalman — published", PUBLISHED["kalman"])
    _row(w, "Kalman q = 5000 — reproduced", [pooled[f]["kalman_q5000"] for f in fr], PUBLISHED["kalman"])
    _row(w, "BLS — published", PUBLISHED["bls"])
    _row(w, "BLS — reproduced", [pooled[f]["bls"] for f in fr], PUBLISHED["bls"])
    _row(w, "sum-of-norms, best λ — published", PUBLISHED["son_best"])
    _row(w, f"sum-of-norms δ = {d0:g}, newest node — reproduced", [pooled[f][sk] for f in fr], PUBLISHED["son_best"])
    _row(w, f"sum-of-norms δ = {d0:g}, mid-window — reproduced", [pooled[f][sk + "_mid"] for f in fr])
    w("")
    w("Ratios to the Kalman filter:")
    w("")
    w("| ratio | " + " | ".join(f"{100 * f:g} %" for f in fr) + " |")
    w("|---|" + "---|" * len(fr))
    w("| SoN / Kalman — published | " + " | ".join(
        f"{s / k:.2f}" for s, k in zip(PUBLISHED["son_best"], PUBLISHED["kalman"])) + " |")
    w("| SoN newest / Kalman — reproduced | " + " | ".join(
        f"{pooled[f][sk] / pooled[f]['kalman_q5000']:.2f}" for f in fr) + " |")
    w("| SoN mid-window / Kalman — reproduced | " + " | ".join(
        f"{pooled[f][sk + '_mid'] / pooled[f]['kalman_q5000']:.2f}" for f in fr) + " |")
    w("| SoN newest / BLS — reproduced | " + " | ".join(
        f"{pooled[f][sk] / pooled[f]['bls']:.2f}" for f in fr) + " |")
    w("")
    w("What reproduces and what does not:")
    w("")
    w("* Measurement, Kalman and BLS rows: within 10 % of the published ones for 1–15 % outliers (deviations in "
      "parentheses). The published 35.24 m at 20 % cannot occur with 40–70 m outliers: even if *every* outlier "
      f"were 70 m the RMS would be ≈ {math.sqrt(0.8 * 2 * 5.7 ** 2 + 0.2 * 70 ** 2):.1f} m; the paper's 20 % "
      "column was made with larger errors, so its Kalman/BLS entries there are not comparable either.")
    w("* The sum-of-norms estimator beats both baselines at every rate, and its advantage grows with the "
      "outlier rate — the paper's claim — but less strongly than published when the newest node is scored "
      f"(ratio {pooled[0.2][sk] / pooled[0.2]['kalman_q5000']:.2f} at 20 % vs the paper's 0.375, whose 20 % "
      "column is inconsistent anyway); scoring the mid-window node gives "
      f"{pooled[0.2][sk + '_mid'] / pooled[0.2]['kalman_q5000']:.2f}.")
    w("* The published sum-of-norms entries (5.85 … 8.95 m) lie between our newest-node and mid-window "
      "values.")
    w("")


def _md_minimum_error(w, sc, pooled, pooled_min):
    fr = PUBLISHED["fractions"]
    d0 = float(sc.fusion["delta"])
    sk = f"son_d{d0:g}"
    w("## Minimum-error tuning")
    w("")
    w("The paper's Kalman tuning is not given; q = 5000 m²/s³ is what reproduces its Kalman ≈ BLS ≈ 0.7 × "
      "measurement rows. A Kalman filter tuned for minimum error is far better. Here every estimator gets a "
      f"tight motion model: Kalman q ∈ {{{', '.join(f'{v:g}' for v in MIN_Q_KALMAN)}}} (q = 1 is the minimum-error "
      f"tuning used below), BLS and sum-of-norms q = {MIN_Q_SON:g} with "
      f"δ ∈ {{{', '.join(f'{v:g}' for v in MIN_DELTAS)}}}.")
    w("")
    w("| RMSE (m) | " + " | ".join(f"{100 * f:g} %" for f in fr) + " |")
    w("|---|" + "---|" * len(fr))
    for q in MIN_Q_KALMAN:
        _row(w, f"Kalman q = {q:g}", [pooled_min[f][f"kalman_q{q:g}"] for f in fr])
    _row(w, f"BLS q = {MIN_Q_SON:g}", [pooled_min[f]["bls"] for f in fr])
    for d in MIN_DELTAS:
        _row(w, f"sum-of-norms q = {MIN_Q_SON:g}, δ = {d:g}, newest", [pooled_min[f][f"son_d{d:g}"] for f in fr])
    for d in MIN_DELTAS:
        _row(w, f"sum-of-norms q = {MIN_Q_SON:g}, δ = {d:g}, mid-window",
             [pooled_min[f][f"son_d{d:g}_mid"] for f in fr])
    _row(w, f"sum-of-norms paper tuning (q = {float(sc.fusion['q']):g}, δ = {d0:g}), newest",
         [pooled[f][sk] for f in fr])
    w("")
    best_son = {f: min(pooled_min[f][f"son_d{d:g}"] for d in MIN_DELTAS) for f in fr}
    k1 = {f: pooled_min[f]["kalman_q1"] for f in fr}
    wins = [f for f in fr if best_son[f] < k1[f]]
    w("Read honestly:")
    w("")
    kbest = {f: min(pooled_min[f][f"kalman_q{q:g}"] for q in MIN_Q_KALMAN) for f in fr}
    w(f"* The Kalman filter's best q depends on the outlier rate (q = 1 at 1–5 %, q ≈ 0.3 from 10 %); its "
      f"best over q ∈ {{{', '.join(f'{v:g}' for v in MIN_Q_KALMAN)}}}: {', '.join(f'{kbest[f]:.2f}' for f in fr)} m.")
    w(f"* The minimum-error Kalman filter (q = 1) beats the paper-tuned sum-of-norms estimator at every rate "
      f"({', '.join(f'{k1[f]:.2f} vs {pooled[f][sk]:.2f}' for f in fr)} m): **the published advantage depends on "
      "the loosely tuned Kalman filter.**")
    w(f"* Against a sum-of-norms estimator with an equally tight motion model, the minimum-error Kalman filter "
      f"still wins at low outlier rates; the sum-of-norms estimator wins at "
      f"{', '.join(f'{100 * f:g} %' for f in wins) if wins else 'no rate'} (best newest-node δ per rate: "
      f"{', '.join(f'{best_son[f]:.2f}' for f in fr)} m vs Kalman q = 1 {', '.join(f'{k1[f]:.2f}' for f in fr)} m); "
      f"against the best Kalman q per rate it wins at "
      f"{', '.join(f'{100 * f:g} %' for f in fr if best_son[f] < kbest[f]) or 'no rate'}, by a few per cent. "
      "Its window holds 15 measurements (≈ 1.5 s); the Kalman filter uses all of them.")
    w("* The mid-window (smoothed) estimate beats the filter everywhere, but it answers a different question "
      "(the position ≈ 0.7 s ago).")
    w("")


def _md_robustness_knob(w, pooled, deltas):
    fr = PUBLISHED["fractions"]
    lsdiff = max(abs(pooled[f]["son_d1000"] - pooled[f]["bls"]) / pooled[f]["bls"] for f in fr)
    w("## The robustness knob (Fig. 4 of the paper)")
    w("")
    w("`carrillo_lambda_sweep.png`: newest-node RMSE against the Huber threshold δ (whitened σ units; top axis "
      f"λ at c = 1 and at c = {PAPER_SCALE:g}), paper tuning. The curves are flat around their minimum "
      "(δ ≈ 0.01–0.3, i.e. the paper's λ ≈ 0.01–0.06 at c = 57: its λ = 0.0209 is δ = 0.036) and coincide "
      "exactly with BLS once δ exceeds the largest whitened residual of every window (λ ≥ λ_max, no outlier "
      f"detected; at δ = 1000 the largest relative difference from BLS over the five rates is {lsdiff:.1e}). "
      "With unit-covariance whitening (c = 1), the least-squares "
      "end is reached only at λ ≳ 0.9; the paper's \"λ ≥ 0.3 equals least squares\" needs c ≈ 57.")
    w("")
    w("| best δ (newest node) | " + " | ".join(f"{100 * f:g} %" for f in fr) + " |")
    w("|---|" + "---|" * len(fr))
    best = {}
    for f in fr:
        vals = {d: pooled[f][f"son_d{d:g}"] for d in deltas}
        best[f] = min(vals, key=vals.get)
    w("| δ* | " + " | ".join(f"{best[f]:g}" for f in fr) + " |")
    w("| RMSE at δ* (m) | " + " | ".join(f"{pooled[f][f'son_d{best[f]:g}']:.2f}" for f in fr) + " |")
    w("| RMSE at δ = 1000 (m) | " + " | ".join(f"{pooled[f]['son_d1000']:.4f}" for f in fr) + " |")
    w("| BLS (m) | " + " | ".join(f"{pooled[f]['bls']:.4f}" for f in fr) + " |")
    w("")


def _hindsight_kalman(res: dict) -> tuple[float, float]:
    """(RMSE, q) of the best Kalman q for one (model, rate), chosen with hindsight."""
    q = min(SWEEP_Q_KALMAN, key=lambda v: res[f"kalman_q{v:g}"])
    return res[f"kalman_q{q:g}"], q


def _md_robust(w, pooled, sigma, seeds):
    fr = PUBLISHED["fractions"]
    mk = f"mhe_q{MHE_Q:g}"
    rk = f"rkf_q{MHE_Q:g}"
    w("## Beyond the paper: robust moving-horizon fusion")
    w("")
    w("The paper's window forgets; a Kalman filter remembers but is not robust. The **robust MHE** "
      "(`agent/estimators/robust_mhe.py`) is the sum-of-norms/Huber window (W = 15) with an arrival cost — "
      "the prior on the oldest node carried from the previous solve (its posterior from the Huber problem's "
      "curvature at the optimum, predicted by the motion model: the robust analogue of the Kalman "
      "prediction) — a tuning-free threshold δ = 1.345·σ̂ (σ̂ the MAD of the whitened residuals of the last "
      "20 windows) and, after the Huber solve, a second solve without the measurements whose residual exceeds "
      f"3σ̂ (gross outliers; they also leave the arrival cost). **One setting for every rate and model:** "
      f"W = 15, q = {MHE_Q:g} m²/s³, c = 1.345, rejection at 3σ̂. Baselines: the paper-tuned sum-of-norms "
      f"(q = 5000, δ = 0.1), the tuned window (q = {TUNED_SON[0]:g}, δ = {TUNED_SON[1]:g}), the Kalman filter at "
      "the paper's q = 5000 and its best q ∈ {" + ", ".join(f"{q:g}" for q in SWEEP_Q_KALMAN) + "} per "
      "rate and model chosen with hindsight, and a robust Kalman filter (Huber M-estimation update, "
      f"iteratively reweighted, the same online δ) at q = {MHE_Q:g} (the MHE's model) and q = 1. Newest-node "
      f"RMSE (m), {seeds} seeds × 100 s per cell; ratio = robust MHE / hindsight-best Kalman.")
    w("")
    verdict = []
    for model in MODELS:
        w(f"### {model}: {MODEL_TEXT[model]}")
        w("")
        w("| RMSE (m) | " + " | ".join(f"{100 * f:g} %" for f in fr) + " |")
        w("|---|" + "---|" * len(fr))
        P = {f: pooled[model, f] for f in fr}
        if model == "student_t":
            from agent.models_uav import student_nu_for
            w("| ν of the Student-t | " + " | ".join(f"{student_nu_for(f, 5.5, 40.0):.2f}" for f in fr) + " |")
        _row(w, "measurement (raw)", [P[f]["measurement"] for f in fr])
        _row(w, "sum-of-norms, paper tuning (q = 5000, δ = 0.1)", [P[f]["son_paper"] for f in fr])
        _row(w, f"sum-of-norms, tuned (q = {TUNED_SON[0]:g}, δ = {TUNED_SON[1]:g})", [P[f]["son_tuned"] for f in fr])
        _row(w, "Kalman, paper q = 5000", [P[f]["kalman_q5000"] for f in fr])
        for q in SWEEP_Q_KALMAN:
            _row(w, f"Kalman q = {q:g}", [P[f][f"kalman_q{q:g}"] for f in fr])
        hb = {f: _hindsight_kalman(P[f]) for f in fr}
        w("| **Kalman, hindsight-best q** | " + " | ".join(f"{hb[f][0]:.2f} (q = {hb[f][1]:g})" for f in fr) + " |")
        _row(w, "robust Kalman (Huber), q = 1", [P[f]["rkf_q1"] for f in fr])
        _row(w, f"robust Kalman (Huber), q = {MHE_Q:g}", [P[f][rk] for f in fr])
        w(f"| **robust MHE, online δ (q = {MHE_Q:g})** | " + " | ".join(f"**{P[f][mk]:.2f}**" for f in fr) + " |")
        if model == "uniform":
            for q in MHE_Q_DECADE:
                if q != MHE_Q:
                    _row(w, f"robust MHE, q = {q:g} (the q decade)", [P[f][f"mhe_q{q:g}"] for f in fr])
        w("| σ̂ of the robust MHE (end of run) | " + " | ".join(f"{sigma[model, f]:.2f}" for f in fr) + " |")
        w("| robust MHE / hindsight-best Kalman | " + " | ".join(f"{P[f][mk] / hb[f][0]:.2f}" for f in fr) + " |")
        w("| robust MHE / best robust Kalman | " + " | ".join(
            f"{P[f][mk] / min(P[f][rk], P[f]['rkf_q1']):.2f}" for f in fr) + " |")
        w("")
        for f in fr:
            r_kal = P[f][mk] / hb[f][0]
            r_rkf = P[f][mk] / min(P[f][rk], P[f]["rkf_q1"])
            need = 0.9 if f >= 0.10 else 1.0
            if r_kal > need:
                verdict.append(f"{model} {100 * f:g} %: robust MHE / hindsight-best Kalman = {r_kal:.2f} "
                               f"(target ≤ {need:g})")
            if r_rkf > 1.0:
                verdict.append(f"{model} {100 * f:g} %: robust MHE / best robust Kalman = {r_rkf:.2f} (target ≤ 1)")
    w("### Targets")
    w("")
    w("Robust MHE ≤ hindsight-best Kalman at every rate and model, ≥ 10 % better from 10 % outliers on, and ≤ the "
      "robust Kalman filter (either q) everywhere:")
    w("")
    if verdict:
        w("Missed:")
        w("")
        for v in verdict:
            w(f"* {v}")
    else:
        w("* met in every cell above.")
    w("")
    uni = {f: pooled["uniform", f] for f in fr}
    spread = max(max(uni[f][f"mhe_q{q:g}"] for q in MHE_Q_DECADE) / min(uni[f][f"mhe_q{q:g}"] for q in MHE_Q_DECADE)
                 for f in fr)
    w(f"The motion-noise level q over a decade (uniform model, q = {MHE_Q_DECADE[0]:g} … {MHE_Q_DECADE[-1]:g}): "
      f"the robust MHE's RMSE varies by at most {100 * (spread - 1):.0f} % per rate, while the Kalman filter's "
      f"best q moves with the rate (rows above). q is not estimated online.")
    w("")


def _md_settings(w):
    w("## Settings the paper leaves unstated (chosen here, see PAPER_NOTES 004)")
    w("")
    w("* Noise: σ = 5.5 m (relative) and 1.5 m (GPS) per axis, 5.7 m in total; outliers 40–70 m in a random "
      "direction, an exact fraction of the measurements.")
    w("* Rate: \"about 10 Hz\" is read as the fused stream (each UAV ≈ 5 Hz); at 10 Hz per UAV the Kalman and BLS "
      "rows come out 15–20 % below the published ones.")
    w("* Motion model: white-noise acceleration q = 5000 m²/s³ for the Kalman filter *and* the graph's motion "
      "edges (BLS, sum-of-norms) — the one tuning under which both baseline rows match.")
    w("* The target: a unicycle at 6 m/s in a 600 m × 300 m area, random turn-rate segments with occasional "
      "sharp turns (0.8 rad/s), steering back at the boundary.")
    w("* Whitening: inverse lower Cholesky factors; Δt floored at 20 ms in the motion covariance.")


def figures(docs: Path, pooled, pooled_min, deltas, d0):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fr = PUBLISHED["fractions"]
    x = np.array(fr) * 100
    sk = f"son_d{d0:g}"
    fig, ax = plt.subplots(figsize=(8, 5))
    series = [("measurement", "measurement", "k", "measurement"),
              ("kalman_q5000", "kalman", "tab:red", "Kalman q = 5000 (≈ BLS)"),
              ("bls", "bls", "tab:orange", "BLS (W = 15)"),
              (sk, "son_best", "tab:blue", f"sum-of-norms δ = {d0:g}, newest node")]
    for key, pub, col, lab in series:
        ax.plot(x, [pooled[f][key] for f in fr], "-D" if key.startswith("kalman") else "-o", color=col, label=lab,
                ms=7 if key.startswith("kalman") else 6, mfc="none" if key.startswith("kalman") else col)
        ax.plot(x, PUBLISHED[pub], "x--", color=col, alpha=0.6, label=f"{lab.split(',')[0]} — published")
    ax.plot(x, [pooled[f][sk + "_mid"] for f in fr], "-s", color="tab:cyan", label="sum-of-norms, mid-window node")
    ax.plot(x, [pooled_min[f]["kalman_q1"] for f in fr], "-^", color="tab:green", label="Kalman q = 1 (minimum error)")
    ax.set_xlabel("outliers (%)")
    ax.set_ylabel("RMS position error (m)")
    ax.set_title("García Carrillo et al., Table I: reproduced (solid) vs published (dashed)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(docs / "carrillo_table1.png", dpi=130)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(8, 5))
    ds = [d for d in deltas if d < 1e3]
    for f, col in zip(fr, plt.cm.viridis(np.linspace(0, 0.9, len(fr)))):
        ax.semilogx(ds, [pooled[f][f"son_d{d:g}"] for d in ds], "-o", color=col, label=f"{100 * f:g} % outliers")
        ax.axhline(pooled[f]["bls"], color=col, ls="--", lw=0.8)
        ax.plot([ds[-1] * 1.6], [pooled[f]["son_d1000"]], ">", color=col)
    ax.set_xlabel("Huber threshold δ (whitened σ units)")
    ax.set_ylabel("RMS position error, newest node (m)")
    ax.set_title("δ sweep (dashed: BLS; ▸: δ = 1000, equal to BLS)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    sec = ax.twiny()
    sec.set_xscale("log")
    sec.set_xlim(ax.get_xlim())
    ticks = [d for d in (0.003, 0.01, 0.03, 0.1, 0.3, 1, 3, 10) if ds[0] <= d <= ds[-1]]
    sec.set_xticks(ticks)
    sec.set_xticklabels([f"{lambda_from_delta(d, PAPER_SCALE):.3f}\n{lambda_from_delta(d):.2f}" for d in ticks],
                        fontsize=7)
    sec.minorticks_off()
    sec.set_xlabel(f"λ at residual scale c = {PAPER_SCALE:g} (upper) and c = 1 (lower)", fontsize=8)
    fig.tight_layout()
    fig.savefig(docs / "carrillo_lambda_sweep.png", dpi=130)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help="2 seeds, 30 s runs (smoke test; writes nothing)")
    ap.add_argument("--duration", type=float, default=None, help="seconds per run (default: the scenario's)")
    ap.add_argument("--docs", default=str(ROOT / "docs"), help="output directory")
    a = ap.parse_args(argv)
    t0 = time.time()
    seeds = 2 if a.quick else a.seeds
    dur = 30.0 if a.quick else a.duration
    sc, pooled, pooled_min, deltas = run_all(seeds, PUBLISHED["fractions"], dur)
    robust = run_robust(seeds, PUBLISHED["fractions"], dur)
    out = Path(a.docs)
    out.mkdir(parents=True, exist_ok=True)
    (out / "carrillo_robust.json").write_text(json.dumps(
        {"seeds": seeds, "duration_s": dur or sc.duration,
         "rmse": {f"{m}/{f:g}": v for (m, f), v in robust[0].items()},
         "sigma_hat": {f"{m}/{f:g}": v for (m, f), v in robust[1].items()}}, indent=1) + "\n")
    lag = mid_lag(sc)
    elapsed = time.time() - t0
    for f in PUBLISHED["fractions"]:
        print(f, {k: round(v, 2) for k, v in pooled[f].items()})
    if a.quick:
        return
    docs = out
    write_markdown(docs / "carrillo_table1.md", sc, pooled, pooled_min, deltas, seeds, lag, elapsed, robust)
    figures(docs, pooled, pooled_min, deltas, float(sc.fusion["delta"]))
    print(f"wrote docs/carrillo_table1.md and two figures in {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
