"""``flocktrack export RUN --format parquet|csv --out DIR``: a run's tables as files, one per table.

``DIR/ticks.parquet``, ``estimates``, ``links``, ``events``, ``faults`` (or ``.csv``): the tables of
:func:`flocktrack.analysis.load`, for pandas, polars, DuckDB, R or a spreadsheet.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

from flocktrack.extras import require

FORMATS = ("parquet", "csv")


def export(run, out: str | Path, fmt: str = "parquet") -> dict[Path, int]:
    """Write every table of ``run`` (a :class:`flocktrack.analysis.Run`) to ``out/<name>.<fmt>``; returns
    the rows written per file."""
    if fmt not in FORMATS:
        raise ValueError(f"format {fmt!r}: one of {', '.join(FORMATS)}")
    if fmt == "parquet":
        require("pyarrow")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[Path, int] = {}
    for name, df in run.tables().items():
        f = out / f"{name}.{fmt}"
        if fmt == "parquet":
            df.to_parquet(f, index=False)
        else:
            df.to_csv(f, index=False)
        written[f] = len(df)
    return written


def cmd_export(args) -> int:
    from flocktrack.analysis.loader import LoadError, TruncatedRecordingWarning, load, truncated_line

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TruncatedRecordingWarning)   # said below, as one line
            run = load(args.run)
    except LoadError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not run.complete:
        print(f"warning: {truncated_line(run.path, run.scenario.run.ticks, run.lost_ticks)}", file=sys.stderr)
    written = export(run, args.out, args.format)
    print(f"{run.path}: wrote {len(written)} tables to {args.out}/")
    width = max(len(f.name) for f in written)
    for f, n in written.items():
        print(f"  {f.name:<{width}}  {n:>8} rows")
    return 0


def register(subparsers) -> None:
    """Add ``flocktrack export`` to the CLI."""
    p = subparsers.add_parser("export", help="a run's tables (ticks, estimates, links, events, faults) as Parquet "
                                             "or CSV files",
                              description="A run's tables — ticks, estimates, links, events, faults"
                                          " — as files, one per table: DIR/<table>.parquet or DIR/<table>.csv.")
    p.add_argument("run", metavar="RUN", help="a run directory (its recording.mcap) or a recording file")
    p.add_argument("--format", choices=FORMATS, default="parquet", help="parquet (default; pyarrow) or csv")
    p.add_argument("--out", required=True, metavar="DIR", help="the directory for the files")
    p.set_defaults(fn=cmd_export)
