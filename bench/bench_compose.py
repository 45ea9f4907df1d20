"""Time to build and start the compose deployment, and the image's size → bench/results/compose.json.

    python bench/bench_compose.py [--sensors 4] [--ticks 100] [--out bench/results/compose.json]

Uses the running Docker engine, else starts one (flocktrack.testbed.docker: no bridge, host networking),
and measures, with the generated files of ``flocktrack compose --network host --base-image …``:

* ``base_image_s``: ``flocktrack image`` (mmdebstrap | docker import), from nothing;
* ``build_first_s``: ``docker compose build`` with an empty build cache (every dependency from PyPI);
* ``build_sources_changed_s``: the same after a change to one source file (the dependency layer cached);
* ``build_nothing_changed_s``: the same once more (everything cached);
* ``up_to_world_started_s`` / ``run_s``: ``docker compose up -d`` until the world container runs, and
  until it exits (lockstep, ``--ticks`` ticks), and ``down_s``;
* ``image_bytes`` / ``base_image_bytes``.

Run it alone on the machine (it builds with both cores).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from flocktrack.testbed.docker import Engine  # noqa: E402 - after the sys.path insert above
from flocktrack.testbed.tools import docker_compose, docker_engine  # noqa: E402 - after the sys.path insert above

from flocktrack.deploy import image  # noqa: E402 - after the sys.path insert above
from flocktrack.cli import main as cli  # noqa: E402 - after the sys.path insert above
from flocktrack.launch.launcher import free_port  # noqa: E402 - after the sys.path insert above

BASE = "flocktrack-base:bench"
IMAGE = "flocktrack:bench"


def timed(fn) -> float:
    t0 = time.monotonic()
    fn()
    return round(time.monotonic() - t0, 1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sensors", type=int, default=4)
    ap.add_argument("--ticks", type=int, default=100)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "compose.json"))
    args = ap.parse_args(argv)
    eng = Engine.start(docker_engine())
    res: dict = {"bench": "compose build and start", "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S"),
                 "cpus": os.cpu_count(), "sensors": args.sensors, "ticks": args.ticks,
                 "engine": eng.docker("version", "--format", "{{.Server.Version}}").stdout.strip()}
    try:
        with tempfile.TemporaryDirectory() as td:
            d = Path(td)
            compose = [*docker_compose(), "-p", "ftbench"]

            def run(*a, timeout=1800):
                p = subprocess.run([*compose, *a], cwd=d, env=eng.env, capture_output=True, text=True, timeout=timeout)
                if p.returncode:
                    raise SystemExit(f"docker compose {' '.join(a)} failed: {p.stderr[-1500:]}")
                return p.stdout

            eng.docker("rmi", "-f", BASE, IMAGE, check=False)
            eng.docker("builder", "prune", "-af", check=False)
            print("[bench] base image …", flush=True)
            res["base_image_s"] = timed(lambda: image.build_base_image(BASE, env=eng.env, progress=None))
            assert cli(["compose", str(ROOT / "scenarios" / "demo.toml"), "--set", f"sensors.n={args.sensors}",
                        "--set", f"run.ticks={args.ticks}", "--mode", "lockstep", "--out", str(d), "--network", "host",
                        "--base-image", BASE, "--image", IMAGE, "--router-port", str(free_port()),
                        "--dashboard-port", str(free_port()), "--data", str(d / "data")]) == 0
            print("[bench] first build …", flush=True)
            res["build_first_s"] = timed(lambda: run("build"))
            # a source change: the compose file's build context is the source tree; touch a copy instead
            # of the tree itself: rebuild from a context with one file changed
            src = ROOT / "flocktrack" / "__init__.py"
            old = src.read_bytes()
            try:
                src.write_bytes(old + b"\n# bench_compose: a source change\n")
                res["build_sources_changed_s"] = timed(lambda: run("build"))
            finally:
                src.write_bytes(old)
            run("build")
            res["build_nothing_changed_s"] = timed(lambda: run("build"))
            t0 = time.monotonic()
            run("up", "-d", "--no-build")
            world = run("ps", "-a", "-q", "world-0").strip()
            while eng.docker("inspect", "-f", "{{.State.StartedAt}}", world).stdout.startswith("0001"):
                time.sleep(0.2)
            res["up_to_world_started_s"] = round(time.monotonic() - t0, 1)
            eng.docker("wait", world, timeout=600)
            res["run_s"] = round(time.monotonic() - t0, 1)
            res["down_s"] = timed(lambda: run("down", "-v", "--timeout", "10"))
            res["image_bytes"] = int(eng.docker("image", "inspect", "-f", "{{.Size}}", IMAGE).stdout)
            res["base_image_bytes"] = int(eng.docker("image", "inspect", "-f", "{{.Size}}", BASE).stdout)
    finally:
        eng.stop()
    Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
