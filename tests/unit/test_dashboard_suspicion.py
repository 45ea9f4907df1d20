"""Byzantine suspicion on the dashboard (dashboards/state.py, plots.py, tabs.py): whom each sensor's
resilient consensus discarded (``Estimate.aux["suspected"]``), kept per tick as valid (i, j) pairs — a
hostile or broken message's values dropped, never raised on —, counted in the series, drawn as red
segments from the suspecting sensor to its suspect and named in the selected sensor's label and text."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from agent.wire import Estimate, decode, encode
from dashboards import plots
from dashboards.live import replay_model_from_file
from dashboards.state import DashboardState, RunInfo, synthetic_tick, valid_suspects
from dashboards.tabs import inspect_text, selection_label

from conftest import ROOT
from dashboard_feed import feed


def with_suspects(msgs, suspects: dict):
    """A synthetic tick's messages with ``aux["suspected"] = suspects[i]`` on node i's estimate (every
    node of ``suspects``; the others without the key)."""
    out = []
    for key, m in msgs:
        if isinstance(m, Estimate) and key.startswith("agent/") and m.src in suspects:
            m = Estimate(src=m.src, k=m.k, x=m.x, x_next=m.x_next, P=m.P, name=m.name,
                         aux={"suspected": np.asarray(suspects[m.src], float)})
        out.append((key, m))
    return out


def test_only_possible_suspects_are_kept():
    n = 6
    ids, dropped = valid_suspects(2, [4.0, 1.0, 4.0, 2.0, -1.0, 6.0, 1.5, 1e300, np.inf, np.nan, 5.0], n)
    assert ids.tolist() == [1, 4, 5] and ids.dtype.kind == "i"
    assert dropped == 8          # a repeat, itself, out of range (3), not an integer, not finite (2)
    assert valid_suspects(0, np.array([[1.0, 2.0], [3.0, 0.0]]), n)[0].tolist() == [1, 2, 3]
    ids, dropped = valid_suspects(0, np.zeros(0), n)
    assert ids.size == 0 and dropped == 0
    for junk in (None, "3", {"a": 1}, object(), [[1.0], [2.0, 3.0]]):
        ids, dropped = valid_suspects(0, junk, n)
        assert ids.size == 0 and dropped == 1, junk


def test_the_state_keeps_the_ticks_suspicion_pairs_and_counts_them():
    n = 5
    ticks = [with_suspects(synthetic_tick(n, k), {i: [] for i in range(n)}) for k in range(6)]
    ticks[2] = with_suspects(synthetic_tick(n, 2), {0: [3], 1: [3, 4], 2: [], 3: [0], 4: [3]})
    ticks[3] = with_suspects(synthetic_tick(n, 3), {0: [0, 3, 7, -2, 2.5], 1: [3.0, 3.0]})   # hostile values
    ticks[4] = synthetic_tick(n, 4)                  # (no node says anything: resilience off at that tick)
    st = DashboardState(RunInfo(n=n))
    feed(st, ticks)
    st.finalize_all()
    s = st.series()
    assert s["suspected"][[0, 1, 2, 3, 5]].tolist() == [0, 0, 5, 2, 0] and np.isnan(s["suspected"][4])
    assert st.snapshot(2).suspicions.tolist() == [[0, 3], [1, 3], [1, 4], [3, 0], [4, 3]]
    assert st.snapshot(3).suspicions.tolist() == [[0, 3], [1, 3]]
    assert st.invalid_suspects == 4 + 1
    assert st.snapshot(2).suspects_of(1) == [3, 4] and st.snapshot(2).suspects_of(2) == []
    assert "suspicions" in [p.key for p in plots.uplot_panels(s, n)]


def test_hostile_suspect_lists_through_the_wire_never_raise():
    """What a Byzantine sensor can put in its own ``aux`` — any shape of finite floats the wire accepts —
    reaches the model only as valid pairs."""
    n = 4
    rng = np.random.default_rng(7)
    st = DashboardState(RunInfo(n=n))
    for k in range(30):
        msgs = []
        for key, m in synthetic_tick(n, k):
            if isinstance(m, Estimate):
                shape = [(0,), (3,), (2, 2), (50,)][k % 4]
                aux = {"suspected": rng.choice([-3.0, 0.0, 1.0, 2.0, 3.0, 4.0, 0.5, 1e308, -1e308], size=shape)}
                with np.errstate(over="ignore", invalid="ignore"):     # (the wire sums ±1e308 to check them)
                    m = decode(key, encode(Estimate(src=m.src, k=m.k, x=m.x, x_next=m.x_next, P=m.P, name=m.name,
                                                    aux=aux)))
            msgs.append((key, m))
        feed(st, [msgs])
    st.finalize_all()
    for k in st.ticks_available():
        pairs = st.snapshot(k).suspicions
        assert np.all((pairs >= 0) & (pairs < n)) and np.all(pairs[:, 0] != pairs[:, 1])
        assert len({tuple(p) for p in pairs.tolist()}) == len(pairs)
    assert np.nanmax(st.series()["suspected"]) <= n * (n - 1)


def test_a_run_without_resilience_shows_nothing_new():
    n = 4
    st = DashboardState(RunInfo(n=n))
    feed(st, [synthetic_tick(n, k) for k in range(5)])
    snap = st.snapshot()
    assert np.isnan(st.series()["suspected"]).all() and snap.suspicions.shape == (0, 2)
    assert "suspicions" not in [p.key for p in plots.uplot_panels(st.series(), n)]
    assert plots.scene_arrays(snap).suspicions.shape == (0, 2, 3)
    assert selection_label(snap, 1) == "sensor 1" and "suspects" not in inspect_text(snap, 1, 2, 2.0)


def test_suspicions_are_segments_from_the_suspecting_sensor_to_its_suspect():
    pos = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 5.0, 0.0], [np.nan, np.nan, 0.0]])
    seg = plots.suspicion_segments(pos, np.array([[0, 1], [2, 0], [1, 3], [0, 9], [-1, 0]]))
    assert seg.dtype == np.float32 and seg.shape == (2, 2, 3)        # unknown position, out of range: left out
    np.testing.assert_array_equal(seg[0], [pos[0], pos[1]])
    np.testing.assert_array_equal(seg[1], [pos[2], pos[0]])
    assert plots.suspicion_segments(pos, np.zeros((0, 2), int)).shape == (0, 2, 3)


def test_the_scene_draws_them_in_one_set_and_the_label_names_the_suspects():
    n = 5
    st = DashboardState(RunInfo(n=n))
    feed(st, [with_suspects(synthetic_tick(n, k), {0: [3], 1: [3, 4], 4: [3]}) for k in range(3)])
    snap = st.snapshot()
    sa = plots.scene_arrays(snap, selected=1)
    assert sa.suspicions.shape == (4, 2, 3)
    np.testing.assert_allclose(sa.suspicions[:, 0], snap.positions[[0, 1, 1, 4]], rtol=1e-6)
    np.testing.assert_allclose(sa.suspicions[:, 1], snap.positions[[3, 3, 4, 3]], rtol=1e-6)
    assert selection_label(snap, 1) == "sensor 1 · suspects 3, 4"
    assert selection_label(snap, 3) == "sensor 3"
    text = inspect_text(snap, 1, 2, 2.0)
    assert "suspects (2): 3, 4" in text and "NEES εᵢ = " in text


def test_the_scene_and_the_plots_of_a_real_viser_server(tmp_path: Path):
    """The shared scene's red segments and the two new panels, on a real Viser server (no browser)."""
    from flocktrack.launch.launcher import free_port

    from dashboards.ui import DashboardUI

    n = 6
    st = DashboardState(RunInfo(n=n, link_range=12.0, name="t"))
    feed(st, [with_suspects(synthetic_tick(n, k), {i: ([2] if i in (1, 3) else []) for i in range(n)})
              for k in range(12)])
    ui = DashboardUI(st.info, port=free_port(), live=True)
    try:
        ui.render_scene(st.snapshot(), st.series(last=200)["err"])
        h = ui.scene.h_suspicions
        assert h.visible and np.asarray(h.points).shape == (2, 2, 3)
        ui.render_plots(st.series())
        handles = ui.plot_panel.handles
        assert {"nees", "suspicions"} <= set(handles)
        assert handles["nees"].scales["y"]["distr"] == 3
        assert handles["suspicions"].order == ui.plot_panel.ORDER["suspicions"]
    finally:
        ui.stop()


# ----------------------------------------------------------------------------- a real resilient run

def test_a_byzantine_sensors_neighbours_suspect_it_in_the_recording(tmp_path):
    """Gu & Hu's normal target with resilient_f = 1 and sensor 3 sending huge payloads from tick 20: the
    replayed model's pairs name sensor 3 and nobody else, all of its neighbours from then on, none before."""
    from agent.scenario import parse_scenario, scenario_data
    from flocktrack.engine.run import run_inproc_to_dir

    data = scenario_data(str(ROOT / "scenarios" / "gu_hu_normal.toml"), [],
                         **{"run.ticks": 40, "estimator.resilient_f": 1})
    data["faults"] = {"events": [{"kind": "byzantine", "targets": "agents:3", "mode": "huge", "start": 20}]}
    summary, _ = run_inproc_to_dir(parse_scenario(data, "gu_hu_normal.toml"), data, tmp_path, record=True)
    model = replay_model_from_file(tmp_path / "recording.mcap")
    s = model.state.series()
    assert np.isfinite(s["suspected"]).all() and model.state.invalid_suspects == 0
    for k in model.ticks:
        snap = model.snapshot(k)
        if k < 20:
            assert snap.suspicions.shape == (0, 2), k
        else:
            assert sorted(snap.suspicions[:, 0]) == sorted(snap.neighbours[3]), k
            assert set(snap.suspicions[:, 1]) == {3}, k
    assert summary["suspicion"]["false_suspicions"] == 0
    assert "suspicions" in [p.key for p in plots.uplot_panels(s, model.info.n)]
