"""The MCAP writer of a run: every message as JSON on a channel named by its relative key
(``world/tick``, ``agent/3/estimate``, …) with a JSON Schema per message type; small chunks and an unbuffered
file, so a crash loses at most the last chunk; the scenario (TOML text) and the pre-run design stored as
metadata, so a recording is self-contained.

The timeline is the experiment's: a message's ``log_time`` is its tick's simulated time ``k·T`` (from the
scenario in the metadata; ``timeline = "simulated"`` in it), its ``publish_time`` the wall clock when it was
recorded — in every mode, so a recording of a paused or slowed run reads like one of a fast run. Recordings
written before this kept the wall clock in both (no ``timeline`` entry): the readers take either.

Beside the messages the writer adds Foxglove's views of them (:mod:`flocktrack.record.foxglove`): the 3-D
scene, the log, flat per-tick metrics — when the scenario is known and ``foxglove-sdk`` is installed."""

from __future__ import annotations

import json
import logging
import time
from collections import Counter
from pathlib import Path

import orjson

from agent import wire

log = logging.getLogger(__name__)

CHUNK_BYTES = 64 * 1024
#: a chunk open longer than this is closed and written out: a crash (kill -9 of the recorder or of its
#: launcher) loses at most the last FLUSH_S of messages (tests/runtime/test_recording_crash.py)
FLUSH_S = 0.5


class McapRecorder:
    def __init__(self, path: str | Path, metadata: dict[str, str] | None = None, *, views: bool = True):
        """``views``: add the Foxglove views (when the metadata holds a scenario and foxglove-sdk is there)."""
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
        self.views: Counter = Counter()          #: view messages written per topic
        self.dropped: Counter = Counter()
        self._finished = False
        self._open_since: float | None = None   # when the chunk in progress got its first message
        metadata = {k: str(v) for k, v in (metadata or {}).items()}
        sc = _scenario(metadata)
        self.T = None if sc is None else float(sc.run.T)
        if self.T is not None:
            metadata.setdefault("timeline", "simulated")
        self._views = _views(sc) if views and sc is not None else None
        self._view_channels: dict[str, int] = {}
        if metadata:
            self._w.add_metadata("flocktrack", metadata)
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

    def write(self, key: str, msg: wire.Message, t_ns: int | None = None, *, wall_ns: int | None = None) -> None:
        """Record ``msg`` on ``key``: at log time ``t_ns`` (default: its tick's simulated time, or the wall
        clock without a scenario) and publish time ``wall_ns`` (default: now) — a copy (recover, merge)
        passes both from its source."""
        ch = self._channels.get(key)
        if ch is None:
            ch = self._channels[key] = self._w.register_channel(
                topic=key, message_encoding="json", schema_id=self._schemas[msg.TYPE])
        wall = time.time_ns() if wall_ns is None else wall_ns
        t = t_ns if t_ns is not None else wall if self.T is None else round(max(msg.k, 0) * self.T * 1e9)
        self._w.add_message(ch, log_time=t, data=msg.to_json_bytes(), publish_time=wall, sequence=self.seq)
        self.seq += 1
        self.counts[key] += 1
        if self._views is not None:
            self._write_views(lambda v: v.of(key, msg, t), wall)
        if self._open_since is None:
            self._open_since = time.monotonic()
        self.tick()

    def _write_views(self, make, wall: int) -> None:
        """The Foxglove views ``make(views)`` returns; a view that fails is counted, never raised (the
        messages themselves are already recorded)."""
        try:
            views = make(self._views)
            for topic, view, t in views:
                if isinstance(view, dict):
                    data = orjson.dumps(view, option=orjson.OPT_SERIALIZE_NUMPY)
                else:
                    data = view.encode()
                self._w.add_message(self._view_channel(topic, view), log_time=t, data=data, publish_time=wall,
                                    sequence=self.seq)
                self.seq += 1
                self.views[topic] += 1
        except Exception as exc:  # noqa: BLE001 — a view is never worth a message
            self.dropped["view_failed"] += 1
            if self.dropped["view_failed"] == 1:
                log.warning("a Foxglove view failed (%s: %s); the messages are recorded, the views may have gaps",
                            type(exc).__name__, exc)

    def _view_channel(self, topic: str, view) -> int:
        ch = self._view_channels.get(topic)
        if ch is None:
            if isinstance(view, dict):
                from .foxglove import METRICS_SCHEMA

                sid = self._w.register_schema(name="flocktrack.view.TickMetrics", encoding="jsonschema",
                                              data=json.dumps(METRICS_SCHEMA).encode())
                encoding = "json"
            else:
                schema = type(view).get_schema()
                sid = self._w.register_schema(name=schema.name, encoding=schema.encoding, data=bytes(schema.data))
                encoding = schema.encoding
            ch = self._view_channels[topic] = self._w.register_channel(topic=topic, message_encoding=encoding,
                                                                        schema_id=sid)
        return ch

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
            if self._views is not None:
                self._write_views(lambda v: v.finish(), time.time_ns())
            self._w.finish()
        finally:
            self._f.close()


def _scenario(metadata: dict[str, str]):
    """The scenario the metadata holds (None: none, or one this version cannot read — the recording is still
    written, on the wall clock and without views)."""
    if not metadata.get("scenario", "").strip():
        return None
    import tomllib

    from agent.scenario import parse_scenario

    try:
        return parse_scenario(tomllib.loads(metadata["scenario"]), metadata.get("scenario_path", "recording"))
    except Exception as exc:  # noqa: BLE001 — an unreadable scenario must not stop the recording
        log.warning("the recording's scenario does not parse (%s): wall-clock times, no Foxglove views", exc)
        return None


def _views(sc):
    from .foxglove import FoxgloveViews, available

    if not available():
        log.info("foxglove-sdk is not installed: the recording has no Foxglove views")
        return None
    return FoxgloveViews(sc)


class _PackedRecord:
    """A record already serialised: ``write`` copies its bytes (what the writer's summary calls)."""

    __slots__ = ("raw",)

    def __init__(self, raw: bytes):
        self.raw = raw

    def write(self, stream) -> None:
        stream.write(self.raw)


