"""The sensor role: measure, exchange, estimate, move (DESIGN.md "tick protocol", step 3).

Per tick k, once it holds both the world's ``tick`` k and the target's ``truth`` k, sensor i

1. synthesises yᵢ = bᵢ C x + v with its own seeded noise and publishes ``meas``;
2. runs the estimator's R exchange rounds: publish ``xchg`` (k, r), collect the current neighbours'
   (k, r) payloads until all arrived or the deadline passes (a missing one is a dropped link);
3. updates, publishes ``estimate`` (x̂ₖ used for scoring, x̂ₖ₊₁), applies its controller (flocking:
   Gu & Hu (20) with damping) and publishes ``state`` (position and velocity for tick k+1).

Messages that arrive early (a neighbour already in round r+1, the next tick) are buffered;
messages of a finished round or tick are counted as late and dropped.
"""

from __future__ import annotations

import heapq
import time
from collections import Counter

import numpy as np

from ..bus import Bus
from ..estimators.base import Estimator, TickContext
from ..models import LinearSensor, integrate_double_integrator
from ..seeding import rng_for
from ..wire import Control, Estimate, Meas, Message, State, Tick, Truth, Xchg, int_list, peek
from .common import Role


class SensorRole(Role):
    name = "sensor"

    def __init__(self, i: int, ticks: int, T: float, estimator: Estimator, sensor: LinearSensor,
                 rng: np.random.Generator, q0: np.ndarray, p0: np.ndarray | None = None,
                 controller=None, pos_dims: int = 2, rejoin: bool = False, seed: int = 0):
        super().__init__(ticks)
        self.seed = int(seed)
        self._faults: dict[int, dict] = {}     # active fault-plan events that concern this node
        self._held: list[tuple[int, str, Message]] = []   # delayed payloads (release tick, key, msg)
        self._held_ms: list[tuple[float, int, str, Message]] = []   # heap: (release time, seq, key, msg)
        self._held_seq = 0
        self._clocked = False                  # a process driver calls on_timer; the in-process engine does not
        self._reorder_slot: tuple[str, Message] | None = None
        self._stale: dict[int, dict] = {}      # Byzantine "stale": the payloads replayed, per round
        self._netem_rng = rng_for(seed, "agent", i, "netem")
        self._fault_rng = rng_for(seed, "agent", i, "sensor_faults")
        self.rejoin = bool(rejoin)
        self._joining = False
        self._peer_est: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}
        self.i, self.T = int(i), float(T)
        self.est = estimator
        self.sensor = sensor
        self.rng = rng
        self.q = np.array(q0, float)
        self.p = np.zeros_like(self.q) if p0 is None else np.array(p0, float)
        self.controller = controller
        self.pos_dims = int(pos_dims)
        self.k = 0                      # tick being (or next to be) processed
        self.r = -1                     # current exchange round, -1 = not in a tick
        self._ticks: dict[int, Tick] = {}
        self._truth: dict[int, Truth] = {}
        self._xbuf: dict[tuple[int, int], dict[int, dict]] = {}
        self._withheld: dict[tuple[int, int], set[int]] = {}   # (k, r) → senders whose payload a tick-delay holds
        self._prior: np.ndarray | None = None
        self._nbrs: list[int] = []
        self._dead: set[int] = set()
        self.counters: Counter = Counter()
        self._burst_ticks = 0
        self._burst_mag = 0.0
        self._outlier_rng = rng_for(self.seed, "agent", self.i, "outliers")

    # ------------------------------------------------------------------ wiring
    def subscribe(self, bus: Bus) -> None:
        bus.subscribe("world/tick", self._on_tick)
        bus.subscribe("target/truth", self._on_truth)
        bus.subscribe("agent/*/xchg", self._on_xchg, prefilter=self._wants_xchg)
        if self.rejoin:
            bus.subscribe("agent/*/estimate", self._on_peer_estimate)
        bus.subscribe("control/outlier_burst", self._on_outlier_burst)
        bus.subscribe("world/event", self._on_world_event)

    # ------------------------------------------------------------------ fault plan (topology/faults.py)
    def _on_world_event(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Control)
        a = msg.args
        if msg.verb != "fault" or a.get("kind") not in ("delay", "duplicate", "reorder", "byzantine", "outliers",
                                                         "noise"):
            return
        fid = a.get("id")
        agents_l, links = int_list(a.get("agents", [])), int_list(a.get("links", []))
        if (not isinstance(fid, int) or isinstance(fid, bool) or a.get("phase") not in ("start", "heal")
                or agents_l is None or links is None or len(links) % 2):
            self.counters["rejected_events"] += 1
            return
        if a.get("phase") == "heal":
            self._faults.pop(fid, None)
            self._stale.clear()
            return
        agents = set(agents_l)
        pairs = {frozenset((links[2 * t], links[2 * t + 1])) for t in range(len(links) // 2)}
        bias = a.get("bias")
        if bias is not None and not (isinstance(bias, list) and all(isinstance(b, float) for b in bias)):
            self.counters["rejected_events"] += 1
            return
        for name in ("p", "magnitude", "noise_scale"):
            if name in a and (isinstance(a[name], bool) or not isinstance(a[name], (int, float))):
                self.counters["rejected_events"] += 1
                return
        for name, hi in (("delay_ticks", 1000), ("jitter_ticks", 1000), ("delay_ms", 60_000), ("jitter_ms", 60_000)):
            if name in a and (not isinstance(a[name], (int, float)) or isinstance(a[name], bool)
                              or not 0 <= a[name] <= hi):
                self.counters["rejected_events"] += 1
                return
        if a["kind"] in ("byzantine", "outliers", "noise") and self.i not in agents:
            return
        self._faults[fid] = dict(a, agent_set=agents, pairs=pairs)
        self.counters[f"fault_{a['kind']}"] += 1

    def _link_faults(self, j: int) -> list[dict]:
        """Receiver-side faults (delay, duplicate, reorder) on the link j → self."""
        out = []
        for f in self._faults.values():
            if f["kind"] not in ("delay", "duplicate", "reorder"):
                continue
            if f["pairs"]:
                hit = frozenset((self.i, j)) in f["pairs"]
            else:
                A, d = f["agent_set"], f.get("direction", "both")
                hit = (self.i in A and d in ("both", "in")) or (j in A and d in ("both", "out"))
            if hit:
                out.append(f)
        return out

    def _sender_faults(self, kind: str) -> list[dict]:
        return [f for f in self._faults.values() if f["kind"] == kind]

    def _corrupt(self, r: int, payload: dict) -> dict:
        """Byzantine sender: NaN, huge (×1e6), stale (replayed from the fault's first tick) payloads.
        ("bias" lies about the measurement instead, see _begin.)"""
        for f in self._sender_faults("byzantine"):
            mode = f.get("mode")
            if mode == "nan":
                payload = {k: np.full_like(v, np.nan) for k, v in payload.items()}
            elif mode == "huge":
                payload = {k: v * 1e6 for k, v in payload.items()}
            elif mode == "stale":
                payload = self._stale.setdefault(r, {k: v.copy() for k, v in payload.items()})
            self.counters["byzantine_payloads"] += 1
        return payload

    def _on_outlier_burst(self, key: str, msg: Message) -> None:
        """Impulsive measurement noise (García Carrillo et al.): for the next ``ticks`` ticks add an
        outlier of norm ``magnitude`` in a random direction to this sensor's measurement."""
        assert isinstance(msg, Control)
        who, ticks, mag = msg.args.get("agent", -1), msg.args.get("ticks", 1), msg.args.get("magnitude", 0.0)
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (who, ticks, mag)) \
                or not 0 <= ticks <= 10_000:
            self.counters["rejected_controls"] += 1
            return
        if who in (-1, self.i):
            self._burst_ticks = int(ticks)
            self._burst_mag = float(mag)

    @property
    def finished(self) -> bool:
        return self.k >= self.ticks

    @property
    def waiting(self) -> bool:
        return self.r >= 0

    # ------------------------------------------------------------------ handlers
    def _on_tick(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Tick)
        if msg.positions.shape[1] != self.q.size:
            self.counters["rejected_ticks"] += 1  # not our world: wrong dimension
            return
        if self.rejoin and not self._joining and msg.k > self.k and msg.n > self.i:
            # a restarted process joining a running flock: take up the world's clock and our last
            # known position, and re-initialise the filter from the neighbours' estimates (_begin)
            self.k = msg.k
            self._joining = True
            self.q = np.array(msg.positions[self.i][: self.q.size], float)
            self.p = np.zeros_like(self.q)
            self._forget_past()
        if msg.k >= self.k and msg.n > self.i:
            self._ticks[msg.k] = msg
            if self.r < 0 and msg.k > self.k and not (self.k in self._ticks and self.k in self._truth):
                self._coast_to(msg.k)
            self._try_begin()

    def _coast_to(self, k: int) -> None:
        """The world has moved past ticks we never got (their tick or truth was lost, e.g. while the
        router was down): predict through them with no information (b = 0, no neighbours) and stand
        still, so that we take part again from tick ``k`` on."""
        while self.k < min(k, self.ticks):
            self._predict_blind(self._ticks[k].n)
            self.counters["coasted_ticks"] += 1
        self._forget_past()

    def _predict_blind(self, n: int) -> None:
        """Tick ``self.k`` without information: the estimator's rounds with b = 0 and no neighbours
        (its prediction only), nothing published; the sensor stands still."""
        ctx = TickContext(k=self.k, t=self.k * self.T, n=n, b=0.0, T=self.T)
        self.est.start(ctx, np.zeros(self.sensor.C.shape[0]))
        for r in range(self.est.rounds):
            self.est.absorb(r, {})
        self.est.finish()
        self.k += 1

    def _forget_past(self) -> None:
        """Drop what belongs to ticks before ``self.k``: their tick and truth messages, buffered and
        withheld payloads."""
        for d in (self._ticks, self._truth):
            for kk in [kk for kk in d if kk < self.k]:
                del d[kk]
        for buf in (self._xbuf, self._withheld):
            for kr in [kr for kr in buf if kr[0] < self.k]:
                del buf[kr]

    def _on_truth(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Truth)
        if msg.x.shape != (self.sensor.C.shape[1],):
            self.counters["rejected_truths"] += 1
            return
        if msg.k >= self.k:
            self._truth[msg.k] = msg
            self._try_begin()

    def _on_peer_estimate(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Estimate)
        if msg.src != self.i and (self._joining or self.k == 0) and msg.x_next.shape == self.est.x.shape:
            self._peer_est[msg.src] = (msg.x_next, msg.P)

    def on_member(self, role: str, ident: int, alive: bool) -> None:
        """A neighbour process vanished: stop waiting for its payloads (this tick, and in the ticks the
        world announced before it noticed)."""
        if role == "agent":
            (self._dead.discard if alive else self._dead.add)(ident)
        if role == "agent" and not alive and ident in self._nbrs and self.r >= 0:
            self._nbrs = [j for j in self._nbrs if j != ident]
            self.counters["neighbours_lost"] += 1
            self._check_round()

    def _wants_xchg(self, key: str, data: bytes) -> bool:
        """Cheap pre-decode test mirroring :meth:`_on_xchg`: skip our own, late, and current-tick
        non-neighbour payloads (anything unsure is decoded and judged by the handler)."""
        try:
            j = int(key.split("/")[1])
        except (IndexError, ValueError):
            return True
        if j == self.i:
            return False
        h = peek(data)
        k, r = h.get("k"), h.get("r")
        if k is None or r is None:
            return True
        if k < self.k or (k == self.k and 0 <= self.r and r < self.r):
            self.counters["late_payloads"] += 1
            return False
        if k == self.k and self.r >= 0:
            if j not in self._nbrs:
                self.counters["non_neighbour_payloads"] += 1
                return False
        elif (t := self._ticks.get(k)) is not None and j not in t.links[self.i]:
            # early (a tick we have not begun): the world's link table of that tick already says no
            self.counters["non_neighbour_payloads"] += 1
            return False
        return True

    def _on_xchg(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Xchg)
        if msg.src == self.i:
            return
        if self._faults:
            for f in self._link_faults(msg.src):
                kind = f["kind"]
                if kind == "delay" and self._delay(f, key, msg):
                    return
                if kind == "duplicate" and self._netem_rng.random() < float(f.get("p", 1.0)):
                    self.counters["duplicated_payloads"] += 1
                    self._accept_xchg(key, msg)
                if kind == "reorder" and self._netem_rng.random() < float(f.get("p", 1.0)):
                    prev, self._reorder_slot = self._reorder_slot, (key, msg)
                    self.counters["reordered_payloads"] += 1
                    if prev is not None:
                        self._accept_xchg(*prev)
                    return
        self._accept_xchg(key, msg)
        if self._reorder_slot is not None:  # the held-back one goes after its successor
            prev, self._reorder_slot = self._reorder_slot, None
            self._accept_xchg(*prev)

    def _delay(self, f: dict, key: str, msg: Xchg) -> bool:
        """Hold a payload back (fault plan ``delay``): ``delay_ms`` ± ``jitter_ms`` of wall-clock time, or
        ``delay_ticks`` ± ``jitter_ticks`` ticks (uniform jitter, never below 0). False: not delayed."""
        rng = self._netem_rng
        d_ms, j_ms = float(f.get("delay_ms", 0.0)), float(f.get("jitter_ms", 0.0))
        if d_ms > 0 or j_ms > 0:
            d = max(0.0, d_ms + (rng.uniform(-j_ms, j_ms) if j_ms > 0 else 0.0))
            self._held_seq += 1
            heapq.heappush(self._held_ms, (time.monotonic() + d / 1000.0, self._held_seq, key, msg))
        else:
            jt = int(f.get("jitter_ticks", 0))
            dt = int(f.get("delay_ticks", 1)) + (int(rng.integers(-jt, jt + 1)) if jt > 0 else 0)
            if dt <= 0:
                return False
            self._held.append((msg.k + dt, key, msg))
            # it will certainly miss its round: that round need not wait for it (nor for a deadline)
            self._withheld.setdefault((msg.k, msg.r), set()).add(msg.src)
            if msg.k == self.k and msg.r == self.r:
                self._check_round()
        self.counters["delayed_payloads"] += 1
        return True

    def _release_held_ms(self, now: float | None) -> bool:
        """Let in the payloads held by a delay in ms whose time has come (all of them when ``now`` is None:
        the in-process engine has no wall clock, it delivers them once nothing else is arriving)."""
        n = 0
        while self._held_ms and (now is None or self._held_ms[0][0] <= now):
            _, _, key, msg = heapq.heappop(self._held_ms)
            self._accept_xchg(key, msg)   # late for its round: counted and dropped by the handler
            n += 1
        return n > 0

    def on_timer(self, now: float) -> None:
        self._clocked = True
        if self._held_ms:
            self._release_held_ms(now)

    def _accept_xchg(self, key: str, msg: Xchg) -> None:
        if msg.k < self.k or (msg.k == self.k and 0 <= self.r and msg.r < self.r):
            self.counters["late_payloads"] += 1
            return
        current = msg.k == self.k and self.r >= 0
        if current and msg.src not in self._nbrs:
            self.counters["non_neighbour_payloads"] += 1
            return
        self._xbuf.setdefault((msg.k, msg.r), {})[msg.src] = msg.payload
        if current and msg.r == self.r:
            self._check_round()

    # ------------------------------------------------------------------ the tick
    def _try_begin(self) -> None:
        while self.r < 0 and not self.finished and self.k in self._ticks and self.k in self._truth:
            self._begin()

    def _ctx(self) -> TickContext:
        t = self._ticks[self.k]
        return TickContext(k=t.k, t=t.t, n=t.n, neighbours=tuple(self._nbrs),
                           weights=tuple(t.weights[self.i][t.links[self.i].index(j)] for j in self._nbrs),
                           b=float(t.b[self.i]), delta_max=t.delta_max, T=self.T)

    def _neighbours(self) -> list[int]:
        """This tick's alive neighbours (from the world's link table)."""
        t = self._ticks[self.k]
        return [j for j in t.links[self.i] if t.alive[j] and j not in self._dead]

    def _sensor_faults(self, y: np.ndarray) -> np.ndarray:
        """Sender-side faults on the measurement: noise × scale, impulsive outliers, a Byzantine bias."""
        for f in self._sender_faults("noise"):
            s = float(f.get("noise_scale", 1.0))
            if s > 1:
                y = y + np.sqrt(s * s - 1.0) * (self.sensor._L @ self._fault_rng.standard_normal(y.size))
        for f in self._sender_faults("outliers"):
            if self._fault_rng.random() < float(f.get("p", 1.0)):
                d = self._fault_rng.standard_normal(y.size)
                y = y + float(f.get("magnitude", 50.0)) * d / max(np.linalg.norm(d), 1e-12)
                self.counters["outliers_injected"] += 1
        for f in self._sender_faults("byzantine"):
            if f.get("mode") == "bias":
                bias = f.get("bias") or [float(f.get("magnitude", 50.0))] * y.size
                y = y + np.asarray(bias, float)[: y.size]
        return y

    def _release_held(self) -> None:
        due = [h for h in self._held if h[0] <= self.k]
        if due:
            self._held = [h for h in self._held if h[0] > self.k]
            for _, key, msg in due:
                self._accept_xchg(key, msg)  # arrives late: counted and dropped by the handler

    def _begin(self) -> None:
        tick, truth = self._ticks[self.k], self._truth[self.k]
        if not tick.alive[self.i]:
            # the world's membership is authoritative: a tick that marks us dead (cut off, not yet seen
            # back after a restart) is sat out — predicted only, nothing published
            self._predict_blind(tick.n)
            self.counters["sat_out_ticks"] += 1
            self._forget_past()
            return
        if self._held:
            self._release_held()
        b = float(tick.b[self.i])
        y = self.sensor.measure(truth.x, b, self.rng)
        if self._faults:
            y = self._sensor_faults(y)
        if self._burst_ticks > 0:
            d = self._outlier_rng.standard_normal(y.size)
            y = y + self._burst_mag * d / max(np.linalg.norm(d), 1e-12)
            self._burst_ticks -= 1
            self.counters["outliers_injected"] += 1
        v = getattr(self.sensor, "last_v", None)
        self.publish(f"agent/{self.i}/meas", Meas(src=self.i, k=self.k, t=tick.t, y=y, b=b, pos=self.q.copy(),
                                                  v=None if v is None else np.array(v, float)))
        self._nbrs = self._neighbours()
        if self._joining:
            src = [j for j in self._nbrs if j in self._peer_est] or sorted(self._peer_est)
            if src:
                self.est.reinitialise({j: self._peer_est[j][0] for j in src},
                                      {j: self._peer_est[j][1] for j in src if self._peer_est[j][1] is not None})
                self.counters["reinitialised_from"] = len(src)
            self._joining = False
            self.rejoin = False
        self._prior = self.est.x.copy()
        self.est.start(self._ctx(), y)
        self.r = 0
        self._open_round()

    def _open_round(self) -> None:
        if self.r >= self.est.rounds:
            self._finish()
            return
        payload = self.est.payload(self.r)
        if self._faults:
            payload = self._corrupt(self.r, payload)
        self.publish(f"agent/{self.i}/xchg", Xchg(src=self.i, k=self.k, r=self.r, payload=payload))
        self._check_round()

    def _check_round(self) -> None:
        got = self._xbuf.get((self.k, self.r), {})
        held = self._withheld.get((self.k, self.r), ())
        if all(j in got or j in held for j in self._nbrs):
            self._close_round()

    def on_idle(self) -> bool:
        """Nothing came after a held-back (reordered) payload: let it in now. Without a wall clock (the
        in-process engine), payloads delayed in ms come in now too."""
        if self._reorder_slot is None:
            return bool(self._held_ms) and not self._clocked and self._release_held_ms(None)
        prev, self._reorder_slot = self._reorder_slot, None
        self._accept_xchg(*prev)
        return True

    def _close_round(self) -> None:
        got = self._xbuf.pop((self.k, self.r), {})
        self._withheld.pop((self.k, self.r), None)
        nbrs = self._nbrs
        inbox = {j: got[j] for j in nbrs if j in got}
        self.counters["dropped_links"] += len(nbrs) - len(inbox)
        self.est.absorb(self.r, inbox)
        self.r += 1
        self._open_round()

    def on_deadline(self) -> None:
        if self.r >= 0:
            self.counters["deadline_rounds"] += 1
            self._close_round()

    def _finish(self) -> None:
        k = self.k
        self.est.finish()
        x_next = self.est.x
        P = self.est.P
        eps = getattr(self.est, "last_channel_noise", None) or {}
        self.publish(f"agent/{self.i}/estimate",
                     Estimate(src=self.i, k=k, x=self._prior, x_next=x_next.copy(),
                              P=None if P is None else np.array(P, float), name=type(self.est).__name__,
                              aux={f"eps_{j}": np.asarray(e, float) for j, e in sorted(eps.items())}))
        if self.controller is not None:
            d = self.pos_dims
            tick = self._ticks[k]
            nbr_pos = np.array([tick.positions[j] for j in self._nbrs]).reshape(-1, self.q.size)
            u = self.controller.control(self.q, self.p, x_next[:d], x_next[d:2 * d], nbr_pos)
            self.q, self.p = integrate_double_integrator(self.q, self.p, u, self.T)
        self.publish(f"agent/{self.i}/state", State(src=self.i, k=k, pos=self.q.copy(), vel=self.p.copy()))
        self.r = -1
        self.k = k + 1
        self._forget_past()
        self._try_begin()
