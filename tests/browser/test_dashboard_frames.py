"""One encoding per broadcast frame (dashboards/frames.py): tabs that keep up get the same bytes, encoded
once; every tab still reads the same messages in the same order as it would from Viser's own producer, and
arrays travel as raw buffers after the compressed messages."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from dashboards import frames
from dashboards.probe import decode_frame, report_camera

viser = pytest.importorskip("viser")


def _reader(ws, out: list, stop: threading.Event) -> None:
    while not stop.is_set():
        try:
            out.append(ws.recv(timeout=0.2))
        except TimeoutError:
            continue
        except Exception:  # closed
            return


def _messages(raw: list[bytes], kind: str) -> list:
    """The messages of type ``kind`` on the target in a tab's frames, in order (as decoded)."""
    return [m for f in list(raw) for m in decode_frame(f) if m.get("type") == kind and m.get("name") == "/flock/target"]


def _open_tabs(server, n: int, stop: threading.Event):
    """``n`` tabs on ``server``, each with a reader thread: (sockets, the frames each received, readers)."""
    from websockets.sync.client import connect

    tabs, received, readers = [], [], []
    for _ in range(n):
        ws = connect(f"ws://127.0.0.1:{server.get_port()}/", subprotocols=[f"viser-v{viser.__version__}"],
                     max_size=None, open_timeout=30)
        report_camera(ws)
        out: list[bytes] = []
        t = threading.Thread(target=_reader, args=(ws, out, stop), daemon=True)
        t.start()
        tabs.append(ws)
        received.append(out)
        readers.append(t)
    deadline = time.monotonic() + 20
    while len(server.get_clients()) < n and time.monotonic() < deadline:
        time.sleep(0.05)
    assert len(server.get_clients()) == n
    return tabs, received, readers


def _close_tabs(server, tabs, readers, stop: threading.Event) -> None:
    stop.set()
    for ws in tabs:
        ws.close()
    for t in readers:
        t.join(5)
    server.stop()


def test_tabs_that_keep_up_share_one_encoding_and_read_the_same_stream():
    assert frames.install() and frames.installed()
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    stop = threading.Event()
    tabs, readers = [], []
    try:
        tabs, received, readers = _open_tabs(server, 3, stop)
        time.sleep(0.5)                              # the backlog read by each
        before = frames.stats()
        points = np.arange(300, dtype=np.float32).reshape(100, 3)
        target = server.scene.add_icosphere("/flock/target", radius=0.3, position=(-1.0, 0.0, 0.0))
        for i in range(40):                         # a display clock's worth of frames
            target.position = (float(i), 0.0, 0.0)
            if i % 10 == 0:
                server.scene.add_point_cloud("/flock/cloud", points=points + i, colors=(255, 0, 0), point_size=0.1,
                                        precision="float32")
            time.sleep(0.05)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(
                _last_x(r) != 39.0 for r in received):
            time.sleep(0.1)
        after = frames.stats()
    finally:
        _close_tabs(server, tabs, readers, stop)

    # every tab read the same updates, in the same order, ending at the last one
    streams = [[m["position"] for m in _messages(r, "SetPositionMessage")] for r in received]
    assert streams[0] and streams[0][-1][0] == 39.0
    assert streams[1] == streams[0] and streams[2] == streams[0]
    # live frames were encoded once and handed to the other tabs: with three tabs in step, well under
    # one encoding per frame sent
    encoded = after["frames_encoded"] - before["frames_encoded"]
    shared = after["frames_shared"] - before["frames_shared"]
    assert encoded > 0 and shared >= encoded, (encoded, shared)
    # a point cloud's array rides as raw bytes after the compressed messages, 8-byte aligned
    clouds = [f for f in received[0] if any(m.get("type") == "PointCloudMessage" for m in decode_frame(f))]
    raw = (points + 10).tobytes()
    at = [f.find(raw) for f in clouds if raw in f]
    assert at and all(i % 8 == 0 for i in at), at


def _last_x(raw: list[bytes]) -> float | None:
    m = _messages(raw, "SetPositionMessage")
    return m[-1]["position"][0] if m else None


def test_a_tab_own_buffer_is_never_shared():
    class Own:  # a tab's own buffer: not persistent
        persistent_messages = False

    class Broadcast:
        persistent_messages = True

    assert frames.cache_of(Own()) is None
    b = Broadcast()
    assert frames.cache_of(b) is frames.cache_of(b) is not None


def test_updates_pushed_from_several_threads_at_once_reach_every_tab():
    """The page is updated from the dashboard's loop thread and from Viser's callback threads at once: every
    buffer's message event is one that other threads may set (dashboards/loop_safe.py), no push raises, and
    each tab ends on each thread's last update."""
    from dashboards import loop_safe
    from dashboards.loop_safe import LoopSafeEvent

    assert loop_safe.install() and loop_safe.installed()
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    stop = threading.Event()
    tabs, readers, errors = [], [], []
    try:
        tabs, received, readers = _open_tabs(server, 2, stop)
        assert isinstance(server._websock_server._broadcast_buffer.message_event, LoopSafeEvent)
        nodes = [server.scene.add_icosphere(f"/flock/s{i}", radius=0.1) for i in range(3)]

        def push(node) -> None:
            try:
                for x in range(300):
                    node.position = (float(x), 0.0, 0.0)
            except Exception as exc:  # noqa: BLE001 — what the test looks for
                errors.append(exc)

        pushers = [threading.Thread(target=push, args=(node,)) for node in nodes]
        for p in pushers:
            p.start()
        for p in pushers:
            p.join(60)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(_last_positions(r) != {i: 299.0 for i in range(3)}
                                                  for r in received):
            time.sleep(0.1)
    finally:
        _close_tabs(server, tabs, readers, stop)
    assert errors == []
    assert all(_last_positions(r) == {i: 299.0 for i in range(3)} for r in received)


def _last_positions(raw: list[bytes]) -> dict[int, float]:
    """The last x position each sensor node took in a tab's frames."""
    out: dict[int, float] = {}
    for f in list(raw):
        for m in decode_frame(f):
            name = str(m.get("name", ""))
            if m.get("type") == "SetPositionMessage" and name.startswith("/flock/s"):
                out[int(name[len("/flock/s"):])] = m["position"][0]
    return out
