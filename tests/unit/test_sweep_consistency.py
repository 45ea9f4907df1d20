"""The Monte-Carlo consistency of a sweep's cells (flocktrack/experiment/consistency.py), from tidy rows."""

import pytest

from flocktrack.experiment.consistency import describe, monte_carlo
from flocktrack.experiment.grid import parse_grid


def _rows(cell: str, run: str, metrics: dict, status: str = "ok") -> list[dict]:
    return [{"estimator.rounds": cell, "run_id": run, "status": status, "metric": k, "value": str(v)}
            for k, v in metrics.items()]


def _run(anees: float, consistent: bool = False) -> dict:
    return {"credibility.network.anees": anees, "credibility.network.samples": 100,
            "credibility.network.dof": 4, "credibility.network.consistent": float(consistent)}


AXES = [parse_grid("estimator.rounds=1,5")]


def test_the_verdict_is_whether_m_lies_within_the_seeds_interval():
    rows = []
    for i, a in enumerate((3.2, 4.5, 3.9, 4.3)):              # straddles m = 4
        rows += _rows("5", f"c5-{i}", _run(a))
    for i, a in enumerate((5.1, 5.6, 5.3, 5.9)):              # all above
        rows += _rows("1", f"c1-{i}", _run(a, consistent=True))
    rows += _rows("1", "c1-failed", _run(100.0), status="failed")   # a failed run does not count
    got = {c["estimator.rounds"]: c for c in monte_carlo(AXES, rows)}
    assert got["5"]["verdict"] == "consistent" and got["5"]["anees"] == pytest.approx(3.975)
    assert got["1"]["verdict"] == "optimistic" and got["1"]["runs"] == 4 and got["1"]["runs_consistent"] == 4
    assert got["1"]["samples"] == 400 and got["1"]["chi2_lo"] < 4 < got["1"]["chi2_hi"]
    assert "optimistic" in describe(got["1"], AXES) and "over 4 seeds" in describe(got["1"], AXES)


def test_one_run_keeps_its_own_verdict_and_a_filter_without_covariance_gives_its_energy_ratio():
    one = monte_carlo(AXES, _rows("1", "a", _run(2.0)))[0]
    assert one["runs"] == 1 and one["verdict"] == "conservative"
    hinf = _rows("5", "h0", {"hinf.network_ratio": 6.0, "hinf.bound": 10.0, "hinf.holds": 1.0})
    hinf += _rows("5", "h1", {"hinf.network_ratio": 8.0, "hinf.bound": 10.0, "hinf.holds": 1.0})
    h = monte_carlo(AXES, hinf)[0]
    assert h["runs"] == 0 and h["hinf_ratio"] == 7.0 and h["hinf_runs_holding"] == 2
    assert "kept in 2 runs" in describe(h, AXES)
    assert monte_carlo(AXES, _rows("1", "x", {"network_rmse": 0.1})) == []     # nothing to say: no row
