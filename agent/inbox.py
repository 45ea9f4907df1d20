"""A role's bulk input kept inside Zenoh until the role's thread takes it: no Python on Zenoh's thread.

A subscription with a Python callback makes Zenoh's worker take the GIL for every sample, build the Python
sample and run the callback, which hands it to the role's thread through a queue: two threads and the GIL per
sample. A sensor's own inbox (``agent/*/to/<i>/xchg``) is ~90 % of what it receives — rounds × degree payloads
a tick — so :class:`Inbox` declares that one subscription with a Zenoh FIFO channel instead: Zenoh's worker
pushes the sample in Rust, and the role's thread, blocked in the channel's ``recv`` (the GIL released), takes
it itself.

A channel cannot wait with a timeout, nor beside another queue, so whatever else must wake the role's thread
rings a doorbell: an empty session-local put on the inbox's *wake key* — its pattern with the first wildcard
chunk named ``wake`` (``agent/wake/to/3/xchg``), which no sender has — that lands in the same channel and is
skipped (a put with bytes on that key is a sender's, and is decoded, dropped and counted like any bad key):

* the bus's other subscriptions' callbacks ring it after queueing a sample, while the role's thread is
  blocked (:attr:`Inbox.blocked`: set before the last look at their queue, so a sample is never left behind);
* :class:`Alarm` rings it when a poll's timeout is up and the thread still waits (one thread that sleeps until
  the earliest deadline armed; a later deadline does not wake it; the deadline of a poll that a sample has ended
  since rings nothing);
* :func:`agent.bus.wake_all` rings it from a signal handler.

Measured: N = 10 lockstep, all processes, 26.4 / 26.5 → 24.7 / 24.9 ms CPU a tick (the sensors 2.1 → 1.9 ms
each), 73 → 78 ticks/s.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

#: the channel's capacity: a full channel would block Zenoh's worker (which also carries this process's
#: puts), so it is never expected to fill — a sensor holds a few ticks of payloads at most
CAPACITY = 1 << 16
WAKE_CHUNK = "wake"


def wake_key(pattern: str) -> str | None:
    """The doorbell's key of an inbox on ``pattern``: its first wildcard chunk named ``wake``; None when the
    pattern has no wildcard chunk (it then cannot be an inbox)."""
    chunks = pattern.split("/")
    for i, c in enumerate(chunks):
        if c in ("*", "**"):
            return "/".join(chunks[:i] + [WAKE_CHUNK] + chunks[i + 1:])
    return None


class Alarm:
    """Rings ``ring()`` once the deadline armed last is up. Arming a later deadline than the one it sleeps
    for does not wake its thread (it wakes at the earlier one, finds the new one and sleeps on), so a role that
    polls every millisecond with a 50 ms timeout costs it one wake per 50 ms, not one per poll."""

    def __init__(self, ring: Callable[[], None], clock=time.monotonic):
        self.ring, self.clock = ring, clock
        self._at = math.inf
        self._cond = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="bus-alarm", daemon=True)
        self._thread.start()

    def arm(self, at: float) -> None:
        """Ring at ``at`` (``clock`` time), instead of the deadline armed before."""
        with self._cond:
            if at < self._at:
                self._cond.notify()
            self._at = at

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._closed:
                    wait = self._at - self.clock()
                    if wait <= 0:
                        break
                    self._cond.wait(None if wait == math.inf else wait)
                if self._closed:
                    return
                self._at = math.inf
            try:
                self.ring()     # (outside the lock: a role's thread arming meanwhile does not wait on a put)
            except Exception:   # the session closed under us: nothing left to wake
                return


class Inbox:
    """One subscription's samples in a Zenoh FIFO channel; see the module doc. ``prefix`` is cut from every
    key (the bus's run prefix)."""

    def __init__(self, session, zenoh, prefix: str, pattern: str):
        self.wake = wake_key(pattern)
        if self.wake is None:
            raise ValueError(f"an inbox needs a wildcard chunk in its pattern: {pattern!r}")
        self._n = len(prefix)
        self._full_wake = prefix + self.wake
        self._local = zenoh.Locality.SESSION_LOCAL
        self._session = session
        self.sub = session.declare_subscriber(prefix + pattern, zenoh.handlers.FifoChannel(CAPACITY))
        self.blocked = False        #: the role's thread is (about to be) blocked in the channel
        self.alarm = Alarm(self._ring_if_blocked)

    def ring(self) -> None:
        """Wake the role's thread (from any thread, a signal handler included)."""
        self._session.put(self._full_wake, b"", allowed_destination=self._local)

    def _ring_if_blocked(self) -> None:
        """The alarm's ring: only while the role's thread waits in the channel. A poll that a sample ended before
        its deadline leaves that deadline armed; ringing it would cost a put, and a wake of the next wait, for
        nothing. (The thread sets :attr:`blocked` before it arms its own deadline, so the deadline of a wait
        under way always finds it set.)"""
        if self.blocked:
            self.ring()

    def take(self) -> tuple[str, bytes] | None:
        """The next sample (key relative to the prefix, bytes) without waiting; None when empty. A doorbell
        comes back as ``(wake key, b"")``."""
        s = self.sub.try_recv()
        return None if s is None else (str(s.key_expr)[self._n:], s.payload.to_bytes())

    def wait(self, until: float) -> tuple[str, bytes]:
        """Block until a sample or a doorbell; the alarm rings at ``until`` (:attr:`blocked` is set by the
        caller before its last look at its other queue)."""
        self.alarm.arm(until)
        try:
            s = self.sub.recv()
        finally:
            self.blocked = False
        return str(s.key_expr)[self._n:], s.payload.to_bytes()

    def close(self) -> None:
        self.alarm.close()
        try:
            self.sub.undeclare()
        except Exception:   # already gone with the session
            pass
