"""Hand-written browser tabs for the dashboard's tests: websocket clients that speak the page's own protocol
(msgpack over Viser's websocket, the page's subprotocol), read what the server sends them (the widget ids
among it) and send what a page — or someone pretending to be one — would."""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager

import msgspec


def _decode_frame(data: bytes) -> list[dict]:
    """The messages of one server frame (Viser's wire format: sizes, zstd msgpack, raw buffers)."""
    import zstandard

    inner = int.from_bytes(data[:8], "little")
    n = int.from_bytes(data[8:16], "little")
    raw = zstandard.ZstdDecompressor().decompress(data[16:16 + n], max_output_size=inner)
    return list(msgspec.msgpack.decode(raw).get("messages", ()))


class Tab:
    """A tab on the dashboard at ``port`` whose websocket path is ``path`` ("/" a viewer's,
    "/operator/<token>" an operator's). ``read``: a thread reads every frame (``frames``, ``nbytes``) and
    keeps the ids of the widgets they create (``uuids``) — what a page learns of the GUI."""

    def __init__(self, port: int, path: str = "/", *, read: bool = True, camera: bool = True):
        import viser
        from websockets.sync.client import connect

        self.ws = connect(f"ws://127.0.0.1:{port}{path}", subprotocols=[f"viser-v{viser.__version__}"],
                          max_size=None, open_timeout=30)
        self.uuids: list[str] = []
        self.widgets: dict[str, dict] = {}     #: uuid → the message that created it (type, props)
        self.visible: dict[str, bool] = {}     #: uuid → whether the widget shows, as the server last said
        self.frames = self.nbytes = 0
        self.closed = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True) if read else None
        if self._reader:
            self._reader.start()
        if camera:
            try:
                report_camera(self.ws)
            except Exception:  # refused at once (the dashboard's tab cap)
                self.closed.set()

    def _read(self) -> None:
        seen = set()
        try:
            for data in self.ws:
                self.frames += 1
                self.nbytes += len(data)
                for m in _decode_frame(data):
                    uuid = m.get("uuid") if isinstance(m, dict) else None
                    if isinstance(uuid, str) and uuid not in seen:
                        seen.add(uuid)
                        self.uuids.append(uuid)
                        self.widgets[uuid] = m
                        self.visible[uuid] = (m.get("props") or {}).get("visible", True) is not False
                    elif isinstance(uuid, str) and m.get("type") == "GuiUpdateMessage" \
                            and "visible" in (m.get("updates") or {}):
                        self.visible[uuid] = bool(m["updates"]["visible"])
        except Exception:  # closed (by us, or by the server)
            pass
        finally:
            self.closed.set()

    def find(self, kind: str, option: str | None = None, label: str | None = None) -> str | None:
        """The id of a widget this tab was sent: of message type ``kind`` (e.g. "GuiButtonGroupMessage"), with
        ``option`` among its options or ``label`` as its label."""
        for uuid, m in list(self.widgets.items()):
            props = m.get("props") or {}
            if m.get("type") == kind and (option is None or option in (props.get("options") or ())) \
                    and (label is None or props.get("label") == label):
                return uuid
        return None

    def shown(self, kind: str, option: str | None = None, label: str | None = None) -> str | None:
        """:meth:`find`, only once the server has shown the widget (an operator's folders show when the
        panel is whole and the tab is an operator)."""
        uuid = self.find(kind, option=option, label=label)
        return uuid if uuid is not None and self.visible.get(uuid, True) else None

    def send(self, message: dict) -> bool:
        """Send one message (False: the connection is closed)."""
        return self.send_raw(msgspec.msgpack.encode(message))

    def send_raw(self, data) -> bool:
        try:
            self.ws.send(data)
            return True
        except Exception:
            return False

    def press(self, uuid: str, value=True) -> bool:
        return press(self.ws, uuid, value)

    def close(self) -> None:
        self.ws.close()


def report_camera(ws) -> None:
    """Viser counts a tab as connected once it reports its camera."""
    ws.send(msgspec.msgpack.encode({"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0],
                                    "position": [0.0, -30.0, 20.0], "fov": 1.0, "near": 0.01, "far": 1000.0,
                                    "image_height": 800, "image_width": 600, "look_at": [0.0, 0.0, 0.0],
                                    "up_direction": [0.0, 0.0, 1.0]}))


def press(ws, uuid: str, value=True) -> bool:
    """What the page sends when a button is clicked (or, with ``value``, a field or dropdown changed)."""
    try:
        ws.send(msgspec.msgpack.encode({"type": "GuiUpdateMessage", "uuid": uuid, "updates": {"value": value}}))
        return True
    except Exception:
        return False


def connect(port: int, path: str):
    """A bare websocket tab (no reader), its camera reported."""
    return Tab(port, path, read=False).ws


def wait(cond, timeout_s: float = 20.0) -> bool:
    end = time.monotonic() + timeout_s
    while not cond() and time.monotonic() < end:
        time.sleep(0.05)
    return cond()


@contextmanager
def operator_ui(n: int, **kwargs):
    """A live DashboardUI with operator token "the-token", the controls it sends, and a list of websockets
    (or :class:`Tab`) that are closed (and the UI stopped) on the way out."""
    from dashboards.live import DashboardUI
    from dashboards.state import RunInfo
    from flocktrack.launch import free_port

    sent: list = []
    ui = DashboardUI(RunInfo(n=n, link_range=12.0, name="auth"), port=free_port(), live=True,
                     send_control=lambda v, a: sent.append((v, a)), operator_token="the-token", **kwargs)
    socks: list = []
    try:
        yield ui, sent, socks
    finally:
        for ws in socks:
            ws.close()
        ui.stop()
