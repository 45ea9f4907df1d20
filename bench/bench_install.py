"""Benchmark: what installing flocktrack costs — disk and start-up.

Builds the wheel of this tree, installs it into fresh virtual environments (the core dependencies; then
with every extra, ``flocktrack[all]``) and measures, for each:

* the installed size (the environment's site-packages, and the largest packages in it);
* the import time of ``flocktrack`` and of the CLI in a fresh interpreter, as pip installs them (byte code
  compiled): ``cold`` with the kernel's page cache dropped first (as root; else said in the JSON), and
  ``warm``, the median of the next five;
* the wall time of ``flocktrack --version`` and of ``flocktrack scenarios`` (what a user waits for).

    python bench/bench_install.py [--out bench/results/install.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _du(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and not f.is_symlink())


ENV = {k: v for k, v in os.environ.items() if k not in ("PYTHONDONTWRITEBYTECODE", "PYTHONPATH", "VIRTUAL_ENV")}


def _timed(argv: list[str], cwd: Path) -> float:
    t0 = time.perf_counter()
    subprocess.run(argv, cwd=cwd, check=True, capture_output=True, env=ENV)
    return time.perf_counter() - t0


def _drop_page_cache() -> bool:
    """Empty the kernel's page cache (root only): the next start reads every file from disk."""
    try:
        os.sync()
        Path("/proc/sys/vm/drop_caches").write_text("3\n")
        return True
    except OSError:
        return False


def _measure(venv: Path, work: Path) -> dict:
    py, ft = str(venv / "bin" / "python"), str(venv / "bin" / "flocktrack")
    site = next(venv.glob("lib/python*/site-packages"))
    sizes = sorted(((p.name, _du(p)) for p in site.iterdir() if p.is_dir()), key=lambda x: -x[1])
    out: dict = {"site_packages_mb": round(_du(site) / 2**20, 1),
                 "largest_mb": {n: round(s / 2**20, 1) for n, s in sizes[:8]}}
    for what, code in (("import_flocktrack", "import flocktrack"), ("import_cli", "import flocktrack.cli")):
        out["page_cache_dropped"] = _drop_page_cache()
        cold = _timed([py, "-c", code], work)
        warm = [_timed([py, "-c", code], work) for _ in range(5)]
        out[f"{what}_cold_s"], out[f"{what}_warm_s"] = round(cold, 3), round(statistics.median(warm), 3)
    out["version_s"] = round(statistics.median(_timed([ft, "--version"], work) for _ in range(5)), 3)
    out["scenarios_s"] = round(statistics.median(_timed([ft, "scenarios"], work) for _ in range(5)), 3)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "install.json")
    args = ap.parse_args(argv)
    results: dict = {"machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
                     "date": time.strftime("%Y-%m-%d")}
    with tempfile.TemporaryDirectory() as td:
        base = Path(td)
        print("building the wheel …", file=sys.stderr)
        subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(base / "dist"), str(ROOT)],
                       check=True, capture_output=True, cwd=base)
        wheel = next((base / "dist").glob("flocktrack-*.whl"))
        results["wheel_kb"] = round(wheel.stat().st_size / 1024)
        for label, spec in (("core", str(wheel)), ("all", f"{wheel}[all]")):
            print(f"installing {label} …", file=sys.stderr)
            venv = base / f"venv-{label}"
            subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
            subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q", spec],
                           check=True, capture_output=True, env=ENV)
            work = base / f"work-{label}"
            work.mkdir()
            results[label] = _measure(venv, work)
            print(f"{label}: {json.dumps(results[label])}", file=sys.stderr)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
