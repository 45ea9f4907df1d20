"""The message schema: encode, decode, validate. The only module that knows msgpack (through msgspec).

Every message travels under a key relative to the run prefix (``ft/<run>/``, DESIGN.md "Key space"):

=========================  ============  =======================================================
key                        type          published by
=========================  ============  =======================================================
``world/tick``             Tick          the world (clock, per-tick link table, visibility)
``target/truth``           Truth         the target (its true state at tick k)
``target/state``           State         the target (its position after tick k, i.e. for k+1)
``agent/<i>/meas``         Meas          sensor i (its measurement at tick k)
``agent/<i>/to/<j>/xchg``  Xchg          sensor i, to its out-neighbour j only (round r's consensus
                                         payload; j subscribes once, for life, to its inbox
                                         ``agent/*/to/<j>/xchg`` — delivery grows with degree, not N)
``agent/<i>/via/<host>/   ViaXchg       sensor i, in a run placed on several hosts: the payload once
xchg``                                   for all its out-neighbours on another host (named in ``to``;
                                         they read ``agent/*/via/<host>/xchg``, the others drop it)
``agent/<i>/xchg``         Rounds        sensor i, its tick's payloads once more for observers (recorder,
                                         dashboard), every round in one message when the tick ends; no
                                         sensor reads it
``agent/<i>/estimate``     Estimate      sensor i (x̂ₖ and x̂ₖ₊₁)
``agent/<i>/to/<j>/        Estimate      sensor i, its last estimate once more, to a sensor j whose
estimate``                               liveliness token (re)appeared: a restarted j starts from its
                                         neighbours' estimates (inbox ``agent/*/to/<j>/estimate``)
``agent/<i>/state``        State         sensor i (position/velocity after tick k)
``fusion/estimate``        Estimate      the fusion solver
``world/end``              End           the world (the run is over)
``world/event``            Control       the world (a control/fault applied, k = tick of effect)
``launcher/event``         Control       the launcher (``ack`` of a process fault it executed: crash,
                                         pause, router_restart; ``kill`` / ``restart`` done)
``control/<verb>``         Control       dashboard / CLI (faults, pause, ...)
=========================  ============  =======================================================

:func:`decode` validates everything it returns: field types, array shapes and sizes, finite values,
and that the sender named in the message owns the key it came on. It reads the bytes straight into the
message's wire form (:mod:`agent.wire_form`, msgspec Structs: the map's shape, types, lengths and integer
bounds are checked in compiled code), then checks here what a form cannot say. A bad message raises
:class:`WireError` whose ``reason`` is a short stable label; buses drop such messages and count them
per reason — they never reach a role. A ``Control``'s arguments are typed, once, for the use they have:
:func:`fault_event` (a fault-plan transition on ``world/event``, a launcher ack) and :func:`command` (a
``control/<verb>``) return frozen dataclasses or raise :class:`WireError`; roles never re-check them.

Arrays travel as ``{"s": shape, "d": little-endian float64 bytes}`` so that a round trip is
bit-exact (lockstep over Zenoh must give the same numbers as in-process).
"""

from __future__ import annotations

import functools
import math
import re
from dataclasses import asdict, dataclass, field, fields
from itertools import chain
from typing import Any, ClassVar

import msgspec
import numpy as np
import orjson

from agent import wire_form as wf
from agent.wire_form import MAX_ARRAY_ELEMENTS, MAX_LIST_LEN, MAX_MESSAGE_BYTES


class WireError(ValueError):
    """A message that must be dropped. ``reason`` is a stable label used as a counter name. ``header``: what
    may still be said of it — for an exchange payload whose arrays are unusable, an :class:`UnusableXchg`
    (its sender, tick and round, no arrays), so that its round need not wait for a payload that has come."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
        self.detail = detail
        self.header: Message | None = None


# --------------------------------------------------------------------------- arrays

def _enc_array(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(np.asarray(a, dtype="<f8"))
    return {"s": list(a.shape), "d": a.tobytes()}


_SUM = np.add.reduce   # (ndarray.sum without numpy's Python wrappers: decoding is the hot path)
_F8 = np.dtype("<f8")


def _arrays(*arrs: wf.Arr | None, ndim: tuple[tuple[int, ...], ...] = ()) -> list[np.ndarray | None]:
    """The arrays of a message's decoded :class:`~agent.wire_form.Arr` (None stays None), after the checks
    their form cannot make: dimensions (``ndim[i]``; the form allows 1 or 2), size, data length, finite
    values. All of a message's arrays are read as views of one buffer, in one pass (the hot path: every
    sensor decodes every exchange payload of its neighbours; per array it would cost twice as much)."""
    sizes = []
    for i, a in enumerate(arrs):
        if a is None:
            sizes.append(-1)
            continue
        shape = a.s
        if ndim and len(shape) not in ndim[i]:
            raise WireError("bad_shape", f"shape {shape!r}")
        size = shape[0] if len(shape) == 1 else shape[0] * shape[1]
        if size > MAX_ARRAY_ELEMENTS:
            raise WireError("too_large", f"{size} elements")
        if len(a.d) != 8 * size:
            raise WireError("bad_shape", f"{len(a.d)} bytes for shape {shape}")
        sizes.append(size)
    flat = np.frombuffer(bytearray().join([a.d for a in arrs if a is not None]), dtype=_F8)
    # a finite sum proves every element finite (NaN/inf propagate); only a non-finite sum (which an
    # overflow of huge finite values can also give) needs the element-wise test
    if not math.isfinite(_SUM(flat)) and not np.isfinite(flat).all():
        raise WireError("non_finite", "array holds NaN or inf")
    out: list[np.ndarray | None] = []
    o = 0
    for a, size in zip(arrs, sizes):
        if size < 0:
            out.append(None)
        else:
            out.append(flat[o:o + size] if len(a.s) == 1 else flat[o:o + size].reshape(a.s))
            o += size
    return out


def _named(m: dict[str, wf.Arr]) -> dict[str, np.ndarray]:
    """A map of arrays (an exchange payload, an estimate's aux), read as :func:`_arrays` reads them."""
    return dict(zip(m, _arrays(*m.values()))) if m else {}


def _finite(v: float, name: str) -> float:
    if not math.isfinite(v):
        raise WireError("non_finite", f"{name} is not finite")
    return v


def _finite_list(v: list[float], name: str) -> list[float]:
    if not math.isfinite(sum(v)) and not all(map(math.isfinite, v)):   # (as for arrays: the sum first)
        raise WireError("non_finite", f"{name} is not finite")
    return v


# --------------------------------------------------------------------------- control argument checks

def _float(v: Any, name: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise WireError("bad_field", f"{name} must be a number, got {type(v).__name__}")
    if not math.isfinite(v):
        raise WireError("non_finite", f"{name} is not finite")
    return float(v)


def _list(v: Any, name: str, maxlen: int = MAX_LIST_LEN) -> list:
    if not isinstance(v, list) or len(v) > maxlen:
        raise WireError("bad_field", f"{name} must be a list of at most {maxlen} items")
    return v


# --------------------------------------------------------------------------- messages

@dataclass
class Message:
    """Base class. ``src`` is the sender's id within its role (0 for world/target/fusion)."""

    TYPE: ClassVar[str] = ""
    FORM: ClassVar[type[wf.Form]] = wf.Form   #: its wire form (agent/wire_form.py)
    src: int = 0
    k: int = 0

    def to_wire(self) -> dict:
        out: dict[str, Any] = {"type": self.TYPE}
        for name in _field_names(type(self)):
            out[name] = _to_wire_value(getattr(self, name))
        return out

    @classmethod
    def from_form(cls, f: wf.Form) -> "Message":
        """The message of its decoded wire form (whose type, sender and tick the form has checked)."""
        return cls(src=f.src, k=f.k, **cls._fields_from_form(f))

    @classmethod
    def _fields_from_form(cls, f) -> dict:
        return {}

    def to_json(self) -> dict:
        """A JSON-friendly dict (arrays as nested lists) for recordings and dashboards."""
        return _jsonable(asdict(self)) | {"type": self.TYPE}

    def to_json_bytes(self) -> bytes:
        """``json.dumps(self.to_json())``, fast: orjson writes the numpy arrays itself (the recorder's hot
        path — every message of a run). Floats are written shortest-round-trip, so they read back
        bit-exact; anything orjson refuses (a non-contiguous array) takes the slow path. For decoded
        (validated, hence finite) messages only: orjson would write a NaN or inf as null."""
        d = {name: getattr(self, name) for name in _field_names(type(self))}
        d["type"] = self.TYPE
        try:
            return orjson.dumps(d, option=orjson.OPT_SERIALIZE_NUMPY)
        except TypeError:
            import json

            return json.dumps(self.to_json()).encode()


_FIELD_NAMES: dict[type, tuple[str, ...]] = {}


def _field_names(cls: type) -> tuple[str, ...]:
    names = _FIELD_NAMES.get(cls)
    if names is None:
        names = _FIELD_NAMES[cls] = tuple(f.name for f in fields(cls))
    return names


def _to_wire_value(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return _enc_array(v)
    if isinstance(v, dict):
        return {str(k): _to_wire_value(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_to_wire_value(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    return v


def _jsonable(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    return v


@dataclass
class Tick(Message):
    """World → all: tick k begins. Links are this tick's neighbour lists (after range and faults)."""

    TYPE: ClassVar[str] = "tick"
    t: float = 0.0
    n: int = 0
    links: list[list[int]] = field(default_factory=list)
    weights: list[list[float]] = field(default_factory=list)
    b: list[float] = field(default_factory=list)
    delta_max: int = 0
    alive: list[bool] = field(default_factory=list)
    positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    period: float = 0.0   #: realtime: the wall-clock seconds this tick lasts (topology/pace.py); 0 in lockstep

    FORM: ClassVar[type[wf.Form]] = wf.TickForm

    @classmethod
    def _fields_from_form(cls, f: wf.TickForm) -> dict:
        n = f.n
        if not (len(f.links) == len(f.weights) == len(f.b) == len(f.alive) == n):
            raise WireError("bad_shape", "links/weights/b/alive must have n entries")
        pos, = _arrays(f.positions, ndim=((2,),))
        if pos.shape[0] != n:
            raise WireError("bad_shape", "positions must have n rows")
        if f.delta_max > n:
            raise WireError("bad_field", f"delta_max must be an int in [0, {n}], got {f.delta_max}")
        _neighbours(f.links, f.weights)
        return dict(t=_finite(f.t, "t"), n=n, links=f.links, weights=f.weights, b=_finite_list(f.b, "b[i]"),
                    delta_max=f.delta_max, alive=f.alive, positions=pos, period=_finite(f.period, "period"))


def _neighbours(links: list[list[int]], weights: list[list[float]]) -> None:
    """Validate a tick's neighbour lists and their weights in a few vectorised passes rather than one check
    per entry — every sensor decodes every tick, O(N · degree) entries. Each links[i] (ints ≥ 0 by its form)
    must be within [0, n) without i, sorted and unique, weights[i] as many finite numbers."""
    n = len(links)
    lens = list(map(len, links))
    if lens != list(map(len, weights)):
        raise WireError("bad_field", "links[i] must be aligned with weights[i]")
    col = np.array(list(chain.from_iterable(links)), dtype=np.int64)
    if col.size and col.max() >= n:
        raise WireError("bad_field", f"links[i][j] must be in [0, {n - 1}]")
    row = np.repeat(np.arange(n), lens)
    if (col == row).any() or ((row[1:] == row[:-1]) & (col[1:] <= col[:-1])).any():
        bad = next(i for i, li in enumerate(links) if i in li or li != sorted(set(li)))
        raise WireError("bad_field", f"links[{bad}] must be sorted, unique, without self, aligned with weights")
    _finite_list(list(chain.from_iterable(weights)), "weights[i][j]")


@dataclass
class Truth(Message):
    """Target → sensors, scorer: the true target state xₖ."""

    TYPE: ClassVar[str] = "truth"
    t: float = 0.0
    x: np.ndarray = field(default_factory=lambda: np.zeros(0))

    FORM: ClassVar[type[wf.Form]] = wf.TruthForm

    @classmethod
    def _fields_from_form(cls, f: wf.TruthForm) -> dict:
        x, = _arrays(f.x, ndim=((1,),))
        return dict(t=_finite(f.t, "t"), x=x)


@dataclass
class Meas(Message):
    """Sensor i's measurement at tick k: yᵢ = bᵢ C x + v, stamped with time t."""

    TYPE: ClassVar[str] = "meas"
    t: float = 0.0
    y: np.ndarray = field(default_factory=lambda: np.zeros(0))
    b: float = 1.0
    pos: np.ndarray = field(default_factory=lambda: np.zeros(0))
    v: np.ndarray | None = None   #: the measurement disturbance drawn (simulation ground truth), if known

    FORM: ClassVar[type[wf.Form]] = wf.MeasForm

    @classmethod
    def _fields_from_form(cls, f: wf.MeasForm) -> dict:
        y, pos, v = _arrays(f.y, f.pos, f.v, ndim=((1,),) * 3)
        return dict(t=_finite(f.t, "t"), y=y, b=_finite(f.b, "b"), pos=pos, v=v)


@dataclass
class Xchg(Message):
    """Sensor i's exchange payload for round r of tick k (estimator-defined named arrays)."""

    TYPE: ClassVar[str] = "xchg"
    r: int = 0
    payload: dict[str, np.ndarray] = field(default_factory=dict)

    FORM: ClassVar[type[wf.Form]] = wf.XchgForm

    @classmethod
    def _fields_from_form(cls, f: wf.XchgForm) -> dict:
        return dict(r=f.r, payload=_named(f.payload))


#: an array's faults that leave the rest of an exchange payload readable (its header names the round it missed)
_UNUSABLE_ARRAY = frozenset({"non_finite", "bad_shape", "bad_array", "too_large"})


@dataclass
class UnusableXchg(Xchg):
    """The header of an exchange payload whose arrays did not validate (NaN, inf, a bad shape): the bus
    drops and counts the payload like any bad message, but hands its receiver this — sender, tick, round, no
    arrays — so the round counts it as come and of no use (a lost link) instead of waiting out its deadline
    for it. Without it a Byzantine sensor sending NaN makes every neighbour's every round end by deadline.
    Made by :func:`decode` only, never encoded."""

    reason: str = ""


@dataclass
class ViaXchg(Xchg):
    """Sensor i's exchange payload sent once to another host's router, for the sensors there that hear it
    (``to``): on ``agent/<i>/via/<host>/xchg``, which every sensor of that host reads and only those in ``to``
    keep. A run placed on several hosts sends a payload across a host link once per host, not once per
    hearer (:mod:`agent.roles.routes`)."""

    to: list[int] = field(default_factory=list)
    FORM: ClassVar[type[wf.Form]] = wf.ViaXchgForm

    @classmethod
    def _fields_from_form(cls, f: wf.ViaXchgForm) -> dict:
        return super()._fields_from_form(f) | {"to": f.to}


@dataclass
class Rounds(Message):
    """Sensor i's exchange payloads of tick k, every round (``payloads[r]``: what it sent in round r), once for
    the observers when its tick ends: one sample a tick for the router, the recorder and a dashboard to carry,
    where a copy a round would be R of them."""

    TYPE: ClassVar[str] = "rounds"
    FORM: ClassVar[type[wf.Form]] = wf.RoundsForm
    payloads: list[dict[str, np.ndarray]] = field(default_factory=list)

    @classmethod
    def _fields_from_form(cls, f: wf.RoundsForm) -> dict:
        flat = iter(_arrays(*(a for p in f.payloads for a in p.values())))
        return dict(payloads=[{name: next(flat) for name in p} for p in f.payloads])


@dataclass
class Estimate(Message):
    """A node's (or the fusion solver's) estimate: ``x`` = x̂ₖ (used for scoring at tick k),
    ``x_next`` = x̂ₖ₊₁ (after this tick's update); ``P`` an optional covariance of ``x_next``."""

    TYPE: ClassVar[str] = "estimate"
    x: np.ndarray = field(default_factory=lambda: np.zeros(0))
    x_next: np.ndarray = field(default_factory=lambda: np.zeros(0))
    P: np.ndarray | None = None
    name: str = ""
    aux: dict[str, np.ndarray] = field(default_factory=dict)  #: estimator diagnostics (e.g. channel noise)

    FORM: ClassVar[type[wf.Form]] = wf.EstimateForm

    @classmethod
    def _fields_from_form(cls, f: wf.EstimateForm) -> dict:
        x, xn, P = _arrays(f.x, f.x_next, f.P, ndim=((1,), (1,), (2,)))
        if xn.shape != x.shape:
            raise WireError("bad_shape", "x_next must have the shape of x")
        if P is not None and P.shape != (x.size, x.size):
            raise WireError("bad_shape", "P must be len(x) × len(x)")
        return dict(x=x, x_next=xn, P=P, name=f.name, aux=_named(f.aux))


@dataclass
class State(Message):
    """A mobile agent's position and velocity after tick k (i.e. at tick k+1)."""

    TYPE: ClassVar[str] = "state"
    pos: np.ndarray = field(default_factory=lambda: np.zeros(0))
    vel: np.ndarray = field(default_factory=lambda: np.zeros(0))
    w: np.ndarray | None = None   #: the target's process disturbance over tick k (simulation ground truth)

    FORM: ClassVar[type[wf.Form]] = wf.StateForm

    @classmethod
    def _fields_from_form(cls, f: wf.StateForm) -> dict:
        pos, vel, w = _arrays(f.pos, f.vel, f.w, ndim=((1,),) * 3)
        if pos.shape != vel.shape or pos.size > 3:
            raise WireError("bad_shape", "pos and vel must be equal-length vectors of dimension ≤ 3")
        return dict(pos=pos, vel=vel, w=w)


@dataclass
class Control(Message):
    """Control-plane command (pause, resume, faults); ``args`` is a flat map of scalars/strings."""

    TYPE: ClassVar[str] = "control"
    verb: str = ""
    args: dict[str, Any] = field(default_factory=dict)

    FORM: ClassVar[type[wf.Form]] = wf.ControlForm

    @classmethod
    def _fields_from_form(cls, f: wf.ControlForm) -> dict:
        args: dict[str, Any] = {}
        for a, v in f.args.items():        # (None, flags, texts and bounded ints are as their form says)
            if type(v) is float:
                v = _finite(v, a)
            elif type(v) is list:
                v = _finite_list([float(x) for x in v], a)
            args[a] = v
        return dict(verb=f.verb, args=args)


#: every verb on ``control/<verb>`` and who executes it (the world: topology/world.py WORLD_VERBS; the
#: launcher: kill, restart; the sensors: outlier_burst)
CONTROL_VERBS = ("pause", "resume", "step", "speed", "link_drop", "link_heal", "link_loss", "partition", "heal",
                 "inject", "heal_fault", "kill", "restart", "outlier_burst")


def request_id(args: dict[str, Any]) -> dict[str, str]:
    """``{"req": …}`` of a control's args, for its answer (``flocktrack fault`` waits for the answer that
    echoes its request id); ``{}`` when the sender gave none."""
    req = args.get("req")
    return {"req": req[:64]} if isinstance(req, str) else {}


def control_args(items: list[str] | str) -> dict[str, Any]:
    """``name=value`` words (a list, or one space-separated string) → Control args; values are read as TOML
    (``80`` → int, ``0.3`` → float, ``[1, 2]`` → list, ``true``), anything else stays a string
    (``targets=agents:2``). Raises ValueError naming a word without ``=``."""
    import tomllib

    words = items.split() if isinstance(items, str) else list(items)
    out: dict[str, Any] = {}
    for w in words:
        name, sep, raw = w.partition("=")
        if not sep or not name:
            raise ValueError(f"{w!r} must look like name=value")
        try:
            out[name] = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            out[name] = raw
    return out


# --------------------------------------------------------------------------- typed control arguments
# A Control's args are a flat map of scalars and number lists (above). What each use needs of them is
# checked here, once, into frozen dataclasses: the fault plan's transitions (:func:`fault_event`) and the
# control verbs (:func:`command`). Roles and the world read typed fields; they never re-check.

#: fault kinds of the plan (topology/faults.py), the choices of their parameters and the bounds of their
#: delays: the one copy (a scenario's ``[[faults.events]]`` must stay within the same bounds)
FAULT_KINDS = ("link_loss", "delay", "duplicate", "reorder", "partition", "crash", "pause", "router_restart",
               "byzantine", "outliers", "blind", "noise", "evade")
FAULT_DIRECTIONS = ("both", "in", "out")
BYZANTINE_MODES = ("nan", "huge", "stale", "bias", "drift", "noise", "mimic")
FAULT_LIMITS = {"delay_ticks": 1000, "jitter_ticks": 1000, "delay_ms": 60_000.0, "jitter_ms": 60_000.0}
MAX_BURST_TICKS = 10_000         #: control/outlier_burst ticks
MAX_INJECT_TICKS = 10**7         #: control/inject duration
MAX_EVADE_ACCEL = 1e3            #: |accel| of an evade fault, m/s² (a target is not a rocket)

_INF = math.inf
#: the number parameters of a fault event and their ranges
_FAULT_NUMBERS = {"p": (0.0, 1.0), "delay_ms": (0.0, FAULT_LIMITS["delay_ms"]),
                  "jitter_ms": (0.0, FAULT_LIMITS["jitter_ms"]), "magnitude": (-_INF, _INF),
                  "noise_scale": (-_INF, _INF), "accel": (-MAX_EVADE_ACCEL, MAX_EVADE_ACCEL)}


def _whole(v: Any, name: str, lo: int, hi: int) -> int:
    """An integer in [lo, hi]; a Control arg may carry it as a float (list items always do)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v != int(v) \
            or not lo <= v <= hi:
        raise WireError("bad_field", f"{name} must be an integer in [{lo}, {hi}], got {v!r}")
    return int(v)


def _wholes(v: Any, name: str, lo: int, hi: int) -> tuple[int, ...]:
    return tuple(_whole(x, f"{name}[]", lo, hi) for x in _list(v, name))


def _number(v: Any, name: str, lo: float = -_INF, hi: float = _INF) -> float:
    x = _float(v, name)
    if not lo <= x <= hi:
        raise WireError("bad_field", f"{name} must be in [{lo:g}, {hi:g}], got {v!r}")
    return x


def _choice(v: Any, name: str, choices: tuple[str, ...]) -> str:
    if not isinstance(v, str) or v not in choices:
        raise WireError("bad_field", f"{name} must be one of {', '.join(choices)}, got {v!r}")
    return v


@dataclass(frozen=True)
class FaultEvent:
    """A fault-plan transition: the world's ``world/event`` (verb ``fault``; the args of topology/faults.py
    ``ActiveFault.event_args``) or the launcher's ``launcher/event`` (verb ``ack``: id, kind, phase, agents).
    Parameters a message leaves out take the defaults below."""

    id: int
    kind: str
    phase: str                                   #: "start" | "heal"
    agents: tuple[int, ...] = ()
    links: tuple[tuple[int, int], ...] = ()      #: the wire's flat [a, b, a, b, …], as pairs
    groups: tuple[int, ...] | None = None
    p: float = 1.0
    direction: str = "both"
    delay_ticks: int = 1
    jitter_ticks: int = 0
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    mode: str | None = None
    bias: tuple[float, ...] | None = None
    magnitude: float = 50.0
    noise_scale: float = 1.0
    accel: float = 2.0


def fault_event(args: dict[str, Any], n: int = MAX_LIST_LEN) -> FaultEvent:
    """The :class:`FaultEvent` of a Control's ``args`` (agent ids below ``n``). Raises :class:`WireError`
    (``bad_field``, the detail naming the argument) on anything malformed."""
    a = args
    flat = _wholes(a.get("links", []), "links", 0, n - 1)
    if len(flat) % 2:
        raise WireError("bad_field", "links must be pairs a, b, a, b, …")
    kw: dict[str, Any] = {name: _number(a[name], name, lo, hi) for name, (lo, hi) in _FAULT_NUMBERS.items()
                          if name in a}
    kw.update({name: _whole(a[name], name, 0, FAULT_LIMITS[name]) for name in ("delay_ticks", "jitter_ticks")
               if name in a})
    if a.get("groups") is not None:
        kw["groups"] = _wholes(a["groups"], "groups", 0, 2**31)
    if a.get("bias") is not None:
        kw["bias"] = tuple(_float(b, "bias[]") for b in _list(a["bias"], "bias"))
    if a.get("mode") is not None:
        kw["mode"] = _choice(a["mode"], "mode", BYZANTINE_MODES)
    return FaultEvent(id=_whole(a.get("id"), "id", 0, 2**53), kind=_choice(a.get("kind"), "kind", FAULT_KINDS),
                      phase=_choice(a.get("phase"), "phase", ("start", "heal")),
                      agents=_wholes(a.get("agents", []), "agents", 0, n - 1), links=tuple(zip(flat[::2], flat[1::2])),
                      direction=_choice(a.get("direction", "both"), "direction", FAULT_DIRECTIONS), **kw)


@dataclass(frozen=True)
class Command:
    """A ``control/<verb>`` command with its arguments checked (:func:`command`). pause, resume and heal
    take none; the other verbs are the subclasses below."""

    verb: str


@dataclass(frozen=True)
class Step(Command):
    n: int = 1                   #: ticks to run, then pause again (≥ 1)


@dataclass(frozen=True)
class Speed(Command):
    factor: float = 1.0          #: realtime pace: T / factor seconds per tick (> 0)


@dataclass(frozen=True)
class LinkEdit(Command):
    a: int = 0                   #: link_drop / link_heal: the link a–b (a ≠ b)
    b: int = 0


@dataclass(frozen=True)
class LinkLoss(Command):
    p: float = 0.0               #: every link lost with probability p per tick


@dataclass(frozen=True)
class Partition(Command):
    groups: tuple[int, ...] = ()  #: a group id per sensor; links between groups are cut


@dataclass(frozen=True)
class Inject(Command):
    event: dict[str, Any] = field(default_factory=dict)   #: a [[faults.events]] entry (typed by the scenario schema)
    ticks: int | None = None     #: its duration (None: until healed)


@dataclass(frozen=True)
class HealFault(Command):
    id: int = 0                  #: the live fault to heal (the id its inject was acknowledged with)


@dataclass(frozen=True)
class Member(Command):
    agent: int = 0               #: kill / restart: the sensor process (the launcher's verbs)


@dataclass(frozen=True)
class OutlierBurst(Command):
    agent: int = -1              #: the sensor (−1: every sensor)
    ticks: int = 1               #: impulsive outliers on its next ``ticks`` measurements ...
    magnitude: float = 0.0       #: ... of this norm


def _inject(verb: str, a: dict[str, Any]) -> Inject:
    ticks = a.get("ticks")
    if ticks is not None and (isinstance(ticks, bool) or not isinstance(ticks, (int, float))
                              or not 1 <= ticks <= MAX_INJECT_TICKS):
        raise WireError("bad_field",
                        f"inject.ticks: the fault's duration must be a number of ticks ≥ 1, got {ticks!r}")
    event = {k: v for k, v in a.items() if k not in ("ticks", "id", "start", "heal", "req")}
    for k in ("delay_ticks", "jitter_ticks"):   # integers in a Control may come as floats
        if isinstance(event.get(k), float) and event[k].is_integer():
            event[k] = int(event[k])
    return Inject(verb, event, None if ticks is None else int(ticks))


def command(verb: str, args: dict[str, Any], n: int = MAX_LIST_LEN) -> Command:
    """The typed command of ``control/<verb>`` with ``args``, for a flock of ``n`` sensors — what the world,
    the launcher (kill, restart), the sensors (outlier_burst) and ``flocktrack fault`` (before it sends)
    check. Raises :class:`WireError`: ``unknown_verb``, or ``bad_field`` with a detail that says which
    argument is wrong and why."""
    a = args
    if verb in ("pause", "resume", "heal"):
        return Command(verb)
    if verb in ("kill", "restart"):
        return Member(verb, _whole(a.get("agent"), "agent", 0, n - 1))
    if verb == "step":
        return Step(verb, max(1, _whole(a.get("n") or 1, "n", -2**53, 2**53)))
    if verb == "speed":
        f = _float(a.get("factor"), "factor")
        if not f > 0:
            raise WireError("bad_field", f"factor must be > 0, got {f!r}")
        return Speed(verb, f)
    if verb in ("link_drop", "link_heal"):
        ab = _whole(a.get("a"), "a", 0, n - 1), _whole(a.get("b"), "b", 0, n - 1)
        if ab[0] == ab[1]:
            raise WireError("bad_field", "a and b must be two different sensors")
        return LinkEdit(verb, *ab)
    if verb == "link_loss":
        return LinkLoss(verb, _number(a.get("p"), "p", 0.0, 1.0))
    if verb == "partition":
        groups = _wholes(a.get("groups"), "groups", 0, 2**31)
        if len(groups) != n:
            raise WireError("bad_field", f"groups must give a group id to each of the {n} sensors")
        return Partition(verb, groups)
    if verb == "inject":
        return _inject(verb, a)
    if verb == "heal_fault":
        return HealFault(verb, _whole(a.get("id"), "id", 0, 2**53))
    if verb == "outlier_burst":
        return OutlierBurst(verb, _whole(a.get("agent", -1), "agent", -1, 2**53),
                            _whole(a.get("ticks", 1), "ticks", 0, MAX_BURST_TICKS),
                            _float(a.get("magnitude", 0.0), "magnitude"))
    raise WireError("unknown_verb", verb)


#: the typed command of each control verb (:func:`command` builds it): its fields but ``verb`` are the
#: arguments the verb takes (``inject`` carries a fault event flat: the keys of a ``[[faults.events]]`` entry)
COMMAND_TYPES: dict[str, type[Command]] = {
    "pause": Command, "resume": Command, "heal": Command, "step": Step, "speed": Speed, "link_drop": LinkEdit,
    "link_heal": LinkEdit, "link_loss": LinkLoss, "partition": Partition, "inject": Inject, "heal_fault": HealFault,
    "kill": Member, "restart": Member, "outlier_burst": OutlierBurst}


@dataclass
class End(Message):
    """World → all: the run is over after ``k`` ticks (``reason``: "done", "stopped")."""

    TYPE: ClassVar[str] = "end"
    reason: str = "done"

    FORM: ClassVar[type[wf.Form]] = wf.EndForm

    @classmethod
    def _fields_from_form(cls, f: wf.EndForm) -> dict:
        return dict(reason=f.reason)


MESSAGE_TYPES: dict[str, type[Message]] = {
    c.TYPE: c for c in (Tick, Truth, Meas, Xchg, Rounds, Estimate, State, Control, End)
}

#: a host's name: in a placement file (flocktrack/plan/placement.py) and in a key (``agent/<i>/via/<host>/xchg``)
HOST_NAME = re.compile(r"[a-z0-9][a-z0-9_]*")

#: (first key segment, message type) -> whether the segment after it is an agent id
_KEY_TYPES = {
    ("world", "tick"): Tick,
    ("world", "end"): End,
    ("world", "event"): Control,
    ("launcher", "event"): Control,
    ("target", "truth"): Truth,
    ("target", "state"): State,
    ("agent", "meas"): Meas,
    ("agent", "xchg"): Rounds,
    ("agent", "estimate"): Estimate,
    ("agent", "state"): State,
    ("fusion", "estimate"): Estimate,
}




def xchg_key(src: int, dst: int) -> str:
    """The key sensor ``src`` addresses an exchange payload to sensor ``dst`` on."""
    return f"agent/{src}/to/{dst}/xchg"


def inbox(i: int) -> str:
    """Sensor ``i``'s inbox: the exchange payloads addressed to it (a subscription pattern)."""
    return f"agent/*/to/{i}/xchg"


def via_key(src: int, host: str) -> str:
    """The key sensor ``src`` sends one copy of an exchange payload on for the sensors of ``host`` that hear
    it (a :class:`ViaXchg`)."""
    return f"agent/{src}/via/{host}/xchg"


def host_inbox(host: str) -> str:
    """The exchange payloads sent to the sensors of ``host`` (a subscription pattern; see :func:`via_key`)."""
    return f"agent/*/via/{host}/xchg"


def estimate_key(src: int, dst: int) -> str:
    """The key sensor ``src`` hands its last estimate to a (re)joining sensor ``dst`` on."""
    return f"agent/{src}/to/{dst}/estimate"


def estimate_inbox(i: int) -> str:
    """A rejoining sensor ``i``'s inbox for its peers' last estimates (a subscription pattern)."""
    return f"agent/*/to/{i}/estimate"


def addressed(key: str) -> bool:
    """Is ``key`` addressed to one sensor (``agent/<i>/to/<j>/xchg`` or ``…/estimate``) or to the sensors of
    one host (``agent/<i>/via/<host>/xchg``), not for observers?"""
    return key.count("/") == 4 and key.startswith("agent/")


@functools.lru_cache(maxsize=4096)
def expected_type(key: str) -> tuple[type[Message], int | None]:
    """Message class a relative key carries, and the agent id that owns it (None if not an agent key).
    Remembered per key (a process hears a few dozen keys over and over; a refused key is not remembered)."""
    parts = key.split("/")
    if parts[0] == "agent" and len(parts) == 5 and parts[2] == "to" and parts[4] in ("xchg", "estimate"):
        try:
            owner, dst = int(parts[1]), int(parts[3])
        except ValueError:
            raise WireError("bad_key", key) from None
        if owner < 0 or dst < 0 or dst == owner:
            raise WireError("bad_key", key)
        return (Xchg if parts[4] == "xchg" else Estimate), owner
    if parts[0] == "agent" and len(parts) == 5 and parts[2] == "via" and parts[4] == "xchg":
        if not parts[1].isdigit() or HOST_NAME.fullmatch(parts[3]) is None:
            raise WireError("bad_key", key)
        return ViaXchg, int(parts[1])
    if parts[0] == "agent" and len(parts) == 3:
        try:
            owner = int(parts[1])
        except ValueError:
            raise WireError("bad_key", key) from None
        t = _KEY_TYPES.get(("agent", parts[2]))
        if t is None or owner < 0:
            raise WireError("bad_key", key)
        return t, owner
    if parts[0] == "control" and len(parts) >= 2:
        return Control, None
    if len(parts) == 2 and (parts[0], parts[1]) in _KEY_TYPES:
        return _KEY_TYPES[(parts[0], parts[1])], None
    raise WireError("bad_key", key)


def encode(msg: Message) -> bytes:
    """msgpack bytes of a message: a map of its ``type`` and its fields (arrays as ``{s, d}``, bin data).
    The same bytes as ``msgpack.packb(msg.to_wire())``, written by msgspec's compiled encoder."""
    d: dict[str, Any] = {"type": msg.TYPE}
    for name in _field_names(type(msg)):
        d[name] = getattr(msg, name)
    return _ENCODER.encode(d)


def _enc_hook(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return _enc_array(v)
    if isinstance(v, np.generic):
        return v.item()
    raise NotImplementedError(f"a message cannot carry a {type(v).__name__}")


_ENCODER = msgspec.msgpack.Encoder(enc_hook=_enc_hook)


def decode(key: str, data: bytes) -> Message:
    """Decode and validate a message that arrived on relative ``key``. Raises :class:`WireError`."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise WireError("bad_encoding", "payload is not bytes")
    if len(data) > MAX_MESSAGE_BYTES:
        raise WireError("too_large", f"{len(data)} bytes")
    cls, owner = expected_type(key)
    try:
        form = _decoder(cls).decode(data)
    except msgspec.ValidationError as exc:
        raise _refusal(cls, exc, wf.type_of(data), lambda: _XCHG_HEADER.decode(data), owner) from None
    except msgspec.DecodeError as exc:
        raise WireError("bad_encoding", str(exc)) from None
    return _message(cls, form, key, owner)


@functools.cache
def _decoder(cls: type[Message]) -> msgspec.msgpack.Decoder:
    return msgspec.msgpack.Decoder(cls.FORM)


_XCHG_HEADER = msgspec.msgpack.Decoder(wf.XchgHeader)


def _refusal(cls: type[Message], exc: msgspec.ValidationError, claimed: Any, header, owner: int | None) -> WireError:
    """The :class:`WireError` of a message its form refused: ``wrong_type`` when it claims another type, else
    the fault's label. An exchange payload refused for its arrays keeps its header when ``header()`` (the
    message read as an :class:`~agent.wire_form.XchgHeader`) is whole and names the key's owner."""
    label = wf.reason(exc, _array_fields(cls))
    if label != "bad_encoding" and claimed != cls.TYPE:
        return WireError("wrong_type", f"{claimed!r} for {cls.TYPE}")
    err = WireError(label, str(exc))
    if issubclass(cls, Xchg) and label in _UNUSABLE_ARRAY:
        try:
            h = header()
        except msgspec.MsgspecError:
            h = None
        if h is not None and h.type == cls.TYPE:
            err.header = _unusable(h, label, owner)
    return err


def _unusable(h: wf.XchgHeader | wf.XchgForm, reason: str, owner: int | None) -> UnusableXchg | None:
    """The header of an exchange payload whose arrays are unusable, or None when it lies about its sender."""
    return UnusableXchg(src=h.src, k=h.k, r=h.r, reason=reason) if owner in (None, h.src) else None


def _message(cls: type[Message], form: wf.Form, key: str, owner: int | None) -> Message:
    """The message of a decoded form, after the checks the form cannot make (its type; values; ownership)."""
    if form.type != cls.TYPE:
        raise WireError("wrong_type", f"{form.type!r} on {key}")
    try:
        msg = cls.from_form(form)
    except WireError as exc:
        if isinstance(form, wf.XchgForm) and exc.reason in _UNUSABLE_ARRAY:
            exc.header = _unusable(form, exc.reason, owner)
        raise
    except Exception as exc:  # any other surprise in hostile input is still a drop, never a crash
        raise WireError("bad_field", f"{type(exc).__name__}: {exc}") from None
    if owner is not None and msg.src != owner:
        raise WireError("not_owner", f"src {msg.src} on {key}")
    return msg


def valid_suspects(i: int, values, n: int) -> tuple[np.ndarray, int]:
    """The sensor ids in ``values`` (``Estimate.aux["suspected"]`` of sensor ``i``) that can be suspects:
    integers in 0 … n − 1 other than ``i``, each once, sorted; and how many values were dropped (not
    finite, not an integer, out of range, ``i`` itself, a repeat — or everything, when ``values`` is not
    numeric at all)."""
    try:
        a = np.asarray(values)
    except (TypeError, ValueError, OverflowError):     # (a ragged list)
        return np.zeros(0, int), 1
    if a.dtype.kind not in "iuf":                       # text, objects, booleans: nothing to read an id from
        return np.zeros(0, int), max(a.size, 1)
    a = a.astype(float).reshape(-1)
    with np.errstate(all="ignore"):
        ok = np.isfinite(a) & (a == np.floor(a)) & (a >= 0) & (a < n) & (a != i)
    ids = np.unique(a[ok]).astype(int)
    return ids, int(a.size - ids.size)


def int_list(v: Any, lo: int = 0, hi: int = MAX_LIST_LEN) -> list[int] | None:
    """A Control arg that must be a list of integers in [lo, hi) (numbers arrive as floats); None if not."""
    if not isinstance(v, list):
        return None
    out = []
    for x in v:
        if isinstance(x, bool) or not isinstance(x, (int, float)) or x != int(x) or not lo <= int(x) < hi:
            return None
        out.append(int(x))
    return out


def key_for(msg: Message, role: str) -> str:
    """Relative key a role publishes a message on (``role`` is 'agent', 'target', 'world', 'fusion')."""
    if role == "agent":
        return f"agent/{msg.src}/{msg.TYPE}"
    if isinstance(msg, Control):
        return f"control/{msg.verb}"
    return f"{role}/{msg.TYPE}"


@functools.cache
def _array_fields(cls: type[Message]) -> frozenset[str]:
    """The fields of ``cls`` that are arrays (once per type: reading a recording asks for every message)."""
    import typing

    hints = typing.get_type_hints(cls)
    return frozenset(f.name for f in fields(cls) if "ndarray" in str(hints[f.name]))


def from_json(d: dict) -> Message:
    """Inverse of :meth:`Message.to_json` (recordings → messages), validated like :func:`decode`."""
    cls = MESSAGE_TYPES.get(d.get("type")) if isinstance(d, dict) else None
    if cls is None:
        raise WireError("wrong_type", f"unknown message type {d.get('type') if isinstance(d, dict) else d!r}")
    arrays = _array_fields(cls)
    w: dict[str, Any] = {}
    for k, v in d.items():
        if k in ("payload", "aux") and isinstance(v, dict):
            w[k] = {pk: _enc_array(np.array(pv, dtype=float)) for pk, pv in v.items()}
        elif k == "payloads" and isinstance(v, list):
            w[k] = [{pk: _enc_array(np.array(pv, dtype=float)) for pk, pv in p.items()} if isinstance(p, dict) else p
                    for p in v]
        elif k in arrays and v is not None:
            w[k] = _enc_array(np.array(v, dtype=float))
        else:
            w[k] = v
    try:
        form = msgspec.convert(w, cls.FORM)
    except msgspec.ValidationError as exc:
        raise _refusal(cls, exc, w.get("type"), lambda: msgspec.convert(w, wf.XchgHeader), None) from None
    return _message(cls, form, cls.TYPE, None)


def json_schema(cls: type[Message]) -> dict:
    """A JSON Schema for a message type's JSON form (recordings: Foxglove shows fields by it)."""
    import typing

    hints = typing.get_type_hints(cls)
    props: dict[str, Any] = {"type": {"type": "string", "const": cls.TYPE}}
    for f in fields(cls):
        h = str(hints[f.name])
        if f.name in ("payload", "aux"):
            props[f.name] = {"type": "object", "additionalProperties": {"type": "array"}}
        elif "ndarray" in h:
            props[f.name] = {"type": ["array", "null"] if "None" in h else "array"}
        elif h.startswith("list") or "list[" in h:
            props[f.name] = {"type": "array"}
        elif hints[f.name] is int:
            props[f.name] = {"type": "integer"}
        elif hints[f.name] is float:
            props[f.name] = {"type": "number"}
        elif hints[f.name] is str:
            props[f.name] = {"type": "string"}
        else:
            props[f.name] = {}
    return {"title": f"flocktrack.{cls.__name__}", "type": "object", "properties": props}
