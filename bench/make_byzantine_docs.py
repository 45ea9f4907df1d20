"""Regenerate the Byzantine tables of ``docs/credibility.md``: on Gu & Hu's normal target with
``estimator.resilient_f = 1``, one sensor turns Byzantine at tick 50 in each mode, at the hub (agent 3) and at
the edge (agents 0 and 7); then the magnitudes a sensor can lie by, small to large, and other start ticks; then
``resilient_f = 2`` with two sensors lying the same way, on the same target with a link range that spans the flock
(the complete graph on 10 sensors, which the run verifies 5-robust at every tick). For each run: the honest
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
MAGNITUDES = [("bias", 0.25), ("bias", 0.5), ("bias", 2.0), ("drift", 2.0), ("drift", 5.0), ("drift", 200.0),
              ("mimic", 0.25), ("mimic", 0.5), ("mimic", 1.0), ("mimic", 2.0), ("mimic", 100.0),
              ("noise", 10.0), ("noise", 300.0)]
#: (mode, magnitude, start tick) at agent 3: an attack from the first tick, before any running test has
#: history, and a late one
STARTS = [("mimic", 1.0, 0), ("bias", 0.5, 0), ("drift", 5.0, 0), ("mimic", 1.0, 200), ("stale", None, 200)]
#: resilient_f = 2: two sensors lying the same way (mode, attackers, magnitude)
DENSE = {"estimator.resilient_f": 2, "topology.range": 40.0}
COLLUDERS = [(m, pair, None) for m in MODES for pair in ("3,5", "0,7")] + [("mimic", "3,5", 1.0),
                                                                         ("bias", "0,7", 0.5)]
SKIP = 60


def run(events: list[dict], ticks: int, out: Path, **over) -> tuple[np.ndarray, dict]:
    data = scenario_data(str(SCENARIO), [], **{"run.ticks": ticks, "estimator.resilient_f": 1, **over})
    data["faults"] = {"events": events}
    summary, _ = run_inproc_to_dir(parse_scenario(data, SCENARIO.name), data, out)
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    n = sum(1 for c in rows[0] if c.startswith("err_"))
    e = np.array([[float(r[f"err_{i}"]) for i in range(n)] for r in rows[SKIP:]])
    return np.sqrt(np.mean(e ** 2, axis=0)), summary


def case(mode: str, node: int | str, magnitude: float | None, base: np.ndarray, ticks: int, work: Path,
         start: int = 50, **over) -> dict:
    """One attack by the sensors ``node`` (one id, or several "3,5" lying the same way) from ``start``."""
    bad = [int(a) for a in str(node).split(",")]
    ev = {"kind": "byzantine", "targets": f"agents:{node}", "mode": mode, "start": start}
    if magnitude is not None:
        ev["magnitude"] = magnitude
    tag = f"{mode}-{str(node).replace(',', '+')}-{magnitude}-{start}-f{over.get('estimator.resilient_f', 1)}"
    per, s = run([ev], ticks, work / tag, **over)
    honest = [i for i in range(len(per)) if i not in bad]
    seen = [s["suspicion"]["attackers"].get(str(a), {}) for a in bad]
    lat = [x.get("latency_ticks") for x in seen]
    return {"mode": mode, "node": node, "magnitude": magnitude, "start": start,
            "f": over.get("estimator.resilient_f", 1),
            "ratio": float(max(per[honest]) / max(base[honest])),
            "latency_ticks": None if any(v is None for v in lat) else max(lat),
            "discarded_share": None if any(x.get("discarded_share") is None for x in seen)
            else min(x["discarded_share"] for x in seen),
            "false_suspicion_rate": s["suspicion"]["false_suspicion_rate"],
            "robustness": s.get("robustness")}


def _cell(r: dict) -> str:
    lat = "—" if r["latency_ticks"] is None else str(r["latency_ticks"])
    return f"{r['ratio']:.2f} ({lat})"


def table(rows: list[dict], base: dict, dense: dict, ticks: int) -> str:
    one = [r for r in rows if r["f"] == 1]
    out = [f"Gu & Hu's normal target, {ticks} ticks, `estimator.resilient_f = 1`, one Byzantine sensor from tick 50.",
           "Each cell: the honest sensors' worst per-node RMSE (ticks 60…) ÷ the fault-free run's, and in brackets",
           "the ticks until a majority of the attacker's neighbours discarded it (— never: NaN payloads are dropped",
           f"by the bus before any estimator sees them). Fault-free: {base['false_suspicion_rate'] * 100:.2f} % of the",
           "honest node-ticks discarded an honest neighbour.", "",
           "| mode (default magnitude) | agent 3 (hub) | agent 0 | agent 7 |", "|---|---|---|---|"]
    for m in MODES:
        cells = [_cell(next(r for r in one if r["mode"] == m and r["node"] == n and r["magnitude"] is None
                            and r["start"] == 50)) for n in NODES]
        out.append(f"| {m} | " + " | ".join(cells) + " |")
    out += ["", "How large a lie must be to be caught (agent 3, from tick 50), and other start ticks. The magnitude is the",
            "fault plan's: a bias in the measurement's units (its noise σ is 0.2), a drift of magnitude/1000 a tick, a",
            "mimic's estimate moved by magnitude/10, noise of magnitude % per value.", "",
            "| mode | magnitude | start tick | ratio (ticks to detection) |", "|---|---|---|---|"]
    for r in one:
        if r["magnitude"] is not None or r["start"] != 50:
            mag = "default" if r["magnitude"] is None else f"{r['magnitude']:g}"
            out.append(f"| {r['mode']} | {mag} | {r['start']} | {_cell(r)} |")
    two = [r for r in rows if r["f"] == 2]
    rob = two[0]["robustness"] if two else {}
    out += ["", "`estimator.resilient_f = 2`, two sensors lying the same way from tick 50, on the same target with",
            "`topology.range = 40` (every sensor hears every other: the complete graph on 10, 5-robust at",
            f"{rob.get('ticks_robust', 0)} of {ticks} ticks as the run verified it). Fault-free:",
            f"{dense['false_suspicion_rate'] * 100:.2f} % false suspicions; in brackets the later of the two detections.",
            "", "| mode | agents 3 and 5 | agents 0 and 7 |", "|---|---|---|"]
    for m in MODES:
        cells = [_cell(next(r for r in two if r["mode"] == m and r["node"] == pair and r["magnitude"] is None))
                 for pair in ("3,5", "0,7")]
        out.append(f"| {m} | " + " | ".join(cells) + " |")
    for r in two:
        if r["magnitude"] is not None:
            out.append(f"| {r['mode']} {r['magnitude']:g} | " + (" | ".join(
                [_cell(r), ""] if r["node"] == "3,5" else ["", _cell(r)])) + " |")
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
    dense_per, dense_s = run([], args.ticks, work / "fault-free-dense", **DENSE)
    dense = {"false_suspicion_rate": dense_s["suspicion"]["false_suspicion_rate"], "robustness": dense_s["robustness"]}
    plan = [(m, n, None, 50, {}) for m in MODES for n in NODES]
    plan += [(m, 3, mag, 50, {}) for m, mag in MAGNITUDES]
    plan += [(m, 3, mag, start, {}) for m, mag, start in STARTS]
    plan += [(m, pair, mag, 50, DENSE) for m, pair, mag in COLLUDERS]
    rows = []
    for i, (m, n, mag, start, over) in enumerate(plan, 1):
        rows.append(case(m, n, mag, dense_per if over else base_per, args.ticks, work, start=start, **over))
        r = rows[-1]
        print(f"[{i}/{len(plan)}] {m} at {n} magnitude {mag} from {start}, f = {r['f']}: {r['ratio']:.2f}x, "
              f"detected after {r['latency_ticks']} ticks", flush=True)
    res = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
           "ticks": args.ticks, "fault_free": base, "fault_free_dense": dense, "rows": rows,
           "wall_s": time.perf_counter() - t0}
    (ROOT / "bench" / "results" / "byzantine.json").write_text(json.dumps(res, indent=1) + "\n")
    doc = ROOT / "docs" / "credibility.md"
    text = doc.read_text()
    begin, end = "<!-- byzantine:begin -->", "<!-- byzantine:end -->"
    block = f"{begin}\n{table(rows, base, dense, args.ticks)}\n{end}"
    if begin in text:
        text = text[:text.index(begin)] + block + text[text.index(end) + len(end):]
    else:
        text = text.rstrip("\n") + "\n\n## Byzantine sensors\n\n" + block + "\n"
    doc.write_text(text)
    print(f"wrote docs/credibility.md and bench/results/byzantine.json in {res['wall_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
