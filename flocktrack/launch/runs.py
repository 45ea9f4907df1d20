"""The runs this machine's launchers are running: one small JSON file per run, owned by its launcher.

``flocktrack run`` (over Zenoh) writes ``<runtime dir>/<run>.json`` when its router is up and removes it
when it shuts down; ``flocktrack ps``, ``fault`` and ``logs`` read them, so a user need not copy a run
name or an endpoint from another terminal's banner. A file whose launcher died without removing it
(kill -9) is ignored (its pid is gone) and cleaned up by the next reader.

The runtime directory: ``$FLOCKTRACK_RUNTIME_DIR``, else ``$XDG_RUNTIME_DIR/flocktrack``, else
``/tmp/flocktrack-<uid>`` (made 0700: the files name the router endpoints and the client configs).
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path


@dataclass(frozen=True)
class LocalRun:
    """What a launcher tells about its run."""

    run: str                  #: the run name (key prefix ``ft/<run>/``)
    endpoint: str             #: its router, e.g. ``tcp/127.0.0.1:40123``
    mode: str                 #: lockstep | realtime
    n_sensors: int
    out: str                  #: the run directory (logs/, recording.mcap, …)
    pid: int                  #: the launcher's process
    started: float            #: time.time() at start
    config: str | None = None  #: a client config with the rights of ``flocktrack fault`` (secure runs)
    dashboard_port: int | None = None


def port_in_use(port: int) -> str | None:
    """None if ``port`` is free on 127.0.0.1, else what holds it (a local run, as far as we know)."""
    import socket

    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", int(port)))
            return None
        except OSError:
            pass
    for e in local_runs():
        if e.dashboard_port == port or e.endpoint.rsplit(":", 1)[-1] == str(port):
            what = "dashboard" if e.dashboard_port == port else "router"
            return f"the {what} of run {e.run} ({e.out}, launcher pid {e.pid})"
    return "another program"


def runtime_dir() -> Path:
    if os.environ.get("FLOCKTRACK_RUNTIME_DIR"):
        d = Path(os.environ["FLOCKTRACK_RUNTIME_DIR"])
    elif os.environ.get("XDG_RUNTIME_DIR"):
        d = Path(os.environ["XDG_RUNTIME_DIR"]) / "flocktrack"
    else:
        d = Path(tempfile.gettempdir()) / f"flocktrack-{os.getuid()}"
    d.mkdir(parents=True, exist_ok=True, mode=0o700)
    return d


def register(entry: LocalRun) -> Path:
    """Write the run's file (atomically: a reader never sees half of it)."""
    p = runtime_dir() / f"{entry.run}.json"
    tmp = p.with_suffix(".tmp")
    tmp.write_text(json.dumps(asdict(entry), indent=1))
    tmp.replace(p)
    return p


def unregister(run: str) -> None:
    (runtime_dir() / f"{run}.json").unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def local_runs() -> list[LocalRun]:
    """The runs of this machine's live launchers, oldest first (stale and unreadable files are removed)."""
    out = []
    for p in sorted(runtime_dir().glob("*.json")):
        try:
            entry = LocalRun(**json.loads(p.read_text()))
        except (OSError, ValueError, TypeError):
            p.unlink(missing_ok=True)
            continue
        if _alive(entry.pid):
            out.append(entry)
        else:
            p.unlink(missing_ok=True)
    return sorted(out, key=lambda e: e.started)


def find_local(run: str | None) -> LocalRun | None:
    """The local run named ``run`` (or whose run directory is ``run``); with ``run`` None, the only one."""
    runs = local_runs()
    if run is None:
        return runs[0] if len(runs) == 1 else None
    for e in runs:
        if run in (e.run, e.out) or Path(run).resolve() == Path(e.out).resolve():
            return e
    return None
