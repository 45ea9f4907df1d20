"""The largest flock this machine holds in realtime: N sensors at a tick rate, minutes long, zero missed deadlines?

    python bench/bench_capacity.py [--sizes 12 16 20 24] [--hz 10] [--minutes 1] [--out bench/results/capacity.json]

Each size is scenarios/demo.toml (the README's main job: Gu & Hu's intelligent target, distributed minimax,
3 rounds, flocking) with ``sensors.n = N`` (placed by the scenario, not the demo's 12 fixed starts), in
realtime at ``--hz`` ticks per second of wall time — the demo's T = 0.04 s of model time (the minimax filter is
stable only for T ≈ 0.03–0.046 against this target) at realtime factor T·hz — one OS process per sensor, the
launcher's embedded router and recorder, no dashboard. Per size: missed round deadlines (the launcher counts
the children's ``deadline on`` lines), late payloads (sum of the sensors' ``late_payloads``), ticks the world
ran late or skipped, the achieved ticks/s and the network RMSE. "Holds" = zero missed round deadlines and
no sensor state that reached the world after its clock closed the tick (``late_states``, ``missing_states``). Writes every
size's numbers (JSON) and prints progress; ``--stop-at-first-miss`` ends the sweep at the first size that misses.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent.scenario import parse_scenario, scenario_data  # noqa: E402 - after the sys.path insert above
from flocktrack.engine.run import run_zenoh_to_dir  # noqa: E402 - same
from machine_gaps import GapMonitor  # noqa: E402 - bench/ is this script's directory


def size_data(n: int, hz: float, minutes: float) -> dict:
    data = scenario_data(str(ROOT / "scenarios" / "demo.toml"), [], **{"run.mode": "realtime", "sensors.n": n})
    data.setdefault("sensors", {}).pop("positions", None)     # the demo's 12 fixed starts: let N be placed
    run = data["run"]
    run["speed"] = round(float(run["T"]) * hz, 6)
    run["ticks"] = int(minutes * 60.0 * hz)
    return data


def run_size(n: int, hz: float, minutes: float) -> dict:
    data = size_data(n, hz, minutes)
    sc = parse_scenario(data, f"demo.toml (sensors.n = {n})")
    print(f"[capacity] {n} sensors, {sc.run.ticks} ticks at {hz:g} Hz ({minutes:g} min)", flush=True)
    with tempfile.TemporaryDirectory(prefix=f"capacity{n}_") as d:
        out = Path(d)
        t0 = time.monotonic()
        with GapMonitor() as gaps:      # the machine's own stops, beside the run (bench/machine_gaps.py)
            summary, info = run_zenoh_to_dir(sc, data, out, quiet=True, timeout_s=minutes * 60 * 3 + 300)
        wall = time.monotonic() - t0
        missed_ticks = sorted({int(k) for f in (out / "logs").glob("*.log")
                               for k in re.findall(r"deadline on \((\d+), \d+\)", f.read_text(errors="replace"))})
        late = sum(int(json.loads(f.read_text()).get("role", {}).get("late_payloads", 0))
                   for f in (out / "stats").glob("agent-*.json"))
        world = json.loads(next((out / "stats").glob("world_*.json")).read_text()) \
            if list((out / "stats").glob("world_*.json")) else {}
    missed = int(info.get("missed_deadlines", 0))
    row = {"sensors": n, "hz": hz, "ticks": sc.run.ticks, "rc": info.get("rc"), "wall_s": round(wall, 1),
           "ticks_per_s": info.get("ticks_per_s"), "missed_deadlines": missed, "late_payloads": late,
           "world": {k: v for k, v in world.get("role", {}).items()
                     if "late" in k or "miss" in k or "skip" in k or "slip" in k},
           "network_rmse": summary.get("network_rmse"),
           # the ticks with a missed deadline; and the moments the machine stopped a 1 ms sleeper > 20 ms
           "ticks_with_misses": missed_ticks[:200], "machine_gaps": _gaps_summary(gaps.result()),
           "holds": missed == 0 and info.get("rc") == 0 and not any(world.get("role", {}).get(k, 0)
                                                                     for k in ("late_states", "missing_states"))}
    g = row["machine_gaps"] or {}
    print(f"[capacity] {n} sensors: {row['ticks_per_s']:.2f} ticks/s, missed deadlines {missed} in "
          f"{len(missed_ticks)} ticks, late payloads {late}, RMSE {row['network_rmse']:.3g}, machine stopped "
          f"> 20 ms {g.get('count', '?')}× (longest {g.get('max_ms', '?')} ms) — "
          f"{'holds' if row['holds'] else 'does not hold'}", flush=True)
    return row


def _gaps_summary(g: dict | None) -> dict | None:
    """bench/machine_gaps.py's result, its list of gaps cut to the 50 longest (ms)."""
    if g is None:
        return None
    return {"count": g["count"], "max_ms": g["max_ms"], "min_ms": g["min_ms"],
            "longest_ms": sorted((x[1] for x in g["gaps"]), reverse=True)[:50]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[12, 16, 20, 24])
    ap.add_argument("--hz", type=float, default=10.0)
    ap.add_argument("--minutes", type=float, default=1.0)
    ap.add_argument("--stop-at-first-miss", action="store_true")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "capacity.json")
    a = ap.parse_args(argv)
    rows = []
    for n in a.sizes:
        rows.append(run_size(n, a.hz, a.minutes))
        if a.stop_at_first_miss and not rows[-1]["holds"]:
            break
    held = [r["sensors"] for r in rows if r["holds"]]
    res = {"date": time.strftime("%Y-%m-%d"), "hz": a.hz, "minutes": a.minutes, "sizes": rows,
           "largest_holding": max(held) if held else None}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1))
    print(f"[capacity] largest flock holding {a.hz:g} Hz for {a.minutes:g} min: {res['largest_holding']} sensors; "
          f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
