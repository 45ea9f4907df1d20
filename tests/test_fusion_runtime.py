"""García Carrillo et al. in the runtime: UAV processes publish asynchronous relative measurements, the
fusion process runs the sum-of-norms estimator (10) and the Kalman / BLS baselines on the same stream;
the scores land in summary.json; over Zenoh in lockstep the fusion estimates equal the in-process ones."""

import json
from pathlib import Path

from flocktrack.cli import main

SCEN = Path(__file__).resolve().parents[1] / "scenarios" / "carrillo_uav.toml"


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


def test_zenoh_lockstep_fusion_equals_inproc(tmp_path):
    args = ["--ticks", "300", "--mode", "lockstep"]
    assert main(["run", str(SCEN), "--transport", "inproc", *args, "--out", str(tmp_path / "in")]) == 0
    assert main(["run", str(SCEN), "--transport", "zenoh", "--quiet", *args, "--out", str(tmp_path / "z")]) == 0
    assert _fusion(tmp_path / "in") == _fusion(tmp_path / "z")
