"""Cost of resilient (W-MSR) consensus vs plain consensus per exchange round of the distributed
minimax filter (4-state target, 2-D measurements), for several neighbour counts.

    python bench/bench_consensus.py  → bench/results/consensus.json
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent.estimators.base import TickContext
from agent.estimators.distributed_minimax import DistributedMinimax
from agent.models import double_integrator


def per_round_us(f: int, degree: int, reps: int = 2000) -> float:
    A, B = double_integrator(0.04, 2)
    C = np.hstack([np.eye(2), np.zeros((2, 2))])
    nodes = [DistributedMinimax(A, B @ B.T * 0.01, C, 0.04 * np.eye(2), 0.09 * np.eye(2), degree + 1, np.zeros(4),
                                np.eye(4), 1, resilient_f=f) for _ in range(degree + 1)]
    rng = np.random.default_rng(0)
    ctx = TickContext(k=0, t=0.0, n=degree + 1, neighbours=tuple(range(1, degree + 1)),
                      weights=(1.0,) * degree, delta_max=degree)
    for nd in nodes:
        nd.start(ctx, rng.normal(size=2))
    inbox = {j: nodes[j].payload(0) for j in range(1, degree + 1)}
    me = nodes[0]
    t0 = time.perf_counter()
    for _ in range(reps):
        me.start(ctx, np.zeros(2))
        me.absorb(0, inbox)
    t1 = time.perf_counter()
    t2 = time.perf_counter()
    for _ in range(reps):
        me.start(ctx, np.zeros(2))
    t3 = time.perf_counter()
    return ((t1 - t0) - (t3 - t2)) / reps * 1e6


def main() -> None:
    out = {"unit": "µs per exchange round (absorb) per node", "degrees": {}}
    for d in (2, 4, 6, 10):
        plain, wmsr = per_round_us(0, d), per_round_us(1, d)
        out["degrees"][str(d)] = {"plain": plain, "w_msr_f1": wmsr, "ratio": wmsr / plain}
        print(f"degree {d}: plain {plain:.1f} µs, W-MSR(f=1) {wmsr:.1f} µs, ×{wmsr / plain:.2f}")
    p = ROOT / "bench" / "results" / "consensus.json"
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
