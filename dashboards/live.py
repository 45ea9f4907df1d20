"""The Viser web dashboard: a read-only subscriber to ``ft/<run>/**`` that writes only ``control/**``.

Live (``python -m dashboards --run R --connect EP --port P --scenario FILE``): the bus delivers on this
process's thread into a :class:`~dashboards.state.DashboardState`; at most every ``scene_period`` seconds
the scene is redrawn from a snapshot (a few batched objects: one point cloud for all sensors, one
line-segment set for all links, …) and every ``plot_period`` seconds the uPlot panels and the status
text. GUI callbacks run on Viser's threads; they only set fields and queue control messages, which this
thread publishes — the bus and the state are touched by one thread only. Each browser tab's camera is
framed on the flock and follows it until the user moves it (:meth:`DashboardUI.update_view`; the camera
state has its own lock, as the tabs' camera reports arrive on Viser's threads).

Replay (``python -m dashboards --recording FILE --port P``): the recording is read with ``mcap`` and
:func:`agent.wire.from_json`, fed once through a :class:`~dashboards.state.ReplayModel`, and shown with a
time slider over its ticks (play / pause / playback speed).
"""

from __future__ import annotations

import json
import logging
import math
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from agent import wire

from . import plots
from .guard import Limits, TabGuard
from .state import DashboardState, ReplayModel, RunInfo, Snapshot
from .tabs import (DisplaySettings, GuardedGui, TabPanel, build_display, build_tab, clamp_index, render_tab, set_segments,
                   show)

log = logging.getLogger(__name__)

#: Everything but the addressed copies of the exchange payloads (agent.wire.OBSERVED). The model relies on
#: the publication order to score a tick in time; the bus's callbacks keep it across subscriptions
#: (agent.bus.ZenohBus._in_order).
SUBSCRIPTIONS = wire.OBSERVED


# ============================================================================ recordings (replay)

@dataclass
class LoadedRecording:
    metadata: dict[str, str]
    messages: list[tuple[str, wire.Message | None, int]]  # None: counted only
    complete: bool = True
    rejected: int = 0


def decoded_key(topic: str) -> bool:
    """Keys decoded and fed to the model (world, truth, estimates, states, fusion, control); the others —
    exchange payloads and measurements, the bulk of the traffic — are only counted."""
    parts = topic.split("/")
    if parts[0] == "agent":
        return len(parts) == 3 and parts[2] in ("estimate", "state")
    if parts[0] == "target":
        return topic == "target/truth"
    return parts[0] in ("world", "fusion", "control")


def load_recording(path: str | Path) -> LoadedRecording:
    """A flocktrack MCAP recording: metadata and the messages in recording order (by sequence number).
    Exchange payloads and measurements are not decoded (the dashboard only counts them). A truncated
    file yields what its readable records hold (``complete=False``)."""
    from mcap.reader import make_reader

    path = Path(path)
    meta: dict[str, str] = {}
    rows: list[tuple[int, str, bytes | None, int]] = []
    complete = True
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            for m in reader.iter_metadata():
                if m.name == "flocktrack":
                    meta.update(m.metadata)
            for _schema, channel, message in reader.iter_messages(log_time_order=False):
                rows.append((message.sequence, channel.topic,
                             message.data if decoded_key(channel.topic) else None, message.log_time))
    except Exception:  # no summary / truncated: stream the records that are there
        complete = False
        rows, meta = _stream_records(path)
    rows.sort(key=lambda r: r[0])
    out: list[tuple[str, wire.Message | None, int]] = []
    rejected = 0
    for _seq, topic, data, t in rows:
        if data is None:
            out.append((topic, None, t))
            continue
        try:
            out.append((topic, wire.from_json(json.loads(data)), t))
        except (wire.WireError, ValueError):
            rejected += 1
    return LoadedRecording(meta, out, complete, rejected)


def _stream_records(path: Path):
    from mcap.records import Channel, Chunk, Message, Metadata
    from mcap.stream_reader import StreamReader, breakup_chunk

    channels: dict[int, str] = {}
    rows: list = []
    meta: dict[str, str] = {}

    def take(rec) -> None:
        if isinstance(rec, Channel):
            channels[rec.id] = rec.topic
        elif isinstance(rec, Message) and rec.channel_id in channels:
            topic = channels[rec.channel_id]
            rows.append((rec.sequence, topic, rec.data if decoded_key(topic) else None, rec.log_time))
        elif isinstance(rec, Metadata) and rec.name == "flocktrack":
            meta.update(rec.metadata)

    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                if isinstance(rec, Chunk):
                    for sub in breakup_chunk(rec, validate_crc=False):
                        take(sub)
                else:
                    take(rec)
        except Exception:  # the torn end of a crashed recording
            pass
    return rows, meta


def recording_metadata(path: str | Path) -> dict[str, str]:
    """The recording's flocktrack metadata (scenario TOML, design JSON) without reading its messages."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            for m in make_reader(f).iter_metadata():
                if m.name == "flocktrack":
                    return dict(m.metadata)
    except Exception:  # truncated: metadata may sit in the readable part
        return _stream_records(Path(path))[1]
    return {}


def replay_model_from_file(path: str | Path, trail_len: int = 200) -> ReplayModel:
    rec = load_recording(path)
    if "scenario" not in rec.metadata:
        raise ValueError(f"{path}: not a flocktrack recording (no scenario metadata)")
    info = RunInfo.from_toml_text(rec.metadata["scenario"], rec.metadata.get("design"))
    return ReplayModel(info, rec.messages, trail_len=trail_len)


# ============================================================================ the Viser UI

@dataclass
class ClientView:
    """The camera of one browser tab, as far as following the flock goes."""

    look_at: np.ndarray | None = None           #: the look-at point last commanded (None: never yet)
    distance: float = 0.0                       #: the camera distance last commanded
    direction: np.ndarray = field(default_factory=lambda: plots.VIEW_DIRECTION.copy())
    fit_now: bool = True                        #: jump (not glide) to the framing at the next update
    follow: bool = True                         #: glide after the flock (off once the tab's user moves it)
    zooming: bool = False
    #: (command number, point) of the camera positions / look-at points this process commanded, newest
    #: last, and those the page starts from (number 0). The page echoes them back, late at times and in any
    #: combination: a command is two messages (position, then look-at), Viser's send buffer replaces an
    #: unsent message by the next one of its kind (so a look-at may overtake a position), and the page's
    #: camera applies each alone (a position keeps the look-at, a look-at keeps the position). Whatever the
    #: user does moves the position, the look-at or both to a point that is in neither list.
    sent_pos: deque = field(default_factory=lambda: deque(maxlen=200))
    sent_look: deque = field(default_factory=lambda: deque(maxlen=400))
    seq: int = 0                                #: number of the last command
    sent_t: float = 0.0                         #: when it was sent (monotonic)
    #: the page's last report is an older pose than the last command: it was stale, or the page put its
    #: camera back (its initial-camera setup runs after the first frames) — send the command again
    resend: bool = False

    def remember(self, seq: int, pos=None, look=None) -> None:
        if pos is not None:
            self.sent_pos.append((seq, np.array(pos, float)))
        if look is not None:
            self.sent_look.append((seq, np.array(look, float)))

    def ours(self, pos: np.ndarray, look: np.ndarray, tol: float) -> int | None:
        """The oldest command number a reported pose is made of (None: the user made it)."""
        seqs = []
        for sent, x in ((self.sent_pos, pos), (self.sent_look, look)):
            seq = next((k for k, y in reversed(sent) if np.linalg.norm(x - y) < tol), None)
            if seq is None:
                return None
            seqs.append(seq)
        return min(seqs)


@dataclass
class UiTimings:
    scene_updates: int = 0
    plot_updates: int = 0
    scene_s: float = 0.0
    plot_s: float = 0.0
    samples: list = field(default_factory=list)


class DashboardUI:
    """The Viser server, its scene objects and GUI. ``send_control(verb, args)`` is called (from Viser's
    threads) by the fault and run-control buttons; None in replay."""

    def __init__(self, info: RunInfo, port: int = 8080, host: str = "127.0.0.1", *, live: bool = True,
                 send_control=None, replay: ReplayModel | None = None, verbose: bool = False,
                 operator_token: str | None = None, tls: tuple[str, str] | None = None,
                 limits: Limits | None = None):
        """``tls``: (certificate, key) files — the page is then HTTPS on ``host:port`` (dashboards/tls.py)
        and Viser itself listens on a free port of 127.0.0.1 behind it. ``limits``: what a tab may send
        (dashboards/guard.py)."""
        import viser

        from .operator import Operators

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
        self._last_plot_k = None
        self._lock = threading.Lock()
        self.replay_k = replay.first if replay else 0
        self.playing = False
        self.controls_sent: list[tuple[str, dict]] = []
        # the camera: per browser tab, framed on the flock and gliding after it while its "Follow" is on
        self._views: dict[int, ClientView] = {}
        self._framing: plots.Framing | None = None
        self._cam_lock = threading.RLock()
        self._view_t = time.monotonic()
        self._build_scene()
        self._build_gui()
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)

    # ------------------------------------------------------------------ scene
    def _build_scene(self) -> None:
        s = self.server.scene
        s.set_up_direction("+z")
        # no shadow maps: a flat flock needs none, and every redraw (≤ 10/s) would render the scene twice
        # (measured: software-rendered Chromium went from 6 to ~20 frames/s)
        s.configure_default_lights(True, cast_shadow=False)
        r = self.info.link_range if math.isfinite(self.info.link_range) else 10.0
        self.extent = max(2.5 * r, 25.0)
        # until the first tick frames the flock (see update_view)
        self.server.initial_camera.position = tuple(-1.4 * self.extent * plots.VIEW_DIRECTION)
        self.server.initial_camera.look_at = (0.0, 0.0, 0.0)
        self.world = s.add_frame("/world", show_axes=False)
        cell = 10 ** math.floor(math.log10(max(r, 1.0)))
        # the ground grid as plain line segments: Viser's shader grid covers the whole view and cost more
        # than the rest of the scene together in a software-rendered browser (measured: 9 → 22 frames/s)
        s.configure_environment_map(None)
        self.grid = s.add_line_segments("/world/grid", plots.grid_segments(10 * self.extent, cell), (222, 222, 222),
                                        thickness=1.0, thickness_units="screen")
        z = np.zeros((1, 3), np.float32)
        zs = np.zeros((1, 2, 3), np.float32)
        self.h_circles = s.add_line_segments("/world/ranges", zs, (160, 185, 215), thickness=1.0,
                                             thickness_units="screen", visible=False)
        self.h_links = s.add_line_segments("/world/links", zs, (70, 110, 170), thickness=2.0,
                                           thickness_units="screen", visible=False)
        self.h_trail = s.add_line_segments("/world/trail", zs, (215, 40, 40), thickness=2.5,
                                           thickness_units="screen", visible=False)
        size = max(0.06 * r, 0.3)
        self.h_sensors = s.add_point_cloud("/world/sensors", z, (0, 0, 0), point_size=1.4 * size,
                                           point_shape="circle", precision="float32", visible=False)
        self.h_est = s.add_point_cloud("/world/estimates", z, (0, 0, 0), point_size=0.7 * size,
                                       point_shape="diamond", precision="float32", visible=False)
        self.h_target = s.add_icosphere("/world/target", radius=0.45 * size, color=(215, 30, 40), visible=False,
                                        cast_shadow=False, receive_shadow=False)
        self.h_fusion = s.add_icosphere("/world/fusion", radius=0.4 * size, color=(148, 103, 189), visible=False,
                                        cast_shadow=False, receive_shadow=False)
        self.marker_size = size

        # a click on the ground near a sensor selects it (in that tab)
        s.on_click()(self.guard.safe(lambda e: self._pick(e.ray_origin, e.ray_direction, e.client_id), "pick"))

    def _pick(self, origin, direction, client_id: int | None = None) -> None:
        snap = self._last_snapshot
        if snap is None or origin is None or direction is None:
            return
        o, dvec = np.asarray(origin, float), np.asarray(direction, float)
        o = o - np.asarray(self.world.position, float)  # into the /world frame
        if abs(dvec[2]) < 1e-9:
            return
        t = -o[2] / dvec[2]
        if t <= 0:
            return
        p = o + t * dvec
        d = np.linalg.norm(snap.positions[:, :2] - p[None, :2], axis=1)
        d[~np.isfinite(d)] = np.inf
        i = int(np.argmin(d))
        if d[i] <= max(3 * self.marker_size, 0.15 * self.info.link_range if math.isfinite(self.info.link_range) else 3):
            self.select(i, client_id)

    _last_snapshot: Snapshot | None = None

    @property
    def last_scene_k(self) -> int | None:
        """The tick the scene shows (None: none drawn yet)."""
        return self._last_scene_k

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
                self._last_plot_k = None
        if client_id is not None:
            self._retarget(client_id, i)

    def _retarget(self, client_id: int | None, i: int) -> None:
        """Tab ``client_id`` inspects sensor ``i``: if that tab is an operator's, its own "Sensor id" and
        "Link a" follow. Another tab's choice — a viewer's above all — never touches them."""
        panel = self.operators.panels.get(client_id) if client_id is not None else None
        if panel is not None:
            for h in (panel.g_kill_id, panel.g_link_a):
                h.value = i

    @staticmethod
    def _segments(h, segs: np.ndarray, visible: bool = True) -> None:
        set_segments(h, segs, visible)

    @staticmethod
    def _cloud(h, pts: np.ndarray, colors, visible: bool = True) -> None:
        if not visible or len(pts) == 0:
            show(h, False)
            return
        h.points = pts
        h.colors = np.asarray(colors, np.uint8)
        show(h, True)

    def render_scene(self, snap: Snapshot | None, err_rows: np.ndarray | None = None) -> plots.SceneArrays | None:
        """Redraw the scene from a snapshot (a handful of batched messages)."""
        if snap is None:
            return None
        if snap.k == self._last_scene_k and not self.dirty:
            return None
        t0 = time.perf_counter()
        self._last_snapshot = snap
        self.dirty = False
        self._last_scene_k = snap.k
        d = self.display
        scale = d.err_scale if d.err_scale > 0 else \
            plots.auto_error_scale(err_rows if err_rows is not None else snap.errors)
        sa = plots.scene_arrays(snap, error_scale=scale, link_range=self.info.link_range, show_circles=d.circles)
        self._framing = plots.flock_framing(snap, min_radius=max(4 * self.marker_size, 2.0)) or self._framing
        with self.server.atomic():
            self._cloud(self.h_sensors, sa.sensor_points, sa.sensor_colors)
            self._cloud(self.h_est, sa.estimate_points, sa.estimate_colors, d.estimates)
            self._segments(self.h_links, sa.links, d.links)
            self._segments(self.h_circles, sa.circles, d.circles)
            self._segments(self.h_trail, sa.trail, d.trail)
            if sa.target is not None:
                self.h_target.position = tuple(sa.target)
                self.h_target.visible = True
            if sa.fusion is not None:
                self.h_fusion.position = tuple(sa.fusion)
                self.h_fusion.visible = True
            else:
                self.h_fusion.visible = False
        self._render_tabs(snap)
        self.update_view()
        self.timings.scene_updates += 1
        self.timings.scene_s += time.perf_counter() - t0
        return sa

    # ------------------------------------------------------------------ camera
    #: the glide's time constant (s): a moving flock is followed smoothly, a jump (replay seek) in ~1 s
    FOLLOW_TAU = 0.35
    #: zoom only when the flock's sphere stops fitting, or fills less than 1/ZOOM_SLACK of the view —
    #: the flock's breathing does not make the camera breathe, but a flock that gathers (the demo's
    #: contracts from 42 to 21 m across in its first 50 ticks: its sphere's fit distance × 1/1.5) is
    #: zoomed in on (1.6 left it a third of the canvas it should fill)
    ZOOM_SLACK = 1.3

    def refresh_tabs(self) -> None:
        """Redraw what changed of the tabs' own parts since a tab's choice (between scene redraws)."""
        if self.tabs_dirty and self._last_snapshot is not None:
            self._render_tabs(self._last_snapshot)

    def _render_tabs(self, snap: Snapshot) -> None:
        """Each tab's own selection and inspector text (dashboards/tabs.py)."""
        self.tabs_dirty = False
        for panel in tuple(self.tabs.values()):
            self.guard.safe(render_tab, "render_tab")(panel, snap, self)

    def _on_disconnect(self, client) -> None:
        self._views.pop(client.client_id, None)
        self.tabs.pop(client.client_id, None)
        self.operators.panels.pop(client.client_id, None)

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

    def _panel_failed(self, client, what: str) -> None:
        self.guard.counters["panel_failures"] += 1
        if self.guard.counters["panel_failures"] == 1:
            log.exception("tab %s: its %s could not be built (logged once)", client.client_id, what)
        try:
            client.add_notification(f"The {what} could not be built", "See the dashboard's log; reload the page.",
                                    color="red", with_close_button=True)
        except Exception:  # the tab is gone
            pass

    def _on_connect(self, client) -> None:
        """A new tab: its own view and inspector, and an operator's (the run's token in its websocket path)
        controls on its own GUI (:meth:`_add_tab_panels`); every tab gets the framing at once (at the next
        update), and its camera reports are watched for the user's own moves. (Viser runs this in its thread
        pool, off the live loop's thread: a new tab's first frame is Viser's backlog, sent by its event loop.)"""
        self._add_tab_panels(client)
        view = ClientView()
        # the page reports its default pose first, then the server's initial camera (applied after its first
        # frames, possibly after our first command): both are ours, not the user's
        ic = self.server.initial_camera
        view.remember(0, ic.position, ic.look_at)
        try:
            view.remember(0, client.camera.position, client.camera.look_at)
        except AssertionError:  # no camera report yet
            pass
        with self._cam_lock:
            self._views[client.client_id] = view
        client.camera.on_update(self.guard.safe(lambda cam, cid=client.client_id: self._on_camera(cid, cam),
                                                "camera"))
        self.update_view(force=True)

    def _on_camera(self, cid: int, cam) -> None:
        """A camera report from a tab (Viser's thread pool). A pose this process did not command means the
        user moved the camera (drag, wheel, keys): stop following, so as not to fight them."""
        with self._cam_lock:
            view = self._views.get(cid)
            if view is None or view.look_at is None or not view.follow:
                return
            P, L = np.asarray(cam.position, float), np.asarray(cam.look_at, float)
            tol = 1e-3 * max(view.distance, 1.0)
            seq = view.ours(P, L, tol)
            if seq is not None:
                view.resend = seq < view.seq
                return
        log.info("camera moved by the user in tab %s: no longer following the flock", cid)
        view.follow = False
        self._follow_box(cid, False)

    def _follow_box(self, cid: int, on: bool) -> None:
        panel = self.tabs.get(cid)
        if panel is not None and panel.widgets["follow"].value != on:
            panel.widgets["follow"].value = on

    def set_follow(self, cid: int, on: bool) -> None:
        """Tab ``cid``'s "Follow the flock" checkbox. Turned on, the tab glides from where its camera is now,
        keeping its viewing direction (the user's orbit), to the flock."""
        client = self.server.get_clients().get(cid)
        with self._cam_lock:
            view = self._views.get(cid)
            if view is None:
                return
            if on and not view.follow and client is not None:
                try:
                    P, L = np.array(client.camera.position, float), np.array(client.camera.look_at, float)
                except AssertionError:
                    P = L = np.zeros(3)
                dist = float(np.linalg.norm(L - P))
                if dist > 1e-9:
                    view.look_at, view.distance, view.direction = L, dist, (L - P) / dist
                    view.seq += 1
                    view.remember(view.seq, P, L)
            view.follow = bool(on)
        self.update_view(force=True)

    def reset_view(self, cid: int | None = None) -> None:
        """Tab ``cid``'s "Reset view" button (None: every tab): framed on the flock at once, from the default
        direction, and following it again."""
        with self._cam_lock:
            for c, view in self._views.items():
                if cid is None or c == cid:
                    view.fit_now, view.follow = True, True
                    view.direction = plots.VIEW_DIRECTION.copy()
        for c in ([cid] if cid is not None else list(self.tabs)):
            self._follow_box(c, True)
        self.update_view(force=True)

    def update_view(self, force: bool = False) -> None:
        """Move each following tab's camera toward the framing of the last drawn tick: look at the flock's
        centre from a distance that fits the flock and the target in the tab's view (its own field of view
        and aspect ratio), gliding with time constant ``FOLLOW_TAU``. The control panel is docked at the
        right edge and the plots at the left, so the canvas is exactly the visible part of the scene: the
        flock centred in the canvas is centred in what the user sees. Called after each scene redraw and
        from the loops (at most 20 times a second); it sends nothing once the camera is where it should be."""
        now = time.monotonic()
        if not force and now - self._view_t < 0.05:
            return
        fr = self._framing
        if fr is None:
            return
        with self._cam_lock:
            a = 1.0 - math.exp(-min(max(now - self._view_t, 0.0), 0.25) / self.FOLLOW_TAU)
            self._view_t = now
            clients = self.server.get_clients()
            for cid, view in list(self._views.items()):
                client = clients.get(cid)
                if client is None or not (view.follow or view.fit_now):
                    continue
                try:
                    fov, aspect = float(client.camera.fov), float(client.camera.aspect)
                except (AssertionError, ZeroDivisionError):
                    continue                  # the tab has not reported its camera yet
                d_fit = plots.camera_distance(fr.radius, fov, aspect)
                if view.fit_now or view.look_at is None:
                    L, d = np.array(fr.centre, float), 1.1 * d_fit
                else:
                    L = view.look_at + a * (fr.centre - view.look_at)
                    d = view.distance
                    if not d_fit <= d <= self.ZOOM_SLACK * d_fit:
                        view.zooming = True
                    if view.zooming:
                        d += a * (1.1 * d_fit - d)
                        view.zooming = abs(d / (1.1 * d_fit) - 1.0) > 0.02
                    step = float(np.linalg.norm(L - view.look_at)) + abs(d - view.distance)
                    if step < 2e-3 * d and not (view.resend and now - view.sent_t > 0.5):
                        continue
                self._command(client, view, L, d)

    def _command(self, client, view: ClientView, L: np.ndarray, d: float) -> None:
        cam = client.camera
        P = L - view.direction * d
        prev_P, prev_L = np.array(cam.position, float), np.array(cam.look_at, float)
        view.seq += 1
        # Viser's position setter also sends the look-at moved along (it keeps the orientation): the tab
        # may report that one too (we hold _cam_lock: its reports are looked at after this is recorded)
        view.remember(view.seq, P, prev_L + (P - prev_P))
        refit = view.fit_now
        view.look_at, view.distance, view.fit_now = L, d, False
        view.sent_t, view.resend = time.monotonic(), False
        with client.atomic():
            if 3 * d > cam.far:
                cam.far = 10 * d
            if 2 * d > cam.max_orbit_distance:
                cam.max_orbit_distance = 4 * d
            cam.position = P
            view.remember(view.seq, None, cam.look_at)   # what the setter sent (a report may have come between)
            view.remember(view.seq, None, L)
            cam.look_at = L
            if refit:
                cam.up_direction = (0.0, 0.0, 1.0)

    # ------------------------------------------------------------------ plots and text
    def render_plots(self, series: dict[str, np.ndarray], force: bool = False) -> None:
        if not len(series["k"]):
            return
        last_k = int(series["k"][-1])
        if last_k == self._last_plot_k and not force:
            return
        t0 = time.perf_counter()
        self._last_plot_k = last_k
        ser = plots.decimate(series, self.max_plot_points)
        fe = series.get("fusion_err")
        self._has_fusion = self._has_fusion or bool(fe is not None and np.isfinite(fe).any())
        specs = plots.uplot_panels(ser, self.info.n, self.selected, has_lower=self.info.tmsee_lower is not None,
                                   has_fusion=self._has_fusion)
        with self.server.atomic():
            for spec in specs:
                h = self.h_plots.get(spec.key)
                if h is None or len(h.series) != len(spec.series):
                    if h is not None:
                        h.remove()
                    self.h_plots[spec.key] = self._add_plot(spec)
                else:
                    h.data = tuple(np.asarray(a, float) for a in spec.data)
        self.timings.plot_updates += 1
        self.timings.plot_s += time.perf_counter() - t0

    def _add_plot(self, spec: plots.PanelSpec):
        with self.plot_tab:
            return self.server.gui.add_uplot(data=tuple(np.asarray(a, float) for a in spec.data), series=spec.series,
                                             title=spec.title, scales=spec.scales, axes=spec.axes, aspect=2.5,
                                             order=self._plot_order[spec.key])

    def render_status(self, st: dict) -> None:
        def f(v, fmt="{:.3g}"):
            return "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else fmt.format(v)

        mode = "replay" if not self.live else ("**paused**" if st.get("paused") else "running")
        if st.get("ended"):
            mode = "ended" if self.live else mode
        lines = [f"**{self.info.name}** · {self.info.n} sensors · {self.info.estimator} · {mode}",
                 f"tick **{f(st.get('k'), '{}')}** (world at {f(st.get('latest_tick'), '{}')}) · "
                 f"t = {f(st.get('t'), '{:.2f}')} s",
                 f"RMSE {f(st.get('rmse'))} · λ₂ {f(st.get('lambda2'))} · links {f(st.get('links'), '{:.0f}')}",
                 f"{f(st.get('msg_rate'), '{:.0f}')} msg/s · dropped {f(st.get('drop_rate'), '{:.1f}')}/s "
                 f"(bus {st.get('bus_dropped', 0)}, missing {st.get('missing', 0)})"]
        if st.get("speed") is not None:
            lines.append(f"speed ×{f(st.get('speed'))}")
        if st.get("last_event"):
            lines.append(f"last event: `{st['last_event']}`")
        text = "  \n".join(lines)
        if text != self.g_status.content:
            self.g_status.content = text

    # ------------------------------------------------------------------ GUI
    def control(self, verb: str, **args) -> None:
        """Send ``control/<verb>`` with ``args`` (what the buttons do); recorded in ``controls_sent``.
        Nothing in replay."""
        if self.send_control is None:
            return
        self.controls_sent.append((verb, args))
        self.send_control(verb, args)

    #: where each part of the control panel goes, top to bottom: the shared parts (status, replay, the
    #: legend) and each tab's own (dashboards/tabs.py: view, inspect; an operator's, dashboards/operator.py:
    #: run control, faults, the plan-fault form, display)
    LAYOUT = {"status": 1.0, "note": 1.5, "replay": 2.0, "run": 2.5, "view": 3.0, "inspect": 4.0, "faults": 5.0,
              "plan": 6.0, "display": 7.0, "legend": 8.0}

    def _build_gui(self) -> None:
        """The shared control panel (docked right): the status, the replay's slider, the legend; then the
        plots panel (docked left). Each tab adds its own panels at the places of :attr:`LAYOUT`."""
        self.layout = dict(self.LAYOUT)
        self._gui_frame()
        if not self.live:
            self._gui_replay()
            build_display(GuardedGui(self.server.gui, self.guard.allow), self, self.layout["display"])
        self._gui_legend()
        self._gui_plots_panel()

    def _gui_frame(self) -> None:
        """The theme, the docked control panel, the plot bookkeeping and the status line at its top."""
        gui = self.server.gui
        gui.configure_theme(control_width="large", show_share_button=False, show_logo=False,
                            brand_color=(40, 90, 160))
        # docked, not floating over the scene: the canvas is then exactly the part of the scene the user
        # sees, and a camera centred on the flock shows it clear of the panel (a floating panel hid the
        # flock, which sits in the canvas's middle, behind it)
        gui.main_panel.dock_right()
        self.max_plot_points = 1500
        self._has_fusion = False          # once a fusion line is drawn it stays (the panel keeps its lines)
        self.h_plots: dict = {}
        self._plot_order = {k: 100 + i for i, k in enumerate(["errors", "tmsee", "disagreement", "lambda2", "rates"])}
        self.g_status = gui.add_markdown("waiting for the first tick …", order=self.layout["status"])
        if self.live:
            gui.add_markdown("*read-only; the run and fault controls are on the run's operator link "
                             "(`flocktrack run` prints it)*", order=self.layout["note"])

    def _gui_replay(self) -> None:
        """Replay: the tick slider, play / pause / first / last, and the playback speed (shared: a replay
        has nothing to steer, and every tab watches the same recording)."""
        gui = GuardedGui(self.server.gui, self.guard.allow)
        rp = self.replay
        safe = self.guard.safe
        with gui.add_folder("Replay", order=self.layout["replay"]):
            self.g_slider = gui.add_slider("Tick", rp.first if rp else 0, max(rp.last if rp else 1, 1), 1,
                                           rp.first if rp else 0)
            bg = gui.add_button_group("Playback", ("Play", "Pause", "First", "Last"))
            self.g_play_speed = gui.add_slider("Playback ×", 0.1, 10.0, 0.1, 1.0)
        self.g_slider.on_update(safe(lambda _e: self._seek(int(self.g_slider.value)), "seek"))
        bg.on_click(safe(lambda e: self._playback(e.target.value), "playback"))

    def _seek(self, k: int) -> None:
        self.replay_k = k
        self.dirty = True

    def _playback(self, v: str) -> None:
        if v == "Play":
            self.playing = True
        elif v == "Pause":
            self.playing = False
        elif v in ("First", "Last") and self.replay:
            self.playing = False
            self.g_slider.value = self.replay.first if v == "First" else self.replay.last

    def _gui_legend(self) -> None:
        self.server.gui.add_markdown("colour: own error, green (low) → red (≥ scale); grey = dead  \n"
                                     "● sensor  ◆ its estimate  red ball = target (trail)  purple = fusion  \n"
                                     "orange = selected sensor's links, blue = its covariance ellipse",
                                     order=self.layout["legend"])

    def _gui_plots_panel(self) -> None:
        """The plots, in their own panel docked left (the uPlot panels are added by :meth:`render_plots`)."""
        gui = self.server.gui
        panel = gui.add_panel()
        self.plot_tab = panel.add_tab("Plots")
        panel.dock_left()
        panel.set_width(460)
        with self.plot_tab:
            gui.add_markdown("live series (uPlot; drag to zoom, double-click to reset)", order=1)

    def stats(self) -> dict:
        """The tabs' counters for the stats file: operators / viewers / wrong tokens / refused controls and
        the guard's (dashboards/guard.py), totals and per tab."""
        return {**self.operators.counters, "guard": self.guard.stats()}

    def attach_replay(self, model: ReplayModel) -> None:
        """The recording is loaded (the page is served meanwhile): set the slider to its ticks."""
        self.replay = model
        self.g_slider.min = model.first
        self.g_slider.max = max(model.last, model.first + 1)
        self.g_slider.value = model.first
        self.replay_k = model.first
        self.dirty = True

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

    def stop(self) -> None:
        self.guard.uninstall()
        if self.tls_front is not None:
            self.tls_front.close()
        try:
            self.server.stop()
        except Exception:  # already stopped
            pass


# ============================================================================ the live loop

class LiveDashboard:
    """Bus → state → UI, on one thread. :meth:`step` does one poll / publish / redraw round."""

    def __init__(self, state: DashboardState, ui: DashboardUI | None, bus, *, scene_period: float = 0.1,
                 plot_period: float = 0.5, max_messages: int = 4000, clock=time.monotonic):
        self.state, self.ui, self.bus = state, ui, bus
        self.scene_period, self.plot_period = scene_period, plot_period
        self.max_messages = max_messages
        self.clock = clock
        self.controls: queue.SimpleQueue = queue.SimpleQueue()
        self._next_scene = 0.0
        self._next_plot = 0.0
        self.published: list[wire.Control] = []

    def attach(self) -> None:
        """One raw subscription; the keys the model needs go through the bus's own decode-validate-count
        path (:func:`agent.bus.deliver`, drops land in ``bus.stats.dropped``), the rest is only counted."""
        from agent.bus import deliver

        st, clock, stats = self.state, self.clock, self.bus.stats
        handlers = [lambda key, msg: st.ingest(key, msg, clock())]
        wanted: dict[str, bool] = {}

        def on_raw(key: str, data: bytes) -> None:
            w = wanted.get(key)
            if w is None:
                w = wanted[key] = decoded_key(key)
            if w:
                deliver(stats, handlers, key, data)
            else:
                st.count(clock())

        for pattern in SUBSCRIPTIONS:
            self.bus.subscribe_raw(pattern, on_raw)

    def send_control(self, verb: str, args: dict) -> None:
        """Thread-safe: queue a control message for the loop thread to publish."""
        if verb not in wire.CONTROL_VERBS:
            raise ValueError(f"unknown control verb {verb!r}")
        self.controls.put((verb, dict(args)))

    def step(self, timeout: float = 0.02) -> None:
        st = self.state
        self.bus.poll(timeout, max_messages=self.max_messages)
        now = self.clock()
        st.last_now = max(st.last_now, now)
        st.note_bus_dropped(sum(self.bus.stats.dropped.values()), now)
        while True:
            try:
                verb, args = self.controls.get_nowait()
            except queue.Empty:
                break
            msg = wire.Control(verb=verb, args=args, k=max(st.latest_tick, 0))
            self.bus.publish(f"control/{verb}", msg)
            self.published.append(msg)
            log.info("published control/%s %s", verb, args)
        if self.ui is None:
            return
        if now >= self._next_scene and (st.shown_k != self.ui.last_scene_k or self.ui.dirty):
            # at most one redraw per scene_period, and only when there is a new tick (or a GUI change)
            self._next_scene = now + self.scene_period
            self.ui.render_scene(st.snapshot(), st.series(last=200)["err"])
        else:
            self.ui.refresh_tabs()    # a tab's own inspector, at once (also while paused)
            self.ui.update_view()     # the camera's glide goes on between ticks (and while paused)
        if now >= self._next_plot:
            self._next_plot = now + self.plot_period
            self.ui.render_plots(st.series(last=self.ui.max_plot_points * 4))
            summ = st.summary()
            if st.events:
                k, verb, args = st.events[-1]
                summ["last_event"] = f"{verb} {args} @k={k}" if args else f"{verb} @k={k}"
            self.ui.render_status(summ)


def run_live(run: str, connect: str, port: int, info: RunInfo, *, host: str = "127.0.0.1",
             config_file: str | None = None, exit_on_end: bool = False, stop_event: threading.Event | None = None,
             token: str = "dashboard/0", operator_token: str | None = None,
             tls: tuple[str, str] | None = None, limits: Limits | None = None) -> int:
    """``token``: this process's liveliness token; ``operator_token``: the run's operator token (None: a
    read-only page for everyone, see dashboards/operator.py); ``limits``: what a tab may send
    (dashboards/guard.py)."""
    from agent.bus import ZenohBus
    from agent.runner import quick_gil_handoff, write_stats

    stop_event = stop_event or threading.Event()
    # Zenoh's receive thread needs the GIL for every sample; with the default 5 ms switch interval a busy
    # loop thread lets through ~200 samples/s and the backlog backs up to the publishers (measured with
    # bench/bench_dashboard.py: 100 sensors, 6 000 msg/s). 1 ms keeps the callbacks flowing.
    quick_gil_handoff()
    bus = ZenohBus(run, connect=connect, config_file=config_file)
    state = DashboardState(info)
    loop = LiveDashboard(state, None, bus)
    ui = DashboardUI(info, port=port, host=host, live=True, send_control=loop.send_control,
                     operator_token=operator_token, tls=tls, limits=limits)
    cpu0, wall0 = time.process_time(), time.monotonic()
    loop.ui = ui
    log.info("dashboard for run %s on %s://%s:%d (%s)", run, ui.scheme, host, ui.port,
             "controls for the operator link" if operator_token else "read-only for everyone")
    try:
        loop.attach()
        bus.declare_token(token)
        end_at = None
        while not stop_event.is_set():
            loop.step()
            if exit_on_end and state.ended:
                end_at = end_at or time.monotonic() + 1.0
                if time.monotonic() > end_at:
                    break
    finally:
        log.info("dashboard model: %d ticks scored, %d leading partial ticks skipped, %d ticks never heard of, "
                 "%d late messages, %d missing estimates/states, %d invalid messages", len(state.series_buf),
                 state.partial_start, state.gap_ticks, state.late, state.missing_total, state.bus_dropped)
        # the bus's counters, the tabs' (operators, viewers, wrong tokens, the guard's per tab) and this
        # process's CPU (bench/bench_dashboard.py reads it)
        write_stats(token, bus, SimpleNamespace(counters={**ui.stats(), "cpu_s": time.process_time() - cpu0,
                                                          "wall_s": time.monotonic() - wall0}))
        bus.close()
        ui.stop()
    return 0


def run_replay(path: str | Path, port: int, *, host: str = "127.0.0.1",
               stop_event: threading.Event | None = None, autoplay: bool = False) -> int:
    stop_event = stop_event or threading.Event()
    meta = recording_metadata(path)
    if "scenario" not in meta:
        raise ValueError(f"{path}: not a flocktrack recording (no scenario metadata)")
    ui = DashboardUI(RunInfo.from_toml_text(meta["scenario"], meta.get("design")), port=port, host=host,
                     live=False)
    ui.g_status.content = f"loading `{Path(path).name}` …"
    t0 = time.monotonic()
    model = replay_model_from_file(path)
    ui.attach_replay(model)
    log.info("replaying %s (%d ticks, loaded in %.1f s) on http://%s:%d", path, len(model), time.monotonic() - t0,
             host, ui.port)
    ui.playing = autoplay
    T = model.info.T or 0.1
    last_plot = 0.0
    acc = 0.0
    last = time.monotonic()
    try:
        while not stop_event.is_set():
            now = time.monotonic()
            if ui.playing and model.ticks:
                acc += (now - last) * float(ui.g_play_speed.value) / T
                adv = int(acc)
                if adv:
                    acc -= adv
                    nxt = min(ui.replay_k + adv, model.last)
                    if nxt >= model.last:
                        ui.playing = False
                    ui.g_slider.value = nxt
            else:
                acc = 0.0
            last = now
            k = ui.replay_k
            if ui.render_scene(model.snapshot(k), model.series(k, last=200)["err"]) is None:
                ui.refresh_tabs()
                ui.update_view()
            if now - last_plot > (0.3 if ui.playing else 0.1):
                last_plot = now
                ui.render_plots(model.series(k))
                st = model.state
                row = st.rows.get(model.seek(k), {})
                ui.render_status({"k": model.seek(k), "latest_tick": model.last, "t": row.get("t"),
                                  "rmse": row.get("rmse"), "lambda2": row.get("lambda2"), "links": row.get("links"),
                                  "msg_rate": row.get("msg_rate"), "drop_rate": row.get("drop_rate"),
                                  "bus_dropped": 0, "missing": int(np.nansum(model.series(k)["missing"]))})
            time.sleep(0.02)
    finally:
        ui.stop()
    return 0
