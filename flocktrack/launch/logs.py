"""``flocktrack logs RUN [MEMBER] [-f]``: the per-process logs of a run directory (``logs/*.log``), each
line tagged with its process; ``-f`` follows them live (``dora logs``, ``docker compose logs -f``) until
Ctrl-C, or until the run has ended and its files stop growing.

RUN is a run directory, or the name of a run of this machine's launchers (flocktrack/launch/runs.py); without
it, the only such run.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

from flocktrack.launch.runs import find_local, local_runs


class LogsError(ValueError):
    """RUN or MEMBER names nothing that has logs (the message says what does)."""


def run_dir(run: str | None) -> Path:
    if run is not None and (Path(run) / "logs").is_dir():
        return Path(run)
    e = find_local(run)
    if e is not None:
        return Path(e.out)
    live = ", ".join(f"{r.run} ({r.out})" for r in local_runs()) or "none"
    what = f"{run!r} is neither a run directory (with logs/) nor" if run else "give RUN:"
    raise LogsError(f"{what} a run of this machine's launchers; runs now: {live}")


def member_of(path: Path) -> str:
    """logs/agent-3.log → agent/3; logs/world-0.log → world/0 (a node's log is named by its slug)."""
    head, _, tail = path.stem.partition("-")
    return f"{head}/{tail}" if head and tail else path.stem


def _names(p: Path) -> set[str]:
    """What a user may call the process of a log file: agent/3, agent-3, agent-3.log; world/0, world."""
    m = member_of(p)
    return {m, p.stem, p.name} | ({m.split("/")[0]} if m.endswith("/0") else set())


def log_files(d: Path, member: str | None) -> list[Path]:
    files = sorted((d / "logs").glob("*.log"))
    if member is None:
        return files
    hit = [p for p in files if member.rstrip("/") in _names(p)]
    if not hit:
        raise LogsError(f"no log of {member!r} in {d / 'logs'}; there are: "
                        f"{', '.join(member_of(p) for p in files) or 'none'}")
    return hit


def show(d: Path, member: str | None = None, follow: bool = False, out=sys.stdout, *,
         still_running: Callable[[], bool] | None = None, poll_s: float = 0.2) -> int:
    """Print the logs (tagged ``[member]`` when there are several); with ``follow``, keep printing what is
    appended until Ctrl-C or until ``still_running()`` is False and nothing came for a second."""
    files = log_files(d, member)
    tag = len(files) > 1 or member is None
    offsets: dict[Path, int] = {}
    partial: dict[Path, str] = {}

    def drain() -> bool:
        got = False
        for p in log_files(d, member) if member is None else files:   # (a restarted member's file reappears)
            try:
                with open(p, "rb") as f:
                    f.seek(offsets.get(p, 0))
                    data = f.read()
                    offsets[p] = f.tell()
            except OSError:
                continue
            if not data:
                continue
            got = True
            text = partial.pop(p, "") + data.decode("utf-8", "replace")
            lines = text.split("\n")
            if not text.endswith("\n"):
                partial[p] = lines.pop()
            for ln in lines[:-1] if text.endswith("\n") else lines:
                out.write(f"[{member_of(p)}] {ln}\n" if tag else f"{ln}\n")
        out.flush()
        return got

    drain()
    if not follow:
        return 0
    alive = still_running or (lambda: find_local(str(d)) is not None)
    quiet_since = time.monotonic()
    try:
        while True:
            if drain():
                quiet_since = time.monotonic()
            elif not alive() and time.monotonic() - quiet_since > 1.0:
                return 0
            time.sleep(poll_s)
    except KeyboardInterrupt:
        return 0
