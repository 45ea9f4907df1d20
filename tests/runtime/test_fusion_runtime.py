"""García Carrillo et al. in the runtime: UAV processes publish asynchronous relative measurements, the
fusion process runs the sum-of-norms estimator (10) and the Kalman / BLS baselines on the same stream;
the scores land in summary.json; over Zenoh in lockstep the fusion estimates equal the in-process ones."""

import json
from pathlib import Path

import numpy as np

from flocktrack.cli import main

SCEN = Path(__file__).resolve().parents[2] / "scenarios" / "carrillo_uav.toml"


def _fusion(d: Path) -> dict:
    return json.loads((d / "summary.json").read_text())["fusion"]


def test_inproc_fusion_scores(tmp_path):
    assert main(["run", str(SCEN), "--transport", "inproc", "--ticks", "1200",
                 "--set", "uavs.outlier_fraction=0.15", "--out", str(tmp_path)]) == 0
    f = _fusion(tmp_path)
    assert {"sum_of_norms", "bls", "kalman_q5000", "kalman_q1", "measurement_rmse"} <= set(f)
    son, kal, bls = f["sum_of_norms"]["rmse_newest"], f["kalman_q5000"]["rmse_newest"], f["bls"]["rmse_newest"]
    assert son < kal and son < bls and son < f["measurement_rmse"], f
    assert f["sum_of_norms"]["rmse_midwindow"] < son  # the smoothed (lagged) estimate is better still
    assert f["sum_of_norms"]["estimates"] > 100
    # each estimate's covariance: through 15 % outliers the Kalman filter's is optimistic many times over (its P
    # knows nothing of the outliers it takes in); the window, which sets them aside, is far closer to honest
    son_nees, kal_nees = f["sum_of_norms"]["nees_newest"], f["kalman_q5000"]["nees_newest"]
    assert son_nees["dof"] == 2 and son_nees["samples"] > 100
    assert kal_nees["verdict"] == "optimistic" and kal_nees["anees"] > 5 * 2, kal_nees
    assert 0.5 < son_nees["anees"] < kal_nees["anees"] / 3, (son_nees, kal_nees)
    assert f["sum_of_norms"]["nees_midwindow"]["anees"] < son_nees["anees"]    # the smoothed one more so


def test_zenoh_lockstep_fusion_equals_inproc(tmp_path):
    args = ["--ticks", "300", "--mode", "lockstep"]
    assert main(["run", str(SCEN), "--transport", "inproc", *args, "--out", str(tmp_path / "in")]) == 0
    assert main(["run", str(SCEN), "--transport", "zenoh", "--quiet", *args, "--out", str(tmp_path / "z")]) == 0
    assert _fusion(tmp_path / "in") == _fusion(tmp_path / "z")


# ----------------------------------------------------------------------------- [fusion] mode = "distributed"

ROBUST = SCEN.parent / "carrillo_robust.toml"
DIST = ["--set", 'fusion.mode="distributed"']


def test_distributed_fusion_over_zenoh_equals_inproc(tmp_path):
    """Each UAV process fuses its own measurements and agrees with the other by consensus ADMM over its
    exchange rounds: in lockstep over Zenoh the run equals the in-process one (the whole summary), both UAVs
    hold the same estimate, and the central robust MHE beside them scores the same data."""
    args = ["--ticks", "300", "--mode", "lockstep", *DIST]
    assert main(["run", str(ROBUST), "--transport", "inproc", *args, "--out", str(tmp_path / "in")]) == 0
    assert main(["run", str(ROBUST), "--transport", "zenoh", "--quiet", *args, "--out", str(tmp_path / "z")]) == 0
    s_in = json.loads((tmp_path / "in" / "summary.json").read_text())
    assert s_in == json.loads((tmp_path / "z" / "summary.json").read_text())
    f = s_in["fusion"]
    assert f["admm/0"] == f["admm/1"] and f["admm/0"]["estimates"] > 100
    assert {"robust_mhe", "kalman_q1", "robust_kalman_q3"} <= set(f)
    for i, j in ((0, 1), (1, 0)):
        st = json.loads((tmp_path / "z" / "stats" / f"agent-{i}.json").read_text())
        assert st["sent_by_key"][f"agent/{i}/to/{j}/xchg"] == 300 * 9     # round 0 + 8 ADMM iterations a tick
        assert st["role"].get("dropped_links", 0) == 0
    # the dashboard's model of the recording draws both UAVs' estimates and the central one
    from dashboards.state import DashboardState, RunInfo
    from flocktrack.record.reader import read_recording

    ds = DashboardState(RunInfo(n=2))
    for key, msg, t in read_recording(tmp_path / "z" / "recording.mcap").messages:
        ds.ingest(key, msg, t / 1e9)
    ds.finalize_all()
    snap = ds.snapshot(250)
    assert snap is not None and np.isfinite(snap.est_pos[:, :2]).all() and snap.fusion_pos is not None
    assert np.array_equal(snap.est_pos[0], snap.est_pos[1])


def test_distributed_fusion_keeps_estimating_through_a_killed_uav_and_agrees_again(tmp_path):
    """UAV 1's process is killed at tick 100 and restarted at tick 200 (control/kill, control/restart): UAV 0
    keeps estimating from its own measurements meanwhile; the restarted UAV takes the window over in its first
    round 0 and from then on the two publish the same estimates."""
    from agent.scenario import parse_scenario, scenario_data
    from control_plan import ControlPlan
    from flocktrack.record.reader import read_recording
    from flocktrack.engine.run import run_zenoh_to_dir

    # 800 ticks: in lockstep the world runs on without the dead UAV, so the restarted process rejoins after
    # as many ticks as its start-up takes at the world's pace: 56–162 ticks here with two copies of this test
    # at once (fresh interpreters: 125–201), 311 once in a flake hunt beside the browser tests
    data = scenario_data(str(ROBUST), ['fusion.mode="distributed"'], **{"run.ticks": 800, "run.mode": "lockstep"})
    sc = parse_scenario(data, str(ROBUST))
    ctl = ControlPlan({100: ("kill", {"agent": 1}), 200: ("restart", {"agent": 1})})
    try:
        summary, info = run_zenoh_to_dir(sc, data, tmp_path, quiet=True, on_poll=ctl, timeout_s=300)
    finally:
        ctl.close()
    assert info["rc"] == 0 and ctl.sent == {100, 200}
    rec = read_recording(tmp_path / "recording.mcap")
    alive1 = {m.k: m.alive[1] for key, m, _ in rec.messages if key == "world/tick"}
    down = [k for k in sorted(alive1) if not alive1[k]]
    assert down and alive1[max(alive1)], "the world saw UAV 1 leave and come back"
    est = {i: {m.k: m for key, m, _ in rec.messages if key == f"agent/{i}/estimate"} for i in (0, 1)}
    # UAV 0 alone: its newest node keeps moving with its own measurements while UAV 1 is down
    moved = [k for k in down if "t_newest" in est[0][k].aux] if all(k in est[0] for k in down) else []
    assert len(moved) >= 10, (len(down), len(moved))
    # back together: the same estimate on both UAVs from a few ticks after the rejoin on
    back = [k for k in sorted(est[1]) if k > max(down) + 5 and k in est[0]]
    assert len(back) > 100
    assert all(np.array_equal(est[0][k].x_next, est[1][k].x_next) for k in back)
    f = summary["fusion"]
    assert f["admm/0"]["estimates"] > f["admm/1"]["estimates"]
    assert f["admm/0"]["rmse_newest"] < 2.0 * f["robust_mhe"]["rmse_newest"]
