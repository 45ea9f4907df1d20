"""The dashboard's model (dashboards/state.py), its figures (dashboards/plots.py), the recording reader
and the live loop — without a browser (tests/browser/test_dashboard_browser.py has the real-browser tests)."""

from __future__ import annotations

import ast
import csv
import json
import math
import random
from pathlib import Path

import numpy as np
import pytest

from agent.wire import Control, End, Estimate, decode, encode
from dashboards import plots
from dashboards.live import LiveDashboard, load_recording, replay_model_from_file
from dashboards.state import (DashboardState, RateMeter, RunInfo, algebraic_connectivity_of_links,
                              synthetic_tick)

from dashboard_feed import feed

ROOT = Path(__file__).resolve().parents[2]
SCEN = ROOT / "scenarios"


def synth(n, ticks, **kw):
    return [synthetic_tick(n, k, **kw) for k in range(ticks)]


# ----------------------------------------------------------------------------- against the metrics of real runs

@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """Two short in-process runs with recordings: Gu & Hu (flocking, range links, covariances) and
    Chen et al. (switching schedule, TMSEE lower bound)."""
    from flocktrack.cli import main

    out = {}
    for name, scen, ticks in (("gh", "gu_hu_intelligent.toml", 60), ("chen", "chen_switching.toml", 80)):
        d = tmp_path_factory.mktemp(name)
        assert main(["run", str(SCEN / scen), "--transport", "inproc", "--record", "--ticks", str(ticks),
                     "--out", str(d)]) == 0
        out[name] = d
    return out


@pytest.mark.parametrize("name", ["gh", "chen"])
def test_series_equal_the_runtime_metrics_on_a_recording(recorded, name):
    d = recorded[name]
    model = replay_model_from_file(d / "recording.mcap")
    rows = list(csv.DictReader(open(d / "metrics.csv")))
    s = model.state.series()
    assert len(s["k"]) == len(rows) == len(model)
    assert list(s["k"].astype(int)) == [int(r["k"]) for r in rows]
    for col in ("rmse", "tmsee", "disagreement", "mean_err", "lambda2", "links"):
        ref = np.array([float(r[col]) for r in rows])
        np.testing.assert_allclose(s[col], ref, rtol=1e-12, atol=1e-12, err_msg=col)
    n = model.info.n
    err = np.array([[float(r[f"err_{i}"]) for i in range(n)] for r in rows])
    np.testing.assert_allclose(s["err"], err, rtol=1e-12, atol=1e-12)
    assert np.all(s["missing"] == 0) and np.all(s["drop_rate"] == 0)
    assert np.all(s["msg_rate"] > 0)
    if name == "chen":  # the pre-run design's TMSEE lower bound comes along from the recording's metadata
        lower = json.loads((d / "design.json").read_text())["tmsee_lower"]
        np.testing.assert_allclose(s["tmsee_lower"], lower[: len(rows)])
        specs = plots.uplot_panels(s, n)
        assert "lower bound" in specs[1].title and len(specs[1].series) == 3
    else:
        assert np.all(np.isnan(s["tmsee_lower"]))


def test_replay_slider_seek(recorded):
    d = recorded["gh"]
    model = replay_model_from_file(d / "recording.mcap")
    rec = load_recording(d / "recording.mcap")
    ticks = {m.k: m for k, m, _ in rec.messages if k == "world/tick"}
    truth = {m.k: m.x for k, m, _ in rec.messages if k == "target/truth"}
    assert model.first == 0 and model.last == 59
    for k in (40, 5, 59, 0, 33):  # forwards and backwards: any order, same answer
        snap = model.snapshot(k)
        assert snap.k == k
        np.testing.assert_array_equal(snap.positions[:, :2], ticks[k].positions)
        np.testing.assert_array_equal(snap.truth_pos[:2], truth[k][:2])
        assert snap.neighbours == ticks[k].links
        assert len(snap.edges) == sum(map(len, ticks[k].links)) // 2
        assert len(snap.trail) == min(k + 1, 200)
        assert np.all(np.isfinite(snap.errors))
        assert set(snap.cov_pos) == set(range(model.info.n))       # minimax publishes P
        s = model.series(k)
        assert s["k"][-1] == k and len(s["k"]) == k + 1
    assert model.seek(10_000) == 59 and model.seek(-5) == 0
    assert model.series(30, last=10)["k"].tolist() == list(range(21, 31))


def test_truncated_recording_still_replays(recorded, tmp_path):
    src = (recorded["gh"] / "recording.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(src[: int(len(src) * 0.6)])
    rec = load_recording(cut)
    assert not rec.complete and "scenario" in rec.metadata
    full = load_recording(recorded["gh"] / "recording.mcap")
    assert 0 < len(rec.messages) < len(full.messages)
    model = replay_model_from_file(cut)
    assert 10 < len(model) < 60


def test_static_png_of_a_recording(recorded, tmp_path):
    from dashboards.__main__ import main

    out = tmp_path / "summary.png"
    assert main(["--recording", str(recorded["gh"] / "recording.mcap"), "--png", str(out), "--tick", "50"]) == 0
    import matplotlib.image as mpimg

    img = mpimg.imread(out)
    assert img.shape[0] > 500 and img.shape[1] > 1000
    assert img[..., :3].std() > 0.05  # not a blank page


# ----------------------------------------------------------------------------- the model on synthetic streams

def test_lambda2_of_known_graphs():
    path4 = [[1], [0, 2], [1, 3], [2]]
    assert algebraic_connectivity_of_links(path4) == pytest.approx(2 - math.sqrt(2))
    k5 = [[j for j in range(5) if j != i] for i in range(5)]
    assert algebraic_connectivity_of_links(k5) == pytest.approx(5.0)
    assert algebraic_connectivity_of_links([[1], [0], [3], [2]]) == pytest.approx(0.0, abs=1e-12)
    assert algebraic_connectivity_of_links([[]]) == 0.0


def test_errors_and_prompt_finalization():
    n = 6
    st = DashboardState(RunInfo(n=n))
    msgs = synth(n, 5, noise=0.2)
    feed(st, msgs)
    assert st.finalized_k == 4 and st.latest_tick == 4  # complete ticks are scored without waiting
    s = st.series()
    assert s["k"].tolist() == [0, 1, 2, 3, 4]
    truth = [m.x for k, m in msgs[3] if k == "target/truth"][0]
    est = {m.src: m.x for k, m in msgs[3] if k.endswith("/estimate")}
    e = [np.linalg.norm(est[i][:2] - truth[:2]) for i in range(n)]
    np.testing.assert_allclose(s["err"][3], e)
    assert s["rmse"][3] == pytest.approx(np.sqrt(np.mean(np.square(e))))
    X = np.array([est[i] for i in range(n)])
    assert s["tmsee"][3] == pytest.approx(np.sum((X - truth) ** 2))
    assert s["disagreement"][3] == pytest.approx(np.sqrt(np.mean(np.sum((X - X.mean(0)) ** 2, axis=1))))
    snap = st.snapshot()
    assert snap.k == 4 and np.allclose(snap.errors, s["err"][4])


def test_missing_estimates_and_bus_drops_count_as_dropped():
    n = 5
    st = DashboardState(RunInfo(n=n), lag=2)
    ticks = [synthetic_tick(n, k, skip_estimates=(2,) if 5 <= k < 10 else ()) for k in range(25)]
    feed(st, ticks)
    s = st.series()
    assert s["missing"].tolist() == [0] * 5 + [2] * 5 + [0] * 15   # estimate + state of sensor 2
    assert st.missing_total == 10
    assert np.isnan(s["err"][7, 2]) and np.isfinite(s["err"][7, 1])
    # counted when noticed (tick k is given up when tick k+2 arrives), over a 1 s window
    assert s["drop_rate"][9] == 10 and s["drop_rate"][24] == 0
    st.note_bus_dropped(3, now=2.0)
    st.note_bus_dropped(3, now=2.0)                                 # cumulative: no double count
    assert st.drop_meter.total == 13
    assert st.summary()["bus_dropped"] == 3


def test_message_rate_from_the_clock():
    n = 4
    st = DashboardState(RunInfo(n=n))
    ticks = synth(n, 30)
    per_tick = len(ticks[0])
    feed(st, ticks, dt=0.1)
    s = st.series()
    # 1 s window, 10 ticks per second: ten ticks' worth of messages per second
    assert s["msg_rate"][-1] == pytest.approx(10 * per_tick, rel=0.15)
    m = RateMeter(window_s=1.0)
    for i in range(50):
        m.add(i * 0.02)
    assert m.rate(0.99) == pytest.approx(50.0)
    assert m.rate(5.0) == 0.0


def test_dead_sensors_are_not_missing_and_are_grey():
    n = 6
    alive = [True, True, True, False, True, True]
    st = DashboardState(RunInfo(n=n, link_range=12.0))
    feed(st, [synthetic_tick(n, k, alive=alive) for k in range(4)])
    assert st.finalized_k == 3 and st.missing_total == 0
    snap = st.snapshot()
    assert not snap.alive[3] and np.isnan(snap.errors[3]) and snap.neighbours[3] == []
    s = st.series()
    assert np.all(s["lambda2"] == 0) and np.all(s["lambda2_alive"] > 0)   # the dead sensor is isolated
    sa = plots.scene_arrays(snap, selected=3, error_scale=1.0, link_range=12.0)
    assert tuple(sa.sensor_colors[3]) == tuple(plots.DEAD)
    assert sa.ellipse.shape[0] == 0 and sa.selected_links.shape[0] == 0


def test_out_of_order_delivery_gives_the_same_series():
    n = 5
    ticks = synth(n, 12)
    a = DashboardState(RunInfo(n=n))
    feed(a, ticks)
    # interleave neighbouring ticks: estimates of k may come after the world's tick k+1
    flat = [(j, km) for j, t in enumerate(ticks) for km in t]
    rng = random.Random(4)
    shuffled = sorted(flat, key=lambda x: x[0] + rng.uniform(0, 1.5))
    b = DashboardState(RunInfo(n=n), lag=3)
    for j, (key, m) in shuffled:
        if m is None:
            b.count(j * 0.1)
        else:
            b.ingest(key, m, j * 0.1)
    b.finalize_all()
    sa, sb = a.series(), b.series()
    for c in ("k", "rmse", "tmsee", "disagreement", "lambda2", "missing"):
        np.testing.assert_array_equal(sa[c], sb[c], err_msg=c)


def test_memory_is_bounded_for_long_live_runs():
    n = 8
    st = DashboardState(RunInfo(n=n), keep_frames=50, max_points=100, trail_len=30)
    for k in range(1000):
        for key, m in synthetic_tick(n, k):
            if m is not None:
                st.ingest(key, m, k * 0.1)
    assert st.finalized_k == 999
    assert len(st.frames) <= 52 and len(st.truth_pos) <= 52
    assert len(st.series_buf) <= 200
    s = st.series()
    assert len(s["k"]) == 100 and s["k"][-1] == 999 and np.all(np.diff(s["k"]) == 1)
    assert len(st.snapshot().trail) == 30
    assert st.snapshot(10) is None  # long gone


def test_world_events_and_controls():
    st = DashboardState(RunInfo(n=3))
    st.ingest("control/pause", Control(verb="pause"), 0.0)
    assert st.controls[-1][1] == "pause" and not st.paused       # asked, not yet applied
    st.ingest("world/event", Control(k=7, verb="pause"), 0.1)
    assert st.paused and st.events[-1] == (7, "pause", {})
    st.ingest("world/event", Control(k=9, verb="speed", args={"factor": 2.0}), 0.2)
    st.ingest("world/event", Control(k=9, verb="resume"), 0.2)
    assert not st.paused and st.speed == 2.0
    st.ingest("world/end", End(k=10), 0.3)
    assert st.ended


def test_fusion_estimate_is_shown_and_scored():
    n = 4
    st = DashboardState(RunInfo(n=n))
    for k in range(3):
        msgs = synthetic_tick(n, k)
        x = [m.x for key, m in msgs if key == "target/truth"][0]
        msgs.append(("fusion/estimate", Estimate(k=k, x=x + 0.5, x_next=x, name="SON")))
        feed(st, [msgs], k0=k)
    s = st.series()
    assert s["fusion_err"][-1] == pytest.approx(math.hypot(0.5, 0.5))
    assert st.snapshot().fusion_pos is not None
    specs = plots.uplot_panels(s, n)
    assert "fusion" in specs[2].labels


def _assert_plottable(s: dict, n: int) -> None:
    """What a uPlot panel needs to draw (see plots.drawable): per panel, columns of one length, x strictly
    increasing, no ±inf, every line finite in its first row."""
    assert np.all(np.diff(s["k"]) > 0)
    for c, v in s.items():
        assert not np.isinf(v).any(), c
    for p in plots.uplot_panels(s, n):
        assert len({len(a) for a in p.data}) == 1, p.key
        assert np.all(np.diff(p.data[0]) > 0), p.key
        for y, ser in zip(p.data[1:], p.series[1:]):
            assert np.isfinite(y[0]) and not np.isinf(y).any(), (p.key, ser["label"], y[:3])


def test_a_dashboard_joining_during_a_tick_scores_from_its_first_world_tick():
    """The live dashboard starts its web server before it subscribes, so it joins a run that is going — in
    the middle of a tick whose world tick and truth it never sees. That frame used to be scored: a first row
    of NaN (which blanked four uPlot panels for the whole run, tests/browser/test_dashboard_browser.py) and every
    sensor's estimate and state counted as dropped. Now it is left out."""
    n = 6
    ticks = synth(n, 8)
    ticks[0] = [(key, m) for key, m in ticks[0] if key not in ("world/tick", "target/truth")]
    st = DashboardState(RunInfo(n=n))
    feed(st, ticks)
    s = st.series()
    assert s["k"].tolist() == list(range(1, 8)) and st.partial_start == 1
    assert st.missing_total == 0 and np.all(s["missing"] == 0)
    for c in ("rmse", "tmsee", "disagreement", "mean_err", "lambda2", "links"):
        assert np.isfinite(s[c]).all(), c
    _assert_plottable(s, n)
    # a run without any world (no tick at all) is still scored as before: nothing to tell a late join by
    nw = DashboardState(RunInfo(n=n))
    feed(nw, [[(key, m) for key, m in t if key != "world/tick"] for t in synth(n, 5)])
    nw.finalize_all()
    assert nw.series()["k"].tolist() == [0, 1, 2, 3, 4] and nw.partial_start == 0


def test_a_starved_stream_keeps_every_series_plottable():
    """Gaps, NaN, restarts, late and out-of-order data — what a starved machine delivers — give series the
    plots can draw, with the gaps where the data is missing."""
    n = 5
    ticks = []
    for k in range(60):
        alive = [not (i == 3 and 20 <= k < 30) for i in range(n)]          # sensor 3 dies and comes back
        t = synthetic_tick(n, k, alive=alive)
        if 5 <= k < 8:                                                     # no estimate from any sensor
            t = [(key, m) for key, m in t if not key.endswith(("/estimate", "/state"))]
        if k in (12, 13, 14):                                              # nothing at all about the tick
            t = []
        ticks.append(t)
    late_est = {k: [km for km in ticks[k] if km[0].endswith("/estimate")] for k in range(40, 45)}
    for k, est in late_est.items():                                        # estimates after the next tick
        ticks[k] = [km for km in ticks[k] if km not in est]
        ticks[k + 1] = ticks[k + 1][:1] + est + ticks[k + 1][1:]
    ticks[50] += [km for km in synthetic_tick(n, 46) if km[0] == "agent/0/estimate"]   # late
    ticks[52] = ticks[52][:1] + ticks[52]                                  # world tick twice
    st = DashboardState(RunInfo(n=n))
    feed(st, ticks)
    st.ingest("world/end", End(k=60), 6.0)
    s = st.series()
    _assert_plottable(s, n)
    k = s["k"].astype(int).tolist()
    assert k == [j for j in range(60) if j not in (13, 14)]               # one gap row for 12–14
    row = {kk: i for i, kk in enumerate(k)}
    assert np.isnan(s["rmse"][row[12]]) and np.isnan(s["lambda2"][row[12]]) and s["missing"][row[12]] == 2 * n * 3
    assert st.gap_ticks == 3
    assert all(np.isnan(s["rmse"][row[j]]) and s["missing"][row[j]] == 2 * n for j in (5, 6, 7))
    assert np.isfinite(s["rmse"][row[8]]) and np.isfinite(s["lambda2"][row[5]])
    assert np.isnan(s["err"][row[25], 3]) and np.isfinite(s["err"][row[35], 3])  # dead, then back
    assert all(s["missing"][row[j]] == 0 for j in range(40, 46))           # reordered, not lost
    assert st.late >= 1 and st.ended


def test_non_finite_metrics_are_gaps_not_infinities():
    """An estimate far enough off overflows the TMSEE to inf, and a message that bypassed validation may
    hold NaN: the series get NaN (a gap), never ±inf — which uPlot cannot draw at all."""
    n = 3
    ticks = synth(n, 4)
    for j, (key, m) in enumerate(ticks[1]):
        if key == "agent/0/estimate":
            ticks[1][j] = (key, Estimate(src=0, k=1, x=m.x + 1e200, x_next=m.x, name="Synthetic"))
        if key == "agent/1/estimate":
            ticks[2][j] = (key, Estimate(src=1, k=2, x=m.x * np.nan, x_next=m.x, name="Synthetic"))
    st = DashboardState(RunInfo(n=n))
    with np.errstate(all="ignore"):
        feed(st, ticks)
        st.finalize_all()
    s = st.series()
    assert np.isnan(s["tmsee"][1]) and np.isnan(s["rmse"][1]) and np.isnan(s["err"][1, 0])  # ‖·‖ overflowed
    assert np.isfinite(s["err"][1, 1:]).all() and np.isfinite(s["disagreement"][0])
    assert np.isnan(s["rmse"][2]) and np.isnan(s["err"][2, 1])
    assert np.isfinite(s["rmse"][[0, 3]]).all()
    _assert_plottable(s, n)


def test_drawable_gives_uplot_a_finite_start_and_no_infinities():
    """plots.drawable: a column that is not finite in the first row gets an anchor row just before it,
    with its own first value (no range change, no visible line); a column without any value borrows one
    from its scale; ±inf → NaN; rows whose x is not strictly increasing go."""
    series = ({"label": "k"}, {"label": "a"}, {"label": "b"}, {"label": "c", "scale": "links"})
    x = np.array([3.0, 4.0, 4.0, 5.0, 6.0])
    a = np.array([np.nan, 2.0, 9.0, np.inf, 3.0])
    b = np.full(5, np.nan)
    c = np.array([np.nan, np.nan, 0.0, 7.0, 8.0])
    X, A, B, C = plots.drawable((x, a, b, c), series)
    np.testing.assert_array_equal(X, [3 - plots.ANCHOR_DX, 3, 4, 5, 6])
    np.testing.assert_array_equal(A, [2.0, np.nan, 2.0, np.nan, 3.0])
    np.testing.assert_array_equal(B, [2.0, np.nan, np.nan, np.nan, np.nan])    # a's value: same scale "y"
    np.testing.assert_array_equal(C, [7.0, np.nan, np.nan, 7.0, 8.0])          # its own first value
    clean = (np.arange(4.0), np.ones(4))
    assert all(np.array_equal(u, v) for u, v in zip(plots.drawable(clean, series[:2]), clean))
    with pytest.raises(ValueError):
        plots.drawable((np.arange(3.0), np.ones(2)), series[:2])


def test_camera_framing_fits_the_flock():
    """The 3-D view's framing: the centre of the flock and target's bounding box, a sphere around all of
    them, and a camera distance at which that sphere fits the view's narrower angle."""
    n = 12
    st = DashboardState(RunInfo(n=n, link_range=12.0))
    feed(st, synth(n, 3))
    snap = st.snapshot()
    fr = plots.flock_framing(snap, min_radius=1.0)
    pts = np.vstack([snap.positions, snap.truth_pos[None]])
    np.testing.assert_allclose(fr.centre, 0.5 * (pts.min(0) + pts.max(0)))
    assert fr.radius == pytest.approx(np.linalg.norm(pts - fr.centre, axis=1).max())
    fov = math.radians(75)
    d_wide, d_tall = (plots.camera_distance(fr.radius, fov, a) for a in (1.6, 0.5))
    assert d_wide == pytest.approx(1.15 * fr.radius / math.sin(fov / 2))          # the height limits
    assert d_tall > d_wide                                                        # a narrow view stands back
    half_h = math.atan(math.tan(fov / 2) * 0.5)
    assert fr.radius * 1.15 / d_tall == pytest.approx(math.sin(half_h))
    lone = plots.flock_framing(st.snapshot(), min_radius=1e3)
    assert lone.radius == 1e3
    snap.positions[:] = np.nan
    snap.truth_pos = None
    assert plots.flock_framing(snap) is None


# ----------------------------------------------------------------------------- figures

def test_scene_arrays_are_batched_for_a_hundred_sensors():
    n = 100
    st = DashboardState(RunInfo(n=n, link_range=12.0))
    feed(st, synth(n, 3))
    snap = st.snapshot()
    sa = plots.scene_arrays(snap, selected=17, error_scale=0.3, link_range=12.0, circle_segments_n=32)
    assert sa.sensor_points.shape == (n, 3) and sa.sensor_colors.shape == (n, 3)
    assert sa.sensor_colors.dtype == np.uint8
    assert sa.estimate_points.shape == (n, 3)
    assert sa.links.shape == (len(snap.edges), 2, 3) and len(snap.edges) > n
    assert sa.circles.shape == (n * 32, 2, 3)
    assert len(sa.selected_links) == len(snap.neighbours[17])
    assert sa.ellipse.shape == (64, 2, 3)
    # the 2σ ellipse of P = 0.01·I is a circle of radius 0.2 around x̂ₖ₊₁
    r = np.linalg.norm(sa.ellipse[:, 0, :2] - snap.est_next[17][:2], axis=1)
    np.testing.assert_allclose(r, 0.2, rtol=1e-5)
    off = plots.scene_arrays(snap, show_circles=False)
    assert off.circles.shape == (0, 2, 3)


def test_error_colors():
    c = plots.error_colors(np.array([0.0, 0.5, 1.0, 5.0, np.nan]), np.array([1, 1, 1, 1, 1], bool), 1.0)
    assert tuple(c[0]) == (40, 170, 80) and tuple(c[2]) == (210, 30, 40) and tuple(c[3]) == (210, 30, 40)
    assert tuple(c[4]) == tuple(plots.UNKNOWN)
    assert plots.auto_error_scale(np.array([[1.0, 2.0, np.nan]])) == pytest.approx(4.5)


def test_uplot_panels_shapes():
    for n, expect_err_series in ((6, 1 + 6 + 1), (40, 1 + 3 + 1)):
        st = DashboardState(RunInfo(n=n))
        feed(st, synth(n, 20))
        s = st.series()
        panels = plots.uplot_panels(s, n, selected=2)
        assert [p.key for p in panels] == ["errors", "tmsee", "disagreement", "lambda2", "rates", "nees"]
        for p in panels:
            # (tick 0 has no NEES — no covariance came before it —: the NEES panel's anchor row)
            rows = 20 + (p.key == "nees")
            assert len(p.data) == len(p.series) and all(len(a) == rows for a in p.data)
            assert p.scales["x"] == {"time": False}
        assert len(panels[0].series) == expect_err_series
    small = plots.decimate(s, 7)
    assert len(small["k"]) <= 7 and small["k"][-1] == s["k"][-1]


def test_camera_reports_tell_the_users_moves_from_ours():
    """The live UI stops following the flock when the user moves a tab's camera, and knows it only from the
    poses the tab reports. Its own commands come back late and in pieces — a position alone (the look-at
    kept), a look-at alone, an older look-at with a newer position — so a report is ours when its position
    and its look-at are each one we sent; a user's orbit, pan or zoom moves at least one of them elsewhere."""
    from dashboards.camera import ClientView

    v = ClientView()
    v.remember(0, (0.0, -30.0, 40.0), (0.0, 0.0, 0.0))                  # the page's initial camera
    for seq in (1, 2, 3):                                               # three commands gliding east
        v.seq = seq
        v.remember(seq, (seq, -30.0, 40.0), (seq - 1.0, 0.0, 0.0))      # position (+ the look-at moved along)
        v.remember(seq, None, (float(seq), 0.0, 0.0))
    tol = 1e-3 * 50
    P = lambda *x: np.array(x, float)
    assert v.ours(P(3, -30, 40), P(3, 0, 0), tol) == 3                  # the last command
    assert v.ours(P(2, -30, 40), P(3, 0, 0), tol) == 2                  # its look-at overtook its position
    assert v.ours(P(0, -30, 40), P(0, 0, 0), tol) == 0                  # the initial camera, applied late
    assert v.ours(P(3, -30 + 1e-9, 40), P(3, 0, 0), tol) == 3           # float noise on the way back
    assert v.ours(P(5, -28, 41), P(3, 0, 0), tol) is None               # an orbit: the position moved
    assert v.ours(P(3, -25, 33), P(3, 0, 0), tol) is None               # a zoom toward the look-at
    assert v.ours(P(4, -30, 40), P(4, 0, 0), tol) is None               # a pan: both moved


# ----------------------------------------------------------------------------- the live loop and the UI

class FakeBus:
    """Enough of ZenohBus for the live loop: subscribe / subscribe_raw / poll / publish / stats."""

    def __init__(self):
        from agent.bus import BusStats, key_matches

        self.stats, self._match = BusStats(), key_matches
        self.subs, self.raw, self.queue, self.published = [], [], [], []

    def subscribe(self, pattern, handler):
        self.subs.append((pattern, handler))

    def subscribe_raw(self, pattern, cb):
        self.raw.append((pattern, cb))

    def publish(self, key, msg):
        self.published.append((key, decode(key, encode(msg))))

    def push(self, key, msg):
        self.queue.append((key, encode(msg) if msg is not None else b"x"))

    def poll(self, timeout=0.0, max_messages=10_000):
        from agent.bus import deliver

        n = 0
        while self.queue and n < max_messages:
            key, data = self.queue.pop(0)
            for p, h in self.subs:
                if self._match(p, key):
                    deliver(self.stats, [h], key, data)
            for p, cb in self.raw:
                if self._match(p, key):
                    cb(key, data)
            n += 1
        return n


def test_live_loop_counts_decodes_and_publishes_controls():
    n = 5
    bus = FakeBus()
    clock = iter(np.arange(0, 100, 0.01))
    st = DashboardState(RunInfo(n=n))
    loop = LiveDashboard(st, None, bus, clock=lambda: float(next(clock)))
    loop.attach()
    for k in range(6):
        for key, m in synthetic_tick(n, k):
            bus.push(key, m)
    bus.queue.append(("agent/1/estimate", b"\xc1garbage"))   # invalid: dropped by the bus, counted here
    loop.send_control("link_drop", {"a": 0, "b": 1})
    loop.send_control("partition", {"groups": [0, 0, 1, 1, 1]})
    loop.step()
    assert st.finalized_k == 5
    assert st.messages == 6 * len(synthetic_tick(n, 0))
    assert st.bus_dropped == 1 and st.drop_meter.total == 1
    assert [k for k, _ in bus.published] == ["control/link_drop", "control/partition"]
    assert bus.published[0][1].args == {"a": 0, "b": 1}
    assert bus.published[1][1].args == {"groups": [0.0, 0.0, 1.0, 1.0, 1.0]}
    with pytest.raises(ValueError):
        loop.send_control("self_destruct", {})


def test_viser_ui_renders_and_buttons_queue_controls():
    from flocktrack.launch.launcher import free_port

    from dashboards.ui import DashboardUI
    from dashboards.operator import inject_from_form

    n = 12
    st = DashboardState(RunInfo(n=n, link_range=12.0, name="t"))
    feed(st, synth(n, 30))
    sent = []
    ui = DashboardUI(st.info, port=free_port(), live=True, send_control=lambda v, a: sent.append((v, a)),
                     operator_token="t0ken")
    try:
        op = ui.add_operator_panel(ui.server.gui, None)   # (a browser tab's own GUI in a real page)
        sa = ui.render_scene(st.snapshot(), st.series(last=200)["err"])
        assert sa is not None and ui.scene.h_sensors.visible and ui.scene.h_links.visible
        assert ui.render_scene(st.snapshot()) is None  # same tick, nothing to redraw
        ui.render_plots(st.series())
        assert set(ui.plot_panel.handles) == {"errors", "tmsee", "disagreement", "lambda2", "rates", "nees"}
        ui.render_status(st.summary())
        ui.select(4)           # (not a tab's choice: the shared highlight moves, no operator's fields —
        assert ui.selected == 4 and op.g_kill_id.value == 0   # see tests/browser/test_dashboard_auth.py)
        ui.control("kill", agent=4)
        groups = ui.partition_groups()
        assert sorted(groups) == [0] * 6 + [1] * 6
        assert sent == [("kill", {"agent": 4})]
        op.g_inj_kind.value, op.g_inj_targets.value = "delay", "agents:2 "
        op.g_inj_params.value, op.g_inj_ticks.value = "delay_ms=80 jitter_ms=20.5 direction=in", 50
        assert inject_from_form(op, ui.control)
        assert sent[-1] == ("inject", {"delay_ms": 80, "jitter_ms": 20.5, "direction": "in", "kind": "delay",
                                       "targets": "agents:2", "ticks": 50})
        op.g_inj_params.value = "delay_ms 80"
        assert not inject_from_form(op, ui.control) and len(sent) == 2 and "name=value" in op.g_inj_params.value
    finally:
        ui.stop()


def test_dashboards_import_only_agent():
    for f in (ROOT / "dashboards").glob("*.py"):
        tree = ast.parse(f.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module or ""]
            for name in names:
                assert name.split(".")[0] not in ("flocktrack", "topology"), (f.name, name)
