"""Headless viewers for load-testing a dashboard: websocket clients that speak the page's own protocol
(msgpack over Viser's websocket, with the page's subprotocol), read every frame the server sends (and the
widget ids among it) and send what a page — or someone pretending to be one — would. No browser: a
:class:`Tab` costs the machine a thread, not a renderer, so tens of them stand for the viewers of a run.

``python -m dashboards.probe URL --tabs N --seconds S`` opens ``N`` tabs on the page at ``URL`` (its
address, or an operator link) for ``S`` seconds and prints the frames and bytes each received, as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from contextlib import contextmanager
from urllib.parse import parse_qs, urlsplit

import msgspec


def decode_frame(data: bytes) -> list[dict]:
    """The messages of one server frame (Viser's wire format: sizes, zstd msgpack, raw buffers)."""
    import zstandard

    inner = int.from_bytes(data[:8], "little")
    n = int.from_bytes(data[8:16], "little")
    raw = zstandard.ZstdDecompressor().decompress(data[16:16 + n], max_output_size=inner)
    return list(msgspec.msgpack.decode(raw).get("messages", ()))


class Tab:
    """A tab on the dashboard at ``host:port`` whose websocket path is ``path`` ("/" a viewer's,
    "/operator/<token>" an operator's); ``ssl``: a context for a secure run's page (wss). ``read``: a thread
    reads every frame (``frames``, ``nbytes``) and keeps the ids of the widgets they create (``uuids``) —
    what a page learns of the GUI. ``camera``: report a camera at once (Viser serves a tab from then on)."""

    def __init__(self, port: int, path: str = "/", *, host: str = "127.0.0.1", ssl=None, read: bool = True,
                 camera: bool = True):
        import viser
        from websockets.sync.client import connect

        scheme = "ws" if ssl is None else "wss"
        self.ws = connect(f"{scheme}://{host}:{port}{path}", subprotocols=[f"viser-v{viser.__version__}"],
                          max_size=None, open_timeout=30, ssl=ssl)
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
                for m in decode_frame(data):
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

    def report(self) -> dict:
        """What this tab received so far."""
        return {"frames": self.frames, "bytes": self.nbytes, "widgets": len(self.uuids),
                "closed_by_server": self.closed.is_set()}

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
    """A bare websocket tab on 127.0.0.1 (no reader), its camera reported."""
    return Tab(port, path, read=False).ws


def wait(cond, timeout_s: float = 20.0) -> bool:
    """Poll ``cond()`` until it holds or ``timeout_s`` passed; its last value."""
    end = time.monotonic() + timeout_s
    while not cond() and time.monotonic() < end:
        time.sleep(0.05)
    return cond()


@contextmanager
def operator_ui(n: int, *, token: str = "the-token", **kwargs):
    """A live :class:`~dashboards.ui.DashboardUI` of an ``n``-sensor run in this process, on a free port of
    127.0.0.1, whose operator token is ``token`` (``kwargs``: the UI's other options). Yields the UI, the
    controls it sent (``(verb, args)``, as the live loop would have published them) and a list for the
    websockets (or :class:`Tab`) to close on the way out, where the UI is stopped."""
    from .state import RunInfo
    from .ui import DashboardUI

    sent: list = []
    ui = DashboardUI(RunInfo(n=n, link_range=12.0, name="probe"), port=0, live=True,
                     send_control=lambda v, a: sent.append((v, a)), operator_token=token, **kwargs)
    socks: list = []
    try:
        yield ui, sent, socks
    finally:
        for ws in socks:
            ws.close()
        ui.stop()


def websocket_address(url: str) -> tuple[str, int, str, bool]:
    """(host, port, path, secure) of the websocket the page at ``url`` opens: its ``?websocket=`` parameter
    (an operator link, dashboards/operator.py), else the page's own address."""
    u = urlsplit(url)
    ws = parse_qs(u.query).get("websocket")
    if ws:
        u = urlsplit(ws[0])
    secure = u.scheme in ("https", "wss")
    return u.hostname or "127.0.0.1", u.port or (443 if secure else 80), u.path or "/", secure


def main(argv: list[str] | None = None) -> int:
    from websockets.exceptions import WebSocketException

    ap = argparse.ArgumentParser(prog="python -m dashboards.probe", description=__doc__.split("\n")[0])
    ap.add_argument("url", help="the page's address (http://HOST:PORT/) or an operator link")
    ap.add_argument("--tabs", type=int, default=1, help="headless tabs to open (default 1)")
    ap.add_argument("--seconds", type=float, default=10.0, help="how long they stay (default 10)")
    ap.add_argument("--cafile", help="an https page: the CA its certificate is checked against (a secure run's)")
    args = ap.parse_args(argv)
    host, port, path, secure = websocket_address(args.url)
    ctx = None
    if secure:
        import ssl

        ctx = ssl.create_default_context(cafile=args.cafile)
    tabs: list[Tab] = []
    try:
        for _ in range(max(0, args.tabs)):
            tabs.append(Tab(port, path, host=host, ssl=ctx))
        end = time.monotonic() + args.seconds
        while time.monotonic() < end and not all(t.closed.is_set() for t in tabs):
            time.sleep(0.1)
        reports = [t.report() for t in tabs]
    except (OSError, WebSocketException) as e:
        print(f"error: {args.url}: {e}", file=sys.stderr)
        return 1
    finally:
        for t in tabs:
            t.close()
    print(json.dumps({"url": args.url, "seconds": args.seconds, "tabs": reports}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
