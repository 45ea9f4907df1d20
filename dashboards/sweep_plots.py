"""Sweep data → figures (matplotlib PNG). Pure: numbers in, an image file out; no run directories,
no CSV, no scenario parsing (that is :mod:`flocktrack.experiment`'s job).

* :func:`error_traces` — the papers' kind of figure: an error (network RMSE, disagreement, …) against
  time, the median over seeds with a 10–90 % band, one line per grid cell, one panel per combination of
  the grid keys that are not on the lines;
* :func:`metric_vs_param` — a scalar metric against a grid key (e.g. RMSE vs fault intensity): the mean
  over seeds with a bootstrap 95 % confidence band, every seed as a faint dot, one line per value of the
  other keys (a categorical key gets error bars instead of a band);
* :func:`mean_ci` — the bootstrap confidence interval both use (:mod:`dashboards.confidence`, also the sweep's summary CSV's).

The y axis turns logarithmic by itself when the values span more than ~1.3 decades (a diverging Kalman
filter next to a bounded minimax one). Drawing uses the object API (``Figure`` + Agg canvas), so nothing
here touches pyplot's global state or the process's matplotlib backend.

Floors: imports numpy, matplotlib and (for the bootstrap) SciPy only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .confidence import mean_ci

#: values spanning more than this ratio (max / 5th percentile of the positive values, ≈ 1.3 decades) get a
#: log y axis
LOG_RATIO = 20.0


# --------------------------------------------------------------------------- statistics

def wants_log(values) -> bool:
    """True when the finite positive values span more than :data:`LOG_RATIO` (max over the 5th percentile)."""
    v = np.asarray(values, float).ravel()
    v = v[np.isfinite(v) & (v > 0)]
    if v.size < 2:
        return False
    return float(v.max()) / float(np.percentile(v, 5)) > LOG_RATIO


# --------------------------------------------------------------------------- data shapes

@dataclass
class Trace:
    """One grid cell: a label, the time axis and one row per seed (NaN-padded to a common length)."""
    label: str
    t: np.ndarray
    Y: np.ndarray  # (seeds, len(t))
    value: float | None = None  # the line key's numeric value (colour ramp), if any


@dataclass
class Panel:
    title: str
    traces: list[Trace] = field(default_factory=list)


@dataclass
class Series:
    """One line of a metric-vs-parameter figure: per x value, the per-seed values of the metric."""
    label: str
    x: list  # numbers (numeric axis) or category labels
    values: list[np.ndarray]


# --------------------------------------------------------------------------- drawing helpers

_CYCLE = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
          "#bcbd22", "#17becf"]


def _colors(n: int, values: Sequence[float | None] | None = None) -> list:
    """A sequential ramp when the lines are ordered numeric values, the qualitative cycle otherwise."""
    if values is not None and n > 1 and all(v is not None for v in values):
        from matplotlib import colormaps

        cmap = colormaps["viridis"]
        vs = np.asarray(values, float)
        order = np.argsort(np.argsort(vs))  # rank, so uneven spacing still spreads the colours
        return [cmap(0.05 + 0.8 * r / max(n - 1, 1)) for r in order]
    return [_CYCLE[i % len(_CYCLE)] for i in range(n)]


def _save(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=110, metadata={"Software": None})
    return path


def _grid(n: int, max_cols: int = 3) -> tuple[int, int]:
    cols = min(n, max_cols)
    return (n + cols - 1) // cols, cols


# --------------------------------------------------------------------------- figures

def error_traces(panels: Sequence[Panel], path: str | Path, *, ylabel: str = "network RMSE",
                 title: str = "", xlabel: str = "t (s)", band: tuple[float, float] = (10.0, 90.0),
                 logy: bool | None = None, legend_title: str = "") -> Path:
    """Median over seeds with a ``band`` percentile band, one line per trace, one panel each; shared y.

    ``logy=None`` decides from the data (:func:`wants_log`)."""
    panels = [p for p in panels if p.traces]
    if not panels:
        raise ValueError("error_traces: nothing to draw")
    rows, cols = _grid(len(panels))
    fig = Figure(figsize=(4.6 * cols + 0.6, 3.4 * rows + 0.6), layout="constrained")
    axes = fig.subplots(rows, cols, sharex=True, sharey=True, squeeze=False)
    if logy is None:
        logy = wants_log(np.concatenate([np.nanmedian(_finite_rows(tr.Y), axis=0) for p in panels for tr in p.traces]))
    for ax, panel in zip(axes.ravel(), panels):
        cols_ = _colors(len(panel.traces), [tr.value for tr in panel.traces])
        for tr, c in zip(panel.traces, cols_):
            Y = _finite_rows(tr.Y)
            with np.errstate(all="ignore"):
                med = np.nanmedian(Y, axis=0)
                lo, hi = np.nanpercentile(Y, band, axis=0)
            n = Y.shape[0]
            t = tr.t[: med.size]
            if logy:
                med, lo, hi = (np.where(a > 0, a, np.nan) for a in (med, lo, hi))
            ax.plot(t, med, color=c, lw=1.4, label=f"{tr.label}" + (f" (n={n})" if n != 1 else ""))
            if n > 1:
                ax.fill_between(t, lo, hi, color=c, alpha=0.18, lw=0)
        ax.set_title(panel.title, fontsize=10)
        ax.grid(True, which="major", alpha=0.3)
        if logy:
            ax.set_yscale("log")
        ax.legend(fontsize=7, title=legend_title or None, title_fontsize=7, loc="best")
    for ax in axes.ravel()[len(panels):]:
        ax.set_visible(False)
    for ax in axes[-1, :]:
        ax.set_xlabel(xlabel)
    for ax in axes[:, 0]:
        ax.set_ylabel(ylabel)
    sub = f"median over seeds, {band[0]:g}–{band[1]:g} % band" + (", log scale" if logy else "")
    fig.suptitle(f"{title}\n{sub}" if title else sub, fontsize=11)
    return _save(fig, path)


def metric_vs_param(series: Sequence[Series], path: str | Path, *, xlabel: str, ylabel: str, title: str = "",
                    categorical: bool = False, logy: bool | None = None, level: float = 0.95,
                    legend_title: str = "") -> Path:
    """Mean over seeds with a bootstrap ``level`` confidence band (error bars when ``categorical``),
    the individual seeds as dots, one line per series."""
    series = [s for s in series if s.x]
    if not series:
        raise ValueError("metric_vs_param: nothing to draw")
    fig = Figure(figsize=(6.4, 4.4), layout="constrained")
    ax = fig.add_subplot()
    allv = np.concatenate([np.asarray(v, float).ravel() for s in series for v in s.values] or [np.zeros(0)])
    if logy is None:
        logy = wants_log(allv)
    cats: list = []
    if categorical:
        for s in series:
            for x in s.x:
                if x not in cats:
                    cats.append(x)
    colors = _colors(len(series))
    width = 0.5
    for si, (s, c) in enumerate(zip(series, colors)):
        stats = np.array([mean_ci(v, level) for v in s.values])  # (len(x), 3)
        if categorical:
            dodge = (si - (len(series) - 1) / 2) * (width / max(len(series), 1))
            xs = np.array([cats.index(x) for x in s.x], float) + dodge
        else:
            xs = np.asarray(s.x, float)
        for xv, v in zip(xs, s.values):
            v = np.asarray(v, float)
            v = v[np.isfinite(v)]
            if logy:
                v = v[v > 0]
            if v.size:
                jit = (np.arange(v.size) - (v.size - 1) / 2) * (0.012 * (np.ptp(xs) if xs.size > 1 and not categorical
                                                                         else 1.0) / max(v.size, 1))
                ax.scatter(xv + jit, v, s=9, color=c, alpha=0.35, lw=0)
        m, lo, hi = stats[:, 0], stats[:, 1], stats[:, 2]
        if categorical:
            ax.errorbar(xs, m, yerr=[m - lo, hi - m], fmt="o", color=c, capsize=4, label=s.label, ms=5)
        else:
            order = np.argsort(xs)
            ax.plot(xs[order], m[order], "o-", color=c, label=s.label, ms=4, lw=1.5)
            ax.fill_between(xs[order], lo[order], hi[order], color=c, alpha=0.2, lw=0)
    if categorical:
        ax.set_xticks(range(len(cats)), [str(x) for x in cats])
        ax.set_xlim(-0.6, len(cats) - 0.4)
    else:
        ticks = sorted({float(x) for s in series for x in s.x})
        if len(ticks) <= 12:  # the grid values themselves, not 1.25, 1.5, …
            ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
    if logy:
        ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    n = max((np.isfinite(np.asarray(v, float)).sum() for s in series for v in s.values), default=0)
    band = "error bars" if categorical else "band"
    sub = f"mean over seeds (n ≤ {n}), {band}: bootstrap {level:.0%} CI of the mean; dots: seeds"
    fig.suptitle(f"{title}\n{sub}" if title else sub, fontsize=10)
    if len(series) > 1 or series[0].label:
        ax.legend(fontsize=8, title=legend_title or None, title_fontsize=8)
    return _save(fig, path)


def _finite_rows(Y: np.ndarray) -> np.ndarray:
    Y = np.atleast_2d(np.asarray(Y, float))
    keep = np.isfinite(Y).any(axis=1)
    return Y[keep] if keep.any() else Y[:1]


__all__ = ["mean_ci", "wants_log", "Trace", "Panel", "Series", "error_traces", "metric_vs_param", "LOG_RATIO"]
