"""``flocktrack ps``: the runs reachable on a router, from their members' liveliness tokens.

A run is the set of tokens ``ft/<run>/alive/<member>`` (every role, the recorder, the launcher, a
dashboard declare one); the sensors alive are its ``agent/<i>`` tokens. Its tick is the newest
``ft/<run>/world/tick`` heard in a short listen, and that tick's ``n`` (its ``alive`` list has one entry
per sensor) the flock's size. Without ``--connect``, every run of this machine's launchers
(flocktrack/launch/runs.py) is asked on its own router; those files also give the mode and the run directory,
which nothing on a router tells (a run heard only through ``--connect`` shows mode ``?``, and its size
``?`` if it ticked nothing during the listen).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field

from flocktrack.launch.runs import LocalRun, local_runs


@dataclass
class RunSeen:
    run: str
    endpoint: str
    members: set[str] = field(default_factory=set)
    tick: int | None = None
    mode: str = "?"
    n_sensors: int | None = None
    out: str = ""

    @property
    def sensors_alive(self) -> int:
        return sum(m.startswith("agent/") for m in self.members)

    def row(self) -> dict:
        others = sorted(m for m in self.members if not m.startswith("agent/"))
        return {"run": self.run, "tick": self.tick, "mode": self.mode,
                "sensors": f"{self.sensors_alive}/{self.n_sensors if self.n_sensors is not None else '?'}",
                "members": " ".join(others), "endpoint": self.endpoint, "out": self.out}


def runs_on(endpoint: str, config_file: str | None = None, run: str | None = None,
            listen_s: float = 0.6) -> dict[str, RunSeen]:
    """The runs whose members hold tokens on the router at ``endpoint`` (only ``run``, if given: a secure
    run's ACL lets a client ask about its own run only)."""
    import zenoh

    from agent.bus import zenoh_config
    from agent.wire import decode

    session = zenoh.open(zenoh_config(endpoint, None, "client", config_file))
    seen: dict[str, RunSeen] = {}
    try:
        scope = f"ft/{run}" if run else "ft/*"
        ticks: dict[str, tuple[int, int]] = {}   # run -> (newest k, its n)

        def on_tick(sample) -> None:
            run = str(sample.key_expr).split("/")[1]
            try:
                t = decode("world/tick", sample.payload.to_bytes())
            except Exception:  # a bad sample tells no tick
                return
            if t.k > ticks.get(run, (-1, 0))[0]:
                ticks[run] = (t.k, t.n)

        sub = session.declare_subscriber(f"{scope}/world/tick", on_tick)
        time.sleep(listen_s)
        sub.undeclare()
        # the members after the ticks: a world declares its token before its first tick, so a run seen
        # ticking is listed with its world (asked first, a run just starting showed ticks but no world)
        for reply in session.liveliness().get(f"{scope}/alive/**", timeout=2.0):
            if reply.ok is None:
                continue
            parts = str(reply.ok.key_expr).split("/", 3)   # ft / <run> / alive / <member>
            if len(parts) == 4:
                seen.setdefault(parts[1], RunSeen(parts[1], endpoint)).members.add(parts[3])
        for run, (k, n) in ticks.items():
            if run in seen:
                seen[run].tick, seen[run].n_sensors = k, n
    finally:
        session.close()
    return seen


def discover(connect: str | None = None, config_file: str | None = None,
             run: str | None = None) -> tuple[list[RunSeen], list[str]]:
    """The runs on ``connect`` (else each local launcher's run on its router), and the endpoints that failed."""
    local = {e.run: e for e in local_runs()}
    targets: list[tuple[str, str | None, str | None]] = (
        [(connect, config_file, run)] if connect else
        [(e.endpoint, e.config, e.run) for e in local.values() if run in (None, e.run)])
    found: dict[str, RunSeen] = {}
    failed = []
    for ep, cfg, name in targets:
        try:
            found.update(runs_on(ep, cfg, name))
        except Exception as exc:  # zenoh.ZError: no router there (reported, not raised)
            failed.append(f"{ep} ({exc})")
    for run, r in found.items():
        e: LocalRun | None = local.get(run)
        if e is not None:
            r.mode, r.n_sensors, r.out = e.mode, e.n_sensors, e.out
    return sorted(found.values(), key=lambda r: r.run), failed


def table(runs: list[RunSeen]) -> str:
    """The rows as aligned columns (``docker compose ps`` style)."""
    cols = ["run", "tick", "mode", "sensors", "members", "endpoint", "out"]
    rows = [[("" if v is None else str(v)) for v in (r.row()[c] for c in cols)] for r in runs]
    widths = [max([len(c)] + [len(row[i]) for row in rows]) for i, c in enumerate(cols)]
    lines = ["  ".join(c.upper().ljust(w) for c, w in zip(cols, widths))]
    lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths)) for row in rows]
    return "\n".join(x.rstrip() for x in lines)


def as_json(runs: list[RunSeen]) -> str:
    return json.dumps([r.row() | {"members": sorted(r.members)} for r in runs], indent=1)
