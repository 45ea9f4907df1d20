"""The target role: publish the truth, move (DESIGN.md "tick protocol", steps 2 and 5).

On tick k the target publishes ``truth`` xₖ. A *normal* target then moves, x⁺ = Ax + Bw (Gu & Hu (1));
an *intelligent* target first waits for the trackers' estimates x̂ₖ of tick k and moves
x⁺ = Axₖ + kₑ(xₖ − x̂ₖ) (Gu & Hu, Section IV), using the mean of the alive nodes' estimates
(``estimate_source = "mean"``) or one node's (``"node:<i>"``). Then it publishes ``state`` (its
position/velocity for tick k+1), which the world needs for range-based visibility.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from ..bus import Bus
from ..ports import Ports
from ..wire import Estimate, FaultEvent, Message, State, Tick, Truth
from .common import Role


class TargetRole(Role):
    name = "target"
    wait_depth = 1
    #: the truth (for the sensors to measure) and its state (for the world); an intelligent target reads the
    #: estimates it evades
    PORTS = Ports(writes=("target/truth", "target/state"), reads=("world/tick", "world/event", "agent/*/estimate"))

    def __init__(self, ticks: int, model, intelligent: bool, pos_dims: int, *, estimate_source: str = "mean",
                 T: float | None = None):
        super().__init__(ticks)
        self.model = model
        self.intelligent = bool(intelligent)
        self.pos_dims = int(pos_dims)
        self.source = estimate_source
        self.k = 0
        self._tick: Tick | None = None
        self._est: dict[int, np.ndarray] = {}
        self._last_xhat: np.ndarray | None = None
        self._waiting = False
        self._dead: set[int] = set()
        self.counters: Counter = Counter()
        self._evade: dict[int, float] = {}  # active "evade" faults: id -> acceleration
        self.T = T

    def on_member(self, role: str, ident: int, alive: bool) -> None:
        if role == "agent":
            (self._dead.discard if alive else self._dead.add)(ident)
            if not alive and self._waiting:
                self._check()

    def subscribe(self, bus: Bus) -> None:
        bus.subscribe("world/tick", self._on_tick)
        bus.subscribe("world/event", self.on_world_event)
        if self.intelligent:
            bus.subscribe("agent/*/estimate", self._on_estimate)

    @property
    def finished(self) -> bool:
        return self.k >= self.ticks

    @property
    def waiting(self) -> bool:
        return self._waiting

    def _on_tick(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Tick)
        if msg.k >= self.ticks:
            self.counters["rejected_ticks"] += 1   # a tick beyond the run (hostile or not our world)
            return
        if msg.k > self.k:
            # ticks we never got (lost while disconnected): the target does not wait for anyone
            if self._waiting:
                self._move_intelligent()
            while self.k < msg.k:
                self._step_unobserved()
        if msg.k != self.k or self._waiting:
            return
        self._tick = msg
        x = self.model.x
        self.publish("target/truth", Truth(k=msg.k, t=msg.t, x=np.array(x, float)))
        if self.intelligent:
            self._waiting = True
            self._check()
        else:
            self.model.step()
            self._moved()

    def step_period(self, k: int) -> float | None:
        t = self._tick
        return t.period if t is not None and t.k == k else None

    def _expected(self) -> list[int]:
        t = self._tick
        if self.source.startswith("node:"):
            return [int(self.source[5:])]
        return [i for i in range(t.n) if t.alive[i] and i not in self._dead]

    def _on_estimate(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Estimate)
        if msg.k == self.k and msg.x.shape == np.shape(self.model.x):
            self._est[msg.src] = msg.x
            if self._waiting:
                self._check()
        # earlier/later ticks: ignore (a late estimate cannot change a past move)

    def _step_unobserved(self) -> None:
        if self.intelligent:
            self.model.step(self._last_xhat if self._last_xhat is not None else np.array(self.model.x, float))
        else:
            self.model.step()
        self.k += 1

    def _check(self) -> None:
        if all(i in self._est for i in self._expected()):
            self._move_intelligent()

    def on_deadline(self) -> None:
        if self._waiting:
            self._move_intelligent()

    def _move_intelligent(self) -> None:
        got = [self._est[i] for i in self._expected() if i in self._est]
        if got:
            xhat = np.mean(got, axis=0)
        elif self._last_xhat is not None:
            xhat = self._last_xhat
        else:
            xhat = np.array(self.model.x, float)  # nobody tracks: no adversarial push
        self._last_xhat = xhat
        self.model.step(xhat)
        self._waiting = False
        self._est.clear()
        self._moved()

    def on_fault(self, ev: FaultEvent) -> None:
        if ev.kind == "evade":          # (|accel| bounded by wire.py)
            if ev.phase == "start":
                self._evade[ev.id] = ev.accel
            else:
                self._evade.pop(ev.id, None)

    def _evasive(self) -> None:
        """Evasive manoeuvre: an extra acceleration ⟂ to the velocity (a hard turn) while active."""
        d = self.pos_dims
        x = self.model.x
        if not self._evade or x.size < 2 * d or d != 2 or self._tick is None:
            return
        T = self.T if self.T is not None else 1.0
        v = x[d:2 * d]
        sp = float(np.linalg.norm(v))
        perp = np.array([-v[1], v[0]]) / sp if sp > 1e-9 else np.array([0.0, 1.0])
        a = sum(self._evade.values()) * perp
        x[:d] += 0.5 * T * T * a
        x[d:2 * d] += T * a

    def _moved(self) -> None:
        self._evasive()
        x = np.asarray(self.model.x, float)
        d = self.pos_dims
        vel = x[d:2 * d] if x.size >= 2 * d else np.zeros(d)
        w = getattr(self.model, "last_w", None)
        self.publish("target/state", State(k=self.k, pos=x[:d].copy(), vel=vel.copy(),
                                           w=None if w is None else np.atleast_1d(np.asarray(w, float))))
        self.k += 1
