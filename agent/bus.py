"""The Bus protocol and the in-process :class:`LocalBus`.

Roles talk only through a ``Bus``: ``publish(key, msg)`` and ``subscribe(pattern, handler)`` on keys
relative to the run prefix (``world/tick``, ``agent/3/xchg``, …; DESIGN.md "Key space"). Patterns use
Zenoh's key-expression wildcards: ``*`` is one chunk, ``**`` any number of chunks.

Both buses push every message through :mod:`agent.wire` (encode → bytes → decode + validate), so a
message that would be dropped over Zenoh is dropped in-process too, and the numbers are bit-identical.
Dropped messages are counted per reason in :attr:`BusStats.dropped`; they never reach a handler.
"""

from __future__ import annotations

import logging
import queue
import time
import weakref
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from . import wire
from .inbox import Inbox

log = logging.getLogger(__name__)

Handler = Callable[[str, wire.Message], None]


def key_matches(pattern: str, key: str) -> bool:
    """Zenoh-style key-expression match: ``*`` = exactly one chunk, ``**`` = zero or more chunks."""
    p, k = pattern.split("/"), key.split("/")

    def rec(i: int, j: int) -> bool:
        if i == len(p):
            return j == len(k)
        if p[i] == "**":
            return any(rec(i + 1, jj) for jj in range(j, len(k) + 1))
        if j == len(k):
            return False
        return (p[i] == "*" or p[i] == k[j]) and rec(i + 1, j + 1)

    return rec(0, 0)


@dataclass
class BusStats:
    """Message counters of one bus endpoint."""

    sent: int = 0
    sent_by_key: Counter = field(default_factory=Counter)
    received: int = 0
    dropped: Counter = field(default_factory=Counter)
    handler_errors: int = 0
    held: int = 0     #: addressed payloads held until their receiver's subscription reached us (ZenohBus)
    undeclared: Counter = field(default_factory=Counter)   #: puts outside the node's declared writes, by key

    def as_dict(self) -> dict:
        return {"sent": self.sent, "sent_by_key": dict(sorted(self.sent_by_key.items())),
                "received": self.received, "dropped": dict(self.dropped),
                "handler_errors": self.handler_errors, "held": self.held,
                "undeclared": dict(sorted(self.undeclared.items()))}



class Bus(Protocol):
    """What a role needs from a transport."""

    stats: BusStats

    def publish(self, key: str, msg: wire.Message) -> None: ...

    def publish_raw(self, key: str, data: bytes) -> None: ...

    def subscribe(self, pattern: str, handler: Handler, *, bulk: bool = False) -> None: ...

    def close(self) -> None: ...


def deliver(stats: BusStats, handlers: list[Handler], key: str, data: bytes,
            decoded: wire.Message | None = None) -> wire.Message | None:
    """Decode ``data`` once, validate, and hand it to ``handlers``; count and drop anything bad.
    Shared by both buses so their receive paths are identical. ``decoded``: the same bytes already
    decoded and validated for a key of the same type and owner (LocalBus: the addressed copies of one
    payload). Returns the message (None if dropped)."""
    if decoded is not None:
        msg = decoded
    else:
        try:
            msg = wire.decode(key, data)
        except wire.WireError as exc:
            stats.dropped[exc.reason] += 1
            log.debug("dropped message on %s: %s", key, exc)
            if exc.header is not None:   # an unusable exchange payload: its round hears that it came
                _call(stats, handlers, key, exc.header)
            return None
    stats.received += 1
    _call(stats, handlers, key, msg)
    return msg


def _call(stats: BusStats, handlers: list[Handler], key: str, msg: wire.Message) -> None:
    for h in handlers:
        try:
            h(key, msg)
        except Exception:  # a role bug must not take the bus down; it is counted and logged
            stats.handler_errors += 1
            log.exception("handler failed on %s", key)


class LocalBus:
    """All roles in one process: FIFO delivery, synchronous, deterministic.

    ``publish`` enqueues; :meth:`drain` delivers until the queue is empty. Subscribers are served in
    subscription order, messages in publication order.
    """

    def __init__(self) -> None:
        self.stats = BusStats()
        self._subs: list[tuple[str, Handler]] = []
        self._queue: deque[tuple[str, bytes]] = deque()
        self.taps: list[Callable[[str, bytes], None]] = []
        self._routes: dict[str, list[Handler]] = {}
        self._types: dict[str, tuple | None] = {}

    def publish(self, key: str, msg: wire.Message) -> None:
        self.publish_raw(key, wire.encode(msg))

    def publish_raw(self, key: str, data: bytes) -> None:
        """Publish already-encoded bytes (used by replay and by hostile-input tests)."""
        self.stats.sent += 1
        self.stats.sent_by_key[key] += 1
        self._queue.append((key, data))

    def subscribe(self, pattern: str, handler: Handler, *, bulk: bool = False) -> None:
        """``handler(key, msg)`` for every message on ``pattern`` (``bulk``: a hint for :class:`ZenohBus`)."""
        self._subs.append((pattern, handler))
        self._routes.clear()

    def drain(self, max_messages: int | None = None) -> int:
        """Deliver queued messages (including those published while delivering). Returns the count."""
        n = 0
        last: tuple = (None, None, None)     # (bytes, (type, owner) of its key, message): one decode per payload
        while self._queue and (max_messages is None or n < max_messages):
            key, data = self._queue.popleft()
            for tap in self.taps:
                tap(key, data)
            handlers = self._routes.get(key)
            if handlers is None:
                handlers = self._routes[key] = [h for p, h in self._subs if key_matches(p, key)]
            if handlers:
                typed = self._typed(key)
                same = data is last[0] and typed is not None and typed == last[1]
                msg = deliver(self.stats, handlers, key, data, last[2] if same else None)
                last = (data, typed, msg) if msg is not None else (None, None, None)
            n += 1
        return n

    def _typed(self, key: str) -> tuple | None:
        """(message type, owner) a key carries, cached; None for a key that carries nothing."""
        t = self._types.get(key, False)
        if t is False:
            try:
                t = wire.expected_type(key)
            except wire.WireError:
                t = None
            self._types[key] = t
        return t

    @property
    def idle(self) -> bool:
        return not self._queue

    def close(self) -> None:
        self._queue.clear()
        self._subs.clear()


# ============================================================================ Zenoh

#: Zenoh ``connect/retry`` of every flocktrack client (see :func:`zenoh_config`)
CLIENT_RETRY = {"period_init_ms": 100, "period_max_ms": 250, "period_increase_factor": 2}


def zenoh_config(connect: str | None = None, listen: str | None = None, mode: str = "client",
                 config_file: str | None = None):
    """A Zenoh config: from a json5 file if given, then mode/endpoints; multicast scouting off
    (endpoints are always explicit in flocktrack)."""
    import json

    import zenoh

    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect.split(",")))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen.split(",")))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if mode == "client" and conf.get_json("connect/retry") == "null":
        # a client that lost its router retries after 0.1 s, then every 0.2–0.25 s (Zenoh's default: 1 s → 4 s),
        # so that after a router restart the flock is back within ~0.3 s of the router: capping the period at
        # 0.25 s instead of 1 s took the router-restart recovery from 1.63 to 1.31 s (median, 1 s of it the
        # outage; docs/reliability.md), for ≤ 4 dials a second per client while the router is down (a config
        # file that sets its own retry, e.g. broker_cfg/mesh/client.json5, keeps it)
        conf.insert_json5("connect/retry", json.dumps(CLIENT_RETRY))
    return conf


#: put into a bus's queue to wake its poll (see :func:`wake_all`)
_WAKE = ("", b"", ("wake", None))
HELD_PER_KEY = 16   #: addressed payloads held per key at most (a receiver that never comes: oldest dropped)
_LIVE: "weakref.WeakSet[ZenohBus]" = weakref.WeakSet()


def wake_all() -> None:
    """Wake every ZenohBus's poll in this process now — call it from a signal handler that asks the loop
    to stop. CPython 3.11's ``SimpleQueue.get(timeout=…)`` can stay blocked after a signal interrupts it
    until an item arrives (seen: a dashboard that got SIGTERM after the run's last message never left its
    poll); ``SimpleQueue.put`` is reentrant, safe in a signal handler."""
    for bus in list(_LIVE):
        bus._enqueue(_WAKE)


class ZenohBus:
    """One role per OS process over Eclipse Zenoh, on the key space ``ft/<run>/…``.

    Zenoh delivers samples on its own threads; the callbacks only enqueue ``(key, bytes, handler)``.
    The role's thread calls :meth:`poll`, which decodes and validates each message through the same
    :func:`deliver` as :class:`LocalBus` — so roles never run concurrently with themselves and a bad
    message is dropped and counted exactly as in-process. A role's bulk input (``subscribe(…, bulk=True)``:
    a sensor's inbox) skips the callback: its samples stay in a Zenoh channel until :meth:`poll` takes them
    (:mod:`agent.inbox`).

    Membership: :meth:`declare_token` makes this process visible under ``ft/<run>/alive/<name>``;
    :meth:`watch_members` reports tokens appearing and disappearing (a killed process's token
    disappears when the router's lease on its session expires).
    """

    def __init__(self, run: str, connect: str | None = None, config_file: str | None = None,
                 mode: str = "client", session=None):
        import queue

        import zenoh

        self._zenoh = zenoh
        zenoh.init_log_from_env_or("error")   # Zenoh's own warnings (RUST_LOG=info for more) in the process log
        self.prefix = f"ft/{run}/"
        self.session = session if session is not None else zenoh.open(zenoh_config(connect, None, mode, config_file))
        self._own_session = session is None
        self.stats = BusStats()
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._pubs: dict[str, object] = {}
        self._matched: dict[str, bool] = {}        # addressed keys: does the receiver's subscription reach us?
        self._held: dict[str, deque] = {}          # addressed payloads put while it did not (in order)
        self._decls: list = []
        self._writes: tuple[str, ...] | None = None   # the declared writes (restrict_writes), None: unchecked
        self._undeclared: set[str] = set()
        self._inbox: Inbox | None = None          # the bulk subscription (agent/inbox.py)
        self._inbox_to: list | tuple = []          # its handlers (or ("raw", callback))
        self._closed = False
        _LIVE.add(self)

    # ------------------------------------------------------------------ Bus protocol
    def publish(self, key: str, msg: wire.Message) -> None:
        self.publish_raw(key, wire.encode(msg))

    def publish_raw(self, key: str, data: bytes) -> None:
        pub = self._publisher(key)
        if not self._matched.get(key, True) and not self._now_matched(key, pub):
            self._hold(key, data)
            return
        pub.put(data)
        self.stats.sent += 1
        self.stats.sent_by_key[key] += 1

    def _publisher(self, key: str):
        pub = self._pubs.get(key)
        if pub is None:
            z = self._zenoh
            pub = self._pubs[key] = self.session.declare_publisher(
                self.prefix + key, congestion_control=z.CongestionControl.BLOCK)
            if wire.addressed(key):
                self._watch_matching(key, pub)
            if self._writes is not None and not any(key_matches(w, key) for w in self._writes):
                self._undeclared.add(key)
                log.warning("put on %s, which this node does not declare among its writes (%s): counted; a "
                            "secure run's router denies it", key, ", ".join(self._writes))
        if key in self._undeclared:
            self.stats.undeclared[key] += 1
        return pub

    def restrict_writes(self, writes) -> None:
        """The keys this node declares it puts (:mod:`agent.ports`). A put outside them is still sent — in a
        secure run the router's access-control list is what denies it — but counted by key
        (``stats.undeclared``) and logged once per key."""
        self._writes = tuple(writes)

    # ------------------------------------------------------------------ addressed payloads: held until matched
    # A put is dropped — at the publisher, or at a router that has not heard of the subscription yet —
    # when the receiver's subscription has not reached this session's router. Observers' keys have the
    # recorder and the world, whose subscriptions precede everyone's first put, but an addressed key
    # (``agent/<i>/to/<j>/xchg``) has one subscriber, j itself: in a mesh of routers (or when j has just
    # restarted) j's declaration can still be on its way when i puts its first payload to j, and lockstep
    # would then wait out a deadline for a payload that was never sent. So an addressed key's payloads
    # are held, in order, until its publisher matches a subscriber (Zenoh's matching listener), then sent.

    def _watch_matching(self, key: str, pub) -> None:
        self._matched[key] = False
        enqueue = self._enqueue

        def on_status(status) -> None:
            enqueue((key, bool(status.matching), ("matched", None)))

        self._decls.append(pub.declare_matching_listener(self._in_order(on_status)))

    def _now_matched(self, key: str, pub) -> bool:
        """Held keys ask Zenoh once more before holding (a listener event may still be queued)."""
        if pub.matching_status.matching:
            self._on_matching(key, True)
            return True
        return False

    def _hold(self, key: str, data: bytes) -> None:
        q = self._held.setdefault(key, deque(maxlen=HELD_PER_KEY))
        if len(q) == q.maxlen:
            self.stats.dropped["unmatched"] += 1     # the oldest held payload gives way
        q.append(data)
        self.stats.held += 1

    def _on_matching(self, key: str, matching: bool) -> None:
        self._matched[key] = matching
        held = self._held.pop(key, None) if matching else None
        if held:
            pub = self._pubs[key]
            for data in held:
                pub.put(data)
                self.stats.sent += 1
                self.stats.sent_by_key[key] += 1

    def await_subscriber(self, key: str, timeout_s: float) -> bool:
        """Wait until someone subscribes to what we would put on ``key`` (a put before the routes reach
        us is dropped at the publisher); False after ``timeout_s`` without one."""
        pub, end = self._publisher(key), time.monotonic() + timeout_s
        while not pub.matching_status.matching:
            if time.monotonic() > end:
                return False
            time.sleep(0.02)
        return True

    def subscribe(self, pattern: str, handler: Handler, *, bulk: bool = False) -> None:
        """``handler(key, msg)`` on the role's thread (:meth:`poll`) for every valid message on ``pattern``.
        ``bulk``: this subscription carries most of what the role receives (a sensor's inbox) — its samples
        stay in Zenoh until :meth:`poll` takes them, no Python on Zenoh's thread (:mod:`agent.inbox`). One per
        bus, on a pattern with a wildcard chunk; any other is an ordinary subscription."""
        self._subscribe(pattern, [handler], bulk)     # (deliver's list, made once, not per sample)

    def subscribe_raw(self, pattern: str, callback: Callable[[str, bytes], None], *, bulk: bool = False) -> None:
        """Undecoded samples (recorder), delivered through :meth:`poll` like the others."""
        self._subscribe(pattern, ("raw", callback), bulk)

    def _subscribe(self, pattern: str, target: list | tuple, bulk: bool) -> None:
        if bulk and self._inbox is None and "*" in pattern:
            self._inbox = Inbox(self.session, self._zenoh, self.prefix, pattern)
            self._inbox_to = target
            return
        n = len(self.prefix)
        enqueue = self._enqueue

        def on_sample(sample) -> None:
            enqueue((str(sample.key_expr)[n:], sample.payload.to_bytes(), target))

        self._decls.append(self.session.declare_subscriber(self.prefix + pattern, self._in_order(on_sample)))

    def _enqueue(self, item: tuple) -> None:
        """Queue ``item`` for :meth:`poll` (from Zenoh's thread, or a signal handler: ``SimpleQueue.put`` is
        reentrant) and wake the role's thread if it waits in the inbox."""
        self._q.put(item)
        inbox = self._inbox
        if inbox is not None and inbox.blocked:
            inbox.blocked = False      # (once: the samples queued after this one are seen with it)
            inbox.ring()

    def _in_order(self, callback):
        """``callback`` run on Zenoh's receiving thread (``indirect=False``): zenoh-python's default runs
        each subscriber's Python callback on a thread of its own, so samples of two subscriptions reach
        the queue out of the order they arrived in (measured: ~1 in 400 of alternating puts on two keys
        swapped). The world's ``event`` k then overtook its ``tick`` k, a fusion's ``meas`` its ``tick``,
        a member's liveliness its data. Direct callbacks keep the link's order — the callbacks only enqueue."""
        return self._zenoh.handlers.Callback(callback, indirect=False)

    def poll(self, timeout: float = 0.05, max_messages: int = 10_000) -> int:
        """Deliver queued messages on the caller's thread; wait up to ``timeout`` for the first. Returns how
        many were delivered (0: the timeout passed, or :func:`wake_all` woke it)."""
        inbox = self._inbox
        if inbox is None:
            return self._poll_queue(timeout, max_messages)[0]
        end = 0.0
        while True:
            n, woken = self._poll_queue(0.0, max_messages)
            if woken or n >= max_messages:
                return n
            while n < max_messages:
                got = inbox.take()
                if got is None:
                    break
                n += self._take_inbox(got, inbox.wake)
            if n or timeout <= 0:
                return n
            now = time.monotonic()
            end = end or now + timeout
            if now >= end:
                return 0
            inbox.blocked = True          # before the last look at the queue: a sample queued after it rings
            if not self._q.empty():
                inbox.blocked = False
                continue
            n = self._take_inbox(inbox.wait(end), inbox.wake)
            if n:                         # (and whatever came with it)
                return n if n >= max_messages else n + self.poll(0.0, max_messages - n)

    def _take_inbox(self, got: tuple[str, bytes], wake: str) -> int:
        """Deliver one sample of the inbox (1), or skip a doorbell (0)."""
        key, data = got
        if key == wake and not data:      # (a put with bytes on it is a sender's: decoded, dropped, counted)
            return 0
        self._dispatch(key, data, self._inbox_to)
        return 1

    def _poll_queue(self, timeout: float, max_messages: int) -> tuple[int, bool]:
        """Deliver what the callbacks queued; wait up to ``timeout`` for the first. (count, woken by
        :func:`wake_all`)."""
        n = 0
        try:
            item = self._q.get(timeout=timeout) if timeout > 0 else self._q.get_nowait()
        except queue.Empty:
            return 0, False
        while item is not _WAKE:
            key, data, handler = item
            if type(handler) is list:
                deliver(self.stats, handler, key, data)
            elif handler[0] == "matched":      # a held key's publisher matched (or lost) its subscriber
                self._on_matching(key, data)
                n -= 1
            else:
                self._dispatch(key, data, handler)
            n += 1
            if n >= max_messages:
                return n, False
            try:
                item = self._q.get_nowait()
            except queue.Empty:
                return n, False
        return n, True

    def _dispatch(self, key: str, data: bytes, target: list | tuple) -> None:
        """One sample to its subscription's handlers (decoded) or callback (``("raw" | "member", cb)``)."""
        if type(target) is list:
            deliver(self.stats, target, key, data)
            return
        try:
            target[1](key, data)
        except Exception:
            self.stats.handler_errors += 1
            log.exception("%s callback failed on %s", target[0], key)

    # ------------------------------------------------------------------ membership
    def declare_token(self, name: str):
        tok = self.session.liveliness().declare_token(self.prefix + "alive/" + name)
        self._decls.append(tok)
        return tok

    def watch_members(self, callback: Callable[[str, bool], None]) -> None:
        """``callback(name, alive)`` for every token under ``alive/**`` (present ones first),
        delivered through :meth:`poll` on the role's thread."""
        n = len(self.prefix + "alive/")
        z = self._zenoh
        enqueue = self._enqueue

        def on_token(sample) -> None:
            enqueue((str(sample.key_expr)[n:], sample.kind == z.SampleKind.PUT, ("member", callback)))

        self._decls.append(self.session.liveliness().declare_subscriber(self.prefix + "alive/**", self._in_order(on_token),
                                                                        history=True))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._inbox is not None:
            self._inbox.close()
        for d in reversed(self._decls):
            try:
                d.undeclare()
            except Exception:  # already gone with the session
                pass
        for p in self._pubs.values():
            try:
                p.undeclare()
            except Exception:
                pass
        if self._own_session:
            self.session.close()
