"""The ``flocktrack`` command.

SCENARIO is a scenario file or the name of a bundled one (``flocktrack scenarios`` lists them).

    flocktrack scenarios [show NAME]              (the bundled scenarios; show prints one, to start from)
    flocktrack validate SCENARIO
    flocktrack run SCENARIO [--transport zenoh|inproc] [--mode lockstep|realtime] [--ticks N] [--seed S]
                            [--estimator NAME] [--rounds R] [--set section.key=value ...]
                            [--restart never|on-failure] [-v] [--out DIR]
    flocktrack design SCENARIO --out FILE
    flocktrack fault VERB [name=value ...] [--run RUN] [--connect ENDPOINT] [--timeout S]
    flocktrack ps [--connect ENDPOINT] [--json]
    flocktrack logs [RUN] [MEMBER] [-f]
    flocktrack compose SCENARIO [--out DIR] [--network bridge|host] [--base-image NAME] [--secure --keys DIR]
    flocktrack image [--name NAME]                (a base image without a registry: mmdebstrap | docker import)
    flocktrack keys SCENARIO --out DIR            (then: flocktrack run … --secure --keys DIR)
    flocktrack sweep SCENARIO --grid KEY=V1,V2 ... --seeds S --out DIR
    flocktrack metrics RECORDING --out DIR
    flocktrack recover RECORDING [--out FILE]
    flocktrack export RUN --format parquet|csv --out DIR   (a run's tables: ticks, estimates, links, events, faults)
    flocktrack replay RECORDING [--connect ENDPOINT] [--speed X]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from agent.estimators.registry import names as estimator_names
from agent.estimators.registry import specs
from agent.scenario import ScenarioError, load_scenario, parse_scenario, scenario_data

from flocktrack import __version__
from flocktrack.resources import MissingDataError, add_scenario_argument


class _Lazy:
    """Choices looked up when a value is checked: the registry imports every estimator (SciPy, …), which
    `flocktrack fault / ps / logs` need not wait for."""

    def __init__(self, fn):
        self.fn = fn

    def __contains__(self, x) -> bool:
        return x in self.fn()

    def __iter__(self):
        return iter(self.fn())

    def __len__(self) -> int:
        return len(self.fn())


class _Parser(argparse.ArgumentParser):
    """argparse with "did you mean …?" for a misspelt sub-command or choice."""

    def error(self, message: str):
        import re

        if message.startswith("argument scenario:"):   # the message lists the names: no usage block above it
            self.exit(2, f"{self.prog}: error: {message}\n")

        from agent.suggest import did_you_mean

        m = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
        if m:
            hint = did_you_mean(m.group(1), re.findall(r"'([^']*)'", m.group(2)), quote="'")
            if hint:
                message = f"{message}; {hint.strip()}"
        super().error(message)


def cmd_scenarios(args) -> int:
    """The bundled scenarios, a line each; ``show NAME``: one of them as TOML (to start a new one from)."""
    from flocktrack.resources import UnknownScenarioError, scenario_description, scenario_file, scenario_names

    if args.action == "show":
        if not args.name:
            print("error: scenarios show NAME: which scenario? (`flocktrack scenarios` lists them)", file=sys.stderr)
            return 2
        try:
            sys.stdout.write(scenario_file(args.name).read_text(encoding="utf-8"))
        except UnknownScenarioError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        return 0
    names = scenario_names()
    width = max(map(len, names))
    for name in names:
        print(f"{name:<{width}}  {scenario_description(name)}")
    print("\n`flocktrack run NAME` runs one; `flocktrack scenarios show NAME > my.toml` copies one to edit.",
          file=sys.stderr)
    return 0


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
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / ".writable").touch()
        (out / ".writable").unlink()
    except OSError as exc:
        print(f"error: cannot write the results to {out}: {exc.strerror or exc}; give --out a directory you "
              f"can write", file=sys.stderr)
        return 2
    from flocktrack.engine.run import run_inproc_to_dir

    def report(summary: dict, info: dict) -> None:
        if info.get("rc") not in (0, None):
            return
        if "shard" in summary:
            print(f"{sc.run.name}: host {summary['shard']} done in {info['wall_s']:.1f} s — its shard of the run is in "
                  f"{out}/; one recording and summary of every host's: flocktrack merge DIR... --out DIR", flush=True)
            return
        print(f"{sc.run.name}: {sc.run.ticks} ticks in {info['wall_s']:.1f} s over {args.transport} — network RMSE "
              f"{_g(summary.get('network_rmse'))}, final {_g(summary.get('final_rmse'))}, "
              f"min distance {_g(summary.get('min_inter_agent_distance'))}, λ₂ min {_g(summary.get('lambda2_min'))}\n"
              f"results in {out}/: {', '.join(run_outputs(out))}", flush=True)

    if args.transport == "inproc":
        summary, info = run_inproc_to_dir(sc, data, out, record=args.record, show_progress=True)
        report(summary, info)
        return 0
    from flocktrack.launch.runs import port_in_use

    for port, flag in ((args.port, "--port"), (args.dashboard_port if args.dashboard else None, "--dashboard-port")):
        holder = port_in_use(port) if port else None
        if holder:
            print(f"error: port {port} is in use by {holder}; give {flag} with a free port (or stop it: "
                  f"`flocktrack ps` lists the runs)", file=sys.stderr)
            return 2
    placement = None
    if args.placement or args.host:
        from flocktrack.plan import load_placement

        if not (args.placement and args.host):
            print("error: --placement HOSTS.toml and --host NAME go together (which host of the placement this is)",
                  file=sys.stderr)
            return 2
        if args.secure:
            print("error: --secure with --placement: the secure mode runs on one host; drop --placement, or run "
                  "the hosts without --secure", file=sys.stderr)
            return 2
        placement = load_placement(args.placement)
        if args.host not in placement.host_names():
            print(f"error: --host {args.host}: not a host of {args.placement} (its hosts: "
                  f"{', '.join(placement.host_names())})", file=sys.stderr)
            return 2
    if args.dashboard:
        print(f"dashboard: http{'s' if args.secure else ''}://localhost:{args.dashboard_port}", file=sys.stderr)
    from flocktrack.deploy.keys import KeySetError

    try:
        summary, info = _run_zenoh(args, sc, data, out, placement=placement, report=report)
    except KeySetError as exc:
        print(f"error: --keys: {exc}", file=sys.stderr)
        return 2
    if info.get("rc") not in (0, None):
        print(f"error: run ended with code {info['rc']}; see {out}/logs/", file=sys.stderr)
        return 1
    return 0


def _run_zenoh(args, sc, data, out: Path, *, placement, report):
    from flocktrack.engine.run import run_zenoh_to_dir

    return run_zenoh_to_dir(sc, data, out, port=args.port, restart=args.restart,
                            placement=placement, host=args.host, startup_timeout_s=args.startup_timeout,
                            max_restarts=args.max_restarts, quiet=args.quiet, verbose=args.verbose,
                            dashboard_port=args.dashboard_port if args.dashboard else None,
                            keep_dashboard=args.dashboard and not args.no_linger,
                            secure_dir=(args.keys or str(out / "keys")) if args.secure else None,
                            on_results=report, dashboard_token=args.dashboard_token)


#: what a run may write to its directory, in the order the README's table gives them
RUN_OUTPUTS = ("summary.json", "metrics.csv", "scenario.toml", "design.json", "meta.json", "plan.json", "run.json",
               "recording.mcap",
               "events.json", "logs/", "stats/", "dashboard_token")


def run_outputs(out: Path) -> list[str]:
    """The run outputs that ``out`` holds (a directory's name ends with ``/``)."""
    return [name for name in RUN_OUTPUTS if (out / name.rstrip("/")).exists()]


def _g(v) -> str:
    return "n/a" if v is None else f"{v:.4g}"


def cmd_fault(args) -> int:
    """Send one control verb to a running flock (what the dashboard's buttons do), checked first, and
    report the run's answer: exit 0 applied, 1 refused, 2 no answer (flocktrack/launch/fault_client.py)."""
    from agent.bus import ZenohBus
    from agent.wire import WireError, control_args

    from flocktrack.launch import fault_client as fc
    from flocktrack.launch.runs import find_local

    local = find_local(args.run) if args.connect is None else None
    try:
        kv = control_args(args.args)
        fc.check(args.verb, kv, local.n_sensors if local is not None else None)
    except fc.UsageError as exc:
        print(f"error: {exc} (nothing sent)", file=sys.stderr)
        return fc.NO_ANSWER
    except (ValueError, WireError) as exc:
        detail = exc.detail if isinstance(exc, WireError) else str(exc)
        print(f"refused (nothing sent): {detail}", file=sys.stderr)
        return fc.REFUSED
    target = _fault_target(args, local)
    if isinstance(target, str):
        print(f"error: {target}", file=sys.stderr)
        return fc.NO_ANSWER
    run, connect, config = target
    try:
        bus = ZenohBus(run, connect=connect, config_file=config)
    except Exception as exc:  # zenoh.ZError: nobody listening there
        print(f"error: cannot reach a router at {connect} ({exc}); is the run going? `flocktrack ps` lists them",
              file=sys.stderr)
        return fc.NO_ANSWER
    try:
        ans = fc.send(bus, args.verb, kv, timeout_s=args.timeout)
    finally:
        bus.close()
    print(f"{run}: {ans.text}", file=sys.stdout if ans.code == fc.APPLIED else sys.stderr)
    return ans.code


def _fault_target(args, local) -> tuple[str, str, str | None] | str:
    """(run, router endpoint, client config) to send a fault to, or why there is none: ``--run`` and
    ``--connect`` as given; ``--connect`` alone: the only run on that router; else a local run's file."""
    from flocktrack.launch.runs import local_runs

    if args.connect is not None:
        return (args.run, args.connect, args.config) if args.run is not None else _only_run_on(args.connect, args.config)
    if local is not None:
        return local.run, local.endpoint, args.config or local.config
    runs = local_runs()
    if not runs:
        return "no run of this machine's launchers is going; give --connect (and --run if its router has several)"
    if args.run is None:
        return f"{len(runs)} runs are going, say which with --run: {', '.join(e.run for e in runs)}"
    return f"no local run {args.run!r}; give --connect for a run elsewhere"


def _only_run_on(connect: str, config: str | None) -> tuple[str, str, str | None] | str:
    """The only run whose members hold tokens on the router at ``connect`` (``flocktrack ps --connect``'s
    query), or why there is not exactly one."""
    from flocktrack.launch.ps import runs_on

    try:
        names = sorted(runs_on(connect, config, listen_s=0.0))
    except Exception as exc:  # zenoh.ZError: no router there
        return f"cannot reach a router at {connect} ({exc})"
    if not names:
        return (f"no run on {connect} (no member holds a token there; a secure router answers a client about its "
                f"own run only: give --run)")
    if len(names) > 1:
        return f"{len(names)} runs on {connect}, say which with --run: {', '.join(names)}"
    return names[0], connect, config


def cmd_ps(args) -> int:
    """The runs reachable on a router (default: every run of this machine's launchers)."""
    from flocktrack.launch.ps import as_json, discover, table

    runs, failed = discover(args.connect, args.config, args.run)
    for f in failed:
        print(f"warning: no router at {f}", file=sys.stderr)
    if args.json:
        print(as_json(runs))
    elif runs:
        print(table(runs))
    else:
        print("no runs" + (f" on {args.connect}" if args.connect else " (no local launcher is running one)"))
    return 0


def cmd_recover(args) -> int:
    """A complete MCAP file from one whose end is missing (flocktrack/record/ ``recover``)."""
    from flocktrack.record.reader import recover

    try:
        dst, rec = recover(args.recording, args.out)
    except OSError as exc:
        print(f"error: {args.recording}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    state = "was complete already" if rec.complete else "had no summary (a crash): salvaged its complete chunks"
    print(f"{args.recording} {state}; {len(rec.messages)} messages, "
          f"{len({k for k, _m, _t in rec.messages})} keys → {dst}")
    return 0


def cmd_logs(args) -> int:
    from flocktrack.launch.logs import LogsError, run_dir, show

    try:
        return show(run_dir(args.run), args.member, follow=args.follow)
    except LogsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def cmd_design(args) -> int:
    """Solve (and store) the pre-run design of a scenario: its estimator's design hook (an SDP, a gain…)."""
    import json as _json

    from flocktrack.engine.build import design as make_design

    sc = load_scenario(args.scenario, args.set or [])
    try:
        d = make_design(sc)
    except ImportError:       # an optional dependency (cvxpy for an SDP): main() names the extra
        raise
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
    from flocktrack.record.reader import metrics_from_recording

    s = metrics_from_recording(args.recording, args.out)
    print(f"{args.recording}: network RMSE {_g(s.get('network_rmse'))} over {s['ticks_seen']} ticks; wrote {args.out}/summary.json")
    return 0


def cmd_replay(args) -> int:
    from flocktrack.engine.run import replay, replay_dashboard

    if args.dashboard:
        return replay_dashboard(args.recording, args.dashboard_port)
    n = replay(args.recording, connect=args.connect, speed=args.speed, port=args.port)
    print(f"replayed {n} messages from {args.recording}")
    return 0


def _add_run(sub) -> None:
    r = sub.add_parser("run", help="run a scenario")
    add_scenario_argument(r)
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
    r.add_argument("--dashboard-token", help="the dashboard's operator token (default: a new one, its link printed "
                                             "once); without it the page is read-only")
    r.add_argument("--no-linger", action="store_true", help="close the dashboard when the run ends")
    r.add_argument("--secure", action="store_true",
                   help="zenoh: TLS + mTLS + per-process passwords + router ACL (keys made in --keys DIR if absent)")
    r.add_argument("--keys", help="key set directory for --secure (default: OUT/keys)")
    r.add_argument("--placement", metavar="HOSTS.toml",
                   help="zenoh: a flock over several hosts (`flocktrack plan --placement` shows it); with --host")
    r.add_argument("--host", help="with --placement: the host this command runs (its router, nodes and recorder)")
    r.add_argument("--startup-timeout", type=float, default=90.0,
                   help="seconds to wait for every host's members before giving up (exit 3)")
    r.add_argument("--ticks", type=int)
    r.add_argument("--seed", type=int)
    r.add_argument("--estimator", choices=_Lazy(estimator_names), metavar="NAME",
                   help="a registered estimator (overrides estimator.name)")
    r.add_argument("--rounds", type=int)
    r.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override any scenario key")
    r.add_argument("--out", help="output directory (default: runs/<scenario>-<YYYYmmdd-HHMMSS>)")
    r.set_defaults(fn=cmd_run)


def _add_fault(sub) -> None:
    from agent.wire import CONTROL_VERBS

    fl = sub.add_parser("fault", help="send a control verb to a running flock and report its answer "
                                      "(exit 0 applied, 1 refused, 2 no answer)",
                        description="Send a control verb to a running flock, checked first (an unknown verb or "
                                    "argument name: exit 2, nothing sent; a bad value: exit 1, nothing sent), and "
                                    "report the run's answer: exit 0 applied (at tick k), 1 refused (with the "
                                    "reason), 2 no answer within --timeout. outlier_burst has no answer (the "
                                    "sensors apply it): it is reported as \"sent (no acknowledgement for this "
                                    "verb: the sensors apply it)\", exit 0.")
    fl.add_argument("verb", help=", ".join(CONTROL_VERBS))
    fl.add_argument("args", nargs="*", help="name=value (TOML values), e.g. agent=3 or groups=[0,0,1,1]")
    fl.add_argument("--run", help="the run name (default: the only run of this machine's launchers, or with "
                                  "--connect the only run on that router)")
    fl.add_argument("--connect", help="its router (default: the local run's)")
    fl.add_argument("--config", help="Zenoh client config (a secure run's: default the local run's)")
    fl.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the answer (default 5)")
    fl.set_defaults(fn=cmd_fault)


def _add_inspection(sub) -> None:
    """ps, logs, recover, metrics, replay: the commands that look at runs (going or recorded)."""
    ps = sub.add_parser("ps", help="the runs reachable on a router: name, tick, mode, members, endpoint")
    ps.add_argument("--connect", help="a router (default: every local launcher's)")
    ps.add_argument("--config", help="Zenoh client config for --connect")
    ps.add_argument("--run", help="only this run (a secure router answers a client about its own run only)")
    ps.add_argument("--json", action="store_true", help="as JSON")
    ps.set_defaults(fn=cmd_ps)
    rc = sub.add_parser("recover", help="rewrite a recording cut short by a crash as a complete MCAP file")
    rc.add_argument("recording")
    rc.add_argument("--out", help="the new file (default: NAME.recovered.mcap beside it)")
    rc.set_defaults(fn=cmd_recover)
    lg = sub.add_parser("logs", help="the per-process logs of a run; -f follows them")
    lg.add_argument("run", nargs="?", help="run directory or local run name (default: the only local run)")
    lg.add_argument("member", nargs="?", help="one process, e.g. agent/3, world, recorder")
    lg.add_argument("-f", "--follow", action="store_true", help="follow (until Ctrl-C or the run's end)")
    lg.set_defaults(fn=cmd_logs)
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


def parser() -> _Parser:
    """The ``flocktrack`` command line: every sub-command, the ones of other modules registered by them."""
    ap = _Parser(prog="flocktrack", description=__doc__.split("\n\n")[0])
    ap.add_argument("--version", action="version", version=f"flocktrack {__version__}")
    sub = ap.add_subparsers(dest="cmd", required=True)
    ls = sub.add_parser("scenarios", help="list the bundled scenarios; `show NAME` prints one")
    ls.add_argument("action", nargs="?", choices=["list", "show"], default="list")
    ls.add_argument("name", nargs="?", help="with show: the scenario")
    ls.set_defaults(fn=cmd_scenarios)
    v = sub.add_parser("validate", help="check a scenario file")
    add_scenario_argument(v)
    v.set_defaults(fn=cmd_validate)
    _add_run(sub)
    dg = sub.add_parser("design", help="solve and store a scenario's pre-run design (its estimator's design hook)")
    add_scenario_argument(dg)
    dg.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE")
    dg.add_argument("--out", required=True)
    dg.set_defaults(fn=cmd_design)
    _add_fault(sub)
    _add_inspection(sub)
    from flocktrack.analysis import export as _export
    from flocktrack.plan import cli as _plan
    from flocktrack.record import merge as _merge

    _plan.register(sub)
    _merge.register(sub)
    _export.register(sub)
    from flocktrack.deploy import compose as _compose
    from flocktrack.experiment import sweep as _experiment
    from flocktrack.deploy import image as _image
    from flocktrack.deploy import keys as _keys

    _compose.register(sub)
    _image.register(sub)
    _keys.register(sub)
    _experiment.register(sub)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        return args.fn(args)
    except ScenarioError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except MissingDataError as exc:   # a broken install: say what is missing and how to mend it
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ImportError as exc:        # an optional dependency that is not installed: which extra brings it
        from flocktrack.extras import missing_extra

        line = missing_extra(exc)
        if line is None:
            raise
        print(f"error: {args.cmd}: {line}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
