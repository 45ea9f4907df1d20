"""Viser's message buffers, safe to push to from any thread.

The dashboard updates its page from its own loop thread, and Viser runs GUI callbacks on a thread pool; both
push messages into Viser's buffers. A push sets the buffer's ``asyncio.Event`` twice: once directly, from
the pushing thread (so that synchronous code sees it set at once), and once on the server's event loop
through ``call_soon_threadsafe`` (to wake the producers waiting on it). The direct ``Event.set()`` walks the
event's waiters from the wrong thread while the loop adds and removes them: under load it raises "deque
mutated during iteration" in the pushing thread (a dashboard callback failed on it in a fresh-clone test run),
and a future completed off its loop is not thread-safe either.

:class:`LoopSafeEvent` has the event's interface (``set``, ``clear``, ``is_set``, ``wait``); set from a thread
that is not running its waiters' loop, it only raises the flag, and the loop's own ``set`` (the
``call_soon_threadsafe`` that every push schedules) wakes the waiters. Its waiters are touched on the loop
thread only. :func:`install` makes every buffer Viser creates afterwards use it for its message event
(idempotent); with a Viser whose buffers do not look as expected it changes nothing and says so once.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import threading

log = logging.getLogger(__name__)

_lock = threading.Lock()
_state: dict = {"installed": False}


class LoopSafeEvent:
    """An ``asyncio.Event`` whose ``set`` may be called from any thread: only a ``set`` made on the loop that
    its waiters wait on wakes them; from elsewhere it raises the flag and leaves the waking to that loop."""

    def __init__(self) -> None:
        self._flag = False
        self._waiters: list[asyncio.Future] = []   # (touched on the waiters' loop thread only)

    def is_set(self) -> bool:
        return self._flag

    def clear(self) -> None:
        self._flag = False

    def set(self) -> None:
        self._flag = True
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return          # another thread, no loop: the flag is up, the waiters' loop will wake them
        for fut in self._waiters:
            if fut.get_loop() is loop and not fut.done():
                fut.set_result(True)

    async def wait(self) -> bool:
        if self._flag:
            return True
        fut = asyncio.get_running_loop().create_future()
        self._waiters.append(fut)
        try:
            await fut
            return True
        finally:
            self._waiters.remove(fut)


def install() -> bool:
    """Make the message buffers of every Viser server created from now on use :class:`LoopSafeEvent`
    (idempotent). False, with one log line, when this Viser's buffer is not the one expected."""
    with _lock:
        if _state["installed"]:
            return True
        try:
            from viser.infra import _async_message_buffer, _infra

            base = _infra.AsyncMessageBuffer
            fields = {f.name for f in dataclasses.fields(base)}
            expected = base is _async_message_buffer.AsyncMessageBuffer and "message_event" in fields
        except Exception:  # noqa: BLE001 — any other Viser: leave its buffers as they are
            expected = False
        if not expected:
            log.info("loop_safe: this Viser's message buffer is not the expected one; it is left as it is")
            return False

        @dataclasses.dataclass
        class LoopSafeMessageBuffer(base):
            """Viser's message buffer with a message event that any thread may set."""

            message_event: LoopSafeEvent = dataclasses.field(default_factory=LoopSafeEvent)

        _infra.AsyncMessageBuffer = LoopSafeMessageBuffer
        _state["installed"] = True
        return True


def installed() -> bool:
    return bool(_state["installed"])
