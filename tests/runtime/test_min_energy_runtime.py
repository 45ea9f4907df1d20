"""Zamani & Ugrinovskii in the runtime: the design computed before the run (or loaded from a stored
design), the per-node filters in the sensor role, the measured H∞ ratios in summary.json, and the
same numbers over Zenoh in lockstep as in-process."""

import json
from pathlib import Path

import pytest

from flocktrack.cli import main
from test_zenoh_runtime import assert_same_summary

SCEN = Path(__file__).resolve().parents[2] / "scenarios" / "zamani_chua.toml"


def test_inproc_run_reports_ratios_below_designed_bounds(tmp_path):
    assert main(["run", str(SCEN), "--transport", "inproc", "--ticks", "800", "--out", str(tmp_path)]) == 0
    s = json.loads((tmp_path / "summary.json").read_text())
    h = s["hinf"]
    assert h["gamma2_star"] == pytest.approx(0.25, abs=1e-3)
    assert 0 < h["network_ratio"] < h["network_bound"]
    for r, b in zip(h["node_ratio"], h["node_bound"]):
        assert 0 < r < b
    assert s["final_rmse"] < 0.2  # converging from |x(0)| ≈ 1.4 under disturbances


def test_stored_design_is_used_and_checked(tmp_path):
    d = tmp_path / "sim2.json"
    assert main(["design", str(SCEN), "--set", "estimator.zbar_min=0.1", "--out", str(d)]) == 0
    assert json.loads(d.read_text())["gamma2_star"] == pytest.approx(0.3116, abs=1e-3)
    assert main(["run", str(SCEN), "--transport", "inproc", "--ticks", "50", "--set", f'estimator.design_file="{d}"',
                 "--set", "estimator.zbar_min=0.1", "--out", str(tmp_path / "r")]) == 0
    assert json.loads((tmp_path / "r" / "summary.json").read_text())["hinf"]["gamma2_star"] == pytest.approx(
        0.3116, abs=1e-3)
    # a design for other problem data is refused, naming the key
    rc = main(["run", str(SCEN), "--transport", "inproc", "--ticks", "5", "--set", f'estimator.design_file="{d}"',
               "--set", "sensors.v_std=2.0", "--set", 'estimator.W=[[2.0,0,0],[0,2.0,0],[0,0,2.0]]',
               "--out", str(tmp_path / "bad")])
    assert rc == 2


def test_zenoh_lockstep_equals_inproc(tmp_path):
    args = ["--ticks", "150", "--mode", "lockstep"]
    assert main(["run", str(SCEN), "--transport", "inproc", *args, "--out", str(tmp_path / "in")]) == 0
    assert main(["run", str(SCEN), "--transport", "zenoh", "--quiet", *args, "--out", str(tmp_path / "z")]) == 0
    assert_same_summary(json.loads((tmp_path / "in" / "summary.json").read_text()),
                        json.loads((tmp_path / "z" / "summary.json").read_text()))
