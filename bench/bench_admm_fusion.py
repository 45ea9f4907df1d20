"""The distributed robust fusion (consensus ADMM between the UAVs, agent/estimators/admm_fusion.py) against
the central robust MHE on the same data, and what its iterations per tick buy.

    python bench/bench_admm_fusion.py [--seeds 5] [--duration 100] [--out bench/results/admm_fusion.json]

The world is scenarios/carrillo_robust.toml's (two UAVs at ~5 Hz each, 40–70 m outliers, T = 0.05 s), at the
outlier rates of its [table]. Per rate and seed: the central :class:`RobustMHE` fed as the fusion role feeds it
(every UAV's records of a tick in time order, a solve after each) and the two ADMM nodes, each with its own
UAV's records (``UavTrack`` — the runtime's own split), run in lockstep in one process (``run_lockstep``).
Scored like summary.json's ``fusion`` block: RMSE of the newest-node position against the truth at that node's
time. Then, at 10 % outliers, the RMSE and the CPU per node and tick for 1, 2, 4, 8 and 16 ADMM iterations
per tick. Writes the JSON and docs/distributed_fusion.md; prints a line per cell.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent.estimators.admm_fusion import AdmmFusionNode, run_lockstep  # noqa: E402 - after the sys.path line: runs from a checkout
from agent.estimators.robust_mhe import RobustMHE  # noqa: E402 - same
from agent.models_uav import config_from_tables  # noqa: E402 - same
from agent.roles.uav import UavTrack, track_records  # noqa: E402 - same
from agent.seeding import rng_for  # noqa: E402 - same


def world(frac: float, seed: int, duration: float):
    data = tomllib.loads((ROOT / "scenarios" / "carrillo_robust.toml").read_text())
    data["run"]["duration"], data["uavs"]["outlier_fraction"] = duration, frac
    cfg = config_from_tables(data)
    return cfg, cfg.sim().generate(duration, rng_for(seed, "uav_stream"))


def truth_at(stream, t: float) -> np.ndarray:
    d = stream.dense
    return np.array([np.interp(t, d["t"], d["pos"][:, 0]), np.interp(t, d["t"], d["pos"][:, 1])])


def rmse(stream, est) -> float:
    e = [x[:2] - truth_at(stream, t) for t, x in est]
    return float(np.sqrt(np.mean(np.sum(np.square(e), axis=1))))


def central(cfg, stream, T: float, ticks: int) -> list:
    u = cfg.uav
    R, G = np.eye(2) * u.sigma_rel ** 2, np.eye(2) * u.sigma_gps ** 2
    tracks = [UavTrack(stream, i, T) for i in range(u.n)]
    srcs = [track_records(tr, R, G) for tr in tracks]
    f = cfg.fusion
    est = RobustMHE(W=int(f["window"]), q=float(f["q"]), c=float(f["c"]), reject=float(f["reject"]),
                    scale_window=int(f["scale_window"]))
    out = []
    for k in range(ticks):
        for rec in sorted((r for s in srcs for r in s(k)), key=lambda r: (r.t, r.agent)):
            est.add(rec)
            r = est.solve()
            out.append((r.t_newest, r.newest))
    return out


def distributed(cfg, stream, T: float, ticks: int, iterations: int, rho: float) -> tuple[list, float, dict]:
    u = cfg.uav
    R, G = np.eye(2) * u.sigma_rel ** 2, np.eye(2) * u.sigma_gps ** 2
    f = cfg.fusion
    nodes = {i: AdmmFusionNode(i, track_records(UavTrack(stream, i, T), R, G), W=int(f["window"]), q=float(f["q"]),
                               iterations=iterations, rho=rho, c=float(f["c"]), reject=float(f["reject"]),
                               scale_window=int(f["scale_window"]), T=T) for i in range(u.n)}
    out, last = [], [None]

    def on_tick(k):
        n = nodes[0]
        if math.isfinite(n.t_newest) and n.t_newest != last[0]:
            last[0] = n.t_newest
            out.append((n.t_newest, n.newest.copy()))

    t0 = time.process_time()
    run_lockstep(nodes, T, range(ticks), on_tick=on_tick)
    cpu = time.process_time() - t0
    return out, cpu / (ticks * len(nodes)) * 1e6, dict(nodes[0].counters)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--duration", type=float, default=100.0)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "admm_fusion.json")
    ap.add_argument("--doc", type=Path, default=ROOT / "docs" / "distributed_fusion.md")
    a = ap.parse_args(argv)
    data = tomllib.loads((ROOT / "scenarios" / "carrillo_robust.toml").read_text())
    T, rates = float(data["run"]["T"]), data["table"]["outlier_fractions"]
    it0, rho = int(data["fusion"]["admm_iterations"]), float(data["fusion"]["admm_rho"])
    ticks = int(math.ceil(a.duration / T))
    cells = []
    for frac in rates:
        rc, rd = [], []
        for seed in range(1, a.seeds + 1):
            cfg, st = world(frac, seed, a.duration)
            rc.append(rmse(st, central(cfg, st, T, ticks)))
            rd.append(rmse(st, distributed(cfg, st, T, ticks, it0, rho)[0]))
            print(f"outliers {frac:.2f} seed {seed}: central {rc[-1]:.3f} m, distributed {rd[-1]:.3f} m", flush=True)
        cells.append({"outlier_fraction": frac, "central_rmse": statistics.fmean(rc), "distributed_rmse": statistics.fmean(rd),
                      "ratio": statistics.fmean(rd) / statistics.fmean(rc), "per_seed": {"central": rc, "distributed": rd}})
    sweep = []
    load = os.getloadavg()[0]
    cfg, st = world(0.10, 1, a.duration)
    c10 = rmse(st, central(cfg, st, T, ticks))
    for it in (1, 2, 4, 8, 16):
        est, us, cnt = distributed(cfg, st, T, ticks, it, rho)
        sweep.append({"iterations": it, "rmse": rmse(st, est), "central_rmse": c10, "cpu_us_per_node_tick": us,
                      "ticks_consensus": cnt["ticks_consensus"]})
        print(f"iterations {it:2d}: {sweep[-1]['rmse']:.3f} m (central {c10:.3f}), {us:.0f} µs CPU per node-tick", flush=True)
    res = {"date": time.strftime("%Y-%m-%d"), "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
           "seeds": a.seeds, "duration_s": a.duration, "T": T, "iterations": it0, "rho": rho, "cells": cells,
           "iteration_sweep": sweep, "load_avg": round(load, 2)}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1))
    a.doc.write_text(doc(res))
    print(f"wrote {a.out} and {a.doc}")
    return 0


def doc(res: dict) -> str:
    lines = ["# Distributed robust fusion: consensus ADMM between the UAVs",
             "",
             "Generated by `python bench/bench_admm_fusion.py` (results: bench/results/admm_fusion.json). García "
             "Carrillo et al. name distributing the solver among the agents as future work; `[fusion] mode = "
             "\"distributed\"` (scenarios/carrillo_robust.toml) does it for the robust moving-horizon fusion: each UAV "
             "process fuses only its own measurements and agrees with the other UAV on the window's target states by "
             "consensus ADMM, one iteration per exchange round (agent/estimators/admm_fusion.py has the splitting, the "
             "round protocol and what happens when a UAV is down). The central process still runs beside them.",
             "",
             f"Newest-node position RMSE (m), mean over {res['seeds']} seeds of {res['duration_s']:g} s, "
             f"{res['iterations']} ADMM iterations per tick (T = {res['T']:g} s), ρ = {res['rho']:g}:",
             "",
             "| outliers | central robust MHE | distributed (ADMM) | ratio |",
             "|---:|---:|---:|---:|"]
    for c in res["cells"]:
        lines.append(f"| {c['outlier_fraction']:.0%} | {c['central_rmse']:.3f} | {c['distributed_rmse']:.3f} | "
                     f"{c['ratio']:.3f} |")
    lines += ["", "Iterations per tick at 10 % outliers (seed 1): what consensus costs and buys (CPU per UAV and "
              f"tick, both nodes in one process, this {res['machine']['cpus']}-core machine at a load average of "
              f"{res.get('load_avg', float('nan')):.1f}):", "",
              "| iterations | RMSE (m) | central (m) | CPU per node-tick (µs) |", "|---:|---:|---:|---:|"]
    for s in res["iteration_sweep"]:
        lines.append(f"| {s['iterations']} | {s['rmse']:.3f} | {s['central_rmse']:.3f} | {s['cpu_us_per_node_tick']:.0f} |")
    lines += ["", "The distributed estimate can come out *below* the central one: a UAV judges its own gross outliers "
              "(residual beyond reject·σ̂) after the tick's first iteration, at a consensus barely moved by the new "
              "measurement, where the central estimator judges them at its full Huber solution, which the outlier "
              "has already pulled (bounded by δ) towards itself.", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
