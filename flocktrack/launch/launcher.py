"""The launcher: the embedded Zenoh router, and one OS process per node of its host's share of the run plan.

``Launcher(plan, options)`` opens a Zenoh router *inside this process* (``broker_cfg/local.json5``; no
separately installed ``zenohd``; with a placement, this host's router of the mesh, dialling the other hosts'),
spawns the processes the plan places on its host (:meth:`flocktrack.plan.RunPlan.processes`: ``python -m agent
sensor …``, ``python -m topology …``, ``python -m flocktrack.record …``), forwards their output with a
``[name]`` prefix, and supervises them with each node's declared restart policy
(:class:`flocktrack.plan.RestartPolicy`; a restarted sensor rejoins the running flock).

Process faults of the fault plan (crash, pause, router_restart on ``world/event``) are executed here and
acknowledged on ``launcher/event`` once they have taken effect (the process reaped / stopped / continued,
the restarted process spawned, the router about to close): in lockstep the world holds the fault's tick
for that ack, so a crash scheduled for tick k lands at tick k. The launcher is a member of the run
(liveliness token ``launcher/0``, ``launcher/HOST`` with a placement) so the world knows someone will
answer; each host's launcher executes the faults of its own nodes.

Shutdown (end of run, Ctrl-C, SIGTERM) sends SIGTERM to every child, waits, then SIGKILLs what is
left; every child also has PR_SET_PDEATHSIG so it dies with the launcher even if the launcher is
SIGKILLed. No orphan processes.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

from agent.ports import Ports, slug
from flocktrack.launch.commands import Child, Commands, LaunchOptions
from flocktrack.launch.forkserver import ForkedProcess, die_with_parent, forkable, start_server
from flocktrack.plan.model import RunPlan
from flocktrack.resources import broker_config

log = logging.getLogger(__name__)

LOCAL_ROUTER_CFG = "local.json5"

#: the supervisor's control client: it answers kill/restart and the process faults on ``launcher/event``,
#: follows the ticks (the tick a kill names) and the end (a host without the world ends with it)
PORTS = Ports(writes=("launcher/event",), reads=("control/kill", "control/restart", "world/event", "world/tick",
                                                 "world/end"))   # the embedded router's config: broker_cfg/local.json5 of the package


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def open_router(port: int, config_file: Path | None = None, host: str = "127.0.0.1", proto: str = "tcp"):
    """Open the embedded router in this process, listening on PROTO/host:port (``tls`` with a secure
    config from ``flocktrack keys``; default config: the package's ``broker_cfg/local.json5``)."""
    from agent.bus import zenoh_config
    import zenoh

    zenoh.init_log_from_env_or("error")
    config_file = config_file or broker_config(LOCAL_ROUTER_CFG)
    return zenoh.open(zenoh_config(listen=f"{proto}/{host}:{port}", mode="router", config_file=str(config_file)))


def _wait_stopped(pid: int, timeout_s: float) -> bool:
    """Wait until process ``pid`` is in the stopped state (``T`` in /proc/PID/stat); False on timeout."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            return False
        if state in ("T", "t"):
            return True
        time.sleep(0.002)
    return False


STARTUP_REPORT_S = 5.0    #: how often a run that has not begun says what it waits for


_ALARMS = ("WARNING", "ERROR", "CRITICAL", "error:", "Traceback")


def worth_showing(line: str, in_traceback: bool) -> tuple[bool, bool]:
    """Whether a child's log line belongs on the terminal without ``-v`` (a warning, an error, a
    traceback with its last line), and whether we are inside a traceback after it."""
    if line.startswith("Traceback"):
        return True, True
    if in_traceback:
        return True, line[:1].isspace()
    return line.startswith(_ALARMS) or " WARN " in line or " ERROR " in line, False


#: the lifecycle events of a child that the launcher also publishes (verb ``process`` on ``launcher/event``)
PROCESS_EVENTS = frozenset({"exit", "spawn", "restart", "killed"})


def publish_process(bus, k: int, what: str, name: str, kw: dict) -> None:
    """A child's life on the record: ``launcher/event`` verb ``process`` (event exit / spawn / restart / killed,
    the node, its exit code or rejoin), so a recording shows crashes and rejoins on its timeline."""
    if bus is None:
        return
    from agent.wire import Control

    args = {"event": what, "name": name, **{a: kw[a] for a in ("rc", "rejoin", "attempt") if a in kw}}
    try:
        bus.publish("launcher/event", Control(k=k, verb="process", args=args))
    except Exception as exc:  # noqa: BLE001 — the bus closing under a late exit: the event stays in events.json
        log.debug("process event %s %s not published: %s", what, name, exc)


def startup_line(waited_s: float, missing: dict[str, list[str]], links: str = "",
                 gave_up_after_s: float | None = None) -> str:
    """What a run that has not begun says every few seconds — the hosts and nodes it waits for, and ``links``
    (a placed run's router links, :func:`flocktrack.deploy.mesh.router_links`) — or, once it gives up after
    ``gave_up_after_s``, its error line."""
    if gave_up_after_s is None:
        text = f"waiting {waited_s:.0f} s for " + "; ".join(
            f"host {h}: {', '.join(ns[:5])}{' …' if len(ns) > 5 else ''}" for h, ns in missing.items())
    else:
        where = "; ".join(f"host {h}: {', '.join(ns)}" for h, ns in missing.items()) or "the first tick"
        text = f"error: the run did not start within {gave_up_after_s:.0f} s; still waiting for {where}"
    return text + (f"; {links}" if links else "")


class Launcher:
    """Spawns and supervises the processes of one host of a :class:`~flocktrack.plan.RunPlan`."""

    def __init__(self, plan: RunPlan, opts: LaunchOptions):
        self.plan, self.opts = plan, opts
        self.run, self.run_dir, self.mode = plan.run, Path(opts.run_dir), plan.mode
        self.host = plan.host(opts.host) if opts.host else plan.hosts[0]
        self.n = len(plan.of_kind("agent"))
        self.keys = opts.keys
        self.port = self.host.port if plan.multi_host else (opts.port or free_port())
        self.endpoint = f"tls/localhost:{self.port}" if self.keys is not None else f"tcp/127.0.0.1:{self.port}"
        # the children's output always goes to DIR/logs/; on the terminal: every line with ``verbose``,
        # warnings and errors only by default, nothing with ``quiet``
        self.quiet, self.verbose = opts.quiet, opts.verbose
        self.deadlines = 0                 # "deadline on" lines seen in the children's logs (missed rounds)
        self.on_output = None              # called before a child's line is printed (a status line clears)
        self.children: dict[str, Child] = {}
        self.router = None
        self.events: list[dict] = []   # supervisor timeline (spawn / exit / restart), also in run.json
        self._lock = threading.Lock()
        self.stopping = threading.Event()   #: set once the launcher is stopping (no more restarts)
        self.dashboard_port = opts.dashboard_port
        #: the dashboard's operator token (dashboards/operator.py), kept 0600 in the run directory
        self.dashboard_token = opts.dashboard_token
        self._registered = False             # this run is in the machine's list (flocktrack/launch/runs.py)
        self.ctl_bus = None
        self.tick_seen = 0                   # the newest world/tick k (the tick a kill/restart answer names)
        self.ticking = False                 # a world/tick seen: the run has begun on every host
        self.world_ended = False             # world/end seen (how a host without the world knows the end)
        self.members: set[str] = set()       # the plan's members alive (the start barrier across hosts)
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)

    @property
    def name(self) -> str:
        """This launcher's node name (``launcher/0``, or ``launcher/HOST`` with a placement)."""
        return next(n.name for n in self.plan.on(self.host.name) if n.kind == "launcher")

    # ------------------------------------------------------------------ processes
    def child_plan(self) -> list[Child]:
        """This host's children, one per process of the plan on it (:class:`~flocktrack.launch.commands.Commands`)."""
        return Commands(self.plan, self.opts, self.host.name, self.endpoint).children()

    def _open_router(self):
        if self.plan.multi_host:
            return open_router(self.port, config_file=self._mesh_config(), host=self.host.listen or "0.0.0.0")
        if self.keys is None:
            return open_router(self.port)
        return open_router(self.port, config_file=self.keys.router(), proto="tls")

    def _mesh_config(self) -> Path:
        """This host's router config in a placement's mesh (:func:`flocktrack.deploy.mesh.host_router_configs`),
        written to the run directory."""
        from flocktrack.deploy.mesh import host_router_configs

        return host_router_configs(self.plan, self.run_dir / "router")[self.host.name]

    def _record_exit(self, c: Child) -> int | None:
        """The exit code of ``c``'s process if it has exited and was not yet recorded (then records it)."""
        rc = c.proc.poll() if c.proc is not None else None
        if rc is None or c.seen_exit == c.proc.pid:
            return None
        c.seen_exit = c.proc.pid
        c.exits.append(rc)
        self._event("exit", c.name, rc=rc)
        return rc

    def _spawn(self, c: Child, rejoin: bool = False) -> None:
        self._record_exit(c)  # a restart right after a kill: the old exit is on the record first
        argv = list(c.argv) + ([c.rejoin_flag] if rejoin and c.rejoin_flag else [])
        env = dict(os.environ, PYTHONUNBUFFERED="1", RUST_LOG=os.environ.get("RUST_LOG", "error"))
        env["FLOCKTRACK_STATS_DIR"] = str(self.run_dir / "stats")
        if forkable(argv):   # python -m …: forked from the pre-imported template (flocktrack/launch/forkserver.py)
            c.proc = ForkedProcess(argv, env, os.getcwd())
        else:
            c.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                      env=env, preexec_fn=die_with_parent)
        self._event("spawn", c.name, pid=c.proc.pid, rejoin=rejoin, forked=isinstance(c.proc, ForkedProcess))
        threading.Thread(target=self._forward, args=(c, c.proc), daemon=True).start()

    def _forward(self, c: Child, proc: subprocess.Popen) -> None:
        in_traceback = False
        with open(c.log_path, "ab") as logf:
            for line in proc.stdout:  # type: ignore[union-attr]
                logf.write(line)
                text = line.decode(errors="replace")
                if "deadline on" in text:
                    self.deadlines += 1
                show, in_traceback = worth_showing(text, in_traceback)
                if not self.quiet and (self.verbose or show):
                    if self.on_output is not None:
                        self.on_output()
                    sys.stderr.write(f"[{c.name}] {text}")

    def _event(self, what: str, name: str, **kw) -> None:
        with self._lock:
            self.events.append({"t": time.time(), "event": what, "name": name, **kw})
        if what in PROCESS_EVENTS and self.ticking and not (what == "exit" and kw.get("rc") == 0):
            publish_process(self.ctl_bus, self.tick_seen, what, name, kw)  # (start-up spawns are the plan; a clean
                                                                            # exit at the end is not news)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        kids = self.child_plan()
        if any(forkable(c.argv) for c in kids):
            start_server()        # the template's imports, once, before the router and the children
        self.router = self._open_router()
        from agent.bus import ZenohBus

        self.ctl_bus = ZenohBus(self.run, connect=self.endpoint,
                                config_file=str(self.keys.client(slug(self.name))) if self.keys is not None else None)
        self.ctl_bus.restrict_writes(PORTS.writes)
        self.ctl_bus.subscribe("control/kill", self._on_control)
        self.ctl_bus.subscribe("control/restart", self._on_control)
        self.ctl_bus.subscribe("world/event", self._on_world_event)
        self.ctl_bus.subscribe("world/tick", self._on_tick)
        self.ctl_bus.subscribe("world/end", self._on_end)
        self.ctl_bus.watch_members(self._on_member)
        self.ctl_bus.declare_token(self.name)
        self._register()
        self._started_at = time.monotonic()
        self._told_at = self._started_at
        for c in kids:
            self.children[c.name] = c
            self._spawn(c)

    def _on_member(self, name: str, alive: bool) -> None:
        (self.members.add if alive else self.members.discard)(name)

    def _on_end(self, key: str, msg) -> None:
        self.world_ended = True

    def waiting_for(self) -> dict[str, list[str]]:
        """Before the first tick: the plan's members not yet alive, by host."""
        out: dict[str, list[str]] = {}
        for n in self.plan.nodes:
            if n.member and n.name not in self.members and n.name != self.name:
                out.setdefault(n.host, []).append(n.name)
        return out

    def _router_links(self) -> str:
        if not self.plan.multi_host or self.router is None:
            return ""
        from flocktrack.deploy.mesh import router_links

        return router_links(self.plan, self.host.name, {str(z) for z in self.router.info.routers_zid()})

    def _startup_check(self) -> int | None:
        """Until the first tick: every few seconds, which hosts and nodes the run still waits for (and, with a
        placement, this host's router links); after ``startup_timeout_s`` the run gives up (exit 3)."""
        if self.ticking:
            return None
        now = time.monotonic()
        late = now - self._started_at > self.opts.startup_timeout_s
        if late or now - self._told_at >= STARTUP_REPORT_S:
            self._told_at, missing = now, self.waiting_for()
            if missing or late:
                print(startup_line(now - self._started_at, missing, self._router_links(),
                                   self.opts.startup_timeout_s if late else None), file=sys.stderr, flush=True)
        return 3 if late else None

    def _register(self) -> None:
        """This run in the machine's list of runs (flocktrack/launch/runs.py: ``flocktrack ps``, ``fault``, ``logs``)."""
        from flocktrack.launch.runs import LocalRun, register

        config = self.keys.client("dashboard") if self.keys is not None else None
        try:
            register(LocalRun(self.run, self.endpoint, self.mode, self.n, str(self.run_dir.resolve()), os.getpid(),
                              time.time(), str(config) if config else None, self.dashboard_port))
            self._registered = True
        except OSError as exc:
            print(f"warning: run not listed for `flocktrack ps` ({exc})", file=sys.stderr)

    def _on_control(self, key: str, msg) -> None:
        """control/kill {agent} SIGKILLs a sensor and holds it down; control/restart {agent} brings it
        back (rejoining the flock). Each is answered on ``launcher/event`` (verb = the command's, args:
        agent, applied, reason, and the sender's ``req``) — what ``flocktrack fault`` waits for."""
        from agent.wire import WireError, command

        try:
            cmd = command(msg.verb, msg.args, self.n)
        except WireError as exc:
            return self._answer(msg, None, f"{exc.detail or exc.reason}")
        name = f"agent/{cmd.agent}"
        c = self.children.get(name)
        if c is None:
            return  # (another host's launcher runs it)
        if msg.verb == "kill":
            if not self.alive(name):
                return self._answer(msg, cmd.agent, f"{name} is not running")
            c.hold = True
            c.restart_at = None
            self.kill(name, signal.SIGKILL)
            self._answer(msg, cmd.agent, None)
        elif self.stopping.is_set():
            self._answer(msg, cmd.agent, "the run is stopping")
        elif self.alive(name):
            self._answer(msg, cmd.agent, f"{name} is running (kill it first)")
        else:
            c.hold = False
            c.restart_at = None
            self._event("restart", name, attempt=c.restarts, requested=True)
            self._spawn(c, rejoin=True)
            self._answer(msg, cmd.agent, None)

    def _on_tick(self, key: str, msg) -> None:
        self.ticking = True
        self.tick_seen = max(self.tick_seen, msg.k)

    def _answer(self, msg, agent: int | None, refusal: str | None) -> None:
        """A control's outcome on ``launcher/event``: applied (``refusal`` None) or refused, and why, at the
        newest tick the launcher has seen."""
        from agent.wire import Control, request_id

        args = {"agent": agent, "applied": refusal is None, "reason": (refusal or "")[:300], **request_id(msg.args)}
        if self.ctl_bus is not None:
            self.ctl_bus.publish("launcher/event", Control(k=self.tick_seen, verb=msg.verb, args=args))

    def _on_world_event(self, key: str, msg) -> None:
        """Process-level faults of the plan (topology/faults.py): crash → SIGKILL (restart at heal),
        pause → SIGSTOP (SIGCONT at heal), router_restart → close the router (reopen 1 s later). Each is
        acknowledged on ``launcher/event`` once it has taken effect."""
        if msg.verb != "fault" or msg.args.get("kind") not in ("crash", "pause", "router_restart"):
            return
        from agent.wire import int_list

        kind, phase = msg.args["kind"], msg.args.get("phase")
        agents = int_list(msg.args.get("agents", []), 0, self.n)
        if agents is None or phase not in ("start", "heal"):
            return
        names = [f"agent/{a}" for a in agents]
        if kind == "router_restart" and "world/0" not in self.children:
            return   # (the world's host's launcher bounces its router)
        if kind != "router_restart" and not any(nme in self.children for nme in names):
            return   # (another host's launcher runs them, and answers)
        self._event("fault", kind, phase=phase, agents=names, k=msg.k)
        if kind == "crash":
            for nme in names:
                c = self.children.get(nme)
                if c is None:
                    continue
                if phase == "start":
                    c.hold, c.restart_at = True, None
                    self.kill(nme, signal.SIGKILL)
                elif not self.alive(nme) and not self.stopping.is_set():
                    c.hold = False
                    self._spawn(c, rejoin=True)
                    self._event("restart", nme, attempt=c.restarts, fault=True)
        elif kind == "pause":
            for nme in names:
                self.kill(nme, signal.SIGSTOP if phase == "start" else signal.SIGCONT)
        self._ack(msg, agents)
        if kind == "router_restart" and phase == "start" and self.router is not None:
            self._router_down_at = time.monotonic()
            threading.Thread(target=self._bounce_router, daemon=True).start()

    def _ack(self, msg, agents: list[int]) -> None:
        """Tell the world a process fault has taken effect (``launcher/event`` ack, k = the fault's tick)."""
        from agent.wire import Control

        a = msg.args
        if self.ctl_bus is not None:
            self.ctl_bus.publish("launcher/event", Control(k=msg.k, verb="ack", args={
                "id": a.get("id"), "kind": a.get("kind"), "phase": a.get("phase"), "agents": [float(x) for x in agents]}))

    def _bounce_router(self, down_s: float = 1.0, flush_s: float = 0.05) -> None:
        """Close the embedded router (``flush_s`` after the ack, so the ack reaches the world), keep it
        down ``down_s``, reopen it on the same port."""
        time.sleep(flush_s)
        old, self.router = self.router, None
        old.close()
        self._event("router", "down")
        time.sleep(down_s)
        self.router = self._open_router()
        self._event("router", "up")

    def kill(self, name: str, sig: int = signal.SIGKILL, wait_s: float = 5.0) -> None:
        """Fault injection / tests: signal one child and wait (up to ``wait_s``) until the signal has
        taken effect — SIGKILL: the process is reaped (a restart right after sees it dead; the supervision
        loop records its exit and applies the restart policy); SIGSTOP: the process is stopped."""
        c = self.children[name]
        if not (c.proc and c.proc.poll() is None):
            return
        c.proc.send_signal(sig)
        self._event("signal", name, signal=int(sig))
        if sig == signal.SIGKILL:
            try:
                c.proc.wait(wait_s)
            except subprocess.TimeoutExpired:
                pass
        elif sig == signal.SIGSTOP:
            _wait_stopped(c.proc.pid, wait_s)

    def supervise_once(self, timeout_s: float = 0.0) -> None:
        """One supervision step: control and fault messages (waiting up to ``timeout_s`` for the first,
        so a fault is executed the moment it arrives), exits, due restarts."""
        if self.ctl_bus is not None:
            self.ctl_bus.poll(timeout_s)
        elif timeout_s > 0:
            time.sleep(timeout_s)
        now = time.monotonic()
        for c in self.children.values():
            if c.proc is None:
                continue
            rc = self._record_exit(c)
            if rc is not None:
                if rc != 0 and c.policy.mode == "on-failure" and c.restarts < c.policy.max_restarts \
                        and not self.stopping.is_set() and not c.hold:
                    c.restarts += 1
                    c.restart_at = now + c.policy.delay(c.restarts)
            if c.restart_at is not None and now >= c.restart_at and not self.stopping.is_set():
                c.restart_at = None
                self._event("restart", c.name, attempt=c.restarts)
                self._spawn(c, rejoin=True)

    def alive(self, name: str) -> bool:
        c = self.children.get(name)
        return bool(c and c.proc and c.proc.poll() is None)

    def wait(self, timeout_s: float | None = None, on_poll=None) -> int:
        """Supervise until the world exits — or, on a host without the world, until its end — then give the
        rest a moment to finish. Returns the world's exit code (0 on a host without it; 3 when the run did not
        start, 124 on timeout, 130 when stopped)."""
        t0 = time.monotonic()
        world = self.children.get("world/0")
        while True:
            self.supervise_once(0.05)
            if on_poll is not None:
                on_poll(self)
            if self.stopping.is_set():
                return 130
            rc = self._startup_check()
            if rc is not None:
                return rc
            done = world.proc is not None and world.proc.poll() is not None if world is not None else self.world_ended
            if done:
                rc = world.proc.returncode if world is not None else 0
                end = time.monotonic() + 20.0
                while time.monotonic() < end and any(
                        c.proc and c.proc.poll() is None for c in self.children.values() if not c.service):
                    self.supervise_once(0.05)
                self.supervise_once()
                return rc
            if timeout_s is not None and time.monotonic() - t0 > timeout_s:
                return 124

    def request_stop(self) -> None:
        self.stopping.set()

    def shutdown(self, grace_s: float = 5.0) -> None:
        """SIGTERM every child, wait, SIGKILL what is left, close the router."""
        self.stopping.set()
        procs = [c.proc for c in self.children.values() if c.proc and c.proc.poll() is None]
        # the recorder last, so it records the others' goodbyes
        recorders = [c for c in self.children.values() if c.name.startswith("recorder/")]
        for p in procs:
            if all(p is not r.proc for r in recorders):
                p.send_signal(signal.SIGTERM)
        end = time.monotonic() + grace_s
        for p in procs:
            try:
                p.wait(max(0.0, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
        rec = recorders[0] if recorders else None
        if rec and rec.proc and rec.proc.poll() is None:
            rec.proc.send_signal(signal.SIGTERM)
            try:
                rec.proc.wait(grace_s)
            except subprocess.TimeoutExpired:
                pass
        for c in self.children.values():
            if c.proc and c.proc.poll() is None:
                c.proc.kill()
                c.proc.wait()
                self._event("killed", c.name)
        if self._registered:
            from flocktrack.launch.runs import unregister

            unregister(self.run)
            self._registered = False
        if self.ctl_bus is not None:
            self.ctl_bus.close()
            self.ctl_bus = None
        if self.router is not None:
            self.router.close()
            self.router = None

    def pids(self) -> list[int]:
        return [c.proc.pid for c in self.children.values() if c.proc]

    def write_events(self, path: Path) -> None:
        path.write_text(json.dumps(self.events, indent=1))
