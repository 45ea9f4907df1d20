"""Recordings: every message of a run in an MCAP file, replay, and re-scoring.

* :class:`McapRecorder` writes each message as JSON on a channel named by its relative key
  (``world/tick``, ``agent/3/xchg``, …) with a JSON Schema per message type, so Foxglove opens the file.
  Chunks are small and the file is unbuffered, so a crash loses at most the last chunk; the
  scenario (TOML text) and the pre-run design are stored as metadata, so a recording is self-contained.
* ``python -m flocktrack.record --run R --connect EP --out FILE [--plan FILE --name recorder/HOST]`` is the
  recorder *role*: a read-only subscriber to what the run plan's nodes write (its reads in the plan: every
  key but the addressed copies of the exchange payloads, which it records once, from ``agent/<i>/xchg``; with
  a placement, what its own host's nodes write) that stops at ``world/end`` (or SIGTERM) and finishes the
  file. Without ``--plan`` it takes the plan of the scenario in its ``--meta``.
* :func:`read_recording` yields the messages back (recovering what a truncated file still holds);
  :func:`metrics_from_recording` recomputes ``summary.json`` from a recording alone.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path


from agent.ports import slug

from .reader import metrics_from_recording
from .writer import McapRecorder

log = logging.getLogger(__name__)


# ============================================================================ the recorder role

#: Members that watch or steer a run, not roles that publish its results.
_NOT_ROLES = frozenset({"recorder", "launcher", "dashboard"})


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m flocktrack.record")
    ap.add_argument("--run", required=True)
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447")
    ap.add_argument("--out", required=True)
    ap.add_argument("--meta", default=None, help="JSON file of metadata (scenario text, design)")
    ap.add_argument("--linger", type=float, default=0.5,
                    help="seconds to keep recording after world/end (at least; then until the roles have exited)")
    ap.add_argument("--linger-max", type=float, default=20.0,
                    help="seconds after world/end at which the recording stops even if a role is still up")
    ap.add_argument("--config", default=None)
    ap.add_argument("--plan", default=None, help="the run plan (JSON, as `flocktrack plan --format json` prints it)")
    ap.add_argument("--name", default="recorder/0", help="this recorder's node name in the plan (recorder/HOST)")
    ap.add_argument("--summary", metavar="DIR", default=None,
                    help="after the run, score the recording into DIR/summary.json and DIR/metrics.csv "
                         "(what `flocktrack run` writes; a deployment without a launcher, e.g. compose, needs it)")
    return ap


class RecorderSession:
    """The recorder role's loop: every payload the bus delivers into ``rec``, until ``world/end`` and the
    roles that were still finishing have gone (:meth:`over`), a stop signal, or a write failure."""

    def __init__(self, rec: McapRecorder, bus, out: str, linger: float, linger_max: float, *,
                 name: str = "recorder/0", reads: tuple[str, ...] = ("**",)):
        self.rec, self.bus, self.out = rec, bus, out
        self.name, self.reads = name, reads
        self.linger, self.linger_max = linger, linger_max
        self.end_at: float | None = None      #: when world/end arrived (monotonic)
        self.roles_up: set[str] = set()
        self.failed: list[str] = []           #: why writing failed (empty: it did not)

    def fail(self, exc: OSError) -> None:
        """A full disk, a vanished directory: the recording stops cleanly with what is written."""
        if not self.failed:
            log.error("writing %s failed (%s): the recording stops at %d messages; `flocktrack recover %s` "
                      "makes a complete file of them", self.out, exc.strerror or exc, self.rec.seq, self.out)
        self.failed.append(exc.strerror or str(exc))

    def on_raw(self, key: str, data: bytes) -> None:
        if self.failed:
            return
        try:
            self.rec.write_raw(key, data)
        except OSError as exc:
            return self.fail(exc)
        if key == "world/end" and self.end_at is None:
            self.end_at = time.monotonic()

    def on_member(self, name: str, alive: bool) -> None:
        if name.split("/")[0] in _NOT_ROLES:
            return
        (self.roles_up.add if alive else self.roles_up.discard)(name)

    def over(self) -> bool:
        """After world/end: the roles still finishing (e.g. the fusion solving its last measurements)
        publish until they exit, so the file closes once every role's token is gone."""
        if self.end_at is None:
            return False
        waited = time.monotonic() - self.end_at
        return waited > self.linger_max or (waited > self.linger and not self.roles_up)

    def loop(self, stop) -> None:
        bus = self.bus
        for pattern in self.reads:      # every payload once: not its addressed copies
            bus.subscribe_raw(pattern, self.on_raw)
        bus.watch_members(self.on_member)
        bus.declare_token(self.name)
        while not stop.set and not self.over() and not self.failed:
            bus.poll(0.05)
            try:
                self.rec.tick()
            except OSError as exc:
                self.fail(exc)
        bus.poll(0)  # whatever is already queued

    def close(self) -> None:
        """Finish the file (its summary and indexes) and leave the bus."""
        try:
            self.rec.finish()
        except OSError as exc:
            self.fail(exc)
        self.bus.close()


def subscriptions(plan_file: str | None, name: str, meta: dict) -> tuple[str, ...]:
    """What recorder ``name`` subscribes to: its reads in the run plan (``--plan``), else in the plan of the
    scenario its metadata holds."""
    from flocktrack.plan import RunPlan, build_plan

    if plan_file:
        plan = RunPlan.from_json(Path(plan_file).read_text())
    else:
        import tomllib

        from agent.scenario import parse_scenario

        if "scenario" not in meta:
            raise ValueError("give --plan FILE, or --meta with the run's scenario")
        plan = build_plan(parse_scenario(tomllib.loads(meta["scenario"]), meta.get("scenario_path", "meta")))
    return plan.node(name).reads


def _score(out: str, summary_dir: str, failed: list[str]) -> None:
    """``--summary``: the recording scored into ``summary_dir`` (a failure is added to ``failed``)."""
    try:
        s = metrics_from_recording(out, summary_dir)
    except (OSError, ValueError) as exc:
        log.error("scoring %s into %s failed: %s", out, summary_dir, exc)
        failed.append(str(exc))
    else:
        log.info("wrote %s/summary.json (%s ticks scored)", summary_dir, s.get("ticks_seen"))


def _write_stats(rec: McapRecorder, failed: list[str], name: str) -> None:
    """``$FLOCKTRACK_STATS_DIR/<name>.json`` (``recorder-0.json``): what was recorded per key, dropped, and a
    write failure."""
    import os

    if os.environ.get("FLOCKTRACK_STATS_DIR"):
        p = Path(os.environ["FLOCKTRACK_STATS_DIR"]) / f"{slug(name)}.json"
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(json.dumps({"recorded_by_key": dict(sorted(rec.counts.items())), "dropped": dict(rec.dropped),
                                 "write_failed": failed[0] if failed else None}, indent=1))


def main(argv: list[str] | None = None) -> int:
    from agent.bus import ZenohBus
    from agent.runner import StopFlag, lean_zenoh_runtime, observer_priority, profiled, quick_gil_handoff

    observer_priority()
    lean_zenoh_runtime()
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    meta = json.loads(Path(args.meta).read_text()) if args.meta else {}
    stop = StopFlag().install()
    quick_gil_handoff()
    try:
        reads = subscriptions(args.plan, args.name, meta)
    except (OSError, ValueError, KeyError) as exc:
        print(f"error: no subscriptions for {args.name}: {exc}", file=sys.stderr)
        return 2
    try:
        rec = McapRecorder(args.out, meta)
    except OSError as exc:
        print(f"error: cannot record to {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    session = RecorderSession(rec, ZenohBus(args.run, connect=args.connect, config_file=args.config), args.out,
                              args.linger, args.linger_max, name=args.name, reads=reads)
    try:
        profiled(args.name, lambda: session.loop(stop))
    finally:
        session.close()
    log.info("recorded %d messages on %d keys to %s (dropped %s)", rec.seq, len(rec.counts), args.out,
             dict(rec.dropped))
    if args.summary and not session.failed:
        _score(args.out, args.summary, session.failed)
    _write_stats(rec, session.failed, args.name)
    return 1 if session.failed else 0


if __name__ == "__main__":
    sys.exit(main())
