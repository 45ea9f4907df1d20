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
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from . import wire

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
    received: int = 0
    dropped: Counter = field(default_factory=Counter)
    handler_errors: int = 0

    def as_dict(self) -> dict:
        return {"sent": self.sent, "received": self.received, "dropped": dict(self.dropped),
                "handler_errors": self.handler_errors}


class Bus(Protocol):
    """What a role needs from a transport."""

    stats: BusStats

    def publish(self, key: str, msg: wire.Message) -> None: ...

    def subscribe(self, pattern: str, handler: Handler) -> None: ...

    def close(self) -> None: ...


def deliver(stats: BusStats, handlers: list[Handler], key: str, data: bytes) -> None:
    """Decode ``data`` once, validate, and hand it to ``handlers``; count and drop anything bad.
    Shared by both buses so their receive paths are identical."""
    try:
        msg = wire.decode(key, data)
    except wire.WireError as exc:
        stats.dropped[exc.reason] += 1
        log.debug("dropped message on %s: %s", key, exc)
        return
    stats.received += 1
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

    def publish(self, key: str, msg: wire.Message) -> None:
        self.publish_raw(key, wire.encode(msg))

    def publish_raw(self, key: str, data: bytes) -> None:
        """Publish already-encoded bytes (used by replay and by hostile-input tests)."""
        self.stats.sent += 1
        self._queue.append((key, data))

    def subscribe(self, pattern: str, handler: Handler) -> None:
        self._subs.append((pattern, handler))
        self._routes.clear()

    def drain(self, max_messages: int | None = None) -> int:
        """Deliver queued messages (including those published while delivering). Returns the count."""
        n = 0
        while self._queue and (max_messages is None or n < max_messages):
            key, data = self._queue.popleft()
            for tap in self.taps:
                tap(key, data)
            handlers = self._routes.get(key)
            if handlers is None:
                handlers = self._routes[key] = [h for p, h in self._subs if key_matches(p, key)]
            if handlers:
                deliver(self.stats, handlers, key, data)
            n += 1
        return n

    @property
    def idle(self) -> bool:
        return not self._queue

    def close(self) -> None:
        self._queue.clear()
        self._subs.clear()
