"""The dashboard's consistency panel (dashboards/nees.py, dashboards/state.py, dashboards/plots.py): each
tick's NEES εᵢ = eᵢ′Pᵢ⁻¹eᵢ against the covariance reported for x̂ᵢ,ₖ (the P sent with tick k − 1), the mean
over the nodes and its 95 % χ² band — the same numbers as the run's summary.json — and the log-scale
panel that shows them only when the estimates carry covariances."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image
from scipy.stats import chi2

from agent.wire import Estimate
from dashboards import plots
from dashboards.live import replay_model_from_file
from dashboards.nees import chi2_interval, nees, network_nees, usable_covariances
from dashboards.state import DashboardState, RunInfo, synthetic_tick
from flocktrack.record import credibility

from conftest import ROOT
from dashboard_feed import feed


def with_covariances(msgs, cov_of):
    """A synthetic tick's messages with each node's estimate carrying ``cov_of(i)`` (None: no P)."""
    out = []
    for key, m in msgs:
        if isinstance(m, Estimate) and key.startswith("agent/"):
            m = Estimate(src=m.src, k=m.k, x=m.x, x_next=m.x_next, P=cov_of(m.src), name=m.name)
        out.append((key, m))
    return out


# ----------------------------------------------------------------------------- the pure pieces

def test_nees_is_e_P_inverse_e_by_hand():
    E = np.array([[1.0, 2.0], [1.0, 1.0], [3.0, 0.0]])
    P = np.array([np.diag([1.0, 4.0]), [[2.0, 1.0], [1.0, 2.0]], np.eye(2) * 9.0])
    # 1²/1 + 2²/4 = 2;  [1 1]·(1/3)[[2 −1] [−1 2]]·[1 1]′ = 2/3;  3²/9 = 1
    np.testing.assert_allclose(nees(E, P), [2.0, 2.0 / 3.0, 1.0], rtol=1e-14)


def test_a_covariance_that_is_not_symmetric_positive_definite_is_skipped():
    good = np.diag([1.0, 2.0])
    Ps = np.array([good, [[1.0, 0.5], [0.0, 1.0]], np.diag([1.0, 0.0]), np.diag([1.0, -1.0]),
                   [[np.nan, 0.0], [0.0, 1.0]], good, np.zeros((2, 2))])
    E = np.ones((7, 2))
    E[5, 1] = np.inf                                    # an error that is not finite: no NEES either
    assert usable_covariances(Ps).tolist() == [True, False, False, False, False, True, False]
    eps = nees(E, Ps)
    assert eps[0] == pytest.approx(1.5) and np.isnan(eps[1:]).all()
    assert nees(np.ones((2, 3)), np.ones((2, 2, 2))).shape == (2,)   # wrong shapes: all NaN, no raise
    assert np.isnan(nees(np.ones((2, 3)), np.ones((2, 2, 2)))).all()


def test_the_band_is_the_two_sided_chi2_interval_of_the_mean():
    for n_k, m in ((1, 4), (10, 4), (12, 2), (100, 6)):
        lo, hi = chi2_interval(n_k * m, n_k)
        assert lo == pytest.approx(chi2.ppf(0.025, n_k * m) / n_k, rel=1e-12)
        assert hi == pytest.approx(chi2.ppf(0.975, n_k * m) / n_k, rel=1e-12)
        assert (lo, hi) == pytest.approx(credibility.chi2_interval(n_k * m, n_k), rel=1e-12)
        assert lo < m < hi


def test_the_network_nees_is_the_run_summarys_anees_of_the_same_samples():
    """One tick's nodes are what consistency() pools over: the same mean and the same interval."""
    rng = np.random.default_rng(3)
    m, n = 4, 9
    A = rng.normal(size=(n, m, m))
    P = A @ A.swapaxes(1, 2) + 0.1 * np.eye(m)
    E = np.einsum("kij,kj->ki", np.linalg.cholesky(P), rng.normal(size=(n, m)))
    r = network_nees(E, P)
    ref = credibility.consistency(E, P)
    assert r["scored"] == ref["samples"] == n
    assert r["mean"] == pytest.approx(ref["anees"], rel=1e-12)
    assert [r["lo"], r["hi"]] == pytest.approx(ref["interval"], rel=1e-12)
    P[2] = -P[2]                                        # a node with an unusable P: left out of both
    r, ref = network_nees(E, P), credibility.consistency(E, P)
    assert r["scored"] == ref["samples"] == n - 1 and np.isnan(r["per_node"][2])
    assert r["mean"] == pytest.approx(ref["anees"], rel=1e-12)
    assert [r["lo"], r["hi"]] == pytest.approx(ref["interval"], rel=1e-12)


# ----------------------------------------------------------------------------- the model

def test_each_ticks_nees_uses_the_covariance_sent_with_the_tick_before():
    """Tick k scores x̂ᵢ,ₖ against the P that came with tick k − 1 (here (k)·σ²I: each tick's own would give
    other numbers); a node that sent no P then is left out of the mean and of the band's n; tick 0 has none."""
    n, ticks, noise = 5, 6, 0.1
    msgs = []
    for k in range(ticks):
        cov = (lambda i, k=k: None if (i == 2 and k == 3) else (k + 1) * noise ** 2 * np.eye(4))
        msgs.append(with_covariances(synthetic_tick(n, k, noise=noise), cov))
    st = DashboardState(RunInfo(n=n))
    feed(st, msgs)
    st.finalize_all()
    s = st.series()
    assert np.isnan(s["nees"][0]) and np.isnan(s["nees_lo"][0]) and np.isnan(s["nees_node"][0]).all()
    for k in range(1, ticks):
        truth = next(m.x for key, m in msgs[k] if key == "target/truth")
        est = {m.src: m.x for key, m in msgs[k] if key.endswith("/estimate")}
        scored = [i for i in range(n) if not (i == 2 and k == 4)]
        eps = {i: float(np.sum((est[i] - truth) ** 2)) / (k * noise ** 2) for i in scored}
        assert s["nees_scored"][k] == len(scored)
        assert s["nees"][k] == pytest.approx(np.mean(list(eps.values())), rel=1e-10)
        lo, hi = chi2.ppf([0.025, 0.975], 4 * len(scored)) / len(scored)
        assert (s["nees_lo"][k], s["nees_hi"][k]) == pytest.approx((lo, hi), rel=1e-10)
        for i in range(n):
            if i in eps:
                assert s["nees_node"][k, i] == pytest.approx(eps[i], rel=1e-10)
            else:
                assert np.isnan(s["nees_node"][k, i])
    snap = st.snapshot(ticks - 1)
    np.testing.assert_array_equal(snap.nees, s["nees_node"][-1])


def test_a_run_without_covariances_has_no_nees_and_no_panel():
    n = 4
    st = DashboardState(RunInfo(n=n))
    feed(st, [with_covariances(synthetic_tick(n, k), lambda i: None) for k in range(5)])
    s = st.series()
    assert np.isnan(s["nees"]).all() and np.isnan(s["nees_node"]).all()
    assert "nees" not in [p.key for p in plots.uplot_panels(s, n, selected=1)]


def test_a_hostile_covariance_gives_a_gap_not_an_error():
    """A P that is finite but absurd (an overflow in its inverse, an asymmetric one, a wrong shape in a
    message that bypassed the wire's checks) leaves that node out; the others are still scored."""
    n = 4
    bad = {0: 1e-320 * np.eye(4), 1: np.triu(np.ones((4, 4))), 2: np.eye(3), 3: None}
    ticks = [synthetic_tick(n, 0), with_covariances(synthetic_tick(n, 1), lambda i: bad[i]), synthetic_tick(n, 2),
             synthetic_tick(n, 3)]
    st = DashboardState(RunInfo(n=n))
    with np.errstate(all="ignore"):
        feed(st, ticks)
        st.finalize_all()
    s = st.series()
    assert np.isnan(s["nees"][2]) and np.isnan(s["nees_node"][2]).all()
    assert np.isfinite(s["nees"][[1, 3]]).all() and s["nees_scored"][3] == n


# ----------------------------------------------------------------------------- the panel and the figure

def test_the_nees_panel_has_the_line_its_band_and_the_selected_sensor_on_a_log_scale():
    n = 6
    st = DashboardState(RunInfo(n=n))
    feed(st, [synthetic_tick(n, k) for k in range(30)])
    s = st.series()
    s["nees"][7] = 0.0                                  # a log axis cannot draw 0: a gap
    p = next(p for p in plots.uplot_panels(s, n, selected=3) if p.key == "nees")
    assert p.labels == ["tick", "NEES", "95 % lo", "95 % hi", "ε3"]
    assert p.scales["y"]["distr"] == 3                  # uPlot's logarithmic distribution
    assert p.scales["y"]["clamp"] < 0                   # a gap is left out, not drawn at the panel's bottom
    k, net, lo, hi, own = p.data
    assert len(k) == 31 and k[0] < k[1] == 0            # the anchor row before tick 0 (no NEES there)
    np.testing.assert_array_equal(net[2:], np.where(np.arange(1, 30) == 7, np.nan, s["nees"][1:]))
    np.testing.assert_array_equal(own[2:], s["nees_node"][1:, 3])
    assert np.all(lo[2:] < hi[2:]) and np.all((lo[2:] > 0) & (hi[2:] > 0))
    without = next(p for p in plots.uplot_panels(s, n, selected=None) if p.key == "nees")
    assert without.labels == ["tick", "NEES", "95 % lo", "95 % hi"]


def test_the_static_figure_holds_the_nees_panel(tmp_path):
    n = 5
    st = DashboardState(RunInfo(n=n))
    feed(st, [synthetic_tick(n, k) for k in range(15)])
    with_p, without = tmp_path / "with.png", tmp_path / "without.png"
    plots.save_static_png(with_p, st.series(), st.snapshot(), n, selected=1)
    bare = DashboardState(RunInfo(n=n))
    feed(bare, [with_covariances(synthetic_tick(n, k), lambda i: None) for k in range(15)])
    plots.save_static_png(without, bare.series(), bare.snapshot(), n, selected=1)
    # six panels and the numbers take a fourth row; five fit in three
    h_with, h_without = Image.open(with_p).size[1], Image.open(without).size[1]
    assert h_with == pytest.approx(4 / 3 * h_without, rel=0.02)


# ----------------------------------------------------------------------------- real runs

@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Gu & Hu's minimax filter (covariances) and Chen's H∞ filter (none), short in-process recordings."""
    from flocktrack.cli import main

    out = {}
    for name, scen, ticks in (("gh", "gu_hu_intelligent.toml", 60), ("chen", "chen_switching.toml", 30)):
        d = tmp_path_factory.mktemp(name)
        assert main(["run", str(ROOT / "scenarios" / scen), "--transport", "inproc", "--record", "--ticks", str(ticks),
                     "--out", str(d)]) == 0
        out[name] = d
    return out


def test_a_recordings_nees_is_the_one_its_summary_reports(runs):
    """The dashboard's εᵢ of a real run, pooled over the ticks summary.json scores (from its ``from_tick``),
    give that summary's network ANEES and each node's."""
    d = runs["gh"]
    s = replay_model_from_file(d / "recording.mcap").state.series()
    cred = json.loads((d / "summary.json").read_text())["credibility"]
    own = s["nees_node"][s["k"] >= cred["from_tick"]]
    assert np.isfinite(own).sum() == cred["network"]["samples"]
    assert np.nanmean(own) == pytest.approx(cred["network"]["anees"], rel=1e-12)
    for i, c in cred["nees"].items():
        assert np.nanmean(own[:, int(i)]) == pytest.approx(c["anees"], rel=1e-12)
    assert np.isfinite(s["nees"][1:]).all() and "nees" in [p.key for p in plots.uplot_panels(s, 10)]


def test_a_filter_without_covariances_shows_no_nees_panel(runs):
    model = replay_model_from_file(runs["chen"] / "recording.mcap")
    s = model.state.series()
    assert len(s["k"]) and np.isnan(s["nees"]).all()
    assert "nees" not in [p.key for p in plots.uplot_panels(s, model.info.n)]
    assert math.isnan(model.snapshot(model.last).row.get("nees", math.nan))
