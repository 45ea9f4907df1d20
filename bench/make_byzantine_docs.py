"""Regenerate the Byzantine table of ``docs/credibility.md``: on Gu & Hu's normal target with
``estimator.resilient_f = 1``, one sensor turns Byzantine at tick 50 in each mode, at the hub (agent 3) and at
the edge (agents 0 and 7); then the magnitudes a sensor can lie by, small to large. For each run: the honest
sensors' worst per-node RMSE over ticks 60… against the fault-free run's (the containment ratio), and when a
majority of the attacker's neighbours first discarded it (summary.json → ``suspicion``).

    python bench/make_byzantine_docs.py [--ticks 300] [--work DIR]

Writes ``bench/results/byzantine.json`` and the block between ``<!-- byzantine:begin -->`` and
``<!-- byzantine:end -->`` in docs/credibility.md.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from agent.scenario import parse_scenario, scenario_data
from flocktrack.engine.run import run_inproc_to_dir

SCENARIO = ROOT / "scenarios" / "gu_hu_normal.toml"
MODES = ("nan", "huge", "stale", "bias", "drift", "noise", "mimic")
NODES = (3, 0, 7)
#: (mode, magnitude): how small a lie gets through, and how large ones fare (defaults: bias 50, drift 0.05 a
#: tick, noise 50 %, mimic 5)
MAGNITUDES = [("bias", 0.5), ("bias", 2.0), ("drift", 5.0), ("drift", 200.0), ("mimic", 1.0), ("mimic", 100.0),
              ("noise", 10.0), ("noise", 300.0)]
SKIP = 60


def run(events: list[dict], ticks: int, out: Path) -> tuple[np.ndarray, dict]:
    data = scenario_data(str(SCENARIO), [], **{"run.ticks": ticks, "estimator.resilient_f": 1})
    data["faults"] = {"events": events}
    summary, _ = run_inproc_to_dir(parse_scenario(data, SCENARIO.name), data, out)
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    n = sum(1 for c in rows[0] if c.startswith("err_"))
    e = np.array([[float(r[f"err_{i}"]) for i in range(n)] for r in rows[SKIP:]])
    return np.sqrt(np.mean(e ** 2, axis=0)), summary


def case(mode: str, node: int, magnitude: float | None, base: np.ndarray, ticks: int, work: Path) -> dict:
    ev = {"kind": "byzantine", "targets": f"agents:{node}", "mode": mode, "start": 50}
    if magnitude is not None:
        ev["magnitude"] = magnitude
    per, s = run([ev], ticks, work / f"{mode}-{node}-{magnitude}")
    honest = [i for i in range(len(per)) if i != node]
    seen = s["suspicion"]["attackers"].get(str(node), {})
    return {"mode": mode, "node": node, "magnitude": magnitude,
            "ratio": float(max(per[honest]) / max(base[honest])), "latency_ticks": seen.get("latency_ticks"),
            "discarded_share": seen.get("discarded_share"),
            "false_suspicion_rate": s["suspicion"]["false_suspicion_rate"]}


def table(rows: list[dict], base: dict, ticks: int) -> str:
    def cell(r):
        lat = "—" if r["latency_ticks"] is None else str(r["latency_ticks"])
        return f"{r['ratio']:.2f} ({lat})"

    out = [f"Gu & Hu's normal target, {ticks} ticks, `estimator.resilient_f = 1`, one Byzantine sensor from tick 50.",
           "Each cell: the honest sensors' worst per-node RMSE (ticks 60…) ÷ the fault-free run's, and in brackets",
           "the ticks until a majority of the attacker's neighbours discarded it (— never: NaN payloads are dropped",
           f"by the bus before any estimator sees them). Fault-free: {base['false_suspicion_rate'] * 100:.2f} % of the",
           "honest node-ticks discarded an honest neighbour.", "",
           "| mode (default magnitude) | agent 3 (hub) | agent 0 | agent 7 |", "|---|---|---|---|"]
    for m in MODES:
        cells = [cell(next(r for r in rows if r["mode"] == m and r["node"] == n and r["magnitude"] is None))
                 for n in NODES]
        out.append(f"| {m} | " + " | ".join(cells) + " |")
    out += ["", "How large a lie must be to be caught (agent 3):", "",
            "| mode | magnitude | ratio (ticks to detection) |", "|---|---|---|"]
    for r in rows:
        if r["magnitude"] is not None:
            out.append(f"| {r['mode']} | {r['magnitude']:g} | {cell(r)} |")
    return "\n".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ticks", type=int, default=300)
    ap.add_argument("--work", default=None, help="where the runs go (default: a temporary directory)")
    args = ap.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="byzantine-"))
    t0 = time.perf_counter()
    base_per, base_s = run([], args.ticks, work / "fault-free")
    base = {"false_suspicion_rate": base_s["suspicion"]["false_suspicion_rate"]}
    rows = [case(m, n, None, base_per, args.ticks, work) for m in MODES for n in NODES]
    rows += [case(m, 3, mag, base_per, args.ticks, work) for m, mag in MAGNITUDES]
    for r in rows:
        print(r, flush=True)
    res = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
           "ticks": args.ticks, "fault_free": base, "rows": rows, "wall_s": time.perf_counter() - t0}
    (ROOT / "bench" / "results" / "byzantine.json").write_text(json.dumps(res, indent=1) + "\n")
    doc = ROOT / "docs" / "credibility.md"
    text = doc.read_text()
    begin, end = "<!-- byzantine:begin -->", "<!-- byzantine:end -->"
    block = f"{begin}\n{table(rows, base, args.ticks)}\n{end}"
    if begin in text:
        text = text[:text.index(begin)] + block + text[text.index(end) + len(end):]
    else:
        text = text.rstrip("\n") + "\n\n## Byzantine sensors\n\n" + block + "\n"
    doc.write_text(text)
    print(f"wrote docs/credibility.md and bench/results/byzantine.json in {res['wall_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
