"""Recordings read back: :func:`read_recording` (the one reader, :mod:`agent.recording`: the messages in
sequence order, recovering what a truncated file still holds), :func:`recover` rewrites a cut file whole,
:func:`metrics_from_recording` recomputes ``summary.json`` from a recording alone."""

from __future__ import annotations

import json
import logging
from pathlib import Path

from agent.recording import Recording, read_recording

from .writer import McapRecorder

log = logging.getLogger(__name__)

__all__ = ["Recording", "read_recording", "recover", "metrics_from_recording"]


def recover(path: str | Path, out: str | Path | None = None) -> tuple[Path, Recording]:
    """Rewrite a recording whose end is missing (the recorder or its launcher killed, the disk full) as a
    complete MCAP file — summary, index and footer — that any MCAP reader (Foxglove, ``mcap`` tools) opens:
    every message of its complete chunks, with its metadata, times and sequence numbers. Returns the new
    file's path (default ``NAME.recovered.mcap`` beside it) and what was salvaged."""
    path = Path(path)
    rec = read_recording(path)
    dst = Path(out) if out is not None else path.with_name(path.stem + ".recovered.mcap")
    meta = dict(rec.metadata)
    if not rec.simulated:
        meta["timeline"] = "wall"        # an older recording: its log times stay the wall clock
    w = McapRecorder(dst, meta)   # (numbers them 0, 1, … in the order read: sequence order)
    try:
        for (key, msg, t), wall in zip(rec.messages, rec.wall):
            w.write(key, msg, t, wall_ns=wall)
    finally:
        w.finish()
    return dst, rec


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


