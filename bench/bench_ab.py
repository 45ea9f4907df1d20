"""Two builds side by side: the runtime's lockstep CPU per tick of build A and build B, measured at once.

On a 2-core VM whose speed changes by 1.5–2 × from minute to minute, two runs of the same build one after the
other differ by more than most changes do (``bench_runtime --sizes 10``: 35.6–59.6 ms a tick in one hour).
Here A and B run *together*, each its own flock of N sensors in lockstep on its own router, so both see the same
phases of the machine; each pair gives B's CPU per tick over A's, and the order of the two launches alternates
from pair to pair. Two copies of one build measured this way differ by 1–2 %.

A build is a directory (a checkout) or a git revision of this repository (checked out into a temporary
worktree); its processes import it through ``PYTHONPATH``. ``--env-a``/``--env-b`` give one build's processes
extra environment variables (a switch under test).

    python bench/bench_ab.py --a HEAD~1 [--b .] [--n 10] [--ticks 600] [--pairs 3]
                                                              → bench/results/ab.json (per pair, per role)

Both flocks on 2 cores run at about half their speed alone, and their CPU per tick is higher than alone: the
ratio is what this measures, not the absolute figures (``bench_runtime`` gives those).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: what each side runs: bench_runtime's lockstep run of its own build, one JSON line on stdout
_ONE = """
import json, sys
sys.path.insert(0, sys.argv[1]); sys.path.insert(0, sys.argv[1] + "/bench")
from bench_runtime import zenoh_run
r = zenoh_run(int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]))
print("RESULT " + json.dumps({"cpu_ms_per_tick": r["cpu_ms_per_tick"], "ticks_per_s": r["ticks_per_s"],
                              "per_sensor": r["per_sensor_per_tick"]}))
"""


def build(spec: str, keep: list[Path]) -> Path:
    """A build's directory: ``spec`` itself when it is one, else a temporary worktree of revision ``spec``."""
    p = Path(spec)
    if p.is_dir():
        return p.resolve()
    d = Path(tempfile.mkdtemp(prefix="flocktrack-ab-")) / "tree"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "--quiet", str(d), spec], check=True)
    keep.append(d)
    return d


def drop(tree: Path) -> None:
    """Remove a worktree :func:`build` made (and its temporary directory)."""
    subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=False)
    shutil.rmtree(tree.parent, ignore_errors=True)


def env_of(tree: Path, extra: list[str]) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=str(tree))
    for kv in extra:
        k, _, v = kv.partition("=")
        env[k] = v
    return env


def ratios(ca: dict[str, float], cb: dict[str, float]) -> dict[str, float]:
    """B's CPU per tick over A's, per role both measured (a role A spent nothing on is left out)."""
    return {k: cb[k] / ca[k] for k in ca if k in cb and ca[k] > 0}


def summarize(pairs: list[dict]) -> dict[str, dict[str, float]]:
    """Median, min and max of B/A over the pairs, per role every pair has."""
    roles = sorted(set.intersection(*(set(p["b_over_a"]) for p in pairs)))
    return {k: {"median": statistics.median(p["b_over_a"][k] for p in pairs),
                "min": min(p["b_over_a"][k] for p in pairs), "max": max(p["b_over_a"][k] for p in pairs)}
            for k in roles}


def one_pair(trees: dict[str, Path], envs: dict[str, dict], order: list[str], a) -> dict[str, dict]:
    """Both builds' runs at once (launched in ``order``); each one's result."""
    procs = {}
    for side in order:
        procs[side] = subprocess.Popen([sys.executable, "-c", _ONE, str(trees[side]), str(a.n), str(a.ticks),
                                        str(a.rounds)], env=envs[side], stdout=subprocess.PIPE, text=True,
                                       cwd=str(trees[side]))
        time.sleep(0.2)
    out = {}
    for side, p in procs.items():
        stdout, _ = p.communicate(timeout=3600)
        lines = [ln for ln in stdout.splitlines() if ln.startswith("RESULT ")]
        if p.returncode != 0 or not lines:
            raise SystemExit(f"build {side} failed (exit {p.returncode}); run it alone to see why")
        out[side] = json.loads(lines[-1][len("RESULT "):])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--a", required=True, help="build A: a directory or a git revision")
    ap.add_argument("--b", default=str(ROOT), help="build B (default: this checkout)")
    ap.add_argument("--env-a", action="append", default=[], metavar="K=V")
    ap.add_argument("--env-b", action="append", default=[], metavar="K=V")
    ap.add_argument("--n", type=int, default=10)
    ap.add_argument("--ticks", type=int, default=600)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "ab.json"))
    a = ap.parse_args()
    keep: list[Path] = []
    try:
        trees = {"a": build(a.a, keep), "b": build(a.b, keep)}
        envs = {"a": env_of(trees["a"], a.env_a), "b": env_of(trees["b"], a.env_b)}
        pairs = []
        for i in range(a.pairs):
            r = one_pair(trees, envs, ["a", "b"] if i % 2 == 0 else ["b", "a"], a)
            ca, cb = r["a"]["cpu_ms_per_tick"], r["b"]["cpu_ms_per_tick"]
            ratio = ratios(ca, cb)
            pairs.append({"a": r["a"], "b": r["b"], "b_over_a": ratio})
            print(f"pair {i + 1}/{a.pairs}: CPU/tick A {ca['total']:.1f} ms, B {cb['total']:.1f} ms, B/A "
                  + ", ".join(f"{k} {v:.3f}" for k, v in ratio.items()), flush=True)
        summary = summarize(pairs)
        res = {"a": a.a, "b": a.b, "env_a": a.env_a, "env_b": a.env_b, "n": a.n, "ticks": a.ticks,
               "rounds": a.rounds, "date": time.strftime("%Y-%m-%d %H:%M"),
               "machine": {"cpus": os.cpu_count(), "loadavg_at_start": list(os.getloadavg())},
               "pairs": pairs, "b_over_a": summary}
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(res, indent=1))
        print("B/A median (min–max): " + ", ".join(f"{k} {v['median']:.3f} ({v['min']:.3f}–{v['max']:.3f})"
                                                   for k, v in summary.items()))
    finally:
        for d in keep:
            drop(d)


if __name__ == "__main__":
    main()
