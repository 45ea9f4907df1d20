"""python -m topology --scenario FILE --connect ENDPOINT [--run NAME] [--expect NAME ...]

Runs the world (clock + link table) in this process over Zenoh. It waits until every sensor, the
target and the ``--expect``-ed members (e.g. ``recorder/0``) are alive, then ticks.
"""

from __future__ import annotations

import argparse
import logging
import sys

from agent.bus import ZenohBus
from agent.runner import StopFlag, WaitBudget, drive, lean_zenoh_runtime, profiled
from agent.scenario import ScenarioError, load_scenario

from .world import build_world


def main(argv: list[str] | None = None) -> int:
    lean_zenoh_runtime()
    ap = argparse.ArgumentParser(prog="python -m topology")
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447")
    ap.add_argument("--run", default=None)
    ap.add_argument("--mode", choices=["lockstep", "realtime"], default=None)
    ap.add_argument("--expect", action="append", default=[], help="extra member that must be alive before tick 0")
    ap.add_argument("--startup-timeout", type=float, default=60.0)
    ap.add_argument("--config", default=None)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        sc = load_scenario(args.scenario)
    except ScenarioError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    mode = args.mode or sc.run.mode
    world = build_world(sc, realtime=(mode == "realtime"))
    expect = [f"agent/{i}" for i in range(sc.sensors.n)] + ["target/0"] + list(args.expect)
    stop = StopFlag().install()
    bus = ZenohBus(args.run or sc.run.name, connect=args.connect, config_file=args.config)
    try:
        # realtime: the clock closes the ticks; the deadline only guards against a clock that stopped, ten of
        # its periods (as the world stretches or a speed change sets it: WorldRole.step_period)
        period = sc.run.T / sc.run.speed
        deadline = (WaitBudget.lockstep(sc.run.deadline_s, rounds=sc.estimator.rounds, depth=world.wait_depth)
                    if mode == "lockstep" else WaitBudget(10 * period, period_s=period))
        rc = profiled("world/0", lambda: drive(world, bus, "world/0", deadline, stop, expect=expect,
                                               startup_timeout_s=args.startup_timeout))
        logging.getLogger("world").info("done: %s", world.stats)
        return rc
    finally:
        bus.close()


if __name__ == "__main__":
    sys.exit(main())
