"""The ``flocktrack`` command.

    flocktrack validate SCENARIO
    flocktrack run SCENARIO [--transport inproc] [--ticks N] [--seed S] [--estimator NAME]
                            [--rounds R] [--set section.key=value ...] --out DIR
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import tomllib
from pathlib import Path

from agent.scenario import Scenario, ScenarioError, load_scenario, parse_scenario


def _parse_value(text: str):
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def apply_overrides(path: str, sets: list[str], **named) -> Scenario:
    """Load a scenario, apply ``section.key=value`` overrides (TOML values), validate once."""
    sc = load_scenario(path)
    if not sets and not any(v is not None for v in named.values()):
        return sc
    data = tomllib.loads(Path(path).read_text())
    for s in sets:
        dotted, sep, raw = s.partition("=")
        if not sep or "." not in dotted:
            raise ScenarioError(path, s, "override must look like section.key=value", "e.g. --set run.ticks=100")
        sect, _, key = dotted.partition(".")
        data.setdefault(sect, {})[key] = _parse_value(raw)
    for dotted, v in named.items():
        if v is not None:
            sect, _, key = dotted.partition(".")
            data.setdefault(sect, {})[key] = v
    return parse_scenario(data, path)


def cmd_validate(args) -> int:
    sc = load_scenario(args.scenario)
    print(f"{args.scenario}: ok — {sc.sensors.n} sensors, {sc.run.ticks} ticks of {sc.run.T} s, "
          f"estimator {sc.estimator.name}, topology {sc.topology.kind}, target {sc.target.kind}")
    return 0


def _progress():
    """A rich progress bar on a terminal, plain periodic lines otherwise."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    if sys.stderr.isatty():
        prog = Progress(TextColumn("[bold]ticks"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                        transient=True)
        return prog
    return None


def cmd_run(args) -> int:
    sc = apply_overrides(args.scenario, args.set or [], **{
        "run.ticks": args.ticks, "run.seed": args.seed, "estimator.name": args.estimator,
        "estimator.rounds": args.rounds})
    out = Path(args.out)
    if args.transport != "inproc":
        print(f"error: transport {args.transport!r} is not available yet; use --transport inproc", file=sys.stderr)
        return 2
    from .inproc import run_inproc

    t0 = time.perf_counter()
    prog = _progress()
    if prog is not None:
        with prog:
            task = prog.add_task("run", total=sc.run.ticks)
            metrics, roles, bus = run_inproc(sc, progress=lambda k, n: prog.update(task, completed=k))
    else:
        step = max(1, sc.run.ticks // 10)

        def report(k: int, n: int) -> None:
            if k % step == 0:
                print(f"tick {k}/{n}", file=sys.stderr, flush=True)

        metrics, roles, bus = run_inproc(sc, progress=report)
    wall = time.perf_counter() - t0
    extra = {"scenario": sc.run.name, "estimator": sc.estimator.name, "seed": sc.run.seed,
             "transport": args.transport, "ticks": sc.run.ticks, "n_sensors": sc.sensors.n,
             "bus": bus.stats.as_dict(),
             "sensor_counters": [dict(sorted(s.counters.items())) for s in roles.sensors]}
    summary = metrics.write(out, extra)
    (out / "timing.json").write_text(json.dumps({"wall_s": wall, "ticks_per_s": sc.run.ticks / wall}, indent=2))
    print(f"{sc.run.name}: {sc.run.ticks} ticks in {wall:.1f} s — network RMSE {summary['network_rmse']:.4g}, "
          f"final {summary['final_rmse']:.4g}, min distance {summary['min_inter_agent_distance']}, "
          f"λ₂ min {summary['lambda2_min']}; wrote {out}/summary.json, metrics.csv")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="flocktrack", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    v = sub.add_parser("validate", help="check a scenario file")
    v.add_argument("scenario")
    v.set_defaults(fn=cmd_validate)
    r = sub.add_parser("run", help="run a scenario")
    r.add_argument("scenario")
    r.add_argument("--transport", choices=["inproc", "zenoh"], default="inproc")
    r.add_argument("--ticks", type=int)
    r.add_argument("--seed", type=int)
    r.add_argument("--estimator", choices=["minimax", "kalman", "hinf_switching"])
    r.add_argument("--rounds", type=int)
    r.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override any scenario key")
    r.add_argument("--out", required=True)
    r.set_defaults(fn=cmd_run)
    args = ap.parse_args(argv)
    try:
        return args.fn(args)
    except ScenarioError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
