"""``flocktrack merge DIR... --out DIR``: one recording and summary from the shards of a run over several hosts.

With a placement every host records what its own nodes write (its recorder's reads in the run plan), into
its own ``DIR/recording.mcap``. Merging reads every shard (a cut one as far as it goes), checks that they are
shards of one run (the same scenario and design metadata, the same run name in their ``plan.json``), writes
every message once into ``OUT/recording.mcap`` in log-time order, and scores it into ``OUT/summary.json`` and
``OUT/metrics.csv`` as a one-host run's directory holds them; ``OUT/run.json`` lists the shards.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

from agent import wire

from .reader import metrics_from_recording, read_recording
from .writer import McapRecorder


class MergeError(ValueError):
    """The directories are not shards of one run; the message names the one that differs."""


def _recording(d: Path) -> Path:
    p = d / "recording.mcap" if d.is_dir() else d
    if not p.is_file():
        raise MergeError(f"{d}: no recording.mcap (give each host's run directory)")
    return p


def merge(dirs: list[str | Path], out: str | Path) -> tuple[dict, dict]:
    """Merge the shards in ``dirs`` into ``out``; returns (summary, info)."""
    dirs = [Path(d) for d in dirs]
    out = Path(out)
    recs = [(d, read_recording(_recording(d))) for d in dirs]
    first_dir, first = recs[0]
    for d, r in recs[1:]:
        for k in ("scenario", "design"):
            if r.metadata.get(k) != first.metadata.get(k):
                raise MergeError(f"{d}: its {k} differs from {first_dir}'s: not a shard of the same run")
    runs = {d: json.loads((d / "plan.json").read_text())["run"] for d in dirs if (d / "plan.json").is_file()}
    if len(set(runs.values())) > 1:
        raise MergeError("not one run: " + ", ".join(f"{d} is run {r!r}" for d, r in runs.items()))
    out.mkdir(parents=True, exist_ok=True)
    messages = sorted(((t, i, key, msg, wall) for i, (_, r) in enumerate(recs)
                       for (key, msg, t), wall in zip(r.messages, r.wall)), key=lambda m: (m[0], m[4], m[1]))
    seen: set[tuple[str, bytes]] = set()
    rec = McapRecorder(out / "recording.mcap", dict(first.metadata))
    dup = 0
    try:
        for t, _, key, msg, wall in messages:
            ident = (key, wire.encode(msg))
            if ident in seen:     # a message two shards both recorded (e.g. one host's control plane)
                dup += 1
                continue
            seen.add(ident)
            rec.write(key, msg, t, wall_ns=wall)
    finally:
        rec.finish()
    for d in dirs:
        if (d / "plan.json").is_file() and not (out / "plan.json").exists():
            shutil.copyfile(d / "plan.json", out / "plan.json")
    summary = metrics_from_recording(out / "recording.mcap", out)
    info = {"transport": "zenoh", "merged": [str(d) for d in dirs], "run": next(iter(runs.values()), None),
            "recorded_messages": len(seen), "duplicates": dup,
            "shards": {str(d): {"messages": len(r.messages), "complete": r.complete} for d, r in recs}}
    (out / "run.json").write_text(json.dumps(info, indent=2))
    return summary, info


def cmd_merge(args) -> int:
    try:
        summary, info = merge(args.dirs, args.out)
    except MergeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"merged {len(args.dirs)} shards ({info['recorded_messages']} messages) into {args.out}/recording.mcap; "
          f"network RMSE {summary.get('network_rmse')}, {summary.get('ticks_seen')} ticks — {args.out}/summary.json")
    return 0


def register(subparsers) -> None:
    """Add ``flocktrack merge`` to the CLI."""
    p = subparsers.add_parser("merge", help="one recording and summary from the hosts' shards of a placed run",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("dirs", nargs="+", metavar="DIR", help="each host's run directory (or its recording.mcap)")
    p.add_argument("--out", required=True, help="directory for the merged recording.mcap, summary.json, metrics.csv")
    p.set_defaults(fn=cmd_merge)
