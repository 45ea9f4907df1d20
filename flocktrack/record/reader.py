"""The one reader of recordings: :func:`read_recording` yields the messages back (recovering what a
truncated file still holds), :func:`recover` rewrites a cut file whole, :func:`metrics_from_recording`
recomputes ``summary.json`` from a recording alone."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

from agent import wire

from .writer import McapRecorder

log = logging.getLogger(__name__)


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

    from flocktrack.record.metrics import MetricsCollector, summary_identity

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


