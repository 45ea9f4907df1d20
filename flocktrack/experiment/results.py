"""A sweep's tidy results: ``results.csv`` (a row per run and metric), ``summary.csv`` (per cell: mean,
bootstrap CI, quantiles) and the figures."""

from __future__ import annotations

import csv
import itertools
import json
import math
from pathlib import Path

import numpy as np



from .grid import Axis, RunSpec, slug, value_repr

#: summary.json fields that identify a run rather than measure it (not written as metrics)
IDENTITY_FIELDS = {"scenario", "estimator", "seed", "ticks", "n_sensors", "rounds", "burn_in",
                   "ticks_scored", "ticks_seen"}
#: metrics drawn against the first numeric grid key (when the runs have them)
FIGURE_METRICS = ["network_rmse", "final_rmse", "max_error", "disagreement_mean", "mean_estimate_rmse",
                  "connected_fraction"]
#: metrics.csv columns drawn against time
TRACE_COLUMNS = {"rmse": "network RMSE (position)", "disagreement": "consensus disagreement"}
CSV_FIXED = ["seed", "run_id", "status", "metric", "value", "error"]


# ============================================================================ tidy results

def scalar_metrics(summary: dict) -> list[tuple[str, float | None]]:
    """The scalar metrics of a ``summary.json``: numbers (dicts of numbers flattened as ``a.b``), lists of
    numbers with one entry per node as ``name[i]``; per-tick series and identity fields are left out."""
    out: list[tuple[str, float | None]] = []
    n = summary.get("n_sensors")

    def is_num(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    def walk(prefix: str, v) -> None:
        if v is None or is_num(v):
            out.append((prefix, None if v is None else float(v)))
        elif isinstance(v, bool):
            out.append((prefix, float(v)))
        elif isinstance(v, dict):
            for k in sorted(v):
                walk(f"{prefix}.{k}", v[k])
        elif isinstance(v, list) and n is not None and len(v) == n and prefix.startswith("per_node"):
            for i, x in enumerate(v):
                out.append((f"{prefix}[{i}]", float(x) if is_num(x) else None))

    for k in sorted(summary):
        if k not in IDENTITY_FIELDS:
            walk(k, summary[k])
    return out


def collect_rows(axes: list[Axis], specs: list[RunSpec], runs_dir: Path, results: dict) -> list[dict]:
    rows: list[dict] = []
    for r in specs:
        res = results[r.run_id]
        base = {a.key: value_repr(v) for a, v in zip(axes, r.cell)}
        base.update(seed=r.seed, run_id=r.run_id)
        summary = None
        if res["status"] == "ok":
            try:
                summary = json.loads((runs_dir / r.run_id / "summary.json").read_text())
            except (OSError, ValueError) as exc:
                res.update(status="failed", error=f"cannot read summary.json ({exc})")
        if summary is None:
            rows.append({**base, "status": "failed", "metric": "", "value": "", "error": res.get("error", "")})
            continue
        for name, v in scalar_metrics(summary):
            rows.append({**base, "status": "ok", "metric": name, "value": "" if v is None or not math.isfinite(v)
                         else repr(v), "error": ""})
    return rows


def _columns(axes: list[Axis]) -> list[str]:
    return [a.key for a in axes] + CSV_FIXED


def write_results_csv(path: Path, axes: list[Axis], rows: list[dict]) -> None:
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=_columns(axes))
        w.writeheader()
        w.writerows(rows)


def read_results_csv(path: str | Path) -> list[dict]:
    with Path(path).open(newline="") as f:
        return list(csv.DictReader(f))


def aggregate(axes: list[Axis], rows: list[dict]) -> list[dict]:
    """Per (cell, metric): n, failed, mean with bootstrap 95 % CI, std, median, 10 % and 90 % quantiles."""
    from dashboards.confidence import mean_ci

    keys = [a.key for a in axes]
    groups: dict[tuple, list[float]] = {}
    failed: dict[tuple, int] = {}
    order: list[tuple] = []
    cells_seen: list[tuple] = []
    for row in rows:
        cell = tuple(row[k] for k in keys)
        if cell not in cells_seen:
            cells_seen.append(cell)
        if row["status"] != "ok":
            failed[cell] = failed.get(cell, 0) + 1
            continue
        g = cell + (row["metric"],)
        if g not in groups:
            groups[g] = []
            order.append(g)
        if row["value"] != "":
            groups[g].append(float(row["value"]))
    out = []
    for g in order:
        v = np.asarray(groups[g], float)
        m, lo, hi = mean_ci(v)
        rec = dict(zip(keys, g[:-1]))
        rec.update(metric=g[-1], n=int(v.size), failed=failed.get(g[:-1], 0), mean=m, ci95_lo=lo, ci95_hi=hi,
                   std=float(v.std(ddof=1)) if v.size > 1 else float("nan"),
                   median=float(np.median(v)) if v.size else float("nan"),
                   p10=float(np.percentile(v, 10)) if v.size else float("nan"),
                   p90=float(np.percentile(v, 90)) if v.size else float("nan"))
        out.append(rec)
    for cell in cells_seen:  # a cell where every run failed still gets a line
        if not any(tuple(rec[k] for k in keys) == cell for rec in out):
            out.append({**dict(zip(keys, cell)), "metric": "", "n": 0, "failed": failed.get(cell, 0)})
    return out


def write_summary_csv(path: Path, axes: list[Axis], rows: list[dict]) -> list[dict]:
    agg = aggregate(axes, rows)
    cols = [a.key for a in axes] + ["metric", "n", "failed", "mean", "ci95_lo", "ci95_hi", "std", "median", "p10",
                                    "p90"]
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        for rec in agg:
            w.writerow({c: (_fmt_num(rec[c]) if isinstance(rec.get(c), float) else rec.get(c, "")) for c in cols})
    return agg


def _fmt_num(v: float) -> str:
    return "" if not math.isfinite(v) else f"{v:.6g}"


# ============================================================================ figures

def _read_columns(path: Path, names: list[str]) -> dict[str, np.ndarray]:
    with path.open(newline="") as f:
        rd = csv.DictReader(f)
        cols: dict[str, list[float]] = {n: [] for n in names}
        for row in rd:
            for n in names:
                s = row.get(n, "")
                cols[n].append(float(s) if s not in ("", None) else math.nan)
    return {n: np.asarray(v, float) for n, v in cols.items()}


def _x_axis(axes: list[Axis]) -> int | None:
    """The axis figures put on x / colour the trace lines by: the first numeric one, else the first."""
    for i, a in enumerate(axes):
        if a.numeric and len(a.values) > 1:
            return i
    return 0 if axes else None


def _cell_label(axes: list[Axis], idx: list[int], cell: tuple) -> str:
    return ", ".join(f"{axes[i].label}={value_repr(cell[i])}" for i in idx)


def make_figures(out: Path, axes: list[Axis], specs: list[RunSpec], results: dict) -> list[Path]:
    """``figures/traces_<col>.png`` (error vs time) and ``figures/<metric>_vs_<key>.png``."""
    from dashboards import sweep_plots as sp

    out = Path(out)
    fig_dir = out / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    runs_dir = out / "runs"
    ok = [r for r in specs if results[r.run_id]["status"] == "ok"]
    if not ok:
        return []
    xi = _x_axis(axes)
    others = [i for i in range(len(axes)) if i != xi]
    scen = _scenario_name(runs_dir / ok[0].run_id)
    written: list[Path] = []

    # --- error traces: one panel per combination of the other keys, one line per value of the x key
    by_cell: dict[tuple, list[RunSpec]] = {}
    for r in ok:
        by_cell.setdefault(_hkey(r.cell), []).append(r)
    series = {r.run_id: _read_columns(runs_dir / r.run_id / "metrics.csv", ["t", *TRACE_COLUMNS]) for r in ok}
    for col, ylabel in TRACE_COLUMNS.items():
        panels: dict[tuple, sp.Panel] = {}
        for rs in by_cell.values():
            cell = rs[0].cell
            pkey = _hkey(cell[i] for i in others)
            panel = panels.setdefault(pkey, sp.Panel(_cell_label(axes, others, cell) or scen))
            length = max(series[r.run_id][col].size for r in rs)
            Y = np.full((len(rs), length), np.nan)
            for j, r in enumerate(rs):
                y = series[r.run_id][col]
                Y[j, : y.size] = y
            longest = max(rs, key=lambda r: series[r.run_id]["t"].size)
            t = series[longest.run_id]["t"]
            if np.isnan(t).all():
                t = np.arange(length, dtype=float)
            label = _cell_label(axes, [xi], cell) if xi is not None else "all seeds"
            value = cell[xi] if xi is not None and axes[xi].numeric else None
            panel.traces.append(sp.Trace(label, t, Y, value))
        if all(np.isnan(tr.Y).all() for p in panels.values() for tr in p.traces):
            continue
        written.append(sp.error_traces(list(panels.values()), fig_dir / f"traces_{col}.png", ylabel=ylabel,
                                       title=f"{scen}: {ylabel} over time"))

    # --- scalar metrics against the x key, one line per combination of the other keys
    if xi is not None:
        ax_x = axes[xi]
        vals: dict[tuple[str, str, tuple], list[float]] = {}
        for r in ok:
            summary = json.loads((runs_dir / r.run_id / "summary.json").read_text())
            sm = dict(scalar_metrics(summary))
            for m in FIGURE_METRICS:
                if sm.get(m) is not None:
                    vals.setdefault((m, value_repr(r.cell[xi]), _hkey(r.cell[i] for i in others)), []).append(sm[m])
        for m in FIGURE_METRICS:
            keys = [k for k in vals if k[0] == m]
            if not keys:
                continue
            groups: dict[tuple, sp.Series] = {}
            for xv in ax_x.values:
                for cell in itertools.product(*(axes[i].values for i in others)) if others else [()]:
                    v = vals.get((m, value_repr(xv), _hkey(cell)))
                    if v is None:
                        continue
                    label = ", ".join(f"{axes[i].label}={value_repr(c)}" for i, c in zip(others, cell))
                    s = groups.setdefault(_hkey(cell), sp.Series(label, [], []))
                    s.x.append(xv if ax_x.numeric else value_repr(xv))
                    s.values.append(np.asarray(v, float))
            written.append(sp.metric_vs_param(list(groups.values()), fig_dir / f"{m}_vs_{slug(ax_x.label)}.png",
                                              xlabel=ax_x.label if ax_x.label == ax_x.key
                                              else f"{ax_x.label} ({ax_x.key})",
                                              ylabel=m, title=f"{scen}: {m} vs {ax_x.label}",
                                              categorical=not ax_x.numeric))
    return written


def _hkey(values) -> tuple[str, ...]:
    """A hashable key for grid values (arrays are lists)."""
    return tuple(value_repr(v) for v in values)


def _scenario_name(run_dir: Path) -> str:
    try:
        return json.loads((run_dir / "summary.json").read_text()).get("scenario", "")
    except (OSError, ValueError):
        return ""


