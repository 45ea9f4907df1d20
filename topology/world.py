"""The world / clock role: ticks, the per-tick link table, target visibility (DESIGN.md step 1, 5).

At tick k the world publishes ``tick`` {k, t, links, weights, b, δ_max, alive, positions}:

* links: from a periodic schedule (Chen's switching graphs) or by range — edge (i, j) iff
  ‖qᵢ − qⱼ‖ ≤ E with positions at the end of tick k−1 (Gu & Hu Sec. III-A) — minus dead nodes;
* visibility bᵢ(k): the schedule's, or β if ‖qᵢ − x_target‖ ≤ sensing range, else 0;
* δ_max of the tick's graph, so every node uses the same consensus rate η.

It then waits for every alive sensor's ``state`` k and the target's ``state`` k (or the deadline),
and starts tick k+1 — in realtime, its clock closes tick k at t0 + (k+1)·T/speed whatever has arrived, except
tick 0, the warm-up (routes and publishers being set up), which closes on its states. While the flock cannot
keep that pace (its states do not come) the clock yields (``run.pace = "adaptive"``, the default) — the period
stretches and comes back once the flock keeps up (pace.py). Each realtime tick announces its period. It is the
only role that knows all positions.

Process faults (crash, pause, router_restart) are executed by the launcher. In lockstep, when a launcher
is a member of the run (its liveliness token ``launcher/0``), the world publishes such a fault's
transition on ``world/event`` and holds tick k until the launcher acknowledges it on ``launcher/event``
(the process is dead / stopped / continued, the router is going down) — and, for a crash's heal, until
the restarted sensor is a member again; after a router restart the next tick waits for every member's
return — so a crash scheduled for tick k lands at tick k and the sensor is back at its heal tick
(``fault_hold.py``). Without a launcher, or past ``ack_timeout_s``, the tick goes on.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from agent.bus import Bus
from agent.ports import Ports
from agent.roles.common import Role
from agent.seeding import rng_for
from agent.wire import (Command, Control, End, HealFault, Inject, LinkEdit, LinkLoss, Message, Partition, Speed, State,
                        Step, Tick, WireError, command, fault_event, request_id)

from agent.scenario import FaultsCfg, Scenario, ScenarioError, parse_fault_event

from .fault_hold import FaultHold
from .faults import FaultPlan
from .graph import GraphSpec, PeriodicSchedule, edge_weights, max_degree, neighbour_lists, range_adjacency
from .pace import PaceGovernor


def schedule_of(sc: Scenario) -> PeriodicSchedule | None:
    """The scenario's switching schedule (None for range-based links)."""
    tp = sc.topology
    if tp.kind != "schedule":
        return None
    graphs = tuple(GraphSpec(n=sc.sensors.n, edges=tuple(tuple(e) for e in g.edges), b=tuple(g.b),
                             weights=None if g.weights is None else tuple(g.weights)) for g in tp.graphs)
    return PeriodicSchedule(graphs=graphs, dwell_ticks=tp.dwell_ticks)


def build_world(sc: Scenario, **kw) -> "WorldRole":
    """The world role of a scenario (extra keyword arguments go to :class:`WorldRole`)."""
    tp = sc.topology
    x0 = np.array(sc.target.x0, float)
    P0 = sc.initial_positions()
    return WorldRole(sc.sensors.n, sc.run.ticks, sc.run.T, P0, x0[: min(sc.pos_dims, P0.shape[1])],
                     schedule=schedule_of(sc), radius=tp.range, sensing_range=sc.sensors.sensing_range,
                     beta=sc.sensors.beta, speed=sc.run.speed, seed=sc.run.seed,
                     faults=FaultPlan(sc.faults, sc.sensors.n, sc.run.seed),
                     **{"adaptive_pace": sc.run.pace == "adaptive", **kw})


log = logging.getLogger(__name__)

#: the fault kinds the launcher executes; in lockstep the world waits for its ack (``launcher/event``)
PROCESS_FAULTS = frozenset({"crash", "pause", "router_restart"})

#: the control verbs the world executes (kill/restart: the launcher; outlier_burst: the sensors)
WORLD_VERBS = frozenset({"pause", "resume", "step", "speed", "link_drop", "link_heal", "link_loss", "partition",
                         "heal", "inject", "heal_fault"})


class WorldRole(Role):
    name = "world"
    wait_depth = 2
    #: the clock and the link table, the fault plan's events, the end; what it reads: the states that close a
    #: tick, the control plane and the launcher's acknowledgements of process faults
    PORTS = Ports(writes=("world/tick", "world/event", "world/end"),
                  reads=("agent/*/state", "target/state", "control/**", "launcher/event"))

    def __init__(self, n: int, ticks: int, T: float, positions0: np.ndarray, target_pos0: np.ndarray, *,
                 schedule: PeriodicSchedule | None = None, radius: float = np.inf,
                 sensing_range: float = np.inf, beta: float = 1.0, realtime: bool = False, speed: float = 1.0,
                 seed: int = 0, faults: FaultPlan | None = None, ack_timeout_s: float = 30.0,
                 adaptive_pace: bool = False):
        super().__init__(ticks)
        # process faults (lockstep, with a launcher): tick k waits for the launcher (fault_hold.py)
        self.hold = FaultHold(timeout_s=ack_timeout_s)
        self._held_graph: tuple[np.ndarray, list[float]] | None = None   # held tick's links before the dead mask
        self.realtime = bool(realtime)
        self.period = float(T) / float(speed)  # wall-clock seconds per tick in realtime
        self.pace, self.adaptive_pace = PaceGovernor(self.period), bool(adaptive_pace)   # run.pace (pace.py)
        self._t0: float | None = None
        self._opened_at, self._arrivals = 0.0, []   # when the open tick was published, its states came after it
        self._expected: set[int] = set()
        self.stats = {"late_states": 0, "missing_states": 0, "controls": 0}
        self._late_logged_at, self._late_unlogged = -float("inf"), 0   # (the late states' log line)
        # control plane (DESIGN.md control/**): pause/step/speed and link faults, applied per tick
        self.paused = False
        self._step_budget: int | None = None
        self._pause_started: float | None = None
        self._hold = False                      # lockstep: tick complete but paused
        self.dropped_links: set[tuple[int, int]] = set()
        self.link_loss = 0.0
        self.groups: list[int] | None = None
        self._fault_rng = rng_for(seed, "world", 0, "faults")
        self.plan = faults if faults is not None else FaultPlan(FaultsCfg(), n, seed)
        self.live_faults: list[int] = []          # ids of the faults injected through control/inject
        self.last_rejection = ""                  # why the last control was refused (world/event "rejected")
        self.n, self.T = int(n), float(T)
        self.schedule = schedule
        self.radius = float(radius)
        self.sensing_range = float(sensing_range)
        self.beta = float(beta)
        self.positions = np.array(positions0, float).reshape(self.n, -1)
        self.target_pos = np.array(target_pos0, float)
        self.alive = [True] * self.n
        self.k = 0
        self._states: dict[int, State] = {}
        self._target_state: State | None = None
        self._open = False
        self.last_tick: Tick | None = None

    def subscribe(self, bus: Bus) -> None:
        bus.subscribe("agent/*/state", self._on_state, bulk=True)    # (n a tick: kept in Zenoh till polled)
        bus.subscribe("target/state", self._on_target_state)
        bus.subscribe("control/**", self._on_control)
        bus.subscribe("launcher/event", self._on_launcher_event)

    # ------------------------------------------------------------------ control plane
    def _on_control(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Control)
        self.last_rejection = "bad arguments"
        if not self.apply_control(msg.verb, msg.args):
            if msg.verb in WORLD_VERBS:   # say why on the timeline (the dashboard shows it); others' verbs: silence
                self.stats["rejected_controls"] = self.stats.get("rejected_controls", 0) + 1
                why = {"verb": msg.verb, "reason": self.last_rejection[:300], **request_id(msg.args)}
                self.publish("world/event", Control(k=self._next_k(), verb="rejected", args=why))
        else:
            self.stats["controls"] += 1
            args = dict(msg.args)
            if msg.verb == "inject":
                args["id"] = self.live_faults[-1]     # to heal it by: control/heal_fault {id}
            self.publish("world/event", Control(k=self._next_k(), verb=msg.verb, args=args))

    def apply_control(self, verb: str, args: dict) -> bool:
        """Apply one control verb, its arguments typed by :func:`agent.wire.command`. False: not the world's
        verb, or refused (:attr:`last_rejection` says why)."""
        if verb not in WORLD_VERBS:
            return False
        try:
            cmd = command(verb, args, self.n)
        except WireError as exc:
            self.last_rejection = exc.detail or exc.reason
            if verb == "inject":
                self.stats["rejected_injections"] = self.stats.get("rejected_injections", 0) + 1
            return False
        return self._execute(cmd)

    def _execute(self, cmd: Command) -> bool:
        match cmd:
            case Step(n=n):
                self.paused, self._step_budget = False, n
                self._release()
            case Speed(factor=f):
                self._set_speed(f)
            case LinkEdit(verb=verb, a=a, b=b):
                (self.dropped_links.add if verb == "link_drop" else self.dropped_links.discard)((min(a, b), max(a, b)))
            case LinkLoss(p=p):
                self.link_loss = p
            case Partition(groups=g):
                self.groups = list(g)
            case Inject():
                return self._inject(cmd)
            case HealFault(id=fid):
                if not self.plan.heal_at(self._next_k(), fid):
                    self.last_rejection = f"no live fault {fid} to heal"
                    return False
            case Command(verb="pause"):
                self.paused, self._step_budget = True, None
            case Command(verb="resume"):
                self.paused, self._step_budget = False, None
                self._release()
            case Command(verb="heal"):
                self.groups, self.link_loss = None, 0.0
                self.dropped_links.clear()
                self.plan.heal_at(self._next_k())
        return True

    def _set_speed(self, factor: float) -> None:
        """Realtime pace T / factor (kept stretched as much as it was, pace.py)."""
        self.pace.set_nominal(self.T / factor)
        self._set_period(self.pace.period, time.monotonic())

    def _set_period(self, period: float, at: float) -> None:
        """The realtime period from ``at`` on; t0 re-anchored so that the ticks elapsed keep their phase."""
        if self._t0 is not None:
            elapsed_ticks = (at - self._t0) / self.period
            self._t0 = at - elapsed_ticks * period
        self.period = period

    def _next_k(self) -> int:
        """The tick a control received now takes effect on (the open one has been published already)."""
        return self.k + 1 if self._open else self.k

    def _inject(self, cmd: Inject) -> bool:
        """control/inject: one fault-plan event, live (the keys of a [[faults.events]] entry, typed by the
        scenario schema, for ``ticks`` ticks). A malformed one is rejected and counted, never raised."""
        try:
            e = parse_fault_event(cmd.event, self.n)
        except ScenarioError as exc:
            self.stats["rejected_injections"] = self.stats.get("rejected_injections", 0) + 1
            self.last_rejection = str(exc)
            return False
        self.live_faults.append(self.plan.inject(e, self._next_k(), cmd.ticks))
        return True

    def _release(self) -> None:
        if self._hold:
            self._hold = False
            self._advance()

    def _apply_link_faults(self, adj: np.ndarray) -> None:
        for a, b in self.dropped_links:
            adj[a, b] = adj[b, a] = 0.0
        if self.groups is not None:
            g = np.array(self.groups)
            adj[g[:, None] != g[None, :]] = 0.0
        if self.link_loss > 0:
            iu = np.triu_indices(self.n, 1)
            lost = self._fault_rng.random(len(iu[0])) < self.link_loss
            adj[iu[0][lost], iu[1][lost]] = 0.0
            adj[iu[1][lost], iu[0][lost]] = 0.0

    @property
    def finished(self) -> bool:
        return self.k >= self.ticks

    @property
    def waiting(self) -> bool:
        return self._open and not self._hold

    def start(self) -> None:
        self._publish_tick()

    def step_period(self, k: int) -> float | None:   # (realtime: the period kept now, stretched or a speed's)
        return self.period if self.realtime else None

    def on_member(self, role: str, ident: int, alive: bool) -> None:
        """A process appeared or vanished. A dead sensor has no links until it returns; a returning one is
        expected to report from the next tick on. (And what a held tick waits for: fault_hold.py.)"""
        outage = self.hold.member((role, ident), alive)
        if role == "agent" and 0 <= ident < self.n and self.alive[ident] != alive:
            self.alive[ident] = alive
            if not alive:
                self._expected.discard(ident)
                self._check()
        self._release_fault_hold(force=outage)

    def on_timer(self, now: float) -> None:
        """Realtime pacing: tick k ≥ 1 closes at t0 + (k+1)·T whatever has arrived (late = lost); tick 0, the
        warm-up, closes on its states as in lockstep, and t0 is set then. In any mode:
        a tick held for the launcher's acks goes on after ``ack_timeout_s``."""
        if self.hold.check_timeout(now, self._held_graph is not None):
            self.stats["fault_hold_timeouts"] = self.hold.timeouts
            self._release_fault_hold()
        if not self.realtime or self.finished:
            return
        if self.k == 0:     # the warm-up tick closes on its states (_check)
            self._check()
            return
        if self._t0 is None:
            # tick 0 was the warm-up, closed on its states like lockstep — every process's routes and
            # addressed publishers got set up in it; the clock starts now: tick 1 closes a period on
            self._t0 = now - self.period
        if self.paused:
            if self._pause_started is None:
                self._pause_started = now
            return
        if self._pause_started is not None:  # the clock stood still while paused
            self._t0 += now - self._pause_started
            self._pause_started = None
        due = self._t0 + (self.k + 1) * self.period
        if self._open and now >= due:
            late = now - due
            if late > 0.1 * self.period:
                # the clock itself is late (this process waited for a core: with ~30 runnable processes on 2
                # cores the scheduler can take ~25 ms to run it): the clock slips by that much instead of
                # taking it from the next tick, whose sensors would otherwise get a short period
                self._t0 += late
                self.stats["clock_slips"] = self.stats.get("clock_slips", 0) + 1
                self.stats["clock_slip_ms_max"] = round(max(self.stats.get("clock_slip_ms_max", 0.0), late * 1e3), 1)
                log.info("world: tick %d closed %.1f ms late; the clock slips by as much", self.k, late * 1e3)
            self._advance()

    def next_timer(self) -> float | None:
        """Realtime: the moment the open tick closes (now, if the clock has yet to start after tick 0)."""
        if not self.realtime or self.finished or self.k == 0 or self.paused or not self._open:
            return None
        return 0.0 if self._t0 is None else self._t0 + (self.k + 1) * self.period

    # ------------------------------------------------------------------ the link table
    def graph(self, k: int) -> tuple[np.ndarray, list[float]]:
        """Symmetric adjacency and visibility of tick k before the fault plan."""
        adj, b = self._linked_graph(k)
        return self._mask_dead(adj), b

    def _linked_graph(self, k: int) -> tuple[np.ndarray, list[float]]:
        """The schedule's or range's links with the world's link faults, dead nodes not yet removed."""
        if self.schedule is not None:
            g = self.schedule.at(k)
            adj = g.adjacency()
            b = [float(v) for v in g.b]
        else:
            adj = range_adjacency(self.positions, self.radius)
            d = self.target_pos.size
            dist = np.linalg.norm(self.positions[:, :d] - self.target_pos[None, :], axis=1)
            b = [self.beta if di <= self.sensing_range else 0.0 for di in dist]
        self._apply_link_faults(adj)
        return adj, b

    def _mask_dead(self, adj: np.ndarray) -> np.ndarray:
        """A dead node has no links (in place; returns ``adj``)."""
        for i, a in enumerate(self.alive):
            if not a:
                adj[i, :] = 0.0
                adj[:, i] = 0.0
        return adj

    def make_tick(self, k: int, graph: tuple[np.ndarray, list[float]] | None = None) -> Tick:
        """The tick message: links[i] = the nodes whose payloads i hears (directed once the fault plan
        drops single directions), weights aligned, b with blinded sensors at 0."""
        adj, b = self.graph(k) if graph is None else graph
        M = adj
        if self.plan is not None and not self.plan.empty:
            M = self.plan.directed_mask(adj)
            for i in self.plan.blind():
                b[i] = 0.0
        return Tick(k=k, t=k * self.T, n=self.n, links=neighbour_lists(M), weights=edge_weights(M), b=b,
                    delta_max=max_degree(M), alive=list(self.alive), positions=self.positions.copy(),
                    period=self.period if self.realtime else 0.0)

    def _publish_tick(self) -> None:
        adj, b = self._linked_graph(self.k)
        g = (self._mask_dead(adj.copy()), b)
        if self.plan is not None and not self.plan.empty:
            for phase, f in self.plan.transitions(self.k, g[0]):
                self.stats[f"fault_{phase}s"] = self.stats.get(f"fault_{phase}s", 0) + 1
                self.publish("world/event", Control(k=self.k, verb="fault", args=f.event_args(phase)))
                if f.cfg.kind in PROCESS_FAULTS and self.hold.launcher and not self.realtime:
                    self.hold.expect(f.id, phase, f.cfg.kind, ("world", 0))
        if self.hold.blocked:
            self._held_graph = (adj, b)   # tick k waits for the launcher (fault_hold.py)
            return
        self._emit_tick(g)

    def _emit_tick(self, g: tuple[np.ndarray, list[float]]) -> None:
        self.last_tick = self.make_tick(self.k, g)
        self._expected = {i for i in range(self.n) if self.alive[i]}
        self._open = True
        self._opened_at, self._arrivals = time.monotonic(), []
        self.publish("world/tick", self.last_tick)

    def _on_launcher_event(self, key: str, msg: Message) -> None:
        """``ack`` {id, kind, phase, agents}: the launcher executed a process fault. A crashed sensor is dead
        from this tick on (its liveliness token may take a moment to go); a restarted one is awaited."""
        assert isinstance(msg, Control)
        if msg.verb != "ack":
            return
        try:
            ack = fault_event(msg.args, self.n)
        except WireError:
            return
        if ack.kind == "crash" and ack.phase == "start":
            for i in ack.agents:
                if self.alive[i]:
                    self.alive[i] = False
                    self._expected.discard(i)
        self.hold.ack(ack.id, ack.phase, ack.kind, list(ack.agents))
        self._release_fault_hold()
        self._check()

    def _release_fault_hold(self, force: bool = False) -> None:
        """Publish the held tick once the launcher has done all it was asked and the members are back
        (``force``: now, whatever is still awaited)."""
        if self._held_graph is None or (self.hold.blocked and not force):
            return
        adj, b = self._held_graph
        self._held_graph = None
        self._emit_tick((self._mask_dead(adj), b))

    # ------------------------------------------------------------------ collecting states
    def _on_state(self, key: str, msg: Message) -> None:
        assert isinstance(msg, State)
        if msg.pos.size < self.positions.shape[1]:
            self.stats["rejected_states"] = self.stats.get("rejected_states", 0) + 1
            return
        if msg.k == self.k and msg.src < self.n:
            if msg.src not in self._states:
                self._arrivals.append(time.monotonic() - self._opened_at)
            self._states[msg.src] = msg
            self._check()
        elif msg.k < self.k:
            self.stats["late_states"] += 1
            self._log_late(msg)

    def _govern_pace(self) -> None:
        """Realtime, a tick closing: the next one's period from when this one's states came (pace.py)."""
        before = self.pace.period
        if (period := self.pace.close(len(self._expected), self._arrivals)) != before:
            self._set_period(period, self._t0 + (self.k + 1) * before)     # from this tick's close on
        if (line := self.pace.change(before)) is not None:
            log.info("world: tick %d: %s", self.k, line)
        self.stats.update(pace_stretched_ticks=self.pace.stretched_ticks, pace_max_stretch=self.pace.max_stretch)

    def _log_late(self, msg: State, every_s: float = 1.0) -> None:
        """A state that came after its tick closed: logged at most once every ``every_s`` seconds, with the
        count since the last line (an overloaded flock sends hundreds a second; each is in ``late_states``)."""
        now = time.monotonic()
        self._late_unlogged += 1
        if now - self._late_logged_at >= every_s:
            log.info("world: late states, come after their tick closed: %d since the last such line (the latest: "
                     "agent/%d's for tick %d, now at %d)", self._late_unlogged, msg.src, msg.k, self.k)
            self._late_logged_at, self._late_unlogged = now, 0

    def _on_target_state(self, key: str, msg: Message) -> None:
        assert isinstance(msg, State)
        if msg.k == self.k and msg.pos.size >= self.target_pos.size:
            self._target_state = msg
            self._check()

    def _check(self) -> None:
        if self.realtime and (self.k > 0 or self.paused):
            return  # realtime: the clock closes the tick (on_timer); tick 0 is the warm-up (_advance)
        if self._open and self._target_state is not None and all(i in self._states for i in self._expected):
            self._advance()

    def on_deadline(self) -> None:
        """A guard against dead processes; a paused realtime world holds its clock (on_timer resumes)."""
        if self._open and not (self.realtime and self.paused):
            self._advance()

    def _advance(self) -> None:
        if self.paused and not self.realtime:
            self._hold = True  # lockstep: the tick is complete; the next one waits for resume/step
            return
        if self._step_budget is not None:
            self._step_budget -= 1
            if self._step_budget <= 0:
                self.paused, self._step_budget = True, None
        missing = self._expected - set(self._states)
        if missing:
            self.stats["missing_states"] += len(missing)
            log.info("world: tick %d closed without the states of %d sensors (%s)", self.k, len(missing),
                     _few(sorted(missing)))
            # on the run's record too (recordings, the Foxglove log, flocktrack.load's events): at most one a tick
            self.publish("world/event", Control(k=self.k, verb="late", args={"missing": len(missing),
                                                                             "agents": sorted(missing)[:64]}))
        if self.realtime and self.adaptive_pace and self._t0 is not None:
            self._govern_pace()
        for i, s in self._states.items():
            self.positions[i] = s.pos[: self.positions.shape[1]]
        if self._target_state is not None:
            self.target_pos = self._target_state.pos.copy()
        self._states.clear()
        self._target_state = None
        self._open = False
        self.k += 1
        if not self.finished:
            self._publish_tick()
        else:
            self.publish("world/end", End(k=self.k, reason="done"))


def _few(ids: list[int], most: int = 8) -> str:
    """'agent/1, agent/4, … (+12)': a log line's list of sensors, short."""
    head = ", ".join(f"agent/{i}" for i in ids[:most])
    return head + (f", … (+{len(ids) - most})" if len(ids) > most else "")
