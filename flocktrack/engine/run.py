"""Run a scenario to an output directory, in-process or process-per-agent over Zenoh.

Both write the same files: ``scenario.toml`` (the resolved scenario, overrides applied),
``design.json`` (pre-run design), ``summary.json`` + ``metrics.csv`` (metrics only; identical across
transports in lockstep), ``run.json`` (transport, timing, bus counters, supervisor events) and — always
over Zenoh, with ``record=True`` in-process — ``recording.mcap``.
"""

from __future__ import annotations

import json
import signal
import sys
import time
import uuid
from pathlib import Path

import tomli_w

from agent.scenario import Scenario
from dashboards.operator import new_token, operator_url

from flocktrack.engine.build import design as make_design
from flocktrack.launch.commands import LaunchOptions, RunInputs
from flocktrack.launch.launcher import Launcher
from flocktrack.record.metrics import summary_identity
from flocktrack.record.writer import McapRecorder
from flocktrack.record.reader import metrics_from_recording, read_recording


class Progress:
    """A rich progress bar on a terminal, periodic plain lines otherwise (never silent)."""

    def __init__(self, total: int, label: str = "ticks"):
        self.total, self.label = total, label
        self._bar = None
        self._step = max(1, total // 10)
        self._last = -1
        if sys.stderr.isatty():
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self._bar = Progress(TextColumn(f"[bold]{label}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                           transient=True)
            self._task = self._bar.add_task(label, total=total)
            self._bar.start()

    def update(self, k: int, _n: int | None = None) -> None:
        if self._bar is not None:
            self._bar.update(self._task, completed=k)
        elif k // self._step != self._last // self._step or k == self.total:
            print(f"{self.label} {k}/{self.total}", file=sys.stderr, flush=True)
        self._last = k

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()


def write_inputs(sc: Scenario, data: dict, out: Path) -> tuple[Path, Path, dict, Path]:
    out.mkdir(parents=True, exist_ok=True)
    scen_file = out / "scenario.toml"
    scen_text = tomli_w.dumps(data)
    scen_file.write_text(scen_text)
    dsg = make_design(sc)
    design_file = out / "design.json"
    design_file.write_text(json.dumps(dsg))
    meta = {"scenario": scen_text, "design": json.dumps(dsg), "scenario_path": sc.source}
    meta_file = out / "meta.json"
    meta_file.write_text(json.dumps(meta))
    return scen_file, design_file, dsg, meta_file


def run_inproc_to_dir(sc: Scenario, data: dict, out: Path, record: bool = False,
                      show_progress: bool = False) -> tuple[dict, dict]:
    from agent.bus import LocalBus

    from flocktrack.engine.inproc import run_inproc

    _, _, dsg, meta_file = write_inputs(sc, data, out)
    bus = LocalBus()
    rec = None
    if record:
        rec = McapRecorder(out / "recording.mcap", json.loads(meta_file.read_text()))
        bus.taps.append(rec.write_raw)
    prog = Progress(sc.run.ticks) if show_progress else None
    t0 = time.perf_counter()
    try:
        metrics, roles, bus = run_inproc(sc, progress=prog.update if prog else None, bus=bus)
    finally:
        if prog:
            prog.close()
        if rec:
            rec.finish()
    wall = time.perf_counter() - t0
    summary = metrics.write(out, summary_identity(sc))
    info = {"transport": "inproc", "wall_s": wall, "ticks_per_s": sc.run.ticks / wall, "bus": bus.stats.as_dict(),
            "sensor_counters": [dict(sorted(s.counters.items())) for s in roles.sensors],
            "world": roles.world.stats}
    (out / "run.json").write_text(json.dumps(info, indent=2))
    return summary, info


def run_zenoh_to_dir(sc: Scenario, data: dict, out: Path, *, port: int | None = None, restart: str = "never",
                     max_restarts: int = 3, quiet: bool = False, on_poll=None,
                     timeout_s: float | None = None, dashboard_port: int | None = None,
                     keep_dashboard: bool = False, secure_dir: str | Path | None = None,
                     placement=None, host: str | None = None, verbose: bool = False, on_results=None,
                     dashboard_token: str | None = None, startup_timeout_s: float = 90.0) -> tuple[dict, dict]:
    """Process per node over an embedded router (the run plan's nodes: :mod:`flocktrack.plan`); metrics are
    recomputed from the recording.

    The terminal gets a live status line (flocktrack/launch/status.py) and the children's warnings and errors
    (every line with ``verbose``; nothing with ``quiet``); every line is in ``out/logs/``. The results
    (summary.json, metrics.csv, run.json) are written the moment the run ends — before a dashboard kept
    up with ``keep_dashboard`` — and ``on_results(summary, info)`` is called then.

    ``secure_dir``: run secured (TLS + mTLS + user/password + ACL, see flocktrack/deploy/keys.py) with the key
    set in that directory — made there for this run if it holds none; an existing one fixes the run
    name its ACL was written for.

    ``placement`` (a :class:`flocktrack.plan.Placement`) and ``host``: run host ``host``'s share of a flock
    placed on several hosts — its router (meshed with the others'), its nodes and its recorder shard; the run
    starts when every host's members are live (or gives up after ``startup_timeout_s``, exit 3), and
    ``flocktrack merge`` makes one recording and summary of the hosts' directories.

    ``dashboard_token``: the dashboard's operator token (default: a new one per run; its link is printed
    once and the token kept 0600 in ``out/dashboard_token``). Without it the page is read-only."""
    from flocktrack.plan import RestartPolicy as Policy
    from flocktrack.plan import build_plan

    run = None if placement is not None else f"{sc.run.name}-{uuid.uuid4().hex[:8]}"
    plan = build_plan(sc, run=run, placement=placement, dashboard=dashboard_port is not None,
                      sensor_restart=Policy(restart, max_restarts))   # (a placement that does not fit fails here)
    scen_file, design_file, dsg, meta_file = write_inputs(sc, data, out)
    keys = None
    if secure_dir is not None:
        from flocktrack.deploy.keys import prepare_keys

        # (every identity a run may use — the dashboard's too: `flocktrack fault` speaks as the dashboard)
        keys = prepare_keys(secure_dir, build_plan(sc, run=plan.run, placement=placement, dashboard=True))
        plan = build_plan(sc, run=keys.run, placement=placement, dashboard=dashboard_port is not None,
                          sensor_restart=Policy(restart, max_restarts))
    plan_file = out / "plan.json"
    plan_file.write_text(plan.to_json())
    opts = LaunchOptions(out, RunInputs(scen_file, design_file, meta_file, plan_file), host=host, port=port,
                         quiet=quiet, verbose=verbose, dashboard_port=dashboard_port, keys=keys,
                         dashboard_token=(dashboard_token or new_token()) if dashboard_port is not None else None,
                         startup_timeout_s=startup_timeout_s)
    launcher = Launcher(plan, opts)
    run = plan.run
    stop_signals = _stop_on_signals(launcher)
    t0 = time.perf_counter()
    t_end: float | None = None
    rc: int | None = None
    status = None
    results: tuple[dict, dict] | None = None
    try:
        launcher.start()
        if not quiet:
            if dashboard_port is not None:
                print(f"dashboard operator link (its buttons steer the run; keep it private, token in "
                      f"{out}/dashboard_token): {operator_url('localhost', dashboard_port, launcher.dashboard_token, tls=keys is not None)}",
                      file=sys.stderr)
            status = _announce(sc, run, launcher, keys, out)
        polls = [f for f in (on_poll, status and (lambda _l: status.poll())) if f]
        rc = launcher.wait(timeout_s=timeout_s, on_poll=(lambda lnch: [f(lnch) for f in polls]) if polls else None)
        t_end = time.perf_counter()  # the run's own time: not the dashboard kept up after it
        if status is not None:
            status.close()
            status = None
        if keep_dashboard and dashboard_port is not None and rc == 0 and launcher.alive("dashboard/0"):
            results = _zenoh_results(sc, out, launcher, rc, t_end - t0)
            if on_results is not None:
                on_results(*results)
            scheme = "https" if keys is not None else "http"   # a secure run's page is HTTPS (dashboards/tls.py)
            print(f"the dashboard stays up at {scheme}://localhost:{dashboard_port} — Ctrl-C to quit", file=sys.stderr)
            while not launcher.stopping.is_set() and launcher.alive("dashboard/0"):
                time.sleep(0.2)
    finally:
        if status is not None:
            status.close(final=False)
        launcher.shutdown()
        for s, h in stop_signals.items():
            signal.signal(s, h)
        launcher.write_events(out / "events.json")
    wall = (t_end if t_end is not None else time.perf_counter()) - t0
    if results is None:
        results = _zenoh_results(sc, out, launcher, rc, wall)
        if on_results is not None:
            on_results(*results)
    else:   # the dashboard's linger: the exits of the processes stopped since are on the record now
        results[1]["exits"] = {n: c.exits for n, c in launcher.children.items()}
        (out / "run.json").write_text(json.dumps(results[1], indent=2))
    return results


def _stop_on_signals(launcher: Launcher) -> dict:
    """SIGINT / SIGTERM stop the launcher (gracefully); returns the previous handlers, to restore."""
    def on_signal(signum, _frame):
        from agent.bus import wake_all

        launcher.request_stop()
        wake_all()      # the supervision loop's poll may sit in its queue (agent/bus.py wake_all)

    return {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}


def _announce(sc: Scenario, run: str, launcher: Launcher, keys, out: Path):
    """Say where the run is and how to reach it; the live status line (or None)."""
    print(f"run {run} on {launcher.endpoint} ({sc.sensors.n} sensors, {sc.run.mode}); logs in {out}/logs/; "
          f"faults: flocktrack fault VERB (--run {run} --connect {launcher.endpoint} when several runs go)", file=sys.stderr)
    if keys is not None:
        print(f"secure: TLS + mTLS + user/password + ACL with the keys in {keys.dir} (a client needs "
              f"its identity's config, e.g. --config {keys.client('dashboard-0')})", file=sys.stderr)
    return _status_line(sc, run, launcher, keys)


def _status_line(sc: Scenario, run: str, launcher: Launcher, keys):
    """The live status line of a run (None if it cannot connect: the run goes on without it)."""
    from flocktrack.launch.status import RunStatus

    rate = sc.run.speed / sc.run.T if sc.run.mode == "realtime" else None
    try:
        st = RunStatus(run, launcher.endpoint, sc.run.ticks, sc.sensors.n, sc.pos_dims, target_rate=rate,
                       config_file=str(keys.client("recorder-0")) if keys is not None else None,
                       deadlines=lambda: launcher.deadlines,
                       processes=sum(1 for c in launcher.children.values() if not c.service),
                       rounds=sc.estimator.rounds)
    except Exception as exc:  # a status line is a convenience, never a reason to fail a run
        print(f"warning: no status line ({exc})", file=sys.stderr)
        return None
    launcher.on_output = st.clear
    return st


def _zenoh_results(sc: Scenario, out: Path, launcher: Launcher, rc: int | None, wall: float) -> tuple[dict, dict]:
    """summary.json + metrics.csv from the recording, and run.json. A host of a placement holds only its own
    nodes' shard of the recording: its summary comes from ``flocktrack merge`` of every host's directory."""
    keys, plan = launcher.keys, launcher.plan
    rec = read_recording(out / "recording.mcap")          # read once: a long run's file is large
    if plan.multi_host:
        summary = {"shard": launcher.host.name, "merge": "flocktrack merge DIR ... --out DIR (every host's run "
                                                         "directory) for the run's summary"}
    else:
        summary = metrics_from_recording(out / "recording.mcap", out, rec=rec)
    info = {"transport": "zenoh", "run": plan.run, "rc": rc, "wall_s": wall, "ticks_per_s": sc.run.ticks / wall,
            "router": launcher.endpoint, "recorded_messages": len(rec.messages), "recording_complete": rec.complete,
            **({} if plan.multi_host else {"unrecorded_messages": unrecorded(out / "stats", rec)}),
            "missed_deadlines": launcher.deadlines,
            **({"pace": pace} if (pace := _pace(out / "stats")) else {}),
            **({"host": launcher.host.name, "hosts": [h.name for h in plan.hosts]} if plan.multi_host else {}),
            **({"secure": True, "keys": str(keys.dir)} if keys is not None else {}),
            "restarts": {n: c.restarts for n, c in launcher.children.items() if c.restarts},
            "exits": {n: c.exits for n, c in launcher.children.items()}}
    (out / "run.json").write_text(json.dumps(info, indent=2))
    launcher.write_events(out / "events.json")
    return summary, info


def _pace(stats_dir: Path) -> dict:
    """A realtime run's clock under load (topology/pace.py): the ticks the world stretched and the largest
    stretch, from its stats; empty when it never stretched (or this host has no world)."""
    try:
        role = json.loads((stats_dir / "world-0.json").read_text()).get("role", {})
    except (OSError, ValueError):
        return {}
    if not role.get("pace_stretched_ticks"):
        return {}
    return {"stretched_ticks": role["pace_stretched_ticks"], "max_stretch": role.get("pace_max_stretch")}


def unrecorded(stats_dir: Path, rec) -> dict[str, int]:
    """Messages the run's processes sent on a key the recorder takes (all but the addressed copies) that are
    not in the recording, by key: each process's ``sent_by_key`` (stats/<process>.json) against the recorded
    count. Empty when the recording lost nothing. (A process killed with SIGKILL writes no stats: what it sent
    is not counted, so a loss can be missed there, never made up.)"""
    from collections import Counter

    from agent.wire import addressed

    recorded = Counter(key for key, _, _ in rec.messages)
    sent: Counter = Counter()
    for f in stats_dir.glob("*.json"):
        try:
            by_key = json.loads(f.read_text()).get("sent_by_key", {})
        except (OSError, ValueError):
            continue
        sent.update({k: int(v) for k, v in by_key.items() if not addressed(k)})
    return {k: v - recorded[k] for k, v in sorted(sent.items()) if recorded[k] < v}


def replay_dashboard(path: str | Path, port: int = 8080) -> int:
    """Serve a recording in the dashboard (time slider) until Ctrl-C."""
    import subprocess

    from flocktrack.launch.launcher import die_with_parent

    proc = subprocess.Popen([sys.executable, "-m", "dashboards", "--recording", str(path), "--port", str(port)],
                            preexec_fn=die_with_parent)
    print(f"dashboard on http://localhost:{port} — Ctrl-C to quit", file=sys.stderr)
    try:
        return proc.wait()
    except KeyboardInterrupt:
        proc.terminate()
        return proc.wait()


def replay(path: str | Path, connect: str | None = None, speed: float = 1.0, port: int = 7447,
           run: str | None = None) -> int:
    """Re-publish a recording's messages (original pacing × 1/speed; speed 0 = as fast as possible)."""
    from agent.bus import ZenohBus

    from flocktrack.launch.launcher import open_router

    rec = read_recording(path)
    router = None
    if connect is None:
        router = open_router(port)
        connect = f"tcp/127.0.0.1:{port}"
    name = run
    if name is None:
        import tomllib

        name = tomllib.loads(rec.metadata["scenario"])["run"].get("name", "run") if "scenario" in rec.metadata else "replay"
    bus = ZenohBus(name, connect=connect)
    n = 0
    try:
        t_first = rec.messages[0][2] if rec.messages else 0
        w0 = time.monotonic()
        for key, msg, t in rec.messages:
            if speed > 0:
                due = w0 + (t - t_first) / 1e9 / speed
                while time.monotonic() < due:
                    time.sleep(min(0.01, due - time.monotonic()))
            bus.publish(key, msg)
            n += 1
        time.sleep(0.2)
    finally:
        bus.close()
        if router is not None:
            router.close()
    return n


__all__ = ["run_inproc_to_dir", "run_zenoh_to_dir", "replay", "Progress"]
