"""The dashboard's page: the Viser server behind the tab guard (and, for a secure run, HTTPS), its panels,
and each browser tab's own panels hooked up as the tab connects.

Shared by every tab: the scene (:mod:`dashboards.scene`), the control panel docked right
(:mod:`dashboards.control_panel`: status, replay, legend) and the plots docked left
(:mod:`dashboards.plot_panel`). Each tab's own: its camera (:mod:`dashboards.camera`), its view and
inspector (:mod:`dashboards.tabs`) and, for a tab with the run's operator token, the run and fault controls
(:mod:`dashboards.operator`). GUI callbacks run on Viser's threads; they only set fields and call
``send_control``, whose caller publishes on its own thread (dashboards/live.py).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from . import plots
from .camera import TabCameras
from .control_panel import LAYOUT, ControlPanel, Playback
from .guard import Limits, TabGuard
from .plot_panel import PlotPanel
from .scene import FlockScene
from .state import ReplayModel, RunInfo, Snapshot
from .tabs import DisplaySettings, GuardedGui, TabPanel, build_display, build_tab, clamp_index, render_tab

log = logging.getLogger(__name__)


@dataclass
class UiTimings:
    """Redraws done and the time they took (s)."""

    scene_updates: int = 0
    plot_updates: int = 0
    scene_s: float = 0.0
    plot_s: float = 0.0
    samples: list = field(default_factory=list)


class DashboardUI:
    """The Viser server and its panels. ``send_control(verb, args)`` is called (from Viser's threads) by the
    fault and run-control buttons; None in replay."""

    def __init__(self, info: RunInfo, port: int = 8080, host: str = "127.0.0.1", *, live: bool = True,
                 send_control=None, replay: ReplayModel | None = None, verbose: bool = False,
                 operator_token: str | None = None, tls: tuple[str, str] | None = None,
                 limits: Limits | None = None):
        """``tls``: (certificate, key) files — the page is then HTTPS on ``host:port`` (dashboards/tls.py)
        and Viser itself listens on a free port of 127.0.0.1 behind it. ``limits``: what a tab may send
        (dashboards/guard.py)."""
        import viser

        from . import frames, loop_safe
        from .operator import Operators

        frames.install()   # one encoding per broadcast frame, not one per tab (dashboards/frames.py)
        loop_safe.install()   # pushes from this process's threads wake Viser's loop from that loop only

        self.info, self.live, self.replay = info, live, replay
        self.operators = Operators(operator_token if live else None)
        # every tab's messages are checked before Viser acts on them; on a replay page (nothing to steer)
        # the shared widgets (slider, display) take any tab's valid update
        self.guard = TabGuard(limits, shared_writable=not live)
        self.guard.quiet_logs()
        self.send_control = send_control
        v_host, v_port = ("127.0.0.1", 0) if tls else (host, port)
        self.server = viser.ViserServer(host=v_host, port=v_port, label=f"flocktrack · {info.name}",
                                        verbose=verbose) \
            if "verbose" in viser.ViserServer.__init__.__code__.co_varnames \
            else viser.ViserServer(host=v_host, port=v_port, label=f"flocktrack · {info.name}")
        self.guard.install(self.server)
        self.tls_front = None
        if tls:
            from .tls import TlsFront

            self.tls_front = TlsFront(host, port, self.server.get_port(), *tls)
        self.port = self.tls_front.port if self.tls_front else self.server.get_port()
        self.scheme = "https" if tls else "http"
        #: the sensor the shared page highlights (the error panel's line): an operator's choice; each tab's
        #: own inspector is in ``tabs`` (dashboards/tabs.py)
        self.selected: int | None = 0 if info.n else None
        self.tabs: dict[int, TabPanel] = {}
        self.tabs_dirty = False           # a tab's own choice changed: redraw the tabs' parts (not the scene)
        self.display = DisplaySettings(circles=info.n <= 40)
        self.dirty = True                 # redraw even if the tick did not change
        self.timings = UiTimings()
        self._last_scene_k = None
        self._last_snapshot: Snapshot | None = None
        self._lock = threading.Lock()
        self.controls_sent: list[tuple[str, dict]] = []
        # the camera: per browser tab, framed on the flock and gliding after it while its "Follow" is on
        self.cameras = TabCameras(self.server, self._follow_box, self.guard.safe)
        self.scene = FlockScene(self.server, info)
        # a click on the ground near a sensor selects it (in that tab)
        self.server.scene.on_click()(self.guard.safe(lambda e: self._pick(e.ray_origin, e.ray_direction, e.client_id),
                                                     "pick"))
        self._build_gui()
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)

    def _build_gui(self) -> None:
        """The shared control panel (docked right): the status, the replay's slider, the legend; then the
        plots panel (docked left). Each tab adds its own panels at the places of ``layout``."""
        self.layout = dict(LAYOUT)
        self.control_panel = ControlPanel(self.server.gui, self.layout, self.info, live=self.live)
        self.player: Playback | None = None
        if not self.live:
            shared = GuardedGui(self.server.gui, self.guard.allow)
            self.player = Playback(shared, self.replay, self.layout["replay"], safe=self.guard.safe,
                                   on_seek=self._mark_dirty)
            build_display(shared, self, self.layout["display"])
        self.control_panel.add_legend()
        self.plot_panel = PlotPanel(self.server, self.info)

    def _mark_dirty(self) -> None:
        self.dirty = True

    # ------------------------------------------------------------------ the scene
    @property
    def last_scene_k(self) -> int | None:
        """The tick the scene shows (None: none drawn yet)."""
        return self._last_scene_k

    def _pick(self, origin, direction, client_id: int | None = None) -> None:
        i = self.scene.nearest(self._last_snapshot, origin, direction)
        if i is not None:
            self.select(i, client_id)

    def render_scene(self, snap: Snapshot | None, err_rows: np.ndarray | None = None) -> plots.SceneArrays | None:
        """Redraw the scene from a snapshot (a handful of batched messages), the tabs' own parts, and move
        the cameras toward the new framing."""
        if snap is None:
            return None
        if snap.k == self._last_scene_k and not self.dirty:
            return None
        t0 = time.perf_counter()
        self._last_snapshot = snap
        self.dirty = False
        self._last_scene_k = snap.k
        self.cameras.frame_on(snap, min_radius=max(4 * self.scene.marker_size, 2.0))
        sa = self.scene.draw(snap, self.display, err_rows)
        self._render_tabs(snap)
        self.update_view()
        self.timings.scene_updates += 1
        self.timings.scene_s += time.perf_counter() - t0
        return sa

    # ------------------------------------------------------------------ each tab's own panels
    def select(self, i: int | None, client_id: int | None = None) -> None:
        """Tab ``client_id`` inspects sensor ``i`` (its dropdown, or its click in the scene): its own
        inspector and overlays follow, and an operator's fields (:meth:`_retarget`) and the sensor the shared
        page highlights. A viewer's choice changes its own tab only. (None: this process's choice, of the
        shared highlight.)"""
        if i is None:
            return
        i = clamp_index(i, self.info.n)
        panel = self.tabs.get(client_id) if client_id is not None else None
        if panel is not None:
            panel.selected, panel.drawn = i, None
            self.tabs_dirty = True
            node = panel.widgets["node"]
            if node.value != str(i):
                node.value = str(i)
        if client_id is None or client_id in self.operators.panels:
            with self._lock:
                self.selected = i
                self.dirty = True
                self.plot_panel.last_k = None
        if client_id is not None:
            self._retarget(client_id, i)

    def _retarget(self, client_id: int | None, i: int) -> None:
        """Tab ``client_id`` inspects sensor ``i``: if that tab is an operator's, its own "Sensor id" and
        "Link a" follow. Another tab's choice — a viewer's above all — never touches them."""
        panel = self.operators.panels.get(client_id) if client_id is not None else None
        if panel is not None:
            for h in (panel.g_kill_id, panel.g_link_a):
                h.value = i

    def refresh_tabs(self) -> None:
        """Redraw what changed of the tabs' own parts since a tab's choice (between scene redraws)."""
        if self.tabs_dirty and self._last_snapshot is not None:
            self._render_tabs(self._last_snapshot)

    def _render_tabs(self, snap: Snapshot) -> None:
        """Each tab's own selection and inspector text (dashboards/tabs.py)."""
        self.tabs_dirty = False
        for panel in tuple(self.tabs.values()):
            self.guard.safe(render_tab, "render_tab")(panel, snap, self)

    def _on_connect(self, client) -> None:
        """A new tab: its own view and inspector, and an operator's (the run's token in its websocket path)
        controls on its own GUI (:meth:`_add_tab_panels`); every tab gets the framing at once (at the next
        update), and its camera reports are watched for the user's own moves. (Viser runs this in its thread
        pool, off the live loop's thread: a new tab's first frame is Viser's backlog, sent by its event loop.)"""
        self._add_tab_panels(client)
        self.cameras.add(client)
        self.update_view(force=True)

    def _on_disconnect(self, client) -> None:
        self.cameras.remove(client.client_id)
        self.tabs.pop(client.client_id, None)
        self.operators.panels.pop(client.client_id, None)

    def _add_tab_panels(self, client) -> None:
        """A new tab's own view and inspector and, with the run's token, its operator controls. Neither may
        fail half-way: a failure is logged once, the tab is told, and a half-built operator panel is removed
        (the tab is then no operator)."""
        from .operator import websocket_path

        cid = client.client_id
        try:
            self.tabs[cid] = build_tab(self, client)
        except Exception:
            self._panel_failed(client, "view and inspector")
        if self.live and self.operators.is_operator(websocket_path(self.server, cid)):
            try:
                self.add_operator_panel(client.gui, cid)
                log.info("tab %s: operator", cid)
            except Exception:
                self.operators.panels.pop(cid, None)
                self._panel_failed(client, "operator controls")

    def add_operator_panel(self, gui, client_id: int | None):
        """The run and fault controls on ``gui`` for tab ``client_id`` (dashboards/operator.py); the tab may
        change them (the guard), and is an operator once they are all built."""
        from .operator import build_panel, show_panel

        if client_id is not None:
            gui = GuardedGui(gui, lambda h: self.guard.allow(h, client_id))
        panel = build_panel(gui, client_id, self, self.layout)
        self.operators.panels[client_id] = panel
        if client_id is not None:
            self.guard.mark_operator(client_id)
        show_panel(panel)   # only now: every button it shows works
        return panel

    def _panel_failed(self, client, what: str) -> None:
        self.guard.counters["panel_failures"] += 1
        if self.guard.counters["panel_failures"] == 1:
            log.exception("tab %s: its %s could not be built (logged once)", client.client_id, what)
        try:
            client.add_notification(f"The {what} could not be built", "See the dashboard's log; reload the page.",
                                    color="red", with_close_button=True)
        except Exception:  # the tab is gone
            pass

    # ------------------------------------------------------------------ the tabs' cameras
    def _follow_box(self, cid: int, on: bool) -> None:
        panel = self.tabs.get(cid)
        if panel is not None and panel.widgets["follow"].value != on:
            panel.widgets["follow"].value = on

    def set_follow(self, cid: int, on: bool) -> None:
        """Tab ``cid``'s "Follow the flock" checkbox (:meth:`dashboards.camera.TabCameras.set_follow`)."""
        self.cameras.set_follow(cid, on)

    def reset_view(self, cid: int | None = None) -> None:
        """Tab ``cid``'s "Reset view" button (None: every tab): framed on the flock at once, from the default
        direction, and following it again."""
        self.cameras.reset(cid)
        for c in ([cid] if cid is not None else list(self.tabs)):
            self._follow_box(c, True)
        self.update_view(force=True)

    def update_view(self, force: bool = False) -> None:
        """Move each following tab's camera toward the framing (:meth:`dashboards.camera.TabCameras.update`)."""
        self.cameras.update(force)

    # ------------------------------------------------------------------ plots, status, controls
    def render_plots(self, series: dict[str, np.ndarray], force: bool = False) -> None:
        t0 = time.perf_counter()
        if self.plot_panel.render(series, self.selected, force):
            self.timings.plot_updates += 1
            self.timings.plot_s += time.perf_counter() - t0

    def render_status(self, st: dict) -> None:
        self.control_panel.render_status(st)

    def control(self, verb: str, **args) -> None:
        """Send ``control/<verb>`` with ``args`` (what the buttons do); recorded in ``controls_sent``.
        Nothing in replay."""
        if self.send_control is None:
            return
        self.controls_sent.append((verb, args))
        self.send_control(verb, args)

    def partition_groups(self) -> list[int]:
        """Two groups split at the median x position of the shown tick (the flock cut in half)."""
        snap = self._last_snapshot
        n = self.info.n
        if snap is None or not np.isfinite(snap.positions[:, 0]).all():
            return [int(i >= n // 2) for i in range(n)]
        x = snap.positions[:, 0]
        order = np.argsort(x, kind="stable")
        g = np.zeros(n, int)
        g[order[n // 2:]] = 1
        return [int(v) for v in g]

    def attach_replay(self, model: ReplayModel) -> None:
        """The recording is loaded (the page is served meanwhile): set the slider to its ticks."""
        self.replay = model
        self.player.attach(model)
        self.dirty = True

    def stats(self) -> dict:
        """The tabs' counters for the stats file: operators / viewers / wrong tokens / refused controls and
        the guard's (dashboards/guard.py), totals and per tab."""
        from . import frames

        return {**self.operators.counters, "guard": self.guard.stats(), "frames": frames.stats()}

    def stop(self) -> None:
        self.guard.uninstall()
        if self.tls_front is not None:
            self.tls_front.close()
        try:
            self.server.stop()
        except Exception:  # already stopped
            pass
