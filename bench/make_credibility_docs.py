"""Regenerate the tables of ``docs/credibility.md``: for each paper's scenario, and for Gu & Hu's normal target
at 1, 2, 5 and 10 consensus rounds, how honest each estimator's covariance is (the network ANEES against its
χ² interval, COIN; each node's innovations, NIS), Chen's constant-gain filter's measured energy ratio against its
bound 1/γ, and how far each error is from the centralized Kalman reference (efficiency) — each the mean over
independent seeds of in-process runs (flocktrack/record/credibility.py); and for García Carrillo et al.'s fusion,
each estimator's position NEES against the covariance it sent.

    python bench/make_credibility_docs.py [--seeds N] [--work DIR]

Writes ``bench/results/credibility.json`` and the block between ``<!-- credibility:begin -->`` and
``<!-- credibility:end -->`` in docs/credibility.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from flocktrack.cli import main as cli

#: (label, scenario, --set overrides)
CASES = [
    ("Chen — switching H∞ (constant gain)", "chen_switching", []),
    ("Gu & Hu — normal target, minimax", "gu_hu_normal", []),
    ("Gu & Hu — normal target, Kalman", "gu_hu_normal", ["estimator.name=kalman"]),
    ("Gu & Hu — intelligent target, minimax", "gu_hu_intelligent", []),
    ("the demo (flocking, minimax)", "demo", []),
    *[(f"Gu & Hu — normal target, rounds = {r}", "gu_hu_normal", [f"estimator.rounds={r}"]) for r in (1, 2, 5, 10)],
]


def one(scenario: str, sets: list[str], seed: int, out: Path) -> dict:
    args = ["run", str(ROOT / "scenarios" / f"{scenario}.toml"), "--transport", "inproc", "--quiet", "--seed",
            str(seed), "--out", str(out)]
    for s in sets:
        args += ["--set", s]
    if not (out / "summary.json").exists():
        assert cli(args) == 0, args
    s = json.loads((out / "summary.json").read_text())
    c, eff = s["credibility"], s["credibility"].get("efficiency", {})
    net = c.get("network") or {}
    nis = [v["anees"] for v in (c.get("nis") or {}).values() if v and v.get("anees") is not None]
    hinf = s.get("hinf") or {}
    return {"nis": float(np.mean(nis)) if nis else None,
            "nis_dof": next((v.get("dof") for v in (c.get("nis") or {}).values() if v), None),
            "energy_ratio": hinf.get("network_ratio"), "energy_bound": hinf.get("bound"),
            "from_tick": c.get("from_tick"),
            "anees": net.get("anees"), "interval": net.get("interval"), "verdict": net.get("verdict"),
            "coin": net.get("coin"), "consistent_nodes": c.get("consistent_nodes"), "nodes": s.get("n_sensors"),
            "efficiency": eff.get("network"), "vs_central": eff.get("network_vs_central_mse"),
            "network_rmse": s.get("network_rmse")}


def _mean(rows: list[dict], key: str):
    v = [r[key] for r in rows if r.get(key) is not None]
    return float(np.mean(v)) if v else None


def _f(v, fmt="{:.2f}") -> str:
    return "—" if v is None else fmt.format(v)


def table(results: list[dict]) -> str:
    lines = ["| case | network ANEES (m = 4): mean (seeds' range) | one run's 95 % interval | verdicts | COIN | "
             "nodes' NIS (m = q) | Chen's energy ratio (≤ 1/γ) | efficiency MSE / tr P_central | MSE / central MSE | "
             "network RMSE |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        iv, rg = r["interval"], r["anees_range"]
        spread = f" ({_f(rg[0])}–{_f(rg[1])})" if rg else ""
        energy = "—" if r["energy_ratio"] is None else f"{_f(r['energy_ratio'])} ≤ {_f(r['energy_bound'])}"
        lines.append(f"| {r['label']} | {_f(r['anees'])}{spread} | {_f(iv[0]) + '–' + _f(iv[1]) if iv else '—'} | "
                     f"{r['verdict'] or 'no covariance'} | {_f(r['coin'])} | {_f(r['nis'])} | {energy} | {_f(r['efficiency'])} | "
                     f"{_f(r['vs_central'])} | {_f(r['network_rmse'], '{:.4f}')} |")
    return "\n".join(lines)


def fusion(seeds: int, work: Path) -> list[dict]:
    """García Carrillo et al.'s fusion: each estimator's position NEES (m = 2) at the newest window node
    against the covariance it sent, over ``seeds`` runs of carrillo_uav."""
    runs = []
    for seed in range(seeds):
        out = work / f"carrillo-{seed}"
        if not (out / "summary.json").exists():
            assert cli(["run", str(ROOT / "scenarios" / "carrillo_uav.toml"), "--transport", "inproc", "--quiet",
                        "--seed", str(seed), "--out", str(out)]) == 0
        runs.append(json.loads((out / "summary.json").read_text())["fusion"])
    rows = []
    for name in sorted(k for k, v in runs[0].items() if isinstance(v, dict) and "nees_newest" in v):
        a = [r[name]["nees_newest"]["anees"] for r in runs]
        m = [r[name]["nees_midwindow"]["anees"] for r in runs if "nees_midwindow" in r[name]]
        verdicts = [r[name]["nees_newest"]["verdict"] for r in runs]
        rows.append({"estimator": name, "anees_newest": float(np.mean(a)), "range": [min(a), max(a)],
                     "anees_midwindow": float(np.mean(m)) if m else None,
                     "interval": runs[0][name]["nees_newest"]["interval"],
                     "verdict": ", ".join(f"{verdicts.count(v)} of {len(runs)} {v}" for v in sorted(set(verdicts))),
                     "rmse_newest": float(np.mean([r[name]["rmse_newest"] for r in runs]))})
    return rows


def fusion_table(rows: list[dict], seeds: int) -> str:
    lines = ["", f"García Carrillo et al.'s fusion (`carrillo_uav`, {seeds} seeds): each estimator's position NEES "
             "(m = 2) against the covariance it sent — the windows' from their own information "
             "(`agent/estimators/son_covariance.py`), the Kalman filters' their P.", "",
             "| estimator | ANEES, newest node: mean (seeds' range) | one run's 95 % interval | verdicts | "
             "ANEES, mid-window | RMSE newest (m) |", "|---|---|---|---|---|---|"]
    for r in rows:
        iv = r["interval"]
        lines.append(f"| {r['estimator']} | {_f(r['anees_newest'])} ({_f(r['range'][0])}–{_f(r['range'][1])}) | "
                     f"{_f(iv[0])}–{_f(iv[1])} | {r['verdict']} | {_f(r['anees_midwindow'])} | "
                     f"{_f(r['rmse_newest'])} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--work", default=str(ROOT / "runs" / "credibility_docs"))
    args = ap.parse_args()
    work = Path(args.work)
    t0 = time.time()
    results = []
    for j, (label, scenario, sets) in enumerate(CASES):
        rows = [one(scenario, sets, seed, work / f"{j}-{seed}") for seed in range(args.seeds)]
        verdicts = [r["verdict"] for r in rows if r["verdict"]]
        anees = [r["anees"] for r in rows if r["anees"] is not None]
        results.append({"label": label, "scenario": scenario, "set": sets, "seeds": args.seeds,
                        "anees": _mean(rows, "anees"), "interval": rows[0]["interval"],
                        "anees_range": [min(anees), max(anees)] if anees else None,
                        "verdict": ", ".join(f"{verdicts.count(v)} of {len(rows)} {v}"
                                             for v in sorted(set(verdicts), key=lambda v: (-verdicts.count(v), v))),
                        "coin": _mean(rows, "coin"), "nis": _mean(rows, "nis"),
                        "energy_ratio": _mean(rows, "energy_ratio"), "energy_bound": rows[0]["energy_bound"],
                        "efficiency": _mean(rows, "efficiency"),
                        "vs_central": _mean(rows, "vs_central"), "network_rmse": _mean(rows, "network_rmse"),
                        "runs": rows})
        print(f"{label}: ANEES {_f(results[-1]['anees'])}, efficiency {_f(results[-1]['efficiency'])}", flush=True)
    fused = fusion(args.seeds, work)
    for r in fused:
        print(f"fusion {r['estimator']}: ANEES {_f(r['anees_newest'])} ({r['verdict']})", flush=True)
    out = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                       "platform": platform.platform(), "date": time.strftime("%Y-%m-%d")},
           "seconds": round(time.time() - t0, 1), "cases": results, "fusion": fused}
    (ROOT / "bench" / "results" / "credibility.json").write_text(json.dumps(out, indent=1))
    doc = ROOT / "docs" / "credibility.md"
    text = doc.read_text()
    a, b = text.index("<!-- credibility:begin -->"), text.index("<!-- credibility:end -->")
    doc.write_text(text[:a] + "<!-- credibility:begin -->\n" + table(results) + "\n"
                   + fusion_table(fused, args.seeds) + "\n" + text[b:])
    return 0


if __name__ == "__main__":
    sys.exit(main())
