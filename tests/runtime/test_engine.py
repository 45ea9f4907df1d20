"""End-to-end runs of the in-process engine (all roles on a LocalBus, real numerics)."""

import json
from pathlib import Path

import numpy as np
import pytest

from agent import wire
from agent.bus import LocalBus
from agent.estimators.minimax import CentralizedMinimax
from agent.scenario import load_scenario
from flocktrack.cli import main
from flocktrack.engine.inproc import run_inproc

SCEN = Path(__file__).resolve().parents[2] / "scenarios"


def test_same_scenario_and_seed_give_identical_summary(tmp_path):
    for d in ("a", "b"):
        assert main(["run", str(SCEN / "gu_hu_intelligent.toml"), "--transport", "inproc", "--ticks", "120", "--out", str(tmp_path / d)]) == 0
    a = (tmp_path / "a" / "summary.json").read_bytes()
    assert a == (tmp_path / "b" / "summary.json").read_bytes()
    assert (tmp_path / "a" / "metrics.csv").read_bytes() == (tmp_path / "b" / "metrics.csv").read_bytes()
    main(["run", str(SCEN / "gu_hu_intelligent.toml"), "--transport", "inproc", "--ticks", "120", "--seed", "7", "--out", str(tmp_path / "c")])
    assert (tmp_path / "c" / "summary.json").read_bytes() != a


@pytest.mark.parametrize("rounds", [0, 1, 4])
def test_mean_of_node_estimates_equals_centralized_filter_in_the_engine(rounds):
    """Gu & Hu invariant, through the real bus and roles: with every payload delivered, the mean of
    the node estimates equals the centralized minimax estimate on the same measurements."""
    sc = load_scenario(SCEN / "gu_hu_normal.toml").with_overrides(**{"run.ticks": 80, "estimator.rounds": rounds})
    bus = LocalBus()
    meas: dict[int, dict[int, np.ndarray]] = {}
    ests: dict[int, dict[int, np.ndarray]] = {}

    def tap(key, data):
        if key.endswith("/meas"):
            m = wire.decode(key, data)
            meas.setdefault(m.k, {})[m.src] = m.y
        elif key.startswith("agent/") and key.endswith("/estimate"):
            m = wire.decode(key, data)
            ests.setdefault(m.k, {})[m.src] = m.x_next

    bus.taps.append(tap)
    run_inproc(sc, bus=bus)
    n = sc.sensors.n
    cen = CentralizedMinimax(sc.A, sc.filter_Q(), [sc.C] * n, [sc.R] * n, np.array(sc.estimator.params.S),
                             sc.initial_estimates()[0], np.eye(sc.m))
    worst_mean, worst_node = 0.0, 0.0
    for k in range(sc.run.ticks):
        xc = cen.step([meas[k][i] for i in range(n)])
        X = np.array([ests[k][i] for i in range(n)])
        worst_mean = max(worst_mean, float(np.max(np.abs(X.mean(axis=0) - xc))))
        worst_node = max(worst_node, float(np.max(np.abs(X - xc))))
    assert worst_mean < 1e-9
    if rounds == 0:
        assert worst_node > 1e-3  # without consensus the nodes really do differ from the centralized filter


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_intelligent_target_kalman_diverges_minimax_bounded_and_flock_holds(tmp_path, seed):
    """Gu & Hu Figs. 6–8: against the intelligent target the distributed Kalman error grows without bound,
    the distributed minimax error stays bounded; the flock stays connected without collisions."""
    base = str(SCEN / "gu_hu_intelligent.toml")
    assert main(["run", base, "--transport", "inproc", "--seed", str(seed), "--out", str(tmp_path / "mm")]) == 0
    assert main(["run", base, "--transport", "inproc", "--seed", str(seed), "--estimator", "kalman", "--out", str(tmp_path / "kf")]) == 0
    import csv

    def rmse(d):
        return np.array([float(r["rmse"]) for r in csv.DictReader(open(tmp_path / d / "metrics.csv"))])

    mm, kf = rmse("mm"), rmse("kf")
    assert mm.max() < 1.0, mm.max()
    assert np.sqrt(np.mean(mm[-300:] ** 2)) < 0.2
    early, late = np.sqrt(np.mean(kf[300:400] ** 2)), np.sqrt(np.mean(kf[-100:] ** 2))
    assert late > 10.0 and late > 50 * early, (early, late)
    assert kf[-1] > kf[-200] > kf[-400]  # still growing at the end
    s = json.loads((tmp_path / "mm" / "summary.json").read_text())
    assert s["connected_fraction"] == 1.0 and s["lambda2_min"] > 0
    assert s["min_inter_agent_distance"] > 2.0
    info = json.loads((tmp_path / "mm" / "run.json").read_text())
    assert info["bus"]["dropped"] == {} and info["bus"]["handler_errors"] == 0


def test_normal_target_both_filters_track(tmp_path):
    for est in ("minimax", "kalman"):
        assert main(["run", str(SCEN / "gu_hu_normal.toml"), "--transport", "inproc", "--ticks", "400", "--estimator", est,
                     "--out", str(tmp_path / est)]) == 0
        s = json.loads((tmp_path / est / "summary.json").read_text())
        assert s["network_rmse"] < 0.3, (est, s["network_rmse"])
        assert s["connected_fraction"] == 1.0


def test_chen_switching_tracks_and_tmsee_stays_above_lower_bound():
    """Chen et al. Sec. 4 through the engine: K from the runtime design, every node tracks, and the
    Monte-Carlo TMSEE (mean over seeds) stays above the lower bound (12) at every tick."""
    base = load_scenario(SCEN / "chen_switching.toml").with_overrides(**{"run.ticks": 150})
    runs = []
    for seed in range(30):
        m, roles, _ = run_inproc(base.with_overrides(**{"run.seed": seed}))
        rows = m.rows()
        runs.append([r["tmsee"] for r in rows])
        if seed == 0:
            assert np.allclose(roles.design["K"], [[0.9376], [0.5884]], atol=5e-5)
            lower = np.array([r["tmsee_lower"] for r in rows])
            s = m.summary()
            assert max(s["per_node_rmse"]) < 0.75, s["per_node_rmse"]
    mc = np.mean(runs, axis=0)
    assert mc[0] == pytest.approx(9.09) and lower[0] == pytest.approx(9.09)
    assert np.all(mc[1:] > lower[1:]), float(np.min(mc[1:] - lower[1:]))
    assert np.mean(mc[-50:]) < 1.0  # bounded steady state
