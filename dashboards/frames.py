"""One encoding per frame, whatever the number of tabs.

Viser sends every tab the same broadcast stream: each connection's producer takes the next window of
messages from the shared buffer and encodes it (msgpack of the messages, zstd, the raw array buffers
appended) on its own — five tabs, five encodings of the same window, about a quarter of the dashboard's CPU
with five viewers. Tabs that keep up take the same windows (the same message objects, in the same order),
so :class:`FrameCache` keeps the last few encoded windows and hands the same bytes to every connection whose
window is one of them; a tab that lags (or a new tab reading the backlog) forms other windows and gets them
encoded for itself. Per-tab messages (a tab's own overlays and folders) are never shared.

:func:`install` puts the sharing producer in place of Viser's, for every server of the process, before any
tab connects. It needs Viser's producer to look as expected (its parameters and its binary-buffer helper);
otherwise Viser's own stays and :func:`installed` says so. The frame layout is Viser's (the page decodes it):
``[u64 msgpack size][u64 compressed size][zstd msgpack][padding][8-byte aligned raw buffers]``.
"""

from __future__ import annotations

import inspect
import logging
import threading
import time
import weakref
from collections import deque

log = logging.getLogger(__name__)

_EXPECTED = ("websocket", "buffer", "client_id", "backlog_done_message")
_lock = threading.Lock()
_state: dict = {"installed": False, "original": None}
_local = threading.local()


class FrameCache:
    """The last ``size`` encoded windows of one buffer: ``frame(window)`` returns the bytes of a window made
    of the same message objects as a cached one, else encodes it (``encoded`` / ``shared`` count both)."""

    def __init__(self, size: int = 8):
        self._entries: deque[tuple[tuple, bytes]] = deque(maxlen=size)
        self.encoded = 0
        self.shared = 0

    def frame(self, window) -> bytes:
        for messages, data in self._entries:
            if len(messages) == len(window) and all(a is b for a, b in zip(messages, window)):
                self.shared += 1
                return data
        data = encode_window(window)
        self._entries.append((tuple(window), data))
        self.encoded += 1
        return data


def encode_window(window) -> bytes:
    """One window of Viser messages as the page reads it (the layout in this module's docstring)."""
    import msgspec
    import zstandard
    from viser.infra import _infra

    buffers: list = []
    messages = tuple(m.as_serializable_dict(buffers) for m in window)
    inner = msgspec.msgpack.encode({"messages": messages, "timestampSec": time.perf_counter(),
                                    "binaryBufferLengths": tuple(b.nbytes for b in buffers)})
    zstd = getattr(_local, "zstd", None)
    if zstd is None:   # one compressor per thread (each server's event loop encodes on its own thread)
        zstd = _local.zstd = zstandard.ZstdCompressor(level=1)
    packed = zstd.compress(inner)
    parts: list = [len(inner).to_bytes(8, "little"), len(packed).to_bytes(8, "little"), packed]
    _infra._append_aligned_buffers(parts, buffers, 16 + len(packed))
    return b"".join(parts)


_caches: weakref.WeakSet[FrameCache] = weakref.WeakSet()   # every live cache, for stats()


def cache_of(buffer) -> FrameCache | None:
    """The frame cache of a broadcast (persistent) buffer, kept on the buffer (it goes with its server);
    None for a tab's own buffer (never shared)."""
    if not getattr(buffer, "persistent_messages", False):
        return None
    with _lock:
        cache = getattr(buffer, "_shared_frames", None)
        if cache is None:
            cache = FrameCache()
            buffer._shared_frames = cache
            _caches.add(cache)
        return cache


async def _producer(websocket, buffer, client_id, backlog_done_message=None) -> None:
    """Viser's per-connection producer, with the encoding shared through the buffer's :class:`FrameCache`."""
    windows = buffer.window_generator(client_id, backlog_done_message=backlog_done_message)
    cache = cache_of(buffer)
    try:
        while not buffer.done:
            try:
                window = await windows.__anext__()
            except StopAsyncIteration:
                break
            await websocket.send(cache.frame(window) if cache is not None else encode_window(window))
    finally:
        await windows.aclose()   # run the window generator's cleanup now (it releases the buffer's cursor)


def install() -> bool:
    """Share the encoding of broadcast frames among this process's tabs (idempotent). False, with one log
    line, when this Viser's producer is not the one this module replaces: Viser's own then stays."""
    with _lock:
        if _state["installed"]:
            return True
        try:
            from viser.infra import _infra

            params = tuple(inspect.signature(_infra._message_producer).parameters)
            helper = callable(getattr(_infra, "_append_aligned_buffers", None))
        except Exception:  # noqa: BLE001 — any other Viser: keep its producer
            params, helper = (), False
        if params != _EXPECTED or not helper:
            log.info("frames: this Viser's producer is not the expected one; each tab encodes its own frames")
            return False
        _state["original"] = _infra._message_producer
        _infra._message_producer = _producer
        _state["installed"] = True
        return True


def installed() -> bool:
    return bool(_state["installed"])


def stats() -> dict:
    """Frames encoded and frames handed out again, over the process's broadcast buffers."""
    with _lock:
        caches = list(_caches)
    return {"frames_encoded": sum(c.encoded for c in caches), "frames_shared": sum(c.shared for c in caches),
            "shared_encoding": installed()}
