"""HTTPS for the dashboard of a secure run: TLS in front of Viser's plain server.

Viser serves its page and its websocket on one plain-TCP port and has no TLS option. In a ``--secure`` run
the dashboard therefore binds Viser to a free port on 127.0.0.1 and puts this front on the public one: it
terminates TLS with a certificate of the run's CA (``flocktrack keys``: ``certs/dashboard-web.pem``, valid
for the run's host names) and passes the bytes through both ways — the page's HTTP requests and its
websocket, whose path (the operator token, dashboards/operator.py) reaches Viser unchanged. It reads and
writes no HTTP itself; a client that does not speak TLS is dropped at the handshake.
"""

from __future__ import annotations

import asyncio
import logging
import ssl
import threading
from pathlib import Path

log = logging.getLogger(__name__)


def server_context(cert: str | Path, key: str | Path) -> ssl.SSLContext:
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.load_cert_chain(str(cert), str(key))
    return ctx


class TlsFront:
    """Listen with TLS on ``host:port``; forward each connection to ``127.0.0.1:backend_port``."""

    def __init__(self, host: str, port: int, backend_port: int, cert: str | Path, key: str | Path):
        self.backend_port = int(backend_port)
        ctx = server_context(cert, key)
        self._loop = asyncio.new_event_loop()
        self._loop.set_exception_handler(self._on_loop_error)
        ready = threading.Event()
        failed: list[BaseException] = []

        def run() -> None:
            asyncio.set_event_loop(self._loop)
            try:
                self._server = self._loop.run_until_complete(asyncio.start_server(self._connection, host, port,
                                                                                  ssl=ctx))
            except OSError as exc:
                failed.append(exc)
                ready.set()
                return
            ready.set()
            self._loop.run_forever()

        self._thread = threading.Thread(target=run, name="dashboard-tls", daemon=True)
        self._thread.start()
        ready.wait(30)
        if failed:
            raise failed[0]
        self.port = self._server.sockets[0].getsockname()[1]

    @staticmethod
    def _on_loop_error(loop, context) -> None:
        exc = context.get("exception")
        if isinstance(exc, (ssl.SSLError, ConnectionError, OSError)):
            return   # a client that is not speaking TLS, or went away mid-handshake: its problem
        loop.default_exception_handler(context)

    async def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            b_reader, b_writer = await asyncio.open_connection("127.0.0.1", self.backend_port)
        except OSError:
            writer.close()
            return
        await asyncio.gather(self._pipe(reader, b_writer), self._pipe(b_reader, writer))

    @staticmethod
    async def _pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
        try:
            while data := await src.read(1 << 16):
                dst.write(data)
                await dst.drain()
        except (ConnectionError, ssl.SSLError, OSError):
            pass
        finally:
            try:
                dst.close()
            except (ConnectionError, ssl.SSLError, OSError, RuntimeError):
                pass

    def close(self) -> None:
        def stop() -> None:
            self._server.close()
            self._loop.stop()

        if self._loop.is_running():
            self._loop.call_soon_threadsafe(stop)
            self._thread.join(5)
