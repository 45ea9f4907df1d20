"""Repeat tests to find flakes: ``python bench/flake_hunt.py TESTS --repeat 10 --parallel 2``.

TESTS are what pytest takes (files, ``file::test`` node ids, directories); ``-k EXPR`` / ``-m EXPR``
narrow them as in pytest. ``--as-given`` runs each TESTS argument as one unit instead (a file whole: its
tests share their module fixtures, e.g. one live run for all the browser tests). Every collected test runs ``--repeat`` times, each run in its own
``python -m pytest`` process with its own ``--basetemp`` (so the logs and run directories of a failed
run stay on disk), ``--parallel`` runs at once — two copies of a multi-process test load a 2-core
machine the way a busy CI host does.

Prints a progress line per finished run and a table (test, passed/runs, median and max seconds, the
first line of the first failure); writes the same as JSON (``--out``, default
``bench/results/flake_hunt.json``). Exit code 1 if any run failed.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def collect(tests: list[str], k: str | None, m: str | None) -> list[str]:
    """The node ids pytest collects from ``tests`` (with -k / -m)."""
    argv = [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", *tests]
    if k:
        argv += ["-k", k]
    if m:
        argv += ["-m", m]
    out = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True)
    ids = [ln.strip() for ln in out.stdout.splitlines() if "::" in ln and not ln.startswith(" ")]
    if not ids:
        sys.exit(f"flake_hunt: nothing collected from {tests} (pytest said: {out.stdout[-500:]}{out.stderr[-500:]})")
    return ids


def failure_line(output: str) -> str:
    """The most telling line of a failed pytest run: its ``E   `` assertion line, else the summary."""
    for ln in output.splitlines():
        if ln.startswith("E   "):
            return ln[4:].strip()[:200]
    for ln in output.splitlines():
        if ln.startswith(("FAILED", "ERROR")):
            return ln.strip()[:200]
    return output.strip().splitlines()[-1][:200] if output.strip() else "(no output)"


def run_once(node: str, attempt: int, workdir: Path, timeout_s: float) -> dict:
    base = workdir / f"{node.replace('/', '_').replace('::', '__')}" / f"run{attempt}"
    base.mkdir(parents=True, exist_ok=True)
    argv = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", f"--basetemp={base / 'tmp'}", node]
    t0 = time.monotonic()
    try:
        p = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=timeout_s)
        rc, out = p.returncode, p.stdout + p.stderr
    except subprocess.TimeoutExpired as exc:
        rc, out = -1, f"timeout after {timeout_s:.0f} s\n{exc.stdout or ''}"
    dt = time.monotonic() - t0
    (base / "pytest.log").write_text(out if isinstance(out, str) else out.decode(errors="replace"))
    skipped = rc == 0 and " skipped" in out and " passed" not in out
    return {"test": node, "attempt": attempt, "rc": rc, "passed": rc == 0 and not skipped, "skipped": skipped,
            "seconds": round(dt, 2), "failure": None if rc == 0 else failure_line(out), "log": str(base / "pytest.log")}


def table(results: list[dict]) -> list[dict]:
    rows = []
    for node in dict.fromkeys(r["test"] for r in results):
        rs = [r for r in results if r["test"] == node]
        secs = [r["seconds"] for r in rs]
        fails = [r for r in rs if not r["passed"] and not r["skipped"]]
        rows.append({"test": node, "runs": len(rs), "passed": sum(r["passed"] for r in rs),
                     "skipped": sum(r["skipped"] for r in rs), "median_s": round(statistics.median(secs), 1),
                     "max_s": round(max(secs), 1), "first_failure": fails[0]["failure"] if fails else None,
                     "failed_logs": [r["log"] for r in fails]})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("tests", nargs="+", help="pytest files / node ids")
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--parallel", type=int, default=2, help="runs at once (2 loads a 2-core machine)")
    ap.add_argument("--as-given", action="store_true", help="one unit per TESTS argument (a file runs whole)")
    ap.add_argument("-k", help="pytest -k expression")
    ap.add_argument("-m", help="pytest -m expression")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per run before it counts as failed")
    ap.add_argument("--workdir", type=Path, help="where run logs go (default: a new temporary directory)")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "flake_hunt.json")
    a = ap.parse_args(argv)
    nodes = list(a.tests) if a.as_given else collect(a.tests, a.k, a.m)
    workdir = a.workdir or Path(tempfile.mkdtemp(prefix="flake_hunt_"))
    jobs = [(n, i) for i in range(a.repeat) for n in nodes]   # round-robin: different tests overlap
    print(f"flake_hunt: {len(nodes)} test(s) × {a.repeat} = {len(jobs)} runs, {a.parallel} at once; logs in {workdir}",
          flush=True)
    results: list[dict] = []
    t0 = time.monotonic()
    with ThreadPoolExecutor(max_workers=max(1, a.parallel)) as ex:
        futs = [ex.submit(run_once, n, i, workdir, a.timeout) for n, i in jobs]
        for f in as_completed(futs):
            r = f.result()
            results.append(r)
            mark = "pass" if r["passed"] else ("skip" if r["skipped"] else "FAIL")
            print(f"[{len(results):>4}/{len(jobs)}] {mark} {r['seconds']:7.1f} s  {r['test']}"
                  + (f"\n        {r['failure']}\n        log: {r['log']}" if r["failure"] else ""), flush=True)
    rows = table(results)
    w = max(len(r["test"]) for r in rows)
    print(f"\n{'test':<{w}}  passed  median_s  max_s  first failure")
    for r in rows:
        print(f"{r['test']:<{w}}  {r['passed']:>2}/{r['runs']:<3}  {r['median_s']:>8}  {r['max_s']:>5}  {r['first_failure'] or ''}")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    a.out.write_text(json.dumps({"commit": commit or None, "repeat": a.repeat, "parallel": a.parallel, "cpus": os.cpu_count(),
                                 "wall_s": round(time.monotonic() - t0, 1), "date": time.strftime("%Y-%m-%d"),
                                 "tests": rows}, indent=1))
    print(f"\nwrote {a.out}")
    return 0 if all(r["passed"] + r["skipped"] == r["runs"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
