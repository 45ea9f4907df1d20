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
from agent.wire import Message, State, Tick

from .graph import PeriodicSchedule, edge_weights, max_degree, neighbour_lists, range_adjacency


class WorldRole(Role):
    name = "world"

    def __init__(self, n: int, ticks: int, T: float, positions0: np.ndarray, target_pos0: np.ndarray,
                 schedule: PeriodicSchedule | None = None, radius: float = np.inf,
                 sensing_range: float = np.inf, beta: float = 1.0):
        super().__init__(ticks)
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
        self._open = True
        self.publish("world/tick", self.last_tick)

    # ------------------------------------------------------------------ collecting states
    def _on_state(self, key: str, msg: Message) -> None:
        assert isinstance(msg, State)
        if msg.k == self.k and msg.src < self.n:
            self._states[msg.src] = msg
            self._check()

    def _on_target_state(self, key: str, msg: Message) -> None:
        assert isinstance(msg, State)
        if msg.k == self.k:
            self._target_state = msg
            self._check()

    def _check(self) -> None:
        if self._open and self._target_state is not None and all(
                i in self._states for i in range(self.n) if self.alive[i]):
            self._advance()

    def on_deadline(self) -> None:
        if self._open:
            self._advance()

    def _advance(self) -> None:
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
