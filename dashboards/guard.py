"""What a browser tab may send the dashboard: every message checked before Viser acts on it.

Viser trusts its page. Its GUI handler casts a value to the widget's type and stores it (a string for a
number raises inside an event-loop task; a huge integer is stored as it is), sets any attribute an update
names, dispatches message types only a server sends, and a frame that does not decode ends its
connection with a traceback in the log. The dashboard serves tabs it does not trust (anyone who can open
the page), so :class:`TabGuard` sits at the one boundary every message crosses — the websocket server's
dispatch (``WebsockServer._handle_incoming_message``), which it replaces for the server and for each
tab's connection — and lets through only:

* the message types the page sends while it is used (camera, GUI update, scene click and pointer);
  any other is dropped and counted (``unknown_messages``);
* at a stated rate per tab and message type (:class:`Limits`); beyond it a message is dropped
  (``throttled``), and a tab that keeps on is closed (``closed_for_rate``);
* a camera or pointer report whose fields are finite numbers of the right shape;
* a GUI update of exactly ``{"value": v}`` to a widget registered for *that* tab (:meth:`TabGuard.allow`)
  — or, on a replay page, to a shared one — with ``v`` of the widget's type, one of its options, finite,
  within its range and, for text, at most ``Limits.text_len`` characters (:func:`value_problem`). An
  invalid update is dropped and counted per tab (``invalid_updates``), never stored, never raised.

A frame that does not decode still ends that tab's connection (Viser's consumer stops), but its traceback is
replaced by one rate-limited line per tab that names the error's type, never the payload
(:class:`_FrameFilter`). At most ``Limits.max_tabs`` tabs are served at once; one more is closed at its
handshake with the reason (``refused_tabs``). Every callback the dashboard registers runs through
:meth:`TabGuard.safe`: an exception there is counted and logged once per callback, never printed per event.

Viser could do most of this itself: validate a ``GuiUpdateMessage`` against the widget's props (type,
options, min/max, finite) and accept only ``value``; accept only client-to-server message types; log a
failed decode as one line. Until it does, this module holds it, and a Viser upgrade that moves these
private names fails the hostile-client tests (tests/browser/test_dashboard_hostile.py) rather than opening a hole.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import Counter
from dataclasses import dataclass, field

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Limits:
    """The limits a tab lives within (``python -m dashboards --max-tabs`` sets the first)."""

    max_tabs: int = 16                   #: tabs served at once; one more is closed at its handshake
    #: sustained messages per second per tab, by type, and the burst above it (a dragged slider sends ~30/s,
    #: an orbiting camera one report per rendered frame)
    rates: tuple = (("GuiUpdateMessage", 30.0, 60), ("ViewerCameraMessage", 90.0, 180),
                    ("ScenePointerMessage", 10.0, 20), ("SceneNodeClickMessage", 10.0, 20))
    close_after: int = 300               #: throttled messages (leaking 10 a second) before a tab is closed
    text_len: int = 1000                 #: longest text a text field takes
    log_every_s: float = 10.0            #: at most one line per tab and kind of trouble this often ...
    log_lines: int = 10                  #: ... and this many from all tabs together


def value_problem(handle, value, text_len: int) -> str | None:
    """Why ``value`` may not become the value of the widget ``handle`` (None: it may): ``type``,
    ``options``, ``finite``, ``range`` or ``length``."""
    import viser

    if isinstance(handle, viser.GuiButtonHandle):
        return None if value is True else "type"
    if isinstance(handle, viser.GuiCheckboxHandle):
        return None if isinstance(value, bool) else "type"
    if isinstance(handle, (viser.GuiDropdownHandle, viser.GuiButtonGroupHandle)):
        if not isinstance(value, str):
            return "type"
        return None if value in handle.options else "options"
    if isinstance(handle, viser.GuiTextHandle):
        if not isinstance(value, str):
            return "type"
        return None if len(value) <= text_len else "length"
    if isinstance(handle, (viser.GuiNumberHandle, viser.GuiSliderHandle)):
        return _number_problem(handle, value)
    return "type"                         # a widget kind the dashboard does not let tabs change


def _number_problem(handle, value) -> str | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return "type"
    if not math.isfinite(value):
        return "finite"
    if isinstance(handle.value, int) and value != int(value):
        return "type"
    lo, hi = handle.min, handle.max
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        return "range"
    return None


def _finite_vector(v, n: int) -> bool:
    return isinstance(v, (list, tuple)) and len(v) == n and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)


def _camera_ok(m) -> bool:
    scalars = (m.fov, m.near, m.far, m.image_height, m.image_width)
    return (all(_finite_vector(v, n) for v, n in ((m.wxyz, 4), (m.position, 3), (m.look_at, 3),
                                                   (m.up_direction, 3)))
            and _finite_vector(scalars, 5) and all(x > 0 for x in scalars))


def _pointer_ok(m) -> bool:
    rays = (m.ray_origin, m.ray_direction)
    return (m.event_type in ("click", "rect-select") and all(r is None or _finite_vector(r, 3) for r in rays)
            and isinstance(m.screen_pos, (list, tuple)) and len(m.screen_pos) <= 2
            and all(_finite_vector(p, 2) for p in m.screen_pos))


def _node_click_ok(m) -> bool:
    return (isinstance(m.name, str) and len(m.name) <= 256 and _finite_vector(m.ray_origin, 3)
            and _finite_vector(m.ray_direction, 3) and _finite_vector(m.screen_pos, 2)
            and (m.instance_index is None or (isinstance(m.instance_index, int)
                                              and not isinstance(m.instance_index, bool))))


_SHAPE_CHECKS = {"ViewerCameraMessage": _camera_ok, "ScenePointerMessage": _pointer_ok,
                 "SceneNodeClickMessage": _node_click_ok}


@dataclass
class Tab:
    """One connected tab, as the guard sees it."""

    client_id: int
    connection: object = None
    dispatch: object = None              #: the tab connection's own dispatch (Viser's), called once admitted
    operator: bool = False
    widgets: dict = field(default_factory=dict)       #: uuid → the widget handles this tab may change
    counters: Counter = field(default_factory=Counter)
    tokens: dict = field(default_factory=dict)        #: message type → (tokens, last refill)
    strikes: float = 0.0
    strikes_t: float = 0.0
    logged: dict = field(default_factory=dict)        #: kind of trouble → when last logged
    closed: bool = False


class TabGuard:
    """The admission of every message from every tab (see the module's docstring). ``shared_writable``:
    shared widgets take validated updates from any tab (a replay page: nothing to steer); live, only an
    operator tab may change a shared widget (the live page has none)."""

    def __init__(self, limits: Limits | None = None, *, shared_writable: bool = False, clock=time.monotonic):
        self.limits = limits or Limits()
        self.shared_writable = shared_writable
        self.clock = clock
        self.tabs: dict[int, Tab] = {}
        self.shared: dict[str, object] = {}
        self.counters: Counter = Counter()      #: the guard's own (tabs seen, refused, …) and retired tabs'
        self.gone: dict[str, dict] = {}           #: counters of tabs gone with trouble (the last 200)
        self._recent: dict[int, tuple] = {}       #: id(connection) → (connection, tab), the last 256 tabs
        self._logged: dict[str, float] = {}
        self._budget = (-math.inf, 0)
        self._rates = {name: (rate, burst) for name, rate, burst in self.limits.rates}
        self._ws = None
        self._filter = None

    # ------------------------------------------------------------------ installation
    def install(self, server) -> None:
        """Put the guard in front of ``server``'s (a ``viser.ViserServer``) dispatch, before any tab connects
        (Viser's own connect callbacks run first; the guard's runs before the tab's first message)."""
        ws = server._websock_server
        self._ws, self._dispatch = ws, ws._handle_incoming_message
        ws._handle_incoming_message = self._incoming
        ws.on_client_connect(self._on_connect)
        ws.on_client_disconnect(self._on_disconnect)
        self.quiet_logs()
        # a tab may have connected while the server started (it listens from its constructor on): guard it
        # the same way, on Viser's loop, before any more of its messages are handled
        loop = ws._background_event_loop
        if loop is not None:
            loop.set_exception_handler(self._task_failed)
        for client in tuple(server.get_clients().values()):
            if loop is not None:
                asyncio.run_coroutine_threadsafe(self._on_connect(client._websock_connection), loop).result(10)

    def quiet_logs(self) -> None:
        """The log filter and warning filters (call it before the server listens: a port probe may come at
        once); :meth:`install` calls it too."""
        if self._filter is None:
            self._filter = _FrameFilter(self)
            logging.getLogger("websockets.server").addFilter(self._filter)
        quiet_viser_warnings()

    def uninstall(self) -> None:
        if self._filter is not None:
            logging.getLogger("websockets.server").removeFilter(self._filter)
            self._filter = None

    async def _on_connect(self, conn) -> None:
        """A tab's websocket is up (its first message has not been read): refuse it past the cap, else keep
        its connection's own dispatch for admitted messages and silence the direct one."""
        cid = conn.client_id
        live = self._ws._live_connections.get(cid)
        if cid in self.tabs or live is None:   # guarded already (installed while it connected), or gone
            return
        if len(self.tabs) >= self.limits.max_tabs:
            self.counters["refused_tabs"] += 1
            self._log_global("refused", "a tab was refused: the dashboard serves at most %d tabs at once (%d "
                             "refused so far)", self.limits.max_tabs, self.counters["refused_tabs"])
            if live is not None:
                await live.close(1013, f"the dashboard serves at most {self.limits.max_tabs} tabs; "
                                       "close another tab and reload")
            return
        tab = self.tabs[cid] = Tab(cid, connection=live, dispatch=conn._handle_incoming_message)
        self.counters["tabs_seen"] += 1
        self._recent[id(live)] = (live, tab)
        while len(self._recent) > 256:
            self._recent.pop(next(iter(self._recent)))

        async def silenced(client_id, message) -> None:   # the guard dispatches it once admitted
            return None

        conn._handle_incoming_message = silenced
        tab.strikes_t = self.clock()

    def _on_disconnect(self, conn) -> None:
        tab = self.tabs.pop(conn.client_id, None)
        if tab is not None:
            self._retire(tab)

    def _retire(self, tab: Tab) -> None:
        """Keep a gone tab's counters in the totals (the stats file lists the tabs with trouble)."""
        self.counters.update({f"total_{k}": v for k, v in tab.counters.items()})
        if any(k != "admitted" for k in tab.counters):
            self.gone[str(tab.client_id)] = dict(tab.counters)
            while len(self.gone) > 200:
                self.gone.pop(next(iter(self.gone)))

    # ------------------------------------------------------------------ what tabs may change
    def allow(self, handle, client_id: int | None = None) -> None:
        """Let tab ``client_id`` (None: any tab, within the rules for shared widgets) change ``handle``."""
        uuid = handle._impl.uuid
        if client_id is None:
            self.shared[uuid] = handle
        elif client_id in self.tabs:
            self.tabs[client_id].widgets[uuid] = handle

    def mark_operator(self, client_id: int) -> None:
        if client_id in self.tabs:
            self.tabs[client_id].operator = True

    def safe(self, fn, name: str | None = None):
        """``fn`` as a Viser callback that never raises: an exception is counted and logged in one line once per
        callback (its traceback at debug level), then only counted."""
        label = name or getattr(fn, "__qualname__", "callback")

        def run(*args, **kwargs):
            try:
                return fn(*args, **kwargs)
            except Exception as exc:
                self.counters["callback_errors"] += 1
                if self.counters[f"callback_errors:{label}"] == 0:
                    log.error("dashboard callback %s failed: %s: %s (logged once; counted after)", label,
                              type(exc).__name__, exc)
                    log.debug("dashboard callback %s failed", label, exc_info=True)
                self.counters[f"callback_errors:{label}"] += 1
                return None

        return run

    # ------------------------------------------------------------------ admission
    async def _incoming(self, client_id, message) -> None:
        """Replaces the server's dispatch: admit, then hand to Viser's server- and tab-level handlers."""
        tab = self.tabs.get(client_id)
        if tab is None or tab.closed or not self.admit(tab, message):
            return
        tab.counters["admitted"] += 1
        for dispatch in (self._dispatch, tab.dispatch):
            try:
                await dispatch(client_id, message)
            except Exception as exc:      # a handler of Viser's that still raised: counted, never a traceback
                self._trouble(tab, "handler_errors", "a handler raised %s on its message",
                              type(exc).__name__)

    def admit(self, tab: Tab, message) -> bool:
        """Is ``message`` from ``tab`` let through? (Counts, logs and closes as the module says.)"""
        kind = type(message).__name__
        if kind not in self._rates:
            self._trouble(tab, "unknown_messages", "sent a %s, which the page never sends: dropped", kind)
            return False
        if not self._take_token(tab, kind):
            self._throttle(tab, kind)
            return False
        if kind == "GuiUpdateMessage":
            return self._update_ok(tab, message)
        if not self._shape_ok(message, kind):
            self._trouble(tab, "invalid_messages", "sent a malformed %s: dropped", kind)
            return False
        return True

    def _shape_ok(self, message, kind: str) -> bool:
        try:
            return bool(_SHAPE_CHECKS[kind](message))
        except Exception:                 # a field of the wrong kind altogether
            return False

    def _update_ok(self, tab: Tab, message) -> bool:
        updates = message.updates
        uuid = message.uuid if isinstance(message.uuid, str) else None
        handle = tab.widgets.get(uuid)
        if handle is None and uuid in self.shared and (self.shared_writable or tab.operator):
            handle = self.shared[uuid]
        if handle is None:
            problem = "not this tab's widget"
        elif not isinstance(updates, dict) or list(updates) != ["value"]:
            problem = "fields other than value"
        else:
            problem = value_problem(handle, updates["value"], self.limits.text_len)
        if problem is None:
            return True
        tab.counters[f"invalid_updates:{problem}"] += 1
        self._trouble(tab, "invalid_updates", "an update was refused (%s): dropped", problem)
        return False

    def _take_token(self, tab: Tab, kind: str) -> bool:
        rate, burst = self._rates[kind]
        now = self.clock()
        tokens, t = tab.tokens.get(kind, (float(burst), now))
        tokens = min(float(burst), tokens + (now - t) * rate)
        ok = tokens >= 1.0
        tab.tokens[kind] = (tokens - 1.0 if ok else tokens, now)
        return ok

    def _throttle(self, tab: Tab, kind: str) -> None:
        now = self.clock()
        tab.strikes = max(0.0, tab.strikes - 10.0 * (now - tab.strikes_t)) + 1.0
        tab.strikes_t = now
        self._trouble(tab, "throttled", "sends %ss faster than %g/s: dropped", kind, self._rates[kind][0])
        if tab.strikes > self.limits.close_after:
            self.close(tab, "closed_for_rate", 1008, "too many messages")

    def close(self, tab: Tab, counter: str, code: int, reason: str) -> None:
        """Close ``tab``'s websocket (from the event loop) and count why."""
        if tab.closed:
            return
        tab.closed = True
        tab.counters[counter] += 1
        self.counters[counter] += 1
        log.warning("tab %s closed: %s", tab.client_id, reason)
        if tab.connection is not None:
            asyncio.ensure_future(tab.connection.close(code, reason))

    # ------------------------------------------------------------------ counting and logging
    def _trouble(self, tab: Tab | None, kind: str, fmt: str, *args) -> None:
        """Count ``kind`` for ``tab`` and log it, at most once per ``Limits.log_every_s`` per tab and kind
        (the line says how many were not logged); never with the payload."""
        target = tab.counters if tab is not None else self.counters
        target[kind] += 1
        key = tab.logged if tab is not None else self._logged
        now = self.clock()
        last = key.get(kind)
        if last is not None and now - last < self.limits.log_every_s:
            return
        key[kind] = now
        if not self._log_budget(now):
            return
        who = f"tab {tab.client_id}" if tab is not None else "a tab"
        log.warning(f"{who}: {fmt} ({kind}: {target[kind]} so far)", *args)

    def _log_budget(self, now: float) -> bool:
        """At most ``Limits.log_lines`` trouble lines per ``log_every_s`` from all tabs together (a client
        that reconnects is a new tab each time); beyond them lines are only counted."""
        t0, n = self._budget
        if now - t0 >= self.limits.log_every_s:
            t0, n = now, 0
        self._budget = (t0, n + 1)
        if n < self.limits.log_lines:
            return True
        self.counters["log_lines_suppressed"] += 1
        return False

    def _task_failed(self, loop, context: dict) -> None:
        """Viser's loop: a task raised and nobody awaited it — a message of a tab that connected while the
        server started, handled by Viser before the guard was in front of it. Counted (``task_errors``) and
        logged in one line, never with a traceback."""
        exc = context.get("exception")
        self.counters["task_errors"] += 1
        self._log_global("task_errors", "a message was handled before the guard and raised %s: dropped (task_errors: "
                         "%d so far)", type(exc).__name__ if exc is not None else context.get("message", "?"),
                         self.counters["task_errors"])

    def _log_global(self, kind: str, fmt: str, *args) -> None:
        now = self.clock()
        if now - self._logged.get(kind, -math.inf) >= self.limits.log_every_s:
            self._logged[kind] = now
            log.warning(fmt, *args)

    def malformed_frame(self, connection, exc: BaseException | None) -> None:
        """A frame of ``connection``'s did not decode: Viser's consumer raised and the tab is gone (its
        counters retired already), so this one is counted in the totals and in the tab's record."""
        tab = self.tab_of(connection)
        what = type(exc).__name__ if exc is not None else "error"
        self.counters["total_malformed_frames"] += 1
        if tab is not None:
            record = self.gone.setdefault(str(tab.client_id), dict(tab.counters))
            record["malformed_frames"] = record.get("malformed_frames", 0) + 1
        self._trouble(tab, "malformed_frames", "sent a frame that does not decode (%s): connection closed", what)

    def tab_of(self, connection) -> Tab | None:
        """The tab (connected or one of the last 256) whose websocket is ``connection``."""
        hit = self._recent.get(id(connection))
        return hit[1] if hit is not None and hit[0] is connection else None

    def stats(self) -> dict:
        """Totals and, per connected tab, its counters (for stats/dashboard_0.json)."""
        out = dict(self.counters)
        for tab in self.tabs.values():
            for k, v in tab.counters.items():
                out[f"total_{k}"] = out.get(f"total_{k}", 0) + v
        out["tabs"] = {str(t.client_id): dict(t.counters) for t in self.tabs.values()}
        out["tabs_gone_with_trouble"] = dict(self.gone)
        out["max_tabs"] = self.limits.max_tabs
        return out


def quiet_viser_warnings() -> None:
    """Viser warns with the offending value when a field of a tab's message does not match its annotation
    (each distinct payload a new warning, printed), and when a message is queued for a tab that has just
    gone: neither is the operator's business, and the first echoes what a hostile tab sent."""
    import warnings

    warnings.filterwarnings("ignore", category=UserWarning, module=r"viser\.infra\._messages")
    warnings.filterwarnings("ignore", message=r"Queued a \w+ on a closed connection", category=UserWarning)


class _FrameFilter(logging.Filter):
    """On ``websockets.server``: the traceback of a tab's connection whose handler failed (a frame Viser
    could not decode), or of a connection that never spoke HTTP, becomes one rate-limited line of the
    guard's; other records pass."""

    def __init__(self, guard: TabGuard):
        super().__init__()
        self.guard = guard

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        if msg == "opening handshake failed":   # not HTTP at all (a port probe, a scanner): one counted line
            self.guard.counters["failed_handshakes"] += 1
            exc = record.exc_info[1] if record.exc_info else None
            self.guard._log_global("handshake", "a connection failed its opening handshake (%s; %d so far)",
                                   type(exc).__name__ if exc else "error", self.guard.counters["failed_handshakes"])
            return False
        if msg != "connection handler failed":
            return True
        conn = getattr(record, "websocket", None)
        exc = record.exc_info[1] if record.exc_info else None
        if self.guard.tab_of(conn) is None and not _raised_decoding(exc):
            return True                   # another server's (tests run several), and not a tab's bad frame
        self.guard.malformed_frame(conn, exc)
        return False


def _raised_decoding(exc: BaseException | None) -> bool:
    """Whether ``exc`` came out of Viser's decoding of a message a tab sent (``viser/infra/_messages.py``):
    a tab's bad frame even when the tab is not known here (refused at the cap, or gone before it was
    registered)."""
    tb = exc.__traceback__ if exc is not None else None
    while tb is not None:
        if tb.tb_frame.f_code.co_filename.replace("\\", "/").endswith("viser/infra/_messages.py"):
            return True
        tb = tb.tb_next
    return False
