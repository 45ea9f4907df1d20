"""The one reader of flocktrack recordings (MCAP files of :mod:`agent.wire` messages as JSON).

:func:`read_recording` gives the recording's metadata (the scenario TOML and the pre-run design) and its
messages ``(key, message, log time ns)`` in sequence order, each decoded and validated by
:func:`agent.wire.from_json` (an invalid one is counted in ``rejected``, never raised). A truncated file — the
recorder or its launcher killed, a full disk — yields what its readable records hold (``complete=False``).
``decode`` chooses which keys are decoded (the others come back with ``None`` for the message: a replay that
only counts the exchange payloads reads a long run fast). The metrics, ``flocktrack recover``, ``merge`` and
``export``, and the dashboard's replay all read through here.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from . import wire


@dataclass
class Recording:
    """A recording as read: its ``flocktrack`` metadata, its messages ``(key, message, log time ns)`` in
    sequence order (message None: a key ``decode`` left out), whether the file was whole, how many messages
    failed validation, and each message's publish time (``wall``, ns: when it was recorded).

    The log time is the tick's simulated time ``k·T`` where ``metadata["timeline"] == "simulated"``; older
    recordings have the wall clock in both (:attr:`simulated` tells which)."""

    metadata: dict[str, str]
    messages: list[tuple[str, wire.Message | None, int]]
    complete: bool = True
    rejected: int = 0
    wall: list[int] = field(default_factory=list)

    @property
    def simulated(self) -> bool:
        return self.metadata.get("timeline") == "simulated"


def read_recording(path: str | Path, decode: Callable[[str], bool] | None = None) -> Recording:
    """Every message of the recording at ``path`` in sequence order (``decode(key)``: decode this key's
    messages; default every key)."""
    from mcap.reader import make_reader

    path = Path(path)
    meta: dict[str, str] = {}
    rows: list[tuple[int, str, bytes | None, int, int]] = []
    complete = True
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            for m in reader.iter_metadata():
                if m.name == "flocktrack":
                    meta = dict(m.metadata)
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                if not _ours(schema.name if schema is not None else ""):
                    continue
                keep = decode is None or decode(channel.topic)
                rows.append((message.sequence, channel.topic, message.data if keep else None, message.log_time,
                             message.publish_time))
    except Exception:  # truncated / no summary: stream through what is there
        complete = False
        rows, meta = _stream(path, decode)
    rows.sort(key=lambda r: r[0])
    out: list[tuple[str, wire.Message | None, int]] = []
    wall: list[int] = []
    rejected = 0
    for _seq, topic, data, t, published in rows:
        try:
            out.append((topic, None if data is None else wire.from_json(json.loads(data)), t))
        except (wire.WireError, ValueError):
            rejected += 1
            continue
        wall.append(published)
    return Recording(meta, out, complete, rejected, wall)


_WIRE_SCHEMAS = frozenset(f"flocktrack.{cls.__name__}" for cls in wire.MESSAGE_TYPES.values())


def _ours(schema_name: str) -> bool:
    """A channel of :mod:`agent.wire` messages (``flocktrack.Tick`` …): the recording's other channels (the
    Foxglove views drawn from them) are derived and skipped by this reader."""
    return schema_name in _WIRE_SCHEMAS


def recording_metadata(path: str | Path) -> dict[str, str]:
    """The recording's flocktrack metadata (scenario TOML, design JSON) without reading its messages."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            for m in make_reader(f).iter_metadata():
                if m.name == "flocktrack":
                    return dict(m.metadata)
    except Exception:  # truncated: the metadata may sit in the readable part
        return _stream(Path(path), lambda _k: False)[1]
    return {}


def _stream(path: Path, decode: Callable[[str], bool] | None):
    """The records a truncated file still holds, chunk by chunk, to its torn end."""
    from mcap.records import Channel, Chunk, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader, breakup_chunk

    schemas: dict[int, str] = {}
    channels: dict[int, str] = {}
    rows: list[tuple[int, str, bytes | None, int, int]] = []
    meta: dict[str, str] = {}

    def take(rec) -> None:
        if isinstance(rec, Schema):
            schemas[rec.id] = rec.name
        elif isinstance(rec, Channel):
            if _ours(schemas.get(rec.schema_id, "")):
                channels[rec.id] = rec.topic
        elif isinstance(rec, Message) and rec.channel_id in channels:
            topic = channels[rec.channel_id]
            keep = decode is None or decode(topic)
            rows.append((rec.sequence, topic, rec.data if keep else None, rec.log_time, rec.publish_time))
        elif isinstance(rec, Metadata) and rec.name == "flocktrack":
            meta.update(rec.metadata)

    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                if isinstance(rec, Chunk):
                    for sub in breakup_chunk(rec, validate_crc=False):
                        take(sub)
                else:
                    take(rec)
        except Exception:  # the torn end of a crashed recording
            pass
    return rows, meta
