"""Benchmark: a sweep on the local process pool against the same sweep on a Dask LocalCluster.

The same 16-run grid (``gu_hu_normal``, ``faults.link_loss=0,0.1,0.2,0.3`` × 4 seeds, 150 ticks, in-process
engine, no figures) runs once through ``--executor local`` and once through ``--executor dask`` with as many
workers as the pool has processes (2 by default). Each wall time is the whole sweep as a user waits for it —
planning, starting the pool or the cluster, the runs, writing the results back (Dask's come back as data) and
the CSVs. Both must give the same ``results.csv``; the target is a Dask throughput of at least 0.9 × the
pool's.

    python bench/bench_sweep.py [--jobs 2] [--ticks 150] [--out bench/results/sweep.json]

Writes the wall times, the throughputs (runs/s), their ratio and the machine (CPU count, Python, platform,
load average before and after).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from flocktrack.experiment.grid import parse_grid  # noqa: E402 - after the sys.path line: runs from a checkout
from flocktrack.experiment.sweep import SweepConfig, run_sweep  # noqa: E402 - same

SCENARIO = str(ROOT / "scenarios" / "gu_hu_normal.toml")
GRID = "faults.link_loss=0,0.1,0.2,0.3"
SEEDS = 4


def _sweep(executor: str, *, jobs: int, ticks: int, out: Path) -> dict:
    cfg = SweepConfig(scenario=SCENARIO, axes=[parse_grid(GRID)], seeds=list(range(SEEDS)), out=out, ticks=ticks,
                      jobs=jobs, resume=False, figures=False, progress=False, executor=executor)
    t0 = time.perf_counter()
    meta = run_sweep(cfg)
    wall = time.perf_counter() - t0
    assert meta["ok"] == meta["runs"] == len(cfg.seeds) * len(cfg.axes[0].values), meta["failures"]
    return {"wall_s": round(wall, 2), "runs": meta["runs"], "runs_per_s": round(meta["runs"] / wall, 3),
            "run_wall_s_total": round(meta["run_wall_s_total"], 2), "executor": meta["executor"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=2, help="pool processes = Dask workers (default 2)")
    ap.add_argument("--ticks", type=int, default=150)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "sweep.json"))
    args = ap.parse_args()
    import distributed

    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench-sweep-") as tmp:
        local = _sweep("local", jobs=args.jobs, ticks=args.ticks, out=Path(tmp) / "local")
        dask = _sweep("dask", jobs=args.jobs, ticks=args.ticks, out=Path(tmp) / "dask")
        same = (Path(tmp) / "local" / "results.csv").read_text() == (Path(tmp) / "dask" / "results.csv").read_text()
    ratio = dask["runs_per_s"] / local["runs_per_s"]
    result = {
        "what": f"{SEEDS * 4} runs of {Path(SCENARIO).name} ({GRID} × {SEEDS} seeds, {args.ticks} ticks, inproc): "
                f"the local process pool vs a Dask LocalCluster, {args.jobs} workers each",
        "local": local,
        "dask": dask,
        "dask_over_local_throughput": round(ratio, 3),
        "target": ">= 0.9",
        "meets_target": ratio >= 0.9,
        "same_results_csv": same,
        "machine": {"cpu_count": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform(),
                    "distributed": distributed.__version__,
                    "loadavg_before": [round(x, 2) for x in load_before],
                    "loadavg_after": [round(x, 2) for x in os.getloadavg()]},
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
