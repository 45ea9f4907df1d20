"""The world / clock role: ticks, the per-tick link table, target visibility (DESIGN.md step 1, 5).

At tick k the world publishes ``tick`` {k, t, links, weights, b, δ_max, alive, positions}:

* links: from a periodic schedule (Chen's switching graphs) or by range — edge (i, j) iff
  ‖qᵢ − qⱼ‖ ≤ E with positions at the end of tick k−1 (Gu & Hu Sec. III-A) — minus dead nodes;
* visibility bᵢ(k): the schedule's, or β if ‖qᵢ − x_target‖ ≤ sensing range, else 0;
* δ_max of the tick's graph, so every node uses the same consensus rate η.

It then waits for every alive sensor's ``state`` k and the target's ``state`` k (or the deadline),
and starts tick k+1. It is the only role that knows all positions.
"""

from __future__ import annotations

import numpy as np

from agent.bus import Bus
from agent.roles.common import Role
from agent.wire import End, Message, State, Tick

from agent.scenario import Scenario

from .graph import GraphSpec, PeriodicSchedule, edge_weights, max_degree, neighbour_lists, range_adjacency


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
                     beta=sc.sensors.beta, speed=sc.run.speed, **kw)


class WorldRole(Role):
    name = "world"

    def __init__(self, n: int, ticks: int, T: float, positions0: np.ndarray, target_pos0: np.ndarray,
                 schedule: PeriodicSchedule | None = None, radius: float = np.inf,
                 sensing_range: float = np.inf, beta: float = 1.0, realtime: bool = False, speed: float = 1.0):
        super().__init__(ticks)
        self.realtime = bool(realtime)
        self.period = float(T) / float(speed)  # wall-clock seconds per tick in realtime
        self._t0: float | None = None
        self._expected: set[int] = set()
        self.stats = {"late_states": 0, "missing_states": 0}
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
        bus.subscribe("agent/*/state", self._on_state)
        bus.subscribe("target/state", self._on_target_state)

    @property
    def finished(self) -> bool:
        return self.k >= self.ticks

    @property
    def waiting(self) -> bool:
        return self._open

    def start(self) -> None:
        self._publish_tick()

    def on_member(self, role: str, ident: int, alive: bool) -> None:
        """A sensor process appeared or vanished: a dead node has no links until it returns; a
        returning node is expected to report from the next tick on."""
        if role == "agent" and 0 <= ident < self.n and self.alive[ident] != alive:
            self.alive[ident] = alive
            if not alive:
                self._expected.discard(ident)
                self._check()

    def on_timer(self, now: float) -> None:
        """Realtime pacing: tick k closes at t0 + (k+1)·T whatever has arrived (late = lost)."""
        if not self.realtime or self.finished:
            return
        if self._t0 is None:
            self._t0 = now
        if self._open and now >= self._t0 + (self.k + 1) * self.period:
            self._advance()

    # ------------------------------------------------------------------ the link table
    def make_tick(self, k: int) -> Tick:
        if self.schedule is not None:
            g = self.schedule.at(k)
            adj = g.adjacency()
            b = [float(v) for v in g.b]
        else:
            adj = range_adjacency(self.positions, self.radius)
            d = self.target_pos.size
            dist = np.linalg.norm(self.positions[:, :d] - self.target_pos[None, :], axis=1)
            b = [self.beta if di <= self.sensing_range else 0.0 for di in dist]
        for i, a in enumerate(self.alive):
            if not a:
                adj[i, :] = 0.0
                adj[:, i] = 0.0
        return Tick(k=k, t=k * self.T, n=self.n, links=neighbour_lists(adj), weights=edge_weights(adj), b=b,
                    delta_max=max_degree(adj), alive=list(self.alive), positions=self.positions.copy())

    def _publish_tick(self) -> None:
        self.last_tick = self.make_tick(self.k)
        self._expected = {i for i in range(self.n) if self.alive[i]}
        self._open = True
        self.publish("world/tick", self.last_tick)

    # ------------------------------------------------------------------ collecting states
    def _on_state(self, key: str, msg: Message) -> None:
        assert isinstance(msg, State)
        if msg.k == self.k and msg.src < self.n:
            self._states[msg.src] = msg
            self._check()
        elif msg.k < self.k:
            self.stats["late_states"] += 1

    def _on_target_state(self, key: str, msg: Message) -> None:
        assert isinstance(msg, State)
        if msg.k == self.k:
            self._target_state = msg
            self._check()

    def _check(self) -> None:
        if self.realtime:
            return  # realtime: the clock closes the tick (on_timer)
        if self._open and self._target_state is not None and all(i in self._states for i in self._expected):
            self._advance()

    def on_deadline(self) -> None:
        if self._open:
            self._advance()

    def _advance(self) -> None:
        self.stats["missing_states"] += len(self._expected - set(self._states))
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
