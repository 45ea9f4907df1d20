"""python -m agent ROLE --id I --scenario FILE --connect ENDPOINT [--run NAME] [--design FILE] [--hosts MAP]

Runs one agent-side role (``sensor`` or ``target``) in this process over Zenoh.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys

from .assemble import build_extra, build_sensor, build_target, extra_processes
from .bus import ZenohBus
from .roles.routes import parse_hosts
from .runner import StopFlag, WaitBudget, drive, lean_zenoh_runtime, profiled
from .scenario import ScenarioError, load_scenario


#: the most of a realtime period kept outside the sensors' rounds: it covers the sensors' late start (they
#: begin once the target's truth for the tick has reached them: two hops after the world's tick) and the
#: hops of the estimates to the target and of the states to the world. 10 ms was too little at 40 sensors
#: and 10 Hz on 2 cores (34–113 sensor states reached the world after its clock closed their tick in 300
#: ticks); 20 ms gave none. At 25 Hz two slots (13 ms) are less and are what is kept.
TAIL_MAX_S = 0.020


def role_budget(sc, mode: str, role: str, *, depth: int = 0) -> WaitBudget:
    """How long each wait may last (:class:`agent.runner.WaitBudget`). Lockstep waits long (only dead
    processes miss it), an outer wait (``depth``: :attr:`Role.wait_depth`) longer than the waits inside it.
    Realtime shares the period T / speed out like a radio slot schedule: a tail of
    min(2 T / speed / (R + 3), ``TAIL_MAX_S``) is kept at its end for the estimates and states, the rest is
    R + 1 slots for the R exchange rounds — a sensor's round r is due r + 2 slots after it began the tick
    (round 0 has two, for the spread of the moments the neighbours begin; a round that closes early leaves
    its time to the next), and no round lasts past T / speed − tail / 2 after the world's tick reached the
    sensor (the window: a sensor that begins late gets what is left of the tick, not a whole new schedule,
    so a stall costs the ticks it hits — without it, 40 sensors at 10 Hz lost ~8 ticks of ~90 missed
    deadlines after one 37 ms freeze of the machine); the last round waits until that window's end, not only
    its slot's (the main job on a 2-core VM over capacity, 8 alternated pairs of 500-tick runs: 1060 round
    deadlines missed against 1645, the last round's 603 against 1226; the target's missed waits 613 against 602
    and the states late at the world 2141 against 2167, unchanged); an intelligent target waits for the
    estimates until half the tail is left. Every wait of the warm-up tick 0 gets two periods. A tick that
    announces another period (``Tick.period``: the world stretched under overload, topology/pace.py, or the
    run's speed changed) gets the same schedule in proportion (:meth:`agent.runner.WaitBudget.scaled`)."""
    if mode == "lockstep":
        return WaitBudget.lockstep(sc.run.deadline_s, rounds=sc.estimator.rounds, depth=depth)
    period = sc.run.T / sc.run.speed
    R = sc.estimator.rounds
    tail = min(2 * period / (R + 3), TAIL_MAX_S)
    if role == "sensor":
        return WaitBudget((period - tail) / (R + 1), schedule=True, head=1, warmup_s=2 * period,
                          window_s=period - tail / 2, period_s=period, final=R - 1)
    if role == "target":
        return WaitBudget(period - tail / 2, warmup_s=2 * period, period_s=period)
    return WaitBudget(period / 2, warmup_s=2 * period)


def main(argv: list[str] | None = None) -> int:
    lean_zenoh_runtime()
    ap = argparse.ArgumentParser(prog="python -m agent")
    ap.add_argument("role", choices=["sensor", "target", "fusion"])
    ap.add_argument("--id", type=int, default=0)
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447")
    ap.add_argument("--run", default=None, help="run name (key prefix ft/<run>/); default: the scenario's")
    ap.add_argument("--design", default=None, help="JSON file with the runtime's pre-run design")
    ap.add_argument("--mode", choices=["lockstep", "realtime"], default=None)
    ap.add_argument("--rejoin", action="store_true", help="join a running flock (after a restart)")
    ap.add_argument("--config", default=None, help="Zenoh json5 config file for this process")
    ap.add_argument("--hosts", default=None, metavar="HOST:FIRST-LAST,...",
                    help="a run placed on several hosts: every sensor's host (a sensor sends a payload to another "
                         "host once, not once per hearer there)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        sc = load_scenario(args.scenario, **{"run.mode": args.mode})   # (None: the file's mode)
    except ScenarioError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    design = json.loads(open(args.design).read()) if args.design else {}
    mode = sc.run.mode
    stop = StopFlag().install()
    if args.role == "sensor":
        if not 0 <= args.id < sc.sensors.n:
            print(f"error: --id {args.id} is not a sensor of {args.scenario} (0..{sc.sensors.n - 1})", file=sys.stderr)
            return 2
        role, name = build_sensor(sc, args.id, design, rejoin=args.rejoin), f"agent/{args.id}"
        if args.hosts and hasattr(role, "place"):
            try:
                role.place(parse_hosts(args.hosts, sc.sensors.n))
            except ValueError as exc:
                print(f"error: --hosts {args.hosts}: {exc}", file=sys.stderr)
                return 2
    elif args.role == "fusion":
        if "fusion" not in extra_processes(sc):
            print(f"error: {args.scenario} has no fusion solver ([uavs]/[fusion] tables)", file=sys.stderr)
            return 2
        role, name = build_extra(sc, "fusion"), "fusion/0"
    else:
        role, name = build_target(sc), "target/0"
    bus = ZenohBus(args.run or sc.run.name, connect=args.connect, config_file=args.config)
    try:
        budget = role_budget(sc, mode, args.role, depth=role.wait_depth)
        return profiled(name, lambda: drive(role, bus, name, budget, stop))
    finally:
        bus.close()


if __name__ == "__main__":
    sys.exit(main())
