"""Each browser tab's own panels: its view (follow the flock, reset) and its inspector (the selected
sensor, its covariance ellipse, its NEES, whom it suspects and its text, drawn on the tab's own scene).

What a viewer chooses changes only its own tab: these widgets live on the tab's GUI (``client.gui``) and
its selection overlays on the tab's scene (``client.scene``), and the guard (dashboards/guard.py) lets a tab
change only its own widgets. The shared page — the flock, the links, the plots, the status — is written by
the dashboard, and what it shows of a choice (the selected sensor's line in the error panel, the display
toggles) is an operator's (dashboards/operator.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import plots


class GuardedGui:
    """``gui`` (a tab's own) whose every ``add_*`` lets that tab, and only it, change the new widget
    (:meth:`dashboards.guard.TabGuard.allow`)."""

    def __init__(self, gui, allow):
        self._gui, self._allow = gui, allow

    def __getattr__(self, name: str):
        attr = getattr(self._gui, name)
        if not name.startswith("add_"):
            return attr

        def add(*args, **kwargs):
            handle = attr(*args, **kwargs)
            self._allow(handle)
            return handle

        return add


@dataclass
class DisplaySettings:
    """What the shared scene shows — every tab's, so set only by an operator (live) or by any tab of a
    replay (dashboards/guard.py)."""

    links: bool = True
    circles: bool = True
    estimates: bool = True
    trail: bool = True
    err_scale: float = 0.0               #: the error colour scale (0: auto)


#: the Display folder's checkboxes: label → DisplaySettings field
DISPLAY_TOGGLES = (("Links", "links"), ("Range circles", "circles"), ("Node estimates", "estimates"),
                   ("Target trail", "trail"))


def build_display(gui, ui, order: float, visible: bool = True) -> tuple:
    """Folded: the Display folder (links, range circles, estimates, trail, the error colour scale), started
    from ``ui.display`` and writing it; returns the folder and its widgets by field name."""
    d, out = ui.display, {}

    def setter(name: str, h, cast):
        def set_(_e) -> None:
            setattr(d, name, cast(h.value))
            ui.dirty = True
        return ui.guard.safe(set_, f"display.{name}")

    with gui.add_folder("Display (every tab)", expand_by_default=False, order=order, visible=visible) as folder:
        for label, name in DISPLAY_TOGGLES:
            out[name] = gui.add_checkbox(label, bool(getattr(d, name)))
        scale = d.err_scale if math.isfinite(d.err_scale) and 0.0 <= d.err_scale <= 1e6 else 0.0
        out["err_scale"] = gui.add_number("Error colour scale (0 = auto)", scale, min=0.0, max=1e6, step=0.1)
    for name, h in out.items():
        h.on_update(setter(name, h, float if name == "err_scale" else bool))
    return folder, out


@dataclass
class TabPanel:
    """One tab's view and inspector widgets, its selection and its overlay handles."""

    client_id: int
    selected: int = 0
    widgets: dict = field(default_factory=dict)     #: name → handle (g_follow, g_node, g_ellipse, …)
    overlays: dict = field(default_factory=dict)    #: name → the tab's own scene handles
    drawn: tuple | None = None                      #: (tick, selection, ellipse, n·σ) last drawn


def clamp_index(i, n: int) -> int:
    """A sensor index in [0, n − 1] (0 for anything else, e.g. a value a tab should never have sent)."""
    try:
        i = int(i)
    except (TypeError, ValueError, OverflowError):
        return 0
    return min(max(i, 0), max(n - 1, 0))


def build_tab(ui, client) -> TabPanel:
    """The tab's View and Inspect folders (at the shared layout's places) and its overlays."""
    cid = client.client_id
    panel = TabPanel(cid, selected=clamp_index(0, ui.info.n))
    gui = GuardedGui(client.gui, lambda h: ui.guard.allow(h, cid))
    w = panel.widgets
    safe = ui.guard.safe
    with gui.add_folder("View", order=ui.layout["view"]):
        w["follow"] = gui.add_checkbox("Follow the flock", True,
                                       hint="keep the camera on the flock (moving the camera stops it)")
        reset = gui.add_button("Reset view", hint="frame the flock and the target, and follow them again")
    w["follow"].on_update(safe(lambda _e: ui.set_follow(cid, bool(w["follow"].value)), "follow"))
    reset.on_click(safe(lambda _e: ui.reset_view(cid), "reset_view"))
    ids = [str(i) for i in range(ui.info.n)] or ["0"]
    with gui.add_folder("Inspect", order=ui.layout["inspect"]):
        w["node"] = gui.add_dropdown("Sensor", ids, initial_value=ids[panel.selected])
        w["ellipse"] = gui.add_checkbox("Covariance ellipse", True)
        w["nsig"] = gui.add_slider("Ellipse n·σ", 1.0, 50.0, 1.0, 2.0, hint="size of the ellipse in σ")
        w["text"] = client.gui.add_markdown("")
    w["node"].on_update(safe(lambda _e: ui.select(int(w["node"].value), cid), "inspect"))
    def redraw(_e) -> None:
        panel.drawn = None
        ui.tabs_dirty = True

    for name in ("ellipse", "nsig"):
        w[name].on_update(safe(redraw, name))
    _add_overlays(client.scene, panel, ui.scene.marker_size)
    return panel


def _add_overlays(scene, panel: TabPanel, size: float) -> None:
    """The selected sensor's links, ring, label, estimate and ellipse, on the tab's own scene."""
    zs = np.zeros((1, 2, 3), np.float32)
    o = panel.overlays
    o["links"] = scene.add_line_segments("/tab/selected/links", zs, (255, 140, 0), thickness=4.0,
                                         thickness_units="screen", visible=False)
    o["ellipse"] = scene.add_line_segments("/tab/selected/ellipse", zs, (30, 110, 200), thickness=3.0,
                                           thickness_units="screen", visible=False)
    o["ring"] = scene.add_line_segments("/tab/selected/ring", zs, (255, 140, 0), thickness=3.0,
                                        thickness_units="screen", visible=False)
    o["est"] = scene.add_point_cloud("/tab/selected/estimate", np.zeros((1, 3), np.float32), (30, 110, 200),
                                     point_size=1.0 * size, point_shape="diamond", precision="float32",
                                     visible=False)
    o["label"] = scene.add_label("/tab/selected/label", "", visible=False)


def show(h, on: bool) -> None:
    """Set a scene handle's visibility, sending nothing when it is already so."""
    if h.visible != on:
        h.visible = on


def set_segments(h, segs: np.ndarray, visible: bool = True) -> None:
    """Draw ``segs`` with the line-segment handle ``h`` (hidden when ``visible`` is off or there are none)."""
    if not visible or len(segs) == 0:
        show(h, False)
        return
    h.points = segs
    show(h, True)


def render_tab(panel: TabPanel, snap, ui) -> None:
    """Draw the tab's selection on its own scene and its inspector text (only what changed)."""
    w, o = panel.widgets, panel.overlays
    key = (snap.k, panel.selected, bool(w["ellipse"].value), float(w["nsig"].value))
    if key == panel.drawn:
        return
    panel.drawn = key
    sel = plots.selection_arrays(snap, panel.selected, nsig=key[3])
    set_segments(o["links"], sel.links)
    if key[2]:
        set_segments(o["ellipse"], sel.ellipse)
    else:
        show(o["ellipse"], False)
    if sel.pos is not None:
        set_segments(o["ring"], plots.circle_segments(sel.pos[None], 1.1 * ui.scene.marker_size, 24))
        o["label"].position = tuple(sel.pos + np.array([0.0, 0.0, 1.5 * ui.scene.marker_size]))
        o["label"].text = selection_label(snap, panel.selected)
        show(o["label"], True)
    else:
        show(o["ring"], False)
        show(o["label"], False)
    if sel.est is not None:
        o["est"].points = sel.est[None].astype(np.float32)
        show(o["est"], True)
    else:
        show(o["est"], False)
    text = inspect_text(snap, panel.selected, ui.info.pos_dims, key[3])
    if text != w["text"].content:
        w["text"].content = text


def selection_label(snap, i: int) -> str:
    """The selected sensor's label in the scene: its id, and whom it suspects at the snapshot's tick."""
    sus = snap.suspects_of(i)
    return f"sensor {i}" + (f" · suspects {', '.join(map(str, sus))}" if sus else "")


def nees_text(snap, i: int) -> str | None:
    """Sensor ``i``'s NEES at the snapshot's tick and the network's, with the network's 95 % band (None:
    no NEES for it)."""
    own = snap.nees[i] if snap.nees is not None and i < len(snap.nees) else math.nan
    if not math.isfinite(own):
        return None
    row = snap.row
    net = f" · network {row['nees']:.3g} (95 % band {row['nees_lo']:.3g} … {row['nees_hi']:.3g})" \
        if all(math.isfinite(row.get(c, math.nan)) for c in ("nees", "nees_lo", "nees_hi")) else ""
    return f"NEES εᵢ = {own:.3g}{net}"


def inspect_text(snap, i: int | None, pos_dims: int, nsig: float) -> str:
    """The inspector's text for sensor ``i`` at the snapshot's tick."""
    if i is None or not 0 <= i < snap.n:
        return "click a sensor, or pick one above"
    nb = snap.neighbours[i] if i < len(snap.neighbours) else []
    xn, P, e = snap.est_next.get(i), snap.cov_pos.get(i), snap.errors[i]
    sigma = ("position σ = " + np.array2string(np.sqrt(np.maximum(np.diag(P), 0)), precision=3)
             + f" (ellipse: {nsig:g}σ)") if P is not None else "position σ = – (no covariance)"
    parts = [f"**sensor {i}** · {'alive' if snap.alive[i] else '**dead**'} · tick {snap.k}",
             f"position {np.array2string(snap.positions[i][:pos_dims], precision=2)}",
             f"own error eᵢ = {e:.3g}" if math.isfinite(e) else "no estimate this tick",
             "x̂ₖ₊₁ = " + (np.array2string(xn, precision=2) if xn is not None else "–"),
             sigma, f"neighbours ({len(nb)}): {', '.join(map(str, nb)) or 'none'}"]
    nees = nees_text(snap, i)
    if nees:
        parts.insert(5, nees)
    sus = snap.suspects_of(i)
    if sus:
        parts.append(f"suspects ({len(sus)}): {', '.join(map(str, sus))}")
    return "  \n".join(parts)
