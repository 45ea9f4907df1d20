"""Benchmark of Zamani & Ugrinovskii's min-energy filters: SDP design time (Clarabel vs SCS) and filter
cost per tick per node. Writes ``bench/results/min_energy.json``.

    python bench/bench_min_energy.py            # full (SCS centring takes ~1–2 min)
    python bench/bench_min_energy.py --quick    # skips the SCS centring solves

OpenBLAS is pinned to one thread *before* numpy is imported: the filter works on 3×3 / 6×6 matrices,
and on a loaded machine multi-threaded OpenBLAS makes each tiny LAPACK call (e.g. inside
scipy.linalg.expm) 10–100× slower. The runtime should do the same for its sensor processes.
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import scipy.linalg

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent.estimators.base import TickContext
from agent.estimators.min_energy import DesignError, MinEnergyNode, design_network

A = np.array([[-3.2, 10.0, 0.0], [1.0, -1.0, 1.0], [0.0, -14.87, 0.0]])
B = np.array([[0.4], [0.4], [0.4]])
C14 = 0.001 * np.array([[3.1923, -4.6597, 1.0]])
C235 = np.array([[-0.8986, 0.1312, -1.9703]])
C = [C14, C235, C235, C14, C235]
D = np.array([[0.025, 0.0, 0.0]])
EDGES = [(i - 1, j - 1) for (i, j) in [(1, 3), (2, 3), (3, 1), (3, 2), (3, 4), (4, 3), (4, 5), (5, 4)]]
T = 0.01


def timed_design(repeat: int = 3, **kw) -> dict:
    """Best-of-``repeat`` wall time (cvxpy compilation + solve) and the solver's own time."""
    best = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        try:
            d = design_network(A, B, C, D, np.eye(3), 0.5 * np.eye(3), EDGES, **kw)
        except DesignError as exc:
            return {"error": str(exc), "status": exc.status}
        wall = time.perf_counter() - t0
        if best is None or wall < best[0]:
            best = (wall, d)
    wall, d = best
    return {"gamma2": d.gamma2, "gamma2_star": d.gamma2_star, "gammabar2": list(d.gammabar2),
            "zbar_min_eig": [d.zbar_min_eig(i) for i in range(5)], "wall_s": wall,
            "solver_time_s": d.solve_time_s, "info": dict(d.info), "_design": d}


def closed_loop(des, ticks: int, substeps: int, method: str = "expm", X0=None) -> dict:
    """Noise-free closed loop; returns per-node-tick cost (finish() only, and the whole node step)
    and the time for every node's error to fall below 1e-6 of its initial value."""
    N = des.N
    x = np.array([1.0, -0.5, 0.8])
    nodes = [MinEnergyNode.from_design(des, i, np.zeros(3), substeps=substeps, method=method,
                                       X0=None if X0 is None else X0[i]) for i in range(N)]
    Ad = scipy.linalg.expm(A * T)
    e0 = np.linalg.norm(x)
    conv_tick = None
    t_finish = t_total = 0.0
    for k in range(ticks):
        t0 = time.perf_counter()
        for i, nd in enumerate(nodes):
            nbrs = des.problem.nbrs[i]
            nd.start(TickContext(k=k, t=k * T, n=N, neighbours=nbrs, weights=(1.0,) * len(nbrs), T=T), C[i] @ x)
        pay = [nd.payload(0) for nd in nodes]
        for i, nd in enumerate(nodes):
            nd.absorb(0, {j: pay[j] for j in des.problem.nbrs[i]})
        t1 = time.perf_counter()
        for nd in nodes:
            nd.finish()
        t2 = time.perf_counter()
        t_finish += t2 - t1
        t_total += t2 - t0
        x = Ad @ x
        err = max(np.linalg.norm(nd.x - x) for nd in nodes)
        if conv_tick is None and err < 1e-6 * e0:
            conv_tick = k + 1
    final = max(np.linalg.norm(nd.x - x) for nd in nodes) / e0
    return {"ticks": ticks, "substeps": substeps, "method": method, "final_error_rel": final,
            "finish_us_per_node_tick": 1e6 * t_finish / (ticks * N),
            "node_step_us_per_node_tick": 1e6 * t_total / (ticks * N),
            "t_error_below_1e-6_s": None if conv_tick is None else conv_tick * T,
            "riccati_converged": all(nd.riccati_converged for nd in nodes), "nodes": nodes}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="skip the SCS centring solves")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "min_energy.json"))
    args = ap.parse_args()

    res: dict = {"machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                             "openblas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
                             "loadavg": os.getloadavg()},
                 "design": {}, "filter": {}}
    designs = {}
    for z, sim in ((0.0, "sim1"), (0.1, "sim2")):
        for solver in ("CLARABEL", "SCS"):
            for step, f in (("supremum", None), ("centred_1.1", 1.1)):
                if solver == "SCS" and step != "supremum" and args.quick:
                    continue
                r = timed_design(repeat=3 if solver == "CLARABEL" else 1, zbar_min=z, solver=solver,
                                 gamma2_factor=f)
                d = r.pop("_design", None)
                if solver == "CLARABEL" and d is not None:
                    designs[(sim, step)] = d
                res["design"][f"{sim}/{solver}/{step}"] = r
                print(f"{sim} {solver:8s} {step:12s} γ²={r.get('gamma2', float('nan')):.6f} "
                      f"wall={r.get('wall_s', float('nan')):.3f}s solver={r.get('solver_time_s', float('nan')):.4f}s"
                      + (f"  [{r['error']}]" if "error" in r else ""), flush=True)

    for sim in ("sim1", "sim2"):
        for step in ("centred_1.1", "supremum"):
            d = designs[(sim, step)]
            for method, sub, ticks in (("expm", 10, 1000), ("expm", 2, 1000), ("rk4", 10, 400)):
                if method == "rk4" and step == "supremum":
                    continue                                   # RK4 at 1 ms substeps diverges there
                r = closed_loop(d, ticks, sub, method)
                r.pop("nodes")
                res["filter"][f"{sim}/{step}/{method}/substeps={sub}/transient"] = r
                print(f"{sim} {step:12s} {method} J={sub:2d} finish {r['finish_us_per_node_tick']:7.1f} µs/node/tick"
                      f"  error<1e-6 after {r['t_error_below_1e-6_s']} s, final {r['final_error_rel']:.1e}", flush=True)
        # converged Riccati: start every node at its steady-state Q (X0 = Q∞⁻¹) → cached affine tick map
        d = designs[(sim, "centred_1.1")]
        warm = closed_loop(d, 3000, 10)
        X0 = [np.linalg.inv(nd.Q) for nd in warm["nodes"]]
        r = closed_loop(d, 1000, 10, X0=X0)
        r.pop("nodes")
        res["filter"][f"{sim}/centred_1.1/expm/substeps=10/converged"] = r
        print(f"{sim} converged Riccati (cached tick map): finish {r['finish_us_per_node_tick']:.1f} µs/node/tick",
              flush=True)

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2, default=float))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
