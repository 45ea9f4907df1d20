"""The README's main job at full speed, several times in a row: does every run keep its realtime pace?

    python bench/bench_demo.py [--runs 3] [--out bench/results/demo.json]

Each run is the README's main command — ``flocktrack run scenarios/demo.toml --dashboard --out DIR`` (12
sensors, the intelligent target, 1000 ticks at T = 0.04 s, realtime at speed 1.0: 25 ticks/s; the embedded
router, one process per role, the live dashboard) — with ``--no-linger`` so that it ends with the run instead of
keeping the dashboard up, and the machine-gap sleeper (bench/machine_gaps.py) beside it. No browser is
connected (the dashboard serves no viewer). Per run: missed round deadlines (run.json), the world's late and
missing states and stretched ticks (stats/world-0.json), the network RMSE, the machine's own stops, and its
speed: the share of the run it spent in slow phases, and the run's ticks and missed deadlines split between
those phases and the rest (``by_speed``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from machine_gaps import (  # noqa: E402 - bench/ is this script's directory
    GapMonitor, by_speed, missed_by_tick, speed_summary, tick_walls)


def one_run(i: int, port: int) -> dict:
    with tempfile.TemporaryDirectory(prefix=f"demo{i}_") as d:
        out = Path(d) / "demo"
        cmd = [sys.executable, "-m", "flocktrack", "run", str(ROOT / "scenarios" / "demo.toml"), "--dashboard",
               "--dashboard-port", str(port), "--no-linger", "--quiet", "--out", str(out)]
        t0 = time.monotonic()
        with GapMonitor() as gaps:
            proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
        wall = time.monotonic() - t0
        info = json.loads((out / "run.json").read_text()) if (out / "run.json").exists() else {}
        summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else {}
        world_f = out / "stats" / "world-0.json"
        world = json.loads(world_f.read_text()).get("role", {}) if world_f.exists() else {}
        missed = missed_by_tick(out / "logs")
        walls = tick_walls(out / "recording.mcap")
    g = gaps.result() or {}
    speed = speed_summary(g)
    split = by_speed(g, walls, missed)
    row = {"run": i, "rc": proc.returncode, "wall_s": round(wall, 1), "ticks_per_s": info.get("ticks_per_s"),
           "missed_deadlines": info.get("missed_deadlines"),
           "world": {k: v for k, v in world.items() if "late" in k or "miss" in k or "slip" in k or "pace" in k},
           "network_rmse": summary.get("network_rmse"),
           "machine_gaps": {"count": g.get("count"), "max_ms": g.get("max_ms")},
           "machine_speed": speed, "missed_by_speed": split}
    print(f"[demo] run {i}: rc {row['rc']}, {row['ticks_per_s'] or 0:.1f} ticks/s, missed deadlines "
          f"{row['missed_deadlines']}, world {row['world']}, RMSE {row['network_rmse'] or float('nan'):.3g}, "
          f"machine stopped > 20 ms {g.get('count', '?')}× (longest {g.get('max_ms', '?')} ms), slow "
          f"{(speed or {}).get('slow_share', '?')} of the time; ticks / missed in slow phases "
          f"{_split(split, 'slow')}, in the rest {_split(split, 'fast')}", flush=True)
    if proc.returncode != 0:
        print(proc.stdout[-2000:], proc.stderr[-2000:], sep="\n", flush=True)
    return row


def _split(split: dict | None, part: str) -> str:
    return "?" if split is None else f"{split[part]['ticks']} / {split[part]['missed']}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--port", type=int, default=8093, help="the dashboard's port")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "demo.json")
    a = ap.parse_args(argv)
    rows = [one_run(i + 1, a.port) for i in range(a.runs)]
    res = {"date": time.strftime("%Y-%m-%d"), "machine": {"cpus": os.cpu_count(), "loadavg": list(os.getloadavg())},
           "command": "flocktrack run scenarios/demo.toml --dashboard --no-linger --quiet --out DIR", "runs": rows,
           "every_run_holds": all(r["rc"] == 0 and r["missed_deadlines"] == 0 for r in rows)}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1))
    print(f"[demo] {a.runs} runs, missed deadlines {[r['missed_deadlines'] for r in rows]}; wrote {a.out}")
    return 0 if res["every_run_holds"] else 1


if __name__ == "__main__":
    sys.exit(main())
