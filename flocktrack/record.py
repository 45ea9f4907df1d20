"""Recordings: every message of a run in an MCAP file, replay, and re-scoring.

* :class:`McapRecorder` writes each message as JSON on a channel named by its relative key
  (``world/tick``, ``agent/3/xchg``, …) with a JSON Schema per message type, so Foxglove opens the file.
  Chunks are small and the file is unbuffered, so a crash loses at most the last chunk; the
  scenario (TOML text) and the pre-run design are stored as metadata, so a recording is self-contained.
* ``python -m flocktrack.record --run R --connect EP --out FILE`` is the recorder *role*: a read-only
  subscriber to ``ft/<run>/…`` (:data:`agent.wire.OBSERVED`: every key but the addressed copies of the
  exchange payloads, which it records once, from ``agent/<i>/xchg``) that stops at ``world/end`` (or
  SIGTERM) and finishes the file.
* :func:`read_recording` yields the messages back (recovering what a truncated file still holds);
  :func:`metrics_from_recording` recomputes ``summary.json`` from a recording alone.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from agent import wire

log = logging.getLogger(__name__)

CHUNK_BYTES = 64 * 1024
#: a chunk open longer than this is closed and written out: a crash (kill -9 of the recorder or of its
#: launcher) loses at most the last FLUSH_S of messages (tests/test_recording_crash.py)
FLUSH_S = 0.5


class McapRecorder:
    def __init__(self, path: str | Path, metadata: dict[str, str] | None = None):
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "wb")
        self._w = Writer(self._f, chunk_size=CHUNK_BYTES, compression=CompressionType.NONE)
        self._packed = 0      # chunk indexes packed so far (_pack_chunk_indexes)
        self._w.start(profile="flocktrack", library="flocktrack")
        self._schemas = {name: self._w.register_schema(
            name=f"flocktrack.{cls.__name__}", encoding="jsonschema",
            data=json.dumps(wire.json_schema(cls)).encode()) for name, cls in wire.MESSAGE_TYPES.items()}
        self._channels: dict[str, int] = {}
        self.seq = 0
        self.counts: Counter = Counter()
        self.dropped: Counter = Counter()
        self._finished = False
        self._open_since: float | None = None   # when the chunk in progress got its first message
        if metadata:
            self._w.add_metadata("flocktrack", {k: str(v) for k, v in metadata.items()})
        self._f.flush()

    def write_raw(self, key: str, data: bytes, t_ns: int | None = None) -> None:
        """Validate and record one wire message (invalid ones are counted, not recorded; the addressed copy
        of an exchange payload, e.g. from an in-process bus's tap, is left out: it is recorded once)."""
        if wire.addressed(key):
            return
        try:
            msg = wire.decode(key, data)
        except wire.WireError as exc:
            self.dropped[exc.reason] += 1
            return
        self.write(key, msg, t_ns)

    def write(self, key: str, msg: wire.Message, t_ns: int | None = None) -> None:
        ch = self._channels.get(key)
        if ch is None:
            ch = self._channels[key] = self._w.register_channel(
                topic=key, message_encoding="json", schema_id=self._schemas[msg.TYPE])
        t = time.time_ns() if t_ns is None else t_ns
        self._w.add_message(ch, log_time=t, data=msg.to_json_bytes(), publish_time=t,
                            sequence=self.seq)
        self.seq += 1
        self.counts[key] += 1
        if self._open_since is None:
            self._open_since = time.monotonic()
        self.tick()

    def tick(self) -> None:
        """Close the chunk in progress once it is FLUSH_S old (also called when no message comes): what is
        recorded reaches the OS within FLUSH_S. Chunks still fill to CHUNK_BYTES at high rates."""
        if self._open_since is not None and time.monotonic() - self._open_since >= FLUSH_S:
            self.flush()

    def flush(self) -> None:
        """Close the chunk in progress now and hand everything written to the OS."""
        self._w.flush()
        self._open_since = None
        self._pack_chunk_indexes()

    def _pack_chunk_indexes(self) -> None:
        """The writer keeps every chunk's index until :meth:`finish` writes the summary — as a record object
        with a dict of per-channel offsets, ~2.8 KB of memory per chunk with ~40 channels: the recorder's RSS
        grew 8 % over a 10-minute soak (docs/reliability.md). Each finished index is replaced by its
        serialised bytes (~0.5 KB), written out unchanged at the end. (Message indexes stay: Foxglove's
        indexed reader refuses a chunk index without them.) Needs the mcap writer's private list; without
        it nothing is packed and the memory simply grows as before."""
        from mcap.data_stream import RecordBuilder
        from mcap.records import ChunkIndex

        idx = getattr(self._w, "_Writer__chunk_indices", None)
        if not isinstance(idx, list):
            return
        for j in range(self._packed, len(idx)):
            if isinstance(idx[j], ChunkIndex):
                b = RecordBuilder()
                idx[j].write(b)
                idx[j] = _PackedRecord(b.end())
        self._packed = len(idx)

    def finish(self) -> None:
        if self._finished:
            return
        self._finished = True
        try:
            self._w.finish()
        finally:
            self._f.close()


class _PackedRecord:
    """A record already serialised: ``write`` copies its bytes (what the writer's summary calls)."""

    __slots__ = ("raw",)

    def __init__(self, raw: bytes):
        self.raw = raw

    def write(self, stream) -> None:
        stream.write(self.raw)


def recover(path: str | Path, out: str | Path | None = None) -> tuple[Path, Recording]:
    """Rewrite a recording whose end is missing (the recorder or its launcher killed, the disk full) as a
    complete MCAP file — summary, index and footer — that any MCAP reader (Foxglove, ``mcap`` tools) opens:
    every message of its complete chunks, with its metadata, times and sequence numbers. Returns the new
    file's path (default ``NAME.recovered.mcap`` beside it) and what was salvaged."""
    path = Path(path)
    rec = read_recording(path)
    dst = Path(out) if out is not None else path.with_name(path.stem + ".recovered.mcap")
    w = McapRecorder(dst, rec.metadata)   # (numbers them 0, 1, … in the order read: sequence order)
    try:
        for key, msg, t in rec.messages:
            w.write(key, msg, t)
    finally:
        w.finish()
    return dst, rec


@dataclass
class Recording:
    metadata: dict[str, str]
    messages: list[tuple[str, wire.Message, int]]  # (key, message, log_time ns) in sequence order
    complete: bool
    rejected: int = 0


def read_recording(path: str | Path) -> Recording:
    """All messages of a recording in sequence order. A truncated file (crash) yields what its
    complete chunks hold, with ``complete=False``."""
    from mcap.reader import make_reader
    from mcap.stream_reader import StreamReader
    from mcap.records import Channel, Chunk, Message, Metadata

    path = Path(path)
    meta: dict[str, str] = {}
    msgs: list[tuple[int, str, wire.Message, int]] = []
    rejected = 0
    complete = True
    try:
        with open(path, "rb") as f:
            r = make_reader(f)
            for m in r.iter_metadata():
                if m.name == "flocktrack":
                    meta = dict(m.metadata)
            for _schema, channel, message in r.iter_messages(log_time_order=False):
                try:
                    msgs.append((message.sequence, channel.topic,
                                 wire.from_json(json.loads(message.data)), message.log_time))
                except (wire.WireError, ValueError):
                    rejected += 1
    except Exception:  # truncated / no summary: stream through what is there
        complete = False
        msgs, rejected = [], 0
        channels: dict[int, str] = {}
        with open(path, "rb") as f:
            try:
                for rec in StreamReader(f, skip_magic=False).records:
                    if isinstance(rec, Metadata) and rec.name == "flocktrack":
                        meta = dict(rec.metadata)
                    elif isinstance(rec, Channel):
                        channels[rec.id] = rec.topic
                    elif isinstance(rec, Chunk):
                        for sub in _chunk_records(rec):
                            if isinstance(sub, Channel):
                                channels[sub.id] = sub.topic
                            elif isinstance(sub, Message):
                                _append(msgs, channels, sub)
                    elif isinstance(rec, Message):
                        _append(msgs, channels, rec)
            except Exception:
                pass
    msgs.sort(key=lambda t: t[0])
    return Recording(meta, [(k, m, t) for _, k, m, t in msgs], complete, rejected)


def _chunk_records(chunk):
    from mcap.reader import breakup_chunk

    return breakup_chunk(chunk, validate_crc=False)


def _append(msgs, channels, rec) -> None:
    try:
        msgs.append((rec.sequence, channels[rec.channel_id], wire.from_json(json.loads(rec.data)), rec.log_time))
    except (KeyError, wire.WireError, ValueError):
        pass


def metrics_from_recording(path: str | Path, out_dir: str | Path | None = None, rec=None) -> dict:
    """Recompute ``summary.json`` (and ``metrics.csv``) from a recording alone (``rec``: the recording
    already read with :func:`read_recording`, to read a large one once)."""
    import tomllib

    from agent.scenario import parse_scenario

    from .metrics import MetricsCollector, summary_identity

    rec = read_recording(path) if rec is None else rec
    if "scenario" not in rec.metadata:
        raise ValueError(f"{path}: not a flocktrack recording (no scenario metadata)")
    sc = parse_scenario(tomllib.loads(rec.metadata["scenario"]), rec.metadata.get("scenario_path", str(path)))
    design = json.loads(rec.metadata.get("design", "{}"))
    m = MetricsCollector.for_scenario(sc, design)
    for key, msg, _t in rec.messages:
        m.ingest(key, msg)
    extra = summary_identity(sc)
    if out_dir is not None:
        return m.write(out_dir, extra)
    return m.summary(extra)


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
    ap.add_argument("--summary", metavar="DIR", default=None,
                    help="after the run, score the recording into DIR/summary.json and DIR/metrics.csv "
                         "(what `flocktrack run` writes; a deployment without a launcher, e.g. compose, needs it)")
    return ap


class RecorderSession:
    """The recorder role's loop: every payload the bus delivers into ``rec``, until ``world/end`` and the
    roles that were still finishing have gone (:meth:`over`), a stop signal, or a write failure."""

    def __init__(self, rec: McapRecorder, bus, out: str, linger: float, linger_max: float):
        self.rec, self.bus, self.out = rec, bus, out
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
        for pattern in wire.OBSERVED:      # every payload once: not its addressed copies
            bus.subscribe_raw(pattern, self.on_raw)
        bus.watch_members(self.on_member)
        bus.declare_token("recorder/0")
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


def _score(out: str, summary_dir: str, failed: list[str]) -> None:
    """``--summary``: the recording scored into ``summary_dir`` (a failure is added to ``failed``)."""
    try:
        s = metrics_from_recording(out, summary_dir)
    except (OSError, ValueError) as exc:
        log.error("scoring %s into %s failed: %s", out, summary_dir, exc)
        failed.append(str(exc))
    else:
        log.info("wrote %s/summary.json (%s ticks scored)", summary_dir, s.get("ticks_seen"))


def _write_stats(rec: McapRecorder, failed: list[str]) -> None:
    """``$FLOCKTRACK_STATS_DIR/recorder_0.json``: what was recorded per key, dropped, and a write failure."""
    import os

    if os.environ.get("FLOCKTRACK_STATS_DIR"):
        p = Path(os.environ["FLOCKTRACK_STATS_DIR"]) / "recorder_0.json"
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
        rec = McapRecorder(args.out, meta)
    except OSError as exc:
        print(f"error: cannot record to {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    session = RecorderSession(rec, ZenohBus(args.run, connect=args.connect, config_file=args.config), args.out,
                              args.linger, args.linger_max)
    try:
        profiled("recorder/0", lambda: session.loop(stop))
    finally:
        session.close()
    log.info("recorded %d messages on %d keys to %s (dropped %s)", rec.seq, len(rec.counts), args.out,
             dict(rec.dropped))
    if args.summary and not session.failed:
        _score(args.out, args.summary, session.failed)
    _write_stats(rec, session.failed)
    return 1 if session.failed else 0


if __name__ == "__main__":
    sys.exit(main())
