"""The sensor role: measure, exchange, estimate, move (DESIGN.md "tick protocol", step 3).

Per tick k, once it holds both the world's ``tick`` k and the target's ``truth`` k, sensor i

1. synthesises yᵢ = bᵢ C x + v with its own seeded noise and publishes ``meas``;
2. runs the estimator's R exchange rounds: address ``xchg`` (k, r) to each sensor that hears it by the
   tick's link table (``agent/i/to/j/xchg``), collect the current neighbours' (k, r) payloads from its own
   inbox until all arrived or the deadline passes (a missing one is a dropped link); the observers get the
   tick's payloads once, every round in one message on ``agent/i/xchg``;
3. updates, publishes ``estimate`` (x̂ₖ used for scoring, x̂ₖ₊₁), applies its controller (flocking:
   Gu & Hu (20) with damping) and publishes ``state`` (position and velocity for tick k+1).

Messages that arrive early (a neighbour already in round r+1, the next tick) are buffered; messages of
a finished round or tick are counted as late and dropped. What the radio and the fault plan do to the
payloads and the measurement is emulated by :class:`agent.link_emulation.LinkEmulator`.

A restarted sensor (``rejoin``) takes up the world's clock at the first tick it sees and starts its filter
from its neighbours' estimates, not from its prior x̂₀ (:mod:`agent.roles.rejoin`).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from ..bus import Bus
from ..estimators.base import Estimator, TickContext
from ..link_emulation import LinkEmulator, noise_factor
from ..models import LinearSensor, integrate_double_integrator
from ..ports import Ports
from ..wire import (Control, Estimate, FaultEvent, Meas, Message, State, Tick, Truth, UnusableXchg, WireError,
                    Xchg, command, estimate_inbox, estimate_key)
from .common import Role
from .rejoin import Rejoin
from .rounds import RoundInbox
from .routes import ExchangeRoutes
from .tick_timing import TickTiming

log = logging.getLogger(__name__)


class SensorRole(Role):
    name = "sensor"
    #: its measurement, estimate, state and exchange payloads (one for observers, one per neighbour that
    #: hears it, and its last estimate handed to a rejoining peer); the tick, the truth, the fault events,
    #: its own inbox and a rejoin's handovers
    PORTS = Ports(writes=("agent/{i}/meas", "agent/{i}/estimate", "agent/{i}/state", "agent/{i}/xchg",
                          "agent/{i}/to/*/xchg", "agent/{i}/to/*/estimate"),
                  reads=("world/tick", "target/truth", "agent/*/to/{i}/xchg", "agent/*/to/{i}/estimate",
                         "control/outlier_burst", "world/event"))
    #: a run placed on several hosts adds: one copy of a payload per other host with hearers, and the
    #: copies sent to its own host (``{host}``; agent/roles/routes.py)
    HOST_PORTS = Ports(writes=("agent/{i}/via/*/xchg",), reads=("agent/*/via/{host}/xchg",))

    def __init__(self, i: int, ticks: int, T: float, estimator: Estimator, sensor: LinearSensor, *,
                 rng: np.random.Generator, q0: np.ndarray, p0: np.ndarray | None = None,
                 controller=None, pos_dims: int = 2, rejoin: bool = False, seed: int = 0,
                 catch_up: bool = False):
        super().__init__(ticks)
        self.catch_up = bool(catch_up)   # realtime: a sensor behind the world skips to its newest tick
        self.i, self.T, self.seed, self.pos_dims = int(i), float(T), int(seed), int(pos_dims)
        self.est, self.sensor, self.rng, self.controller = estimator, sensor, rng, controller
        self.q = np.array(q0, float)
        self.p = np.zeros_like(self.q) if p0 is None else np.array(p0, float)
        self.k, self.r = 0, -1          # tick being (or next to be) processed; exchange round (-1: not in a tick)
        self._ticks: dict[int, Tick] = {}
        self._tick_arrived: dict[int, float] = {}   # when each tick reached us (step_anchor)
        self._truth: dict[int, Truth] = {}
        self._prior: np.ndarray | None = None
        self._nbrs: list[int] = []
        self.routes = ExchangeRoutes(self.i)   # this tick's exchange keys (agent/roles/routes.py)
        self._dead: set[int] = set()
        self._sat_out_last = -2   # the last tick sat out (a log line when a stretch begins)
        self.inbox = RoundInbox(self.counters)               # exchange payloads by (tick, round)
        self.join = Rejoin(self.i, rejoin, self.counters)   # a restart's way back, and the handover to others
        self.link = LinkEmulator(self.i, self.seed, self._accept_xchg, time.monotonic, noise_factor(sensor),
                                 counters=self.counters)
        self.timing = TickTiming(stagger=self.i)     # where each tick's time went (the runner points it at stats/)

    def subscribe(self, bus: Bus) -> None:
        bus.subscribe("world/tick", self._on_tick)
        bus.subscribe("target/truth", self._on_truth)
        for key in self.routes.inboxes():       # (most of what a sensor receives: kept in Zenoh till polled)
            bus.subscribe(key, self._on_xchg, bulk=True)
        if self.join.restarted:
            bus.subscribe(estimate_inbox(self.i), self._on_peer_estimate)
        bus.subscribe("control/outlier_burst", self._on_outlier_burst)
        bus.subscribe("world/event", self.on_world_event)

    def place(self, hosts: list[str]) -> None:
        """A run placed on several hosts: every sensor's host (before :meth:`subscribe`)."""
        self.routes = ExchangeRoutes(self.i, hosts)

    def ports(self) -> Ports:
        host = self.routes.host
        return super().ports() if host is None else super().ports() + self.HOST_PORTS.of(self.i).on_host(host)

    @property
    def finished(self) -> bool:
        return self.k >= self.ticks

    @property
    def waiting(self) -> bool:
        return self.r >= 0 or self.join.pending

    # ------------------------------------------------------------------ the world: ticks, truth, membership
    def _on_tick(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Tick)
        if msg.positions.shape[1] != self.q.size or msg.k >= self.ticks:
            self.counters["rejected_ticks"] += 1  # not our world: wrong dimension, or a tick beyond the run
            return
        if self.join.takes_up(msg, self.k):
            # a restarted process joining a running flock: take up the world's clock and our last
            # known position, and re-initialise the filter from the neighbours' estimates (_begin)
            self.k = msg.k
            log.info("agent/%d: rejoining the flock at tick %d", self.i, msg.k)
            self.q = np.array(msg.positions[self.i][: self.q.size], float)
            self.p = np.zeros_like(self.q)
            self._forget_past()
        if msg.k >= self.k and msg.n > self.i:
            self._ticks[msg.k] = msg
            self._tick_arrived.setdefault(msg.k, time.monotonic())
            if self.r < 0 and msg.k > self.k and not (self.k in self._ticks and self.k in self._truth):
                # the world has moved past ticks we never got (their tick or truth was lost, e.g. while the
                # router was down): coast through them, so that we take part again from tick msg.k on
                while self.k < min(msg.k, self.ticks):
                    self._predict_blind(msg.n)
                    self.counters["coasted_ticks"] += 1
            self._try_begin()

    def step_anchor(self, k: int) -> float | None:
        """The moment tick k's world tick reached us: its rounds end within a window from it, not from when
        we could begin it (its truth come, the previous tick done) — a sensor that begins late, descheduled
        or still waiting out the last tick, gets what is left of the tick, so one late tick does not make the
        next one late too (agent/runner.py WaitBudget.window_s, agent/__main__.py role_budget)."""
        return self._tick_arrived.get(k)

    def step_period(self, k: int) -> float | None:
        tick = self._ticks.get(k)
        return None if tick is None else tick.period

    def _on_truth(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Truth)
        if msg.x.shape != (self.sensor.C.shape[1],):
            self.counters["rejected_truths"] += 1
        elif msg.k >= self.k:
            self._truth[msg.k] = msg
            self._try_begin()

    def on_member(self, role: str, ident: int, alive: bool) -> None:
        """A neighbour process vanished: stop waiting for its payloads (this tick, and in the ticks the
        world announced before it noticed)."""
        if role != "agent":
            return
        (self._dead.discard if alive else self._dead.add)(ident)
        handed = self.join.handover(ident, alive)   # (re)appeared: it may be rejoining from our estimate
        if handed is not None:
            self.publish(estimate_key(self.i, ident), handed)
        if not alive and ident in self._nbrs and self.r >= 0:
            self._nbrs = [j for j in self._nbrs if j != ident]
            self.counters["neighbours_lost"] += 1
            self._check_round()

    def _on_peer_estimate(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Estimate)
        if self.join.offer(msg, self.k, self.est.x.shape):
            self._try_begin()

    # ------------------------------------------------------------------ faults and controls, typed by wire.py
    def on_fault(self, ev: FaultEvent) -> None:
        self.link.apply(ev)

    def _on_outlier_burst(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Control)
        try:
            self.link.burst(command("outlier_burst", msg.args))
        except WireError:
            self.counters["rejected_controls"] += 1

    def on_timer(self, now: float) -> None:
        self.link.on_timer(now)

    def next_timer(self) -> float | None:
        return self.link.next_release()

    def on_idle(self) -> bool:
        return self.link.on_idle()

    # ------------------------------------------------------------------ exchange payloads
    def _on_xchg(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Xchg)
        if not self.routes.for_me(msg):
            self.counters["other_hearers_payloads"] += 1   # (its host's copy, for other sensors there)
            return
        # held for whole ticks, a payload of this round will miss it: the round need not wait for it
        if msg.src != self.i and self.link.admit(key, msg) and msg.k == self.k and msg.r == self.r:
            self._check_round()

    def _accept_xchg(self, key: str, msg: Xchg) -> None:
        """A payload through the link emulator: buffered for its round unless late or not a neighbour's."""
        if not self.inbox.refused(msg.src, msg.k, msg.r, (self.k, self.r), self._nbrs):
            # (an unusable payload — NaN, a bad shape — has come and is of no use: a lost link, no wait)
            self.inbox.put(msg.src, msg.k, msg.r, None if isinstance(msg, UnusableXchg) else msg.payload)
            if msg.k == self.k and msg.r == self.r:
                self._check_round()

    # ------------------------------------------------------------------ the tick: measure → rounds → finish
    def _try_begin(self) -> None:
        while self.r < 0 and not self.finished and self.k in self._ticks and self.k in self._truth:
            if self.catch_up:
                self._skip_stale()
            tick = self._ticks[self.k]
            if self.join.awaiting(tick, self._live_neighbours(tick), self.k):
                return      # rejoining: the neighbours' estimates first (bounded by on_deadline)
            self._begin()

    def _live_neighbours(self, tick: Tick) -> list[int]:
        """The sensors we hear this tick that the world lists alive and we have not seen vanish since."""
        return [j for j in tick.links[self.i] if tick.alive[j] and j not in self._dead]

    def _skip_stale(self) -> None:
        """Realtime: ticks the world has already moved past are coasted through (predicted only, nothing
        published), and the newest tick whose truth is here is taken up. A starved sensor would otherwise
        work through stale ticks whose round slots and state deadline are long gone — every payload late,
        every state dropped by the world — and never catch up; this way it loses the ticks it cannot make,
        not all of them. (Lockstep never gets here: the world announces k+1 only after our state k.)"""
        newest = max(kk for kk in self._ticks if kk in self._truth)
        n = self._ticks[newest].n
        while self.k < newest:
            self._predict_blind(n)
            self.counters["skipped_ticks"] += 1

    def _begin(self) -> None:
        tick, truth = self._ticks[self.k], self._truth[self.k]
        if not tick.alive[self.i]:
            # the world's membership is authoritative: a tick that marks us dead (cut off, not yet seen
            # back after a restart) is sat out — predicted only, nothing published
            if self._sat_out_last != self.k - 1:
                log.info("agent/%d: tick %d marks me dead: sitting out", self.i, self.k)
            self._sat_out_last = self.k
            self._predict_blind(tick.n)
            self.counters["sat_out_ticks"] += 1
            return
        self.timing.begin(self.k, self._tick_arrived.get(self.k))
        self.link.release(self.k)
        b = float(tick.b[self.i])
        y = self._measure(tick, truth, b)
        links = tick.links[self.i]
        self._nbrs = self._live_neighbours(tick)
        self.routes.route(tick.links)   # range-based link dropping at the transport: only our hearers
        if self.join.joining:
            self.join.start_from(self.est, self._nbrs, self.k)
            log.info("agent/%d: back in the flock at tick %d", self.i, self.k)
        self._prior = self.est.x.copy()
        with self.timing.spent("compute"):
            self.est.start(TickContext(k=tick.k, t=tick.t, n=tick.n, neighbours=tuple(self._nbrs), b=b, T=self.T,
                                       weights=tuple(tick.weights[self.i][links.index(j)] for j in self._nbrs),
                                       delta_max=tick.delta_max), y)
        self.r = 0
        self._open_round()

    def _measure(self, tick: Tick, truth: Truth, b: float) -> np.ndarray:
        """Step 1: yᵢ from the truth with this sensor's noise (and the link emulator's faults), published as
        ``meas``; returned for the estimator."""
        with self.timing.spent("compute"):
            y = self.link.perturb(self.sensor.measure(truth.x, b, self.rng))
        v = getattr(self.sensor, "last_v", None)
        with self.timing.spent("publish"):
            self.publish(f"agent/{self.i}/meas", Meas(src=self.i, k=self.k, t=tick.t, y=y, b=b, pos=self.q.copy(),
                                                      v=None if v is None else np.array(v, float)))
        return y

    def _open_round(self) -> None:
        if self.r >= self.est.rounds:
            self._finish()
            return
        with self.timing.spent("compute"):
            payload = self.link.corrupt(self.r, self.est.payload(self.r))
        with self.timing.spent("publish"):
            self.routes.send(self, Xchg(src=self.i, k=self.k, r=self.r, payload=payload))
        self._check_round()

    def _check_round(self) -> None:
        if self.inbox.complete(self.k, self.r, self._nbrs, self.link.withheld(self.k, self.r)):
            self._close_round()

    def _close_round(self, by_deadline: bool = False) -> None:
        with self.timing.spent("compute"):
            self.est.absorb(self.r, self.inbox.take(self.k, self.r, self._nbrs))
        self.timing.round_closed(by_deadline)
        self.r += 1
        self._open_round()

    def waiting_for(self) -> str:
        if self.r < 0:
            return " — the neighbours' estimates (rejoining)" if self.join.pending else ""
        late = self.inbox.missing(self.k, self.r, self._nbrs, self.link.withheld(self.k, self.r))
        return " — no payload from " + ", ".join(f"agent/{j}" for j in late) if late else ""

    def on_deadline(self) -> None:
        if self.join.give_up_waiting():
            self._try_begin()
        elif self.r >= 0:
            self.counters["deadline_rounds"] += 1
            self._close_round(by_deadline=True)

    def _finish(self) -> None:
        with self.timing.spent("compute"):
            self.est.finish()
        x_next, P = self.est.x, self.est.P
        eps = getattr(self.est, "last_channel_noise", None) or {}
        aux = {f"eps_{j}": np.asarray(e, float) for j, e in sorted(eps.items())}
        aux.update(self.est.report())
        self.join.last = Estimate(src=self.i, k=self.k, x=self._prior, x_next=x_next.copy(),
                                  P=None if P is None else np.array(P, float), name=type(self.est).__name__, aux=aux)
        with self.timing.spent("publish"):
            self.routes.send_observed(self, self.k)
            self.publish(f"agent/{self.i}/estimate", self.join.last)
        if self.controller is not None:
            with self.timing.spent("compute"):
                d, tick = self.pos_dims, self._ticks[self.k]
                nbr_pos = np.array([tick.positions[j] for j in self._nbrs]).reshape(-1, self.q.size)
                u = self.controller.control(self.q, self.p, x_next[:d], x_next[d:2 * d], nbr_pos)
                self.q, self.p = integrate_double_integrator(self.q, self.p, u, self.T)
        with self.timing.spent("publish"):
            self.publish(f"agent/{self.i}/state", State(src=self.i, k=self.k, pos=self.q.copy(), vel=self.p.copy()))
        self.timing.end()
        self.r = -1
        self._next_tick()
        self._try_begin()

    # ------------------------------------------------------------------ ticks without information
    def _predict_blind(self, n: int) -> None:
        """Tick ``self.k`` without information (its tick or truth lost, or the world marks us dead): the
        estimator's rounds with b = 0 and no neighbours — its prediction only; nothing published, the
        sensor stands still."""
        self.est.predict_only(TickContext(k=self.k, t=self.k * self.T, n=n, b=0.0, T=self.T), self.sensor.C.shape[0])
        self._next_tick()

    def _next_tick(self) -> None:
        self.k += 1
        self._forget_past()

    def _forget_past(self) -> None:
        """Drop what belongs to ticks before ``self.k``: tick and truth messages, buffered payloads."""
        self._ticks = {kk: m for kk, m in self._ticks.items() if kk >= self.k}
        self._tick_arrived = {kk: t for kk, t in self._tick_arrived.items() if kk >= self.k}
        self._truth = {kk: m for kk, m in self._truth.items() if kk >= self.k}
        self.inbox.forget_before(self.k)
