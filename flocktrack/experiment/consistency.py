"""Monte-Carlo consistency of a sweep: is each cell's stated uncertainty honest over its seeds?

Each run's ``summary.json`` → ``credibility.network`` holds the ANEES of its estimates against the covariances
they were reported with (m degrees of freedom, K scored samples; :mod:`flocktrack.record.credibility`). One run
says little: consecutive ticks share their errors, so its χ² interval — built as if the K samples were
independent — is too narrow. The seeds of a cell are independent, so over N runs (Bar-Shalom, Li &
Kirubarajan, §5.4.2, the Monte-Carlo test):

* ``anees`` — the mean of the runs' ANEES, and its bootstrap 95 % interval over the seeds
  (``seeds_ci95_lo``/``hi``, :func:`dashboards.confidence.mean_ci`);
* ``verdict`` — *consistent* when m lies inside that interval, *conservative* (P larger than the errors)
  when the interval lies below m, *optimistic* above it; with a single run, the run's own verdict;
* ``chi2_lo``/``chi2_hi`` — the textbook interval χ²(m·ΣK)/ΣK of the pooled samples, beside it for
  comparison (it treats every tick as independent);
* ``runs_consistent`` — how many runs passed their own test.

For Chen's constant-gain H∞ filter, which reports no covariance, the cell gives the mean of the runs'
measured energy ratios against the design's bound 1/γ and how many runs kept it (``hinf_*``).

``flocktrack sweep`` writes these as ``consistency.csv`` (a row per cell) and in ``sweep.json``.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from dashboards.confidence import mean_ci
from dashboards.nees import chi2_interval

from .grid import Axis

_ANEES, _SAMPLES, _DOF = "credibility.network.anees", "credibility.network.samples", "credibility.network.dof"
_OWN = "credibility.network.consistent"
_HINF, _BOUND, _HOLDS = "hinf.network_ratio", "hinf.bound", "hinf.holds"

COLUMNS = ["runs", "dof", "samples", "anees", "seeds_ci95_lo", "seeds_ci95_hi", "verdict", "chi2_lo", "chi2_hi",
           "runs_consistent", "hinf_ratio", "hinf_bound", "hinf_runs_holding"]


def _verdict(m: float, lo: float, hi: float) -> str:
    return "consistent" if lo <= m <= hi else ("conservative" if hi < m else "optimistic")


def monte_carlo(axes: list[Axis], rows: list[dict]) -> list[dict]:
    """Per cell of ``axes`` (the tidy ``results.csv`` rows of the sweep's successful runs), the Monte-Carlo
    consistency over its seeds; cells with neither a covariance nor an H∞ ratio are left out."""
    keys = [a.key for a in axes]
    runs: dict[tuple, dict[str, dict[str, float]]] = {}
    for row in rows:
        if row.get("status") != "ok" or row.get("value") in ("", None):
            continue
        cell = tuple(row[k] for k in keys)
        runs.setdefault(cell, {}).setdefault(row["run_id"], {})[row["metric"]] = float(row["value"])
    out = []
    for cell, by_run in runs.items():
        rec = {**dict(zip(keys, cell)), **_cell(list(by_run.values()))}
        if rec["runs"] or rec["hinf_runs_holding"] is not None:
            out.append(rec)
    return out


def _cell(metrics: list[dict[str, float]]) -> dict:
    rec: dict = {c: None for c in COLUMNS}
    scored = [r for r in metrics if all(k in r for k in (_ANEES, _SAMPLES, _DOF)) and r[_SAMPLES] > 0]
    rec["runs"] = len(scored)
    if scored:
        a = np.array([r[_ANEES] for r in scored])
        K = np.array([r[_SAMPLES] for r in scored])
        m = int(scored[0][_DOF])
        mean, lo, hi = mean_ci(a)
        c_lo, c_hi = chi2_interval(int(m * K.sum()), int(K.sum()))
        own = sum(bool(r.get(_OWN)) for r in scored)
        if len(scored) > 1:
            verdict = _verdict(m, lo, hi)
        else:
            verdict = "consistent" if own else _verdict(m, a[0], a[0])
        rec.update(dof=m, samples=int(K.sum()), anees=mean, seeds_ci95_lo=lo, seeds_ci95_hi=hi, verdict=verdict,
                   chi2_lo=c_lo, chi2_hi=c_hi, runs_consistent=own)
    hinf = [r for r in metrics if _HINF in r and _BOUND in r]
    if hinf:
        rec.update(hinf_ratio=float(np.mean([r[_HINF] for r in hinf])), hinf_bound=hinf[0][_BOUND],
                   hinf_runs_holding=sum(bool(r.get(_HOLDS)) for r in hinf))
    return rec


def write_consistency_csv(path: Path, axes: list[Axis], rows: list[dict]) -> list[dict]:
    """``consistency.csv``: :func:`monte_carlo`'s rows (nothing written when no cell has any)."""
    recs = monte_carlo(axes, rows)
    if not recs:
        return recs
    cols = [a.key for a in axes] + COLUMNS
    with Path(path).open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        for rec in recs:
            w.writerow({c: _fmt(rec.get(c)) for c in cols})
    return recs


def describe(rec: dict, axes: list[Axis]) -> str:
    """One line for the terminal: the cell, its ANEES over the seeds against m, the verdict."""
    cell = ", ".join(f"{a.key}={rec[a.key]}" for a in axes) or "all runs"
    if rec.get("runs"):
        return (f"{cell}: ANEES {rec['anees']:.2f} over {rec['runs']} seeds (95 % {rec['seeds_ci95_lo']:.2f}–"
                f"{rec['seeds_ci95_hi']:.2f}) for m = {rec['dof']}: {rec['verdict']}")
    return (f"{cell}: H∞ energy ratio {rec['hinf_ratio']:.2f} against 1/γ = {rec['hinf_bound']:.2f}, "
            f"kept in {rec['hinf_runs_holding']} runs")


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if not math.isfinite(v) else f"{v:.6g}"
    return str(v)
