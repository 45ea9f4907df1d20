"""The ``flocktrack`` command.

    flocktrack validate SCENARIO
    flocktrack run SCENARIO [--transport zenoh|inproc] [--mode lockstep|realtime] [--ticks N] [--seed S]
                            [--estimator NAME] [--rounds R] [--set section.key=value ...]
                            [--restart never|on-failure] [-v] [--out DIR]
    flocktrack design SCENARIO --out FILE
    flocktrack fault VERB [name=value ...] --run RUN --connect ENDPOINT
    flocktrack compose SCENARIO [--out DIR]
    flocktrack keys SCENARIO --out DIR            (then: flocktrack run … --secure --keys DIR)
    flocktrack sweep SCENARIO --grid KEY=V1,V2 ... --seeds S --out DIR
    flocktrack metrics RECORDING --out DIR
    flocktrack replay RECORDING [--connect ENDPOINT] [--speed X]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from agent.estimators.registry import names as estimator_names
from agent.estimators.registry import specs
from agent.scenario import ScenarioError, load_scenario, parse_scenario, scenario_data


class _Parser(argparse.ArgumentParser):
    """argparse with "did you mean …?" for a misspelt sub-command or choice."""

    def error(self, message: str):
        import re

        from agent.suggest import did_you_mean

        m = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
        if m:
            hint = did_you_mean(m.group(1), re.findall(r"'([^']*)'", m.group(2)), quote="'")
            if hint:
                message = f"{message}; {hint.strip()}"
        super().error(message)


def cmd_validate(args) -> int:
    sc = load_scenario(args.scenario)
    print(f"{args.scenario}: ok — {sc.sensors.n} sensors, {sc.run.ticks} ticks of {sc.run.T} s, "
          f"estimator {sc.estimator.name}, topology {sc.topology.kind}, target {sc.target.kind}")
    return 0


def default_out(scenario: str) -> Path:
    """``runs/<scenario>-<YYYYmmdd-HHMMSS>``: where a run goes without ``--out``."""
    import time as _t

    return Path("runs") / f"{Path(scenario).stem}-{_t.strftime('%Y%m%d-%H%M%S')}"


def cmd_run(args) -> int:
    named = {"run.ticks": args.ticks, "run.seed": args.seed, "estimator.name": args.estimator,
             "estimator.rounds": args.rounds, "run.mode": args.mode}
    data = scenario_data(args.scenario, args.set or [], **named)
    sc = parse_scenario(data, args.scenario)
    out = Path(args.out) if args.out else default_out(args.scenario)
    out.mkdir(parents=True, exist_ok=True)
    from .run import run_inproc_to_dir, run_zenoh_to_dir

    def report(summary: dict, info: dict) -> None:
        if info.get("rc") not in (0, None):
            return
        print(f"{sc.run.name}: {sc.run.ticks} ticks in {info['wall_s']:.1f} s over {args.transport} — network RMSE "
              f"{_g(summary.get('network_rmse'))}, final {_g(summary.get('final_rmse'))}, "
              f"min distance {_g(summary.get('min_inter_agent_distance'))}, λ₂ min {_g(summary.get('lambda2_min'))}\n"
              f"results in {out}/: summary.json, metrics.csv, run.json"
              + (", recording.mcap, events.json, logs/" if args.transport == "zenoh" or args.record else ""),
              flush=True)

    if args.transport == "inproc":
        summary, info = run_inproc_to_dir(sc, data, out, record=args.record, show_progress=True)
        report(summary, info)
        return 0
    if args.dashboard:
        print(f"dashboard: http://localhost:{args.dashboard_port}", file=sys.stderr)
    summary, info = run_zenoh_to_dir(sc, data, out, port=args.port, restart=args.restart,
                                     max_restarts=args.max_restarts, quiet=args.quiet, verbose=args.verbose,
                                     dashboard_port=args.dashboard_port if args.dashboard else None,
                                     keep_dashboard=args.dashboard and not args.no_linger,
                                     secure_dir=(args.keys or str(out / "keys")) if args.secure else None,
                                     on_results=report)
    if info.get("rc") not in (0, None):
        print(f"error: run ended with code {info['rc']}; see {out}/logs/", file=sys.stderr)
        return 1
    return 0


def _g(v) -> str:
    return "n/a" if v is None else f"{v:.4g}"


def cmd_fault(args) -> int:
    """Publish one control/fault command on a running flock (what the dashboard's buttons do)."""
    from agent.bus import ZenohBus
    from agent.suggest import did_you_mean
    from agent.wire import CONTROL_VERBS, Control, WireError, control_args, decode, encode

    if args.verb not in CONTROL_VERBS:
        print(f"error: unknown verb {args.verb!r}; {did_you_mean(args.verb, CONTROL_VERBS, quote=chr(39))}"
              f"the verbs are: {', '.join(CONTROL_VERBS)}", file=sys.stderr)
        return 2
    try:
        kv = control_args(args.args)
    except ValueError as exc:
        print(f"error: argument {exc}", file=sys.stderr)
        return 2
    msg = Control(verb=args.verb, args=kv)
    try:
        decode(f"control/{args.verb}", encode(msg))  # the same validation every receiver applies
    except WireError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        bus = ZenohBus(args.run, connect=args.connect)
    except Exception as exc:  # zenoh.ZError: nobody listening there
        print(f"error: cannot reach a router at {args.connect} ({exc}); is the run going? "
              f"`flocktrack run` prints its endpoint", file=sys.stderr)
        return 1
    try:
        import time as _t

        _t.sleep(0.3)  # let the subscription routes reach us
        bus.publish(f"control/{args.verb}", msg)
        _t.sleep(0.2)
    finally:
        bus.close()
    print(f"sent control/{args.verb} {kv} to ft/{args.run}/ via {args.connect}")
    return 0


def cmd_design(args) -> int:
    """Solve (and store) the pre-run design of a scenario: its estimator's design hook (an SDP, a gain…)."""
    import json as _json

    from .build import design as make_design

    sc = load_scenario(args.scenario, args.set or [])
    try:
        d = make_design(sc)
    except Exception as exc:  # DesignError (infeasible / inaccurate) and friends: say which, no numbers
        print(f"error: {args.scenario}: design failed: {exc}", file=sys.stderr)
        return 1
    spec = specs()[sc.estimator.name]
    if spec.report_design is not None:
        out, line = spec.report_design(d)
    else:
        out, line = d, ", ".join(sorted(d)) or "nothing to design"
    print(f"{args.scenario}: {line}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(_json.dumps(out, indent=1))
    stored = "design_file" in spec.param_names()
    print(f"wrote {args.out}" + (f" — use it with `design_file = \"{args.out}\"` in [estimator]" if stored else ""))
    return 0


def cmd_metrics(args) -> int:
    from .record import metrics_from_recording

    s = metrics_from_recording(args.recording, args.out)
    print(f"{args.recording}: network RMSE {_g(s.get('network_rmse'))} over {s['ticks_seen']} ticks; wrote {args.out}/summary.json")
    return 0


def cmd_replay(args) -> int:
    from .run import replay, replay_dashboard

    if args.dashboard:
        return replay_dashboard(args.recording, args.dashboard_port)
    n = replay(args.recording, connect=args.connect, speed=args.speed, port=args.port)
    print(f"replayed {n} messages from {args.recording}")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = _Parser(prog="flocktrack", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    v = sub.add_parser("validate", help="check a scenario file")
    v.add_argument("scenario")
    v.set_defaults(fn=cmd_validate)
    r = sub.add_parser("run", help="run a scenario")
    r.add_argument("scenario")
    r.add_argument("--transport", choices=["inproc", "zenoh"], default="zenoh",
                   help="zenoh: one OS process per agent over an embedded router (default); inproc: one process")
    r.add_argument("--mode", choices=["lockstep", "realtime"], help="override run.mode")
    r.add_argument("--port", type=int, help="embedded router port (default: a free one)")
    r.add_argument("--restart", choices=["never", "on-failure"], default="never", help="sensor restart policy")
    r.add_argument("--max-restarts", type=int, default=3)
    r.add_argument("--record", action="store_true", help="inproc: also write DIR/recording.mcap (zenoh always records)")
    r.add_argument("--quiet", action="store_true", help="no status line, no process output on the terminal")
    r.add_argument("-v", "--verbose", action="store_true",
                   help="also show every process's log lines (always in OUT/logs/; without -v: warnings and errors)")
    r.add_argument("--dashboard", action="store_true", help="zenoh: start the live Viser dashboard")
    r.add_argument("--dashboard-port", type=int, default=8080)
    r.add_argument("--no-linger", action="store_true", help="close the dashboard when the run ends")
    r.add_argument("--secure", action="store_true",
                   help="zenoh: TLS + mTLS + per-process passwords + router ACL (keys made in --keys DIR if absent)")
    r.add_argument("--keys", help="key set directory for --secure (default: OUT/keys)")
    r.add_argument("--ticks", type=int)
    r.add_argument("--seed", type=int)
    r.add_argument("--estimator", choices=estimator_names())
    r.add_argument("--rounds", type=int)
    r.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override any scenario key")
    r.add_argument("--out", help="output directory (default: runs/<scenario>-<YYYYmmdd-HHMMSS>)")
    r.set_defaults(fn=cmd_run)
    dg = sub.add_parser("design", help="solve and store a scenario's pre-run design (its estimator's design hook)")
    dg.add_argument("scenario")
    dg.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE")
    dg.add_argument("--out", required=True)
    dg.set_defaults(fn=cmd_design)
    fl = sub.add_parser("fault", help="send a control/fault command to a running flock")
    from agent.wire import CONTROL_VERBS

    fl.add_argument("verb", help=", ".join(CONTROL_VERBS))
    fl.add_argument("args", nargs="*", help="name=value (TOML values), e.g. agent=3 or groups=[0,0,1,1]")
    fl.add_argument("--run", required=True, help="the run name printed by `flocktrack run`")
    fl.add_argument("--connect", default="tcp/127.0.0.1:7447")
    fl.set_defaults(fn=cmd_fault)
    mt = sub.add_parser("metrics", help="recompute summary.json from a recording")
    mt.add_argument("recording")
    mt.add_argument("--out", required=True)
    mt.set_defaults(fn=cmd_metrics)
    rp = sub.add_parser("replay", help="re-publish a recording on Zenoh")
    rp.add_argument("recording")
    rp.add_argument("--connect", help="router endpoint (default: open an embedded router)")
    rp.add_argument("--port", type=int, default=7447)
    rp.add_argument("--speed", type=float, default=1.0, help="realtime factor (0 = as fast as possible)")
    rp.add_argument("--dashboard", action="store_true", help="show the recording in the dashboard (time slider)")
    rp.add_argument("--dashboard-port", type=int, default=8080)
    rp.set_defaults(fn=cmd_replay)
    from . import compose as _compose
    from . import experiment as _experiment
    from . import keys as _keys

    _compose.register(sub)
    _keys.register(sub)
    _experiment.register(sub)
    args = ap.parse_args(argv)
    try:
        return args.fn(args)
    except ScenarioError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
