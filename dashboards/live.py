"""The dashboard's loops: live, a read-only subscriber to ``ft/<run>/**`` that writes only ``control/**``;
replay, a recording shown with a time slider.

Live (``python -m dashboards --run R --connect EP --port P --scenario FILE``): the bus delivers on this
process's thread into a :class:`~dashboards.state.DashboardState`; at most every ``scene_period`` seconds
the scene is redrawn from a snapshot (a few batched objects: one point cloud for all sensors, one
line-segment set for all links, …) and every ``plot_period`` seconds the uPlot panels and the status
text (the page and its panels: :mod:`dashboards.ui`). GUI callbacks run on Viser's threads; they only set
fields and queue control messages, which this thread publishes — the bus and the state are touched by one
thread only. Each browser tab's camera is framed on the flock and follows it until the user moves it
(:mod:`dashboards.camera`; the camera state has its own lock, as the tabs' camera reports arrive on Viser's
threads).

Replay (``python -m dashboards --recording FILE --port P``): the recording is read with
:func:`agent.recording.read_recording`, fed once through a :class:`~dashboards.state.ReplayModel`, and shown
with a time slider over its ticks (play / pause / playback speed).
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from agent import wire
from agent.recording import Recording, read_recording, recording_metadata

from .guard import Limits
from .state import DashboardState, ReplayModel, RunInfo
from .ui import DashboardUI

log = logging.getLogger(__name__)

#: What the dashboard subscribes to without a run plan: everything, the addressed copies of the exchange
#: payloads dropped on arrival. With one (``--plan``), its node's reads: every node's writes but the addressed
#: copies. The model relies on the publication order to score a tick in time; the bus's callbacks keep it
#: across subscriptions (agent.bus.ZenohBus._in_order).
EVERYTHING = ("**",)


def plan_reads(plan_file: str | Path, name: str = "dashboard/0") -> tuple[str, ...]:
    """The reads of node ``name`` in a run plan's JSON (``plan.json``, ``flocktrack plan --format json``)."""
    doc = json.loads(Path(plan_file).read_text())
    for node in doc.get("nodes", []):
        if node.get("name") == name:
            return tuple(node.get("reads", ()))
    raise ValueError(f"{plan_file}: the plan has no node {name!r}")


def decoded_key(topic: str) -> bool:
    """Keys decoded and fed to the model (world, truth, estimates, states, fusion, control); the others —
    exchange payloads and measurements, the bulk of the traffic — are only counted."""
    parts = topic.split("/")
    if parts[0] == "agent":
        return len(parts) == 3 and parts[2] in ("estimate", "state")
    if parts[0] == "target":
        return topic == "target/truth"
    return parts[0] in ("world", "fusion", "control")


# ============================================================================ recordings (replay)

def load_recording(path: str | Path) -> Recording:
    """A flocktrack recording as the replay reads it: metadata and the messages in recording order, the
    keys of :func:`decoded_key` decoded and the others only counted (message None). A truncated file yields
    what its readable records hold (``complete=False``)."""
    return read_recording(path, decode=decoded_key)


def replay_model_from_file(path: str | Path, trail_len: int = 200) -> ReplayModel:
    rec = load_recording(path)
    if "scenario" not in rec.metadata:
        raise ValueError(f"{path}: not a flocktrack recording (no scenario metadata)")
    info = RunInfo.from_toml_text(rec.metadata["scenario"], rec.metadata.get("design"))
    return ReplayModel(info, rec.messages, trail_len=trail_len)


# ============================================================================ the live loop

class LiveDashboard:
    """Bus → state → UI, on one thread. :meth:`step` does one poll / publish / redraw round."""

    def __init__(self, state: DashboardState, ui: DashboardUI | None, bus, *, scene_period: float = 0.1,
                 plot_period: float = 0.5, max_messages: int = 4000, clock=time.monotonic,
                 subscriptions: tuple[str, ...] = EVERYTHING):
        self.state, self.ui, self.bus = state, ui, bus
        self.subscriptions = subscriptions
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
                if wire.addressed(key):   # (only with a catch-all subscription: a payload's addressed copy)
                    return
                w = wanted[key] = decoded_key(key)
            if w:
                deliver(stats, handlers, key, data)
            else:
                st.count(clock())

        for pattern in self.subscriptions:
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
            self.ui.render_plots(st.series(last=self.ui.plot_panel.max_points * 4))
            summ = st.summary()
            if st.events:
                k, verb, args = st.events[-1]
                summ["last_event"] = f"{verb} {args} @k={k}" if args else f"{verb} @k={k}"
            self.ui.render_status(summ)


def run_live(run: str, connect: str, port: int, info: RunInfo, *, host: str = "127.0.0.1",
             config_file: str | None = None, exit_on_end: bool = False, stop_event: threading.Event | None = None,
             token: str = "dashboard/0", operator_token: str | None = None,
             tls: tuple[str, str] | None = None, limits: Limits | None = None,
             subscriptions: tuple[str, ...] = EVERYTHING) -> int:
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
    loop = LiveDashboard(state, None, bus, subscriptions=subscriptions)
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
    ui.control_panel.g_status.content = f"loading `{Path(path).name}` …"
    t0 = time.monotonic()
    model = replay_model_from_file(path)
    ui.attach_replay(model)
    log.info("replaying %s (%d ticks, loaded in %.1f s) on http://%s:%d", path, len(model), time.monotonic() - t0,
             host, ui.port)
    player = ui.player
    player.playing = autoplay
    T = model.info.T or 0.1
    last_plot = 0.0
    acc = 0.0
    last = time.monotonic()
    try:
        while not stop_event.is_set():
            now = time.monotonic()
            if player.playing and model.ticks:
                acc += (now - last) * float(player.g_speed.value) / T
                adv = int(acc)
                if adv:
                    acc -= adv
                    nxt = min(player.k + adv, model.last)
                    if nxt >= model.last:
                        player.playing = False
                    player.g_slider.value = nxt
            else:
                acc = 0.0
            last = now
            k = player.k
            if ui.render_scene(model.snapshot(k), model.series(k, last=200)["err"]) is None:
                ui.refresh_tabs()
                ui.update_view()
            if now - last_plot > (0.3 if player.playing else 0.1):
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
