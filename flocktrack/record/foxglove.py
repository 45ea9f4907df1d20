"""Foxglove's own views of a run, drawn from its messages as they are recorded.

A recording keeps every :mod:`agent.wire` message on its own channel (``world/tick``, ``agent/3/estimate``,
…, private ``flocktrack.*`` JSON schemas). Beside them :class:`FoxgloveViews` writes what Foxglove — or any
MCAP tool that knows Foxglove's well-known schemas (the ``foxglove-sdk`` package's, protobuf) — draws
without being told how:

=====================  ============================  =====================================================
topic                  schema                        what
=====================  ============================  =====================================================
``/tf``                ``foxglove.FrameTransforms``  the ``world`` frame (once, at the first tick)
``/scene/sensors``     ``foxglove.SceneUpdate``      each sensor: a sphere, its heading (an arrow), its id
``/scene/links``       ``foxglove.SceneUpdate``      the tick's links, as lines
``/scene/ranges``      ``foxglove.SceneUpdate``      each sensor's link range, a flat disk (toggle the topic)
``/scene/target``      ``foxglove.SceneUpdate``      the target's true position
``/scene/estimates``   ``foxglove.SceneUpdate``      each node's estimate and its 2-σ ellipse (from P), a
                                                     flat ellipsoid
``/log``               ``foxglove.Log``              faults (start: warning, heal: info), crashes (error),
                                                     restarts and rejoins, ticks that closed without some
                                                     sensors' states (warning), operator controls, the end
``/metrics``           JSON (flat fields)            per tick: ``rmse``, ``tmsee``, ``disagreement``,
                                                     ``lambda2``, ``links``, ``messages``, ``err_<i>`` …
=====================  ============================  =====================================================

Each view carries its source message's log time (the tick's simulated time ``k·T``), so the views and the
messages share one timeline. A tick's estimates, target and metrics are written once the tick is over: two
ticks later (its late estimates in), or when the recording is finished. The ellipse of node i at tick k is
drawn from the covariance its previous estimate published (``P`` of x̂ₖ, sent with x̂ₖ₋₁'s update).
"""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

from agent import wire

#: ticks after which a tick's estimates are taken as all in (later ones are recorded, not drawn)
LAG_TICKS = 2
METRICS_SCHEMA = {
    "title": "flocktrack view: a tick's metrics", "type": "object",
    "properties": {"k": {"type": "integer"}, "t": {"type": "number"}, "rmse": {"type": "number"},
                   "tmsee": {"type": "number"}, "mean_err": {"type": "number"},
                   "disagreement": {"type": "number"}, "lambda2": {"type": "number"},
                   "links": {"type": "integer"}, "connected": {"type": "integer"},
                   "reporting": {"type": "integer"}, "messages": {"type": "integer"}},
    "additionalProperties": {"type": "number"}}

_LEVELS = {"start": "Warning", "heal": "Info", "ack": "Debug", "kill": "Error", "restart": "Warning"}


def available() -> bool:
    """Whether the Foxglove schemas can be written (the ``foxglove-sdk`` package is installed)."""
    try:
        import foxglove.messages  # noqa: F401 — only whether it imports
    except ImportError:
        return False
    return True


class FoxgloveViews:
    """The views of one run (``sc``: its scenario) — :meth:`of` for each recorded message, :meth:`finish`
    at the end; each returns ``(topic, message, log_time_ns)`` with ``message`` a Foxglove message or a
    dict (``/metrics``, JSON)."""

    def __init__(self, sc):
        import foxglove.messages as fm

        from .metrics import MetricsCollector

        self.fm = fm
        self.T = float(sc.run.T)
        self.d = int(sc.pos_dims)
        self.range = float(sc.topology.range) if sc.topology.kind == "range" else math.inf
        self.metrics = MetricsCollector(sc.sensors.n, sc.run.ticks, sc.pos_dims, sc.run.burn_in)
        self._t_ns: dict[int, int] = {}                  #: tick → its log time
        self._pending: dict[int, dict[int, wire.Estimate]] = defaultdict(dict)
        self._P: dict[int, np.ndarray] = {}              #: node → the covariance its last estimate sent
        self._count: dict[int, int] = defaultdict(int)   #: tick → messages recorded for it
        self._last_pos: np.ndarray | None = None
        self._framed = False
        self._done = -1                                  #: the last tick whose views are written

    # ------------------------------------------------------------------ per message
    def of(self, key: str, msg: wire.Message, t_ns: int) -> list[tuple[str, object, int]]:
        k = msg.k
        open_tick = k > self._done          # (what comes for a tick whose views are written is not kept)
        if open_tick:
            self._count[k] += 1
        if isinstance(msg, (wire.Tick, wire.Truth)) or (isinstance(msg, wire.Estimate) and key.startswith("agent/")):
            self.metrics.ingest(key, msg)      # (what a tick's row needs)
        out: list[tuple[str, object, int]] = []
        if isinstance(msg, wire.Tick):
            if open_tick:
                self._t_ns[k] = t_ns
            if not self._framed:
                self._framed = True
                out.append(("/tf", self._frames(t_ns), t_ns))
            out += self._tick(msg, t_ns)
            out += self._close(k - LAG_TICKS)
        elif isinstance(msg, wire.Estimate) and key.startswith("agent/") and open_tick:
            self._pending[k][msg.src] = msg
        elif isinstance(msg, wire.Control):
            out.append(("/log", self._log(key, msg, t_ns), t_ns))
        elif isinstance(msg, wire.End):
            out.append(("/log", self._entry(t_ns, *log_line(key, msg)), t_ns))
        return out

    def finish(self) -> list[tuple[str, object, int]]:
        """The views of the ticks still open (the last ``LAG_TICKS``)."""
        return self._close(max(self._t_ns, default=-1))

    # ------------------------------------------------------------------ the scene
    def _frames(self, t_ns: int):
        fm = self.fm
        return fm.FrameTransforms(transforms=[fm.FrameTransform(
            timestamp=_stamp(fm, t_ns), parent_frame_id="world", child_frame_id="flock",
            translation=fm.Vector3(x=0.0, y=0.0, z=0.0), rotation=fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))])

    def _tick(self, tick: wire.Tick, t_ns: int) -> list[tuple[str, object, int]]:
        fm = self.fm
        stamp = _stamp(fm, t_ns)
        P = np.asarray(tick.positions, float)
        heading = None if self._last_pos is None or self._last_pos.shape != P.shape else P - self._last_pos
        self._last_pos = P
        sensors, ranges = [], []
        for i in range(tick.n):
            alive = bool(tick.alive[i]) if i < len(tick.alive) else True
            color = fm.Color(r=0.2, g=0.5, b=1.0, a=1.0) if alive else fm.Color(r=0.5, g=0.5, b=0.5, a=0.6)
            at = _point(P[i])
            arrows = []
            if heading is not None and float(np.hypot(*heading[i][:2])) > 1e-9:
                yaw = math.atan2(heading[i][1], heading[i][0])
                arrows.append(fm.ArrowPrimitive(
                    pose=fm.Pose(position=fm.Vector3(**at), orientation=_yaw(fm, yaw)), shaft_length=0.6,
                    shaft_diameter=0.08, head_length=0.3, head_diameter=0.2, color=color))
            sensors.append(fm.SceneEntity(
                timestamp=stamp, frame_id="world", id=f"sensor/{i}", frame_locked=False,
                spheres=[fm.SpherePrimitive(pose=_pose(fm, at), size=fm.Vector3(x=0.4, y=0.4, z=0.4), color=color)],
                arrows=arrows,
                texts=[fm.TextPrimitive(pose=_pose(fm, {**at, "z": at["z"] + 0.5}), billboard=True, font_size=12.0,
                                        scale_invariant=True, color=color, text=str(i))]))
            if math.isfinite(self.range):     # a flat translucent disk of the link range
                ranges.append(fm.SceneEntity(
                    timestamp=stamp, frame_id="world", id=f"range/{i}",
                    cylinders=[fm.CylinderPrimitive(
                        pose=_pose(fm, at), size=fm.Vector3(x=2 * self.range, y=2 * self.range, z=0.01),
                        bottom_scale=1.0, top_scale=1.0, color=fm.Color(r=0.2, g=0.5, b=1.0, a=0.06))]))
        edges = [(i, j) for i, nb in enumerate(tick.links) for j in nb if i < j]
        links = fm.SceneEntity(timestamp=stamp, frame_id="world", id="links", lines=[fm.LinePrimitive(
            type=fm.LinePrimitiveLineType.LineList, pose=_pose(fm, {"x": 0.0, "y": 0.0, "z": 0.0}), thickness=1.5,
            scale_invariant=True, points=[fm.Point3(**_point(P[a])) for e in edges for a in e],
            color=fm.Color(r=0.6, g=0.6, b=0.6, a=0.8))] if edges else [])
        out = [("/scene/sensors", fm.SceneUpdate(entities=sensors), t_ns),
               ("/scene/links", fm.SceneUpdate(entities=[links]), t_ns)]
        if ranges:
            out.append(("/scene/ranges", fm.SceneUpdate(entities=ranges), t_ns))
        return out

    def _close(self, upto: int) -> list[tuple[str, object, int]]:
        """The views of every tick up to ``upto`` not written yet: estimates, target, metrics."""
        out: list[tuple[str, object, int]] = []
        for k in range(self._done + 1, upto + 1):
            t_ns = self._t_ns.pop(k, None)
            if t_ns is None:      # a tick this recording never saw (a cut, a shard)
                self._pending.pop(k, None)
            else:
                out += self._tick_over(k, t_ns)
            self._count.pop(k, None)        # (nothing by tick outlives its views: a long run's memory stays flat)
        self._done = max(self._done, upto)
        self.metrics.forget(self._done)
        return out

    def _tick_over(self, k: int, t_ns: int) -> list[tuple[str, object, int]]:
        fm = self.fm
        stamp = _stamp(fm, t_ns)
        entities = []
        for i, est in sorted(self._pending.pop(k, {}).items()):
            x = np.asarray(est.x, float)
            if x.size < self.d or not np.isfinite(x[: self.d]).all():
                continue
            at = _point(x[: self.d])
            color = fm.Color(r=1.0, g=0.55, b=0.1, a=0.9)
            spheres = [fm.SpherePrimitive(pose=_pose(fm, at), size=fm.Vector3(x=0.25, y=0.25, z=0.25), color=color)]
            P = self._P.get(i)
            ellipse = None if P is None else _ellipse(fm, at, P[:2, :2])
            if ellipse is not None:
                spheres.append(ellipse)
            if est.P is not None and est.P.shape[0] >= 2:
                self._P[i] = np.asarray(est.P, float)
            entities.append(fm.SceneEntity(
                timestamp=stamp, frame_id="world", id=f"estimate/{i}", spheres=spheres))
        out: list[tuple[str, object, int]] = []
        if entities:
            out.append(("/scene/estimates", fm.SceneUpdate(entities=entities), t_ns))
        truth = self.metrics.truth_at(k)
        if truth is not None and truth.size >= self.d:
            out.append(("/scene/target", fm.SceneUpdate(entities=[fm.SceneEntity(
                timestamp=stamp, frame_id="world", id="target",
                spheres=[fm.SpherePrimitive(pose=_pose(fm, _point(truth[: self.d])),
                                            size=fm.Vector3(x=0.5, y=0.5, z=0.5),
                                            color=fm.Color(r=0.9, g=0.1, b=0.1, a=1.0))])]), t_ns))
        row = self.metrics.row(k)
        if row is not None:
            row = {name: v for name, v in row.items() if not (isinstance(v, float) and math.isnan(v))}
            row["messages"] = self._count.pop(k, 0)
            out.append(("/metrics", row, t_ns))
        return out

    # ------------------------------------------------------------------ the log
    def _log(self, key: str, msg: wire.Control, t_ns: int):
        return self._entry(t_ns, *log_line(key, msg))

    def _entry(self, t_ns: int, level: str, text: str, name: str):
        fm = self.fm
        return fm.Log(timestamp=_stamp(fm, t_ns), level=getattr(fm.LogLevel, level), message=text, name=name,
                      file="", line=0)


def log_line(key: str, msg: wire.Control | wire.End) -> tuple[str, str, str]:
    """The ``/log`` entry of an event message: (level, text, name of who said it)."""
    if isinstance(msg, wire.End):
        return "Info", f"run over after {msg.k} ticks ({msg.reason})", "world"
    a = msg.args
    if msg.verb == "fault":
        phase = str(a.get("phase", ""))
        text = f"fault {a.get('id', '?')} {a.get('kind', '?')} {phase}" + _agents(a)
        level = _LEVELS.get(phase, "Info")
    elif msg.verb == "late":
        text, level = f"tick closed without the states of {a.get('missing', '?')} sensors" + _agents(a), "Warning"
    elif msg.verb == "process":
        text, level = _process(a)
    elif msg.verb == "ack":
        text, level = f"acknowledged fault {a.get('id', '?')} {a.get('kind', '?')} {a.get('phase', '')}", "Debug"
    else:
        text = " ".join([msg.verb] + [f"{n}={v}" for n, v in sorted(a.items())])
        level = _LEVELS.get(msg.verb, "Info")
    return level, f"k={msg.k}: {text}", key.rsplit("/", 1)[0] if key.endswith("/event") else key


def _process(a: dict) -> tuple[str, str]:
    """A child's life (the launcher's ``process`` events) as a log line and its level."""
    name, event = a.get("name", "?"), a.get("event", "?")
    if event == "exit":
        rc = a.get("rc")
        return (f"{name} exited ({rc})", "Info") if rc == 0 else (f"{name} crashed (exit {rc})", "Error")
    if event == "spawn":
        return (f"{name} restarted, rejoining", "Warning") if a.get("rejoin") else (f"{name} started", "Info")
    return f"{name}: {event}" + (f" (attempt {a['attempt']})" if "attempt" in a else ""), "Warning"


def _agents(a: dict) -> str:
    agents = a.get("agents")
    if isinstance(agents, list):
        agents = ", ".join(f"agent/{int(x)}" for x in agents)
    return f" ({agents})" if agents not in (None, "") else ""


def _stamp(fm, t_ns: int):
    return fm.Timestamp(sec=int(t_ns // 1_000_000_000), nsec=int(t_ns % 1_000_000_000))


def _point(p) -> dict:
    p = [float(v) for v in p]
    return {"x": p[0], "y": p[1] if len(p) > 1 else 0.0, "z": p[2] if len(p) > 2 else 0.0}


def _pose(fm, at: dict):
    return fm.Pose(position=fm.Vector3(**at), orientation=fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


def _yaw(fm, yaw: float):
    return fm.Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def ellipse_axes(P2: np.ndarray, sigmas: float = 2.0) -> tuple[float, float, float] | None:
    """The ``sigmas``-σ ellipse of a 2×2 position covariance: (major diameter, minor diameter, the major
    axis' angle); None if ``P2`` is not a covariance. (The eigenvalues of [[a, b], [b, c]] in closed form,
    m ± √(((a − c)/2)² + b²) with m = (a + c)/2, and the major axis at ½·atan2(2b, a − c): the recorder draws
    one a sensor and tick, and ``numpy.linalg.eigh`` cost it twenty times as much.)"""
    a, c, b = float(P2[0, 0]), float(P2[1, 1]), 0.5 * (float(P2[0, 1]) + float(P2[1, 0]))
    if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(c)):
        return None
    m, d = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    if m - d < 0:
        return None
    return 2 * sigmas * math.sqrt(m + d), 2 * sigmas * math.sqrt(m - d), 0.5 * math.atan2(2 * b, a - c)


def _ellipse(fm, at: dict, P2: np.ndarray, sigmas: float = 2.0):
    """:func:`ellipse_axes` around ``at`` as a flat translucent ellipsoid (None if not a covariance)."""
    axes = ellipse_axes(P2, sigmas)
    if axes is None:
        return None
    a, b, yaw = axes
    return fm.SpherePrimitive(pose=fm.Pose(position=fm.Vector3(**at), orientation=_yaw(fm, yaw)),
                              size=fm.Vector3(x=a, y=b, z=0.01), color=fm.Color(r=1.0, g=0.55, b=0.1, a=0.25))
