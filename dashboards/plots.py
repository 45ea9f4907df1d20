"""Data → figures: pure functions from :mod:`dashboards.state` snapshots and series to what is drawn.

* :func:`scene_arrays` turns a :class:`~dashboards.state.Snapshot` into a handful of batched arrays
  (one point cloud for all sensors, one for all node estimates, one line-segment set for all links,
  one for all suspicions, one for all range circles, …) so the live scene costs a few messages per update
  whatever the flock size;
* :func:`uplot_panels` turns series into the data and series options of the live uPlot panels;
* :func:`save_static_png` draws the same panels plus a top view of the flock with matplotlib
  (the only function here that touches a file).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .state import Snapshot

# --------------------------------------------------------------------------- colours

#: low error → high error (green, yellow, orange, red)
_RAMP = np.array([[40, 170, 80], [230, 200, 40], [240, 120, 30], [210, 30, 40]], float)
DEAD = np.array([150, 150, 150], np.uint8)
UNKNOWN = np.array([110, 110, 140], np.uint8)
NODE_PALETTE = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
                "#bcbd22", "#17becf", "#393b79", "#637939"]


def error_colors(errors: np.ndarray, alive: np.ndarray, scale: float) -> np.ndarray:
    """(n, 3) uint8: each sensor coloured by its own position error on a green→red ramp saturating at
    ``scale``; grey when dead, blue-grey when it has no estimate this tick."""
    errors = np.asarray(errors, float)
    u = np.clip(np.nan_to_num(errors, nan=0.0) / max(float(scale), 1e-12), 0.0, 1.0) * (len(_RAMP) - 1)
    i0 = np.minimum(np.floor(u).astype(int), len(_RAMP) - 2)
    w = (u - i0)[:, None]
    c = (_RAMP[i0] * (1 - w) + _RAMP[i0 + 1] * w).round().astype(np.uint8)
    c[np.isnan(errors)] = UNKNOWN
    c[~np.asarray(alive, bool)] = DEAD
    return c


def auto_error_scale(err_rows: np.ndarray, factor: float = 3.0, floor: float = 1e-3) -> float:
    """A colour scale from recent errors: ``factor`` × their median (at least ``floor``), so a typical
    sensor is green-yellow and one several times worse than the flock is red."""
    e = np.asarray(err_rows, float)
    e = e[np.isfinite(e)]
    return max(factor * float(np.median(e)), floor) if e.size else 1.0


# --------------------------------------------------------------------------- geometry

def link_segments(positions: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(E, 2, 3) float32 segments for the links (pairs with an unknown end are left out)."""
    edges = np.asarray(edges, int).reshape(-1, 2)
    if edges.size == 0:
        return np.zeros((0, 2, 3), np.float32)
    seg = np.stack([positions[edges[:, 0]], positions[edges[:, 1]]], axis=1)
    ok = np.all(np.isfinite(seg), axis=(1, 2))
    return seg[ok].astype(np.float32)


def suspicion_segments(positions: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(S, 2, 3) float32: one segment per suspicion (i, j) — "i discarded j's payloads this tick" — from the
    suspecting sensor i (``[:, 0]``) to its suspect j (``[:, 1]``); pairs with an id out of range or an
    unknown end are left out."""
    pairs = np.asarray(pairs, int).reshape(-1, 2)
    n = len(positions)
    pairs = pairs[np.all((pairs >= 0) & (pairs < n), axis=1)]
    return link_segments(positions, pairs)


_CIRCLE_CACHE: dict[int, np.ndarray] = {}


def _unit_circle(nseg: int) -> np.ndarray:
    c = _CIRCLE_CACHE.get(nseg)
    if c is None:
        a = np.linspace(0.0, 2 * math.pi, nseg + 1)
        c = _CIRCLE_CACHE[nseg] = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
    return c


def circle_segments(centres: np.ndarray, radius: float, nseg: int = 32) -> np.ndarray:
    """(m·nseg, 2, 3) float32: a circle of ``radius`` in the xy plane around each finite centre."""
    centres = np.asarray(centres, float).reshape(-1, 3)
    centres = centres[np.all(np.isfinite(centres), axis=1)]
    if centres.size == 0 or not math.isfinite(radius) or radius <= 0:
        return np.zeros((0, 2, 3), np.float32)
    ring = _unit_circle(nseg) * radius                          # (nseg+1, 3)
    pts = centres[:, None, :] + ring[None, :, :]                # (m, nseg+1, 3)
    seg = np.stack([pts[:, :-1], pts[:, 1:]], axis=2)           # (m, nseg, 2, 3)
    return seg.reshape(-1, 2, 3).astype(np.float32)


def grid_segments(half_width: float, cell: float) -> np.ndarray:
    """(·, 2, 3) float32: a square ground grid in the xy plane, ±``half_width``, lines every ``cell``."""
    m = max(1, int(half_width // cell))
    v = np.arange(-m, m + 1) * cell
    e = m * cell
    xs = np.stack([np.stack([v, np.full_like(v, -e), np.zeros_like(v)], 1),
                   np.stack([v, np.full_like(v, e), np.zeros_like(v)], 1)], 1)
    ys = xs[:, :, [1, 0, 2]]
    return np.concatenate([xs, ys]).astype(np.float32)


def polyline_segments(points: np.ndarray) -> np.ndarray:
    """(L−1, 2, 3) float32 segments joining consecutive points."""
    p = np.asarray(points, float).reshape(-1, 3)
    if len(p) < 2:
        return np.zeros((0, 2, 3), np.float32)
    return np.stack([p[:-1], p[1:]], axis=1).astype(np.float32)


def ellipse_points(mean: np.ndarray, cov: np.ndarray, nsig: float = 2.0, nseg: int = 64) -> np.ndarray:
    """(nseg+1, 3): the ``nsig``-σ ellipse of a 2-D (or the xy block of a 3-D) covariance around ``mean``."""
    C = np.asarray(cov, float)[:2, :2]
    C = 0.5 * (C + C.T)
    w, V = np.linalg.eigh(C)
    w = np.sqrt(np.maximum(w, 0.0))
    a = np.linspace(0.0, 2 * math.pi, nseg + 1)
    xy = (V @ (nsig * w[:, None] * np.stack([np.cos(a), np.sin(a)]))).T
    out = np.zeros((nseg + 1, 3))
    m = np.asarray(mean, float).reshape(-1)
    out[:, :2] = xy + m[:2]
    out[:, 2] = m[2] if m.size > 2 else 0.0
    return out


@dataclass
class SceneArrays:
    """Everything the scene draws, batched: one array per scene object."""

    sensor_points: np.ndarray          # (n_known, 3) float32
    sensor_colors: np.ndarray          # (n_known, 3) uint8
    sensor_ids: np.ndarray             # (n_known,) which sensor each point is
    estimate_points: np.ndarray        # (m, 3) float32: node estimates of the target position
    estimate_colors: np.ndarray        # (m, 3) uint8
    links: np.ndarray                  # (E, 2, 3) float32
    circles: np.ndarray                # (·, 2, 3) float32 range circles
    trail: np.ndarray                  # (L−1, 2, 3) float32
    target: np.ndarray | None          # (3,)
    fusion: np.ndarray | None          # (3,)
    suspicions: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3), np.float32))  # (S, 2, 3) i → j
    selected: int | None = None
    selected_pos: np.ndarray | None = None
    selected_est: np.ndarray | None = None
    selected_links: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3), np.float32))
    ellipse: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3), np.float32))


def scene_arrays(snap: Snapshot, *, selected: int | None = None, error_scale: float = 1.0,
                 link_range: float = math.inf, show_circles: bool = True, circle_segments_n: int = 32,
                 nsig: float = 2.0) -> SceneArrays:
    """Batch a snapshot into scene arrays (all sensors in one cloud, all links in one segment set)."""
    pos = snap.positions
    known = np.all(np.isfinite(pos), axis=1)
    colors = error_colors(snap.errors, snap.alive, error_scale)
    ids = np.flatnonzero(known)
    est_ok = np.all(np.isfinite(snap.est_pos), axis=1)
    est_cols = (colors[est_ok].astype(float) * 0.55 + 255 * 0.45).astype(np.uint8)  # paler than the sensor
    circles = circle_segments(pos[known & snap.alive], link_range, circle_segments_n) if show_circles \
        else np.zeros((0, 2, 3), np.float32)
    out = SceneArrays(sensor_points=pos[known].astype(np.float32), sensor_colors=colors[known], sensor_ids=ids,
                      estimate_points=snap.est_pos[est_ok].astype(np.float32), estimate_colors=est_cols,
                      links=link_segments(pos, snap.edges), circles=circles, trail=polyline_segments(snap.trail),
                      target=snap.truth_pos, fusion=snap.fusion_pos,
                      suspicions=suspicion_segments(pos, snap.suspicions))
    if selected is not None and 0 <= selected < snap.n:
        sel = selection_arrays(snap, selected, nsig=nsig)
        out.selected, out.selected_pos, out.selected_est = selected, sel.pos, sel.est
        out.selected_links, out.ellipse = sel.links, sel.ellipse
    return out


@dataclass
class Selection:
    """What the scene draws of one selected sensor (a tab's own inspector, dashboards/tabs.py)."""

    pos: np.ndarray | None = None      #: (3,) the sensor, None: position unknown
    est: np.ndarray | None = None      #: (3,) its estimate of the target position
    links: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3), np.float32))
    ellipse: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3), np.float32))


def selection_arrays(snap: Snapshot, selected: int, nsig: float = 2.0) -> Selection:
    """Sensor ``selected``'s links, estimate and nsig·σ covariance ellipse (empty out of range)."""
    out = Selection()
    if not 0 <= selected < snap.n:
        return out
    pos = snap.positions
    known = np.all(np.isfinite(pos), axis=1)
    if known[selected]:
        out.pos = pos[selected]
        nb = [j for j in snap.neighbours[selected] if known[j]] if selected < len(snap.neighbours) else []
        if nb:
            out.links = link_segments(pos, np.array([[selected, j] for j in nb]))
    if np.all(np.isfinite(snap.est_pos[selected])):
        out.est = snap.est_pos[selected]
    P, xn = snap.cov_pos.get(selected), snap.est_next.get(selected)
    if P is not None and xn is not None and P.shape[0] >= 2:
        d = P.shape[0]
        mean = np.zeros(3)
        mean[:min(3, d)] = xn[:min(3, d)]
        out.ellipse = polyline_segments(ellipse_points(mean, P, nsig))
    return out


# --------------------------------------------------------------------------- camera framing

#: the default viewing direction (from the camera to the point it looks at): from the south, 55° below the
#: horizon — steep enough that a planar flock is seen as a flock, not as a row
VIEW_DIRECTION = np.array([0.0, math.cos(math.radians(55.0)), -math.sin(math.radians(55.0))])


@dataclass
class Framing:
    """What the camera keeps in view: a sphere around the flock and the target."""

    centre: np.ndarray     #: (3,) the point to look at
    radius: float


def flock_framing(snap: Snapshot, min_radius: float = 1.0) -> Framing | None:
    """The sphere around every sensor with a known position and the target (None: nothing known yet).
    Centred on the middle of their bounding box — the flock's centre, however the sensors crowd —
    with a radius of at least ``min_radius`` (one sensor alone still gets some surroundings)."""
    pts = [snap.positions[np.all(np.isfinite(snap.positions), axis=1)]]
    if snap.truth_pos is not None and np.all(np.isfinite(snap.truth_pos)):
        pts.append(np.asarray(snap.truth_pos, float)[None])
    p = np.concatenate(pts)
    if not len(p):
        return None
    centre = 0.5 * (p.min(axis=0) + p.max(axis=0))
    radius = float(np.max(np.linalg.norm(p - centre[None], axis=1)))
    return Framing(centre=centre, radius=max(radius, float(min_radius)))


def camera_distance(radius: float, fov: float, aspect: float, margin: float = 1.15) -> float:
    """How far from the centre a perspective camera with vertical field of view ``fov`` (radians) and
    width/height ``aspect`` must stand for a sphere of ``radius`` (× ``margin``) to fit in its view."""
    half_v = 0.5 * float(fov)
    half_h = math.atan(math.tan(half_v) * max(float(aspect), 1e-3))
    return margin * float(radius) / math.sin(max(min(half_v, half_h), 1e-3))


# --------------------------------------------------------------------------- uPlot panels

@dataclass
class PanelSpec:
    """One uPlot panel: ``data`` (x first), per-series options, scales and axes (uPlot option dicts)."""

    key: str
    title: str
    data: tuple[np.ndarray, ...]
    series: tuple[dict, ...]
    scales: dict = field(default_factory=dict)
    axes: tuple[dict, ...] | None = None

    @property
    def labels(self) -> list[str]:
        return [s.get("label", "") for s in self.series]


def _x_series() -> dict:
    return {"label": "tick"}


def _line(label: str, color: str, width: float = 1.5, dash: list[int] | None = None, scale: str = "y") -> dict:
    s: dict = {"label": label, "stroke": color, "width": width, "scale": scale, "spanGaps": False,
               "points": {"show": False}}
    if dash:
        s["dash"] = dash
    return s


def _band(label: str, color: str) -> dict:
    return {"label": label, "stroke": color, "width": 0.5, "scale": "y", "points": {"show": False}}


_X_SCALE = {"x": {"time": False}}


def _axes(ylabel: str, right: str | None = None) -> tuple[dict, ...]:
    ax = [{"label": "tick", "size": 34, "labelSize": 14}, {"label": ylabel, "size": 52, "labelSize": 14}]
    if right:
        ax.append({"label": right, "scale": right, "side": 1, "size": 52, "labelSize": 14, "grid": {"show": False}})
    return tuple(ax)


#: x offset of the anchor row :func:`drawable` may put before the first row, in units of the x spacing
ANCHOR_DX = 1e-3


def drawable(data, series) -> tuple[np.ndarray, ...]:
    """The columns of one uPlot panel made safe to draw: float arrays of equal length, x finite and
    strictly increasing, no ±inf, and every y column finite in its first row.

    Why: Viser ships uPlot data as Float64Array, so a gap can only travel as NaN (there is no null in a
    typed array), and uPlot (1.6, as bundled by Viser 1.1.1) treats NaN as a *value*: its y-range search
    starts from the first non-null point of each series, so a NaN there makes the scale's min and max NaN —
    and every series on that scale, the axis ticks included, disappears; ±inf anywhere does the same. A NaN
    in the middle is fine (a gap). The live dashboard hit it whenever the first row it plots lacks a value:
    it joined the run during a tick, a tick had no estimate at all, a sensor was dead or silent, a panel's
    optional line (the TMSEE lower bound, a node's error) had no value in the window. Measured with
    Chromium on Viser's own uPlot: NaN first → scale NaN, no ticks, no lines; NaN inside → drawn;
    +inf inside → scale NaN.

    So: ±inf becomes NaN; rows with a non-finite or non-increasing x are dropped; and when some column
    is not finite in row 0, one *anchor* row is put before it, ``ANCHOR_DX`` of a tick to the left, holding
    for each column its own first finite value (else the first finite value of another column on the
    same scale, else 0). The anchor changes neither a y range that has data nor a visible line: next to a
    gap it is a lone point (points are not drawn), next to a value it is a level stub 1/1000 of a tick long
    (hovering the panel's left edge shows its values). A
    column with no value at all thus still leaves the panel's other lines drawn. (A user's x zoom
    that starts exactly on a gap still blanks that panel until the zoom is reset with a double click.)"""
    cols = [np.asarray(a, float).reshape(-1) for a in data]
    x, ys = cols[0], cols[1:]
    if any(len(y) != len(x) for y in ys):
        raise ValueError(f"columns of unequal length {[len(c) for c in cols]}")
    ok = np.isfinite(x)
    if len(x):
        prev = np.maximum.accumulate(np.where(ok, x, -np.inf))
        ok[1:] &= x[1:] > prev[:-1]
    x = x[ok]
    ys = [np.where(np.isfinite(y[ok]), y[ok], np.nan) for y in ys]
    if not len(x) or all(np.isfinite(y[0]) for y in ys):
        return (x, *ys)
    scales = [str(s.get("scale", "y")) if isinstance(s, dict) else "y" for s in series[1:len(cols)]]
    scales += ["y"] * (len(ys) - len(scales))

    def first(y: np.ndarray) -> float | None:
        i = np.flatnonzero(np.isfinite(y))
        return float(y[i[0]]) if i.size else None

    own = [first(y) for y in ys]
    anchor = []
    for j, v in enumerate(own):
        if v is None:
            v = next((w for w, sc in zip(own, scales) if w is not None and sc == scales[j]), None)
        anchor.append(0.0 if v is None else v)
    dx = ANCHOR_DX * (float(x[1] - x[0]) if len(x) > 1 else 1.0)
    return (np.r_[x[0] - dx, x], *(np.r_[a, y] for a, y in zip(anchor, ys)))


def _positive(y) -> np.ndarray:
    """``y`` with every value that is not > 0 a gap (NaN): what a log-scale axis can draw."""
    y = np.asarray(y, float)
    with np.errstate(invalid="ignore"):
        return np.where(y > 0, y, np.nan)


def has_values(y) -> bool:
    """Whether the column ``y`` (None: absent) holds a finite value."""
    return bool(y is not None and np.isfinite(np.asarray(y, float)).any())


#: a logarithmic y scale (uPlot's ``distr`` 3). uPlot draws a value a log scale cannot show (≤ 0, and NaN — the
#: only gap a typed array can carry) at its ``clamp``, by default a tenth of the scale's minimum: every gap
#: became a dive to the bottom of the panel (measured in Chromium on Viser 1.1.1's uPlot). A clamp that is
#: itself no value of the scale (−1: log₁₀ of it is NaN) leaves them out — the line joins the points either
#: side, as it does on a linear scale.
LOG_SCALE = {"distr": 3, "log": 10, "clamp": -1.0}


def nees_panel(series: dict[str, np.ndarray], selected: int | None = None) -> PanelSpec:
    """The network NEES (the mean of the nodes' εᵢ), the 95 % χ² interval of that mean as two lines, and
    the selected sensor's own εᵢ, on a log scale (a NEES spans decades: 0.1 … 1e3)."""
    k = np.asarray(series["k"], float)
    data = [k, _positive(series["nees"]), _positive(series["nees_lo"]), _positive(series["nees_hi"])]
    sers = [_x_series(), _line("NEES", "#1f77b4", 1.8), _line("95 % lo", "#2ca02c", 1.0, dash=[5, 4]),
            _line("95 % hi", "#d62728", 1.0, dash=[5, 4])]
    own = series.get("nees_node")
    if selected is not None and own is not None and np.ndim(own) == 2 and 0 <= selected < np.shape(own)[1]:
        data.append(_positive(np.asarray(own, float)[:, selected]))
        sers.append(_line(f"ε{selected}", "#ff7f0e", 1.0))
    axes = _axes("NEES (log)")
    axes[1]["ticks"] = {"show": False}     # (a log axis's minor tick marks crowd into a black bar at this size)
    return PanelSpec("nees", "NEES ε = e′P⁻¹e (mean over nodes) and its 95 % χ² band", tuple(data), tuple(sers),
                     {**_X_SCALE, "y": dict(LOG_SCALE)}, axes)


def suspicion_panel(series: dict[str, np.ndarray]) -> PanelSpec:
    """The number of suspicions (i, j) — i discarded j's payloads — per tick."""
    return PanelSpec("suspicions", "Suspicions: pairs (i suspects j) per tick", (series["k"], series["suspected"]),
                     (_x_series(), _line("suspicions", "#d62728", 1.5)), _X_SCALE, _axes("pairs"))


def uplot_panels(series: dict[str, np.ndarray], n: int, selected: int | None = None, *,
                 max_node_series: int = 10, has_lower: bool | None = None,
                 has_fusion: bool | None = None, has_nees: bool | None = None,
                 has_suspicion: bool | None = None) -> list[PanelSpec]:
    """The live plot panels. Per-node errors are drawn one line per node up to ``max_node_series``
    nodes; above that as the median and maximum over nodes plus the selected node. Each panel's data
    went through :func:`drawable`. ``has_lower`` / ``has_fusion``: whether the TMSEE lower bound / the
    fusion error have a line, ``has_nees`` / ``has_suspicion``: whether the NEES panel (a run whose
    estimates carry covariances) / the suspicions panel (a resilient consensus) is shown (None: whether
    the series hold a value of it) — the live UI fixes them so that the panels and their lines do not
    change as the window slides."""
    k = np.asarray(series["k"], float)
    err = np.asarray(series["err"], float).reshape(len(k), -1)
    panels: list[PanelSpec] = []

    # 1. position errors and the network RMSE
    data = [k]
    sers = [_x_series()]
    if n <= max_node_series:
        for i in range(n):
            data.append(err[:, i])
            w = 2.5 if i == selected else 1.0
            sers.append(_line(f"e{i}", NODE_PALETTE[i % len(NODE_PALETTE)], w))
    else:
        with np.errstate(all="ignore"):
            ok = np.isfinite(err).any(axis=1)
            med = np.full(len(k), np.nan)
            mx = np.full(len(k), np.nan)
            if ok.any():
                med[ok] = np.nanmedian(err[ok], axis=1)
                mx[ok] = np.nanmax(err[ok], axis=1)
        data += [med, mx]
        sers += [_line("median eᵢ", "#2ca02c", 1.2), _line("max eᵢ", "#d62728", 1.2)]
        if selected is not None and 0 <= selected < err.shape[1]:
            data.append(err[:, selected])
            sers.append(_line(f"e{selected}", "#1f77b4", 2.0))
    data.append(series["rmse"])
    sers.append(_line("RMSE", "#000000", 2.5))
    panels.append(PanelSpec("errors", "Position error eᵢ(k) and network RMSE", tuple(data), tuple(sers), _X_SCALE,
                            _axes("error")))

    # 2. TMSEE and its lower bound
    lower = series.get("tmsee_lower")
    has_lower = bool(lower is not None and np.isfinite(lower).any()) if has_lower is None else has_lower
    data = [k, series["tmsee"]]
    sers = [_x_series(), _line("TMSEE", "#1f77b4", 1.8)]
    if has_lower:
        data.append(lower)
        sers.append(_line("lower bound (12)", "#d62728", 1.5, dash=[6, 4]))
    panels.append(PanelSpec("tmsee", "TMSEE" + (" vs its lower bound" if has_lower else " (no lower bound defined)"),
                            tuple(data), tuple(sers), _X_SCALE, _axes("Σ‖x̂ᵢ−x‖²")))

    # 3. consensus disagreement (and the error of the mean estimate, fusion if present)
    data = [k, series["disagreement"], series["mean_err"]]
    sers = [_x_series(), _line("disagreement", "#9467bd", 1.8), _line("‖x̄−x‖", "#8c564b", 1.2)]
    fe = series.get("fusion_err")
    if has_fusion is None:
        has_fusion = bool(fe is not None and np.isfinite(fe).any())
    if has_fusion and fe is not None:
        data.append(fe)
        sers.append(_line("fusion", "#e377c2", 1.2))
    panels.append(PanelSpec("disagreement", "Consensus disagreement √mean‖x̂ᵢ−x̄‖²", tuple(data), tuple(sers),
                            _X_SCALE, _axes("disagreement")))

    # 4. algebraic connectivity
    l2a = series.get("lambda2_alive", series["lambda2"])
    panels.append(PanelSpec("lambda2", "Algebraic connectivity λ₂ and links",
                            (k, series["lambda2"], l2a, series["links"]),
                            (_x_series(), _line("λ₂", "#17becf", 1.8), _line("λ₂ alive", "#17becf", 1.2, dash=[4, 3]),
                             _line("links", "#bbbbbb", 1.0, scale="links")),
                            {**_X_SCALE, "links": {"auto": True}}, _axes("λ₂", right="links")))

    # 5. message rate and dropped messages per second
    panels.append(PanelSpec("rates", "Messages / s and dropped / s", (k, series["msg_rate"], series["drop_rate"]),
                            (_x_series(), _line("msg/s", "#1f77b4", 1.5), _line("dropped/s", "#d62728", 1.5,
                                                                                   scale="drop")),
                            {**_X_SCALE, "drop": {"auto": True}}, _axes("msg/s", right="drop")))

    # 6. consistency: the NEES and its χ² band (estimates with covariances only)
    if (has_values(series.get("nees")) if has_nees is None else has_nees) and "nees" in series:
        panels.append(nees_panel(series, selected))

    # 7. Byzantine suspicion (a resilient consensus only)
    if (has_values(series.get("suspected")) if has_suspicion is None else has_suspicion) and "suspected" in series:
        panels.append(suspicion_panel(series))
    for p in panels:
        p.data = drawable(p.data, p.series)
    return panels


def decimate(series: dict[str, np.ndarray], max_points: int) -> dict[str, np.ndarray]:
    """Every m-th row (keeping the last) so that at most ``max_points`` rows go to the browser."""
    n = len(series["k"])
    if n <= max_points:
        return series
    step = math.ceil(n / max_points)
    idx = np.arange(n - 1, -1, -step)[::-1]
    return {c: v[idx] for c, v in series.items()}


# --------------------------------------------------------------------------- static PNG

def save_static_png(path, series: dict[str, np.ndarray], snap: Snapshot | None, n: int, *, title: str = "",
                    link_range: float = math.inf, selected: int | None = None, max_node_series: int = 10) -> None:
    """A static figure of the dashboard: top view of the flock at the snapshot's tick and the panels of
    :func:`uplot_panels` (the NEES panel on a log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    panels = uplot_panels(series, n, selected, max_node_series=max_node_series)
    rows = max(3, math.ceil((len(panels) + 1) / 2))     # two panels a row, and the numbers' slot
    fig = plt.figure(figsize=(15, 8.5 * rows / 3), dpi=110)
    gs = fig.add_gridspec(rows, 3, width_ratios=[1.25, 1, 1])
    ax0 = fig.add_subplot(gs[:, 0])
    if snap is not None:
        sa = scene_arrays(snap, selected=selected, error_scale=auto_error_scale(series["err"][-200:]),
                          link_range=link_range)
        for seg in sa.circles.reshape(-1, 2, 3)[:: 1]:
            ax0.plot(seg[:, 0], seg[:, 1], color="#cfd8e3", lw=0.5, zorder=1)
        for seg in sa.links:
            ax0.plot(seg[:, 0], seg[:, 1], color="#4a6fa5", lw=0.8, alpha=0.7, zorder=2)
        for seg in sa.suspicions:
            ax0.plot(seg[:, 0], seg[:, 1], color="#e01e28", lw=1.8, zorder=3)
        if len(sa.trail):
            tr = np.concatenate([sa.trail[:, 0], sa.trail[-1:, 1]])
            ax0.plot(tr[:, 0], tr[:, 1], color="#d62728", lw=1.2, alpha=0.6, zorder=3)
        ax0.scatter(sa.sensor_points[:, 0], sa.sensor_points[:, 1], c=sa.sensor_colors / 255.0, s=60,
                    edgecolors="k", linewidths=0.5, zorder=4, label="sensors (colour = own error)")
        if len(sa.estimate_points):
            ax0.scatter(sa.estimate_points[:, 0], sa.estimate_points[:, 1], c=sa.estimate_colors / 255.0, s=14,
                        marker="D", zorder=5, label="node estimates")
        if sa.target is not None:
            ax0.scatter([sa.target[0]], [sa.target[1]], c="#d62728", s=120, marker="*", zorder=6, label="target")
        if sa.fusion is not None:
            ax0.scatter([sa.fusion[0]], [sa.fusion[1]], c="#9467bd", s=60, marker="P", zorder=6, label="fusion")
        if len(sa.ellipse):
            el = np.concatenate([sa.ellipse[:, 0], sa.ellipse[-1:, 1]])
            ax0.plot(el[:, 0], el[:, 1], color="#1f77b4", lw=1.5, zorder=6)
        ax0.set_title(f"tick {snap.k}  t = {snap.t:.2f} s")
        ax0.legend(loc="upper left", fontsize=8)
    ax0.set_aspect("equal", adjustable="datalim")
    ax0.grid(alpha=0.3)
    slots = [gs[r, c] for r in range(rows) for c in (1, 2)]
    for p, slot in zip(panels, slots):
        ax = fig.add_subplot(slot)
        x = p.data[0]
        right = None
        for y, s in zip(p.data[1:], p.series[1:]):
            target_ax = ax
            if s.get("scale", "y") != "y":
                right = right or ax.twinx()
                target_ax = right
            target_ax.plot(x, y, color=s.get("stroke", "k"), lw=s.get("width", 1.0) * 0.8,
                           ls="--" if s.get("dash") else "-", label=s.get("label"))
        if p.scales.get("y", {}).get("distr") == 3 and np.isfinite(np.asarray(p.data[1:], float)).any():
            ax.set_yscale("log")
            for set_format in (ax.yaxis.set_major_formatter, ax.yaxis.set_minor_formatter):
                set_format(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.set_title(p.title, fontsize=9)
        ax.grid(alpha=0.3)
        if len(p.series) <= 8:
            ax.legend(fontsize=7, loc="upper right")
    ax = fig.add_subplot(slots[len(panels)])
    ax.axis("off")
    if len(series["k"]):
        last = {c: series[c][-1] for c in ("k", "rmse", "lambda2", "msg_rate", "drop_rate", "nees", "suspected")
                if c in series and np.isfinite(series[c][-1])}
        ax.text(0.0, 0.9, "\n".join(f"{c}: {v:.4g}" for c, v in last.items()), va="top", family="monospace")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
