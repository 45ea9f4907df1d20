"""Radio and fault emulation at one sensor (DESIGN.md "Extension points"): pure and seeded.

The sensor-side rows of the fault plan (topology/faults.py, "Who executes what"), and the
``control/outlier_burst`` command:

==========================  ================================================================================
receiver, on link j → i     delay: held ``delay_ticks`` ± ``jitter_ticks`` whole ticks (it arrives late and is
                            dropped), or ``delay_ms`` ± ``jitter_ms`` of wall-clock time like netem's delay
                            (in realtime what misses its round's deadline is lost, in lockstep the round
                            waits); duplicate; reorder (a payload held back until its successor has gone in)
sender, at the targeted i   byzantine payloads: nan, huge (×1e6), stale (replayed from the fault's first
                            tick), noise (each value × (1 + ``magnitude``/100 · N(0, 1))), mimic (a
                            neighbour's last payload with its estimate moved by ``magnitude``/10 in every
                            coordinate); byzantine measurements: bias (``bias``, else ``magnitude`` in every
                            coordinate), drift (a bias growing by ``bias``, else ``magnitude``/1000, a tick
                            from the fault's start); outliers (the impulsive measurement noise of García
                            Carrillo et al.); noise (measurement noise covariance × scale²)
==========================  ================================================================================

Every draw comes from the sensor's own generators — ``netem`` (receiver side), ``sensor_faults`` (noise,
outliers), ``outliers`` (bursts) — in a fixed order, so a run gives the same numbers on any bus. The module
knows no bus, codec, clock or file: payloads go in through :meth:`LinkEmulator.admit` and come out through
the ``deliver`` callback; wall-clock time comes from the ``clock`` the role hands in.
"""

from __future__ import annotations

import heapq
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .seeding import rng_for

if TYPE_CHECKING:
    from .wire import FaultEvent, OutlierBurst

LINK_KINDS = frozenset({"delay", "duplicate", "reorder"})       #: on the links, whoever the fault names
SENDER_KINDS = frozenset({"byzantine", "outliers", "noise"})    #: only at the agents the fault names
KINDS = LINK_KINDS | SENDER_KINDS                               #: the fault kinds emulated here

Deliver = Callable[[str, Any], None]


def noise_factor(sensor: Any) -> np.ndarray | None:
    """F with F Fᵀ = the covariance of the sensor's measurement noise v, drawn as F·N(0, I): the Cholesky
    factor of R (agent.models.LinearSensor), or v_std·D (DisturbedSensor); None if the model has neither."""
    if getattr(sensor, "R", None) is not None:
        return np.linalg.cholesky(sensor.R)
    if getattr(sensor, "D", None) is not None:
        return float(getattr(sensor, "v_std", 1.0)) * sensor.D
    return None


@dataclass(frozen=True)
class _Active:
    ev: FaultEvent
    agents: frozenset[int]
    pairs: frozenset[frozenset[int]]

    def on_link(self, i: int, j: int) -> bool:
        """Does this receiver-side fault act on the link j → i?"""
        if self.pairs:
            return frozenset((i, j)) in self.pairs
        d = self.ev.direction
        return (i in self.agents and d in ("both", "in")) or (j in self.agents and d in ("both", "out"))


class LinkEmulator:
    """The faults active at sensor ``i``, applied to what it hears (:meth:`admit`, :meth:`release`,
    :meth:`on_timer`, :meth:`on_idle`) and to what it sends (:meth:`corrupt`, :meth:`perturb`).

    ``deliver(key, msg)`` receives every payload that goes through, in order; ``clock()`` is the wall clock
    (seconds) of delays in ms; ``counters`` (shared with the role, if given) counts what was done."""

    def __init__(self, i: int, seed: int, deliver: Deliver, clock: Callable[[], float],
                 noise: np.ndarray | None = None, *, counters: Counter | None = None):
        self.i = int(i)
        self.deliver, self.clock, self.noise = deliver, clock, noise
        self.counters: Counter = Counter() if counters is None else counters
        self.faults: dict[int, _Active] = {}       # active fault-plan events that concern this sensor
        self._netem = rng_for(seed, "agent", i, "netem")
        self._fault_rng = rng_for(seed, "agent", i, "sensor_faults")
        self._burst_rng = rng_for(seed, "agent", i, "outliers")
        self._held: list[tuple[int, str, Any]] = []                 # delayed in ticks: (release tick, key, msg)
        self._withheld: dict[tuple[int, int], set[int]] = {}        # (k, r) → senders of payloads _held
        self._held_ms: list[tuple[float, int, str, Any]] = []       # heap: (release time, seq, key, msg)
        self._seq = 0
        self._clocked = False                       # a process driver calls on_timer; the in-process engine not
        self._slot: tuple[str, Any] | None = None   # the payload a reorder holds back
        self._stale: dict[int, dict] = {}           # Byzantine "stale": the payloads replayed, per round
        self._heard: dict[str, np.ndarray] | None = None   # Byzantine "mimic": the last payload heard
        self._k = 0                                 # the tick under way (release)
        self._began: dict[int, int] = {}            # fault id → the tick it began at this sensor
        self._burst_ticks, self._burst_mag = 0, 0.0

    # ------------------------------------------------------------------ the fault plan
    def apply(self, ev: FaultEvent) -> None:
        """A start or heal on ``world/event``. Kinds not emulated here are ignored, and so are sender-side
        faults of other agents; a heal forgets the stale payloads (they are taken again if still due)."""
        if ev.kind not in KINDS:
            return
        if ev.phase == "heal":
            self.faults.pop(ev.id, None)
            self._began.pop(ev.id, None)
            self._stale.clear()
            return
        if ev.kind in SENDER_KINDS and self.i not in ev.agents:
            return
        self.faults[ev.id] = _Active(ev, frozenset(ev.agents), frozenset(frozenset(ab) for ab in ev.links))
        self._began[ev.id] = self._k
        self.counters[f"fault_{ev.kind}"] += 1

    def burst(self, cmd: OutlierBurst) -> None:
        """control/outlier_burst: an outlier of norm ``magnitude`` on each of this sensor's next ``ticks``
        measurements (``agent`` −1: every sensor)."""
        if cmd.agent in (-1, self.i):
            self._burst_ticks, self._burst_mag = cmd.ticks, cmd.magnitude

    def _sending(self, kind: str) -> list[FaultEvent]:
        return [f.ev for f in self.faults.values() if f.ev.kind == kind]

    # ------------------------------------------------------------------ receiver side
    def admit(self, key: str, msg: Any) -> bool:
        """A payload (``msg.src``, ``msg.k`` …) heard on the link msg.src → i. Every copy that goes in now —
        a duplicate, a reordered predecessor, the payload itself — is handed to ``deliver``, in order.
        True: the payload is held for whole ticks, so its round need not wait for it."""
        if not self.faults and self._slot is None:     # (no fault active: every payload, so kept short)
            self.deliver(key, msg)
            return False
        if self.faults and getattr(msg, "payload", None):
            self._heard = msg.payload     # (what a mimicking Byzantine sender replays)
        for f in [f for f in self.faults.values() if f.ev.kind in LINK_KINDS and f.on_link(self.i, msg.src)]:
            ev = f.ev
            if ev.kind == "delay":
                held = self._hold(ev, key, msg)
                if held is not None:
                    self.counters["delayed_payloads"] += 1
                    return held
            elif ev.kind == "duplicate" and self._netem.random() < ev.p:
                self.counters["duplicated_payloads"] += 1
                self.deliver(key, msg)
            elif ev.kind == "reorder" and self._netem.random() < ev.p:
                prev, self._slot = self._slot, (key, msg)
                self.counters["reordered_payloads"] += 1
                if prev is not None:
                    self.deliver(*prev)
                return False
        self.deliver(key, msg)
        if self._slot is not None:   # the held-back one goes after its successor
            prev, self._slot = self._slot, None
            self.deliver(*prev)
        return False

    def _hold(self, ev: FaultEvent, key: str, msg: Any) -> bool | None:
        """Hold a payload back: ``delay_ms`` ± ``jitter_ms`` (False), or ``delay_ticks`` ± ``jitter_ticks``
        ticks (True); uniform jitter, never below 0. None: a jitter brought it to 0 ticks, not delayed."""
        if ev.delay_ms > 0 or ev.jitter_ms > 0:
            j = ev.jitter_ms
            d = max(0.0, ev.delay_ms + (self._netem.uniform(-j, j) if j > 0 else 0.0))
            self._seq += 1
            heapq.heappush(self._held_ms, (self.clock() + d / 1000.0, self._seq, key, msg))
            return False
        jt = ev.jitter_ticks
        dt = ev.delay_ticks + (int(self._netem.integers(-jt, jt + 1)) if jt > 0 else 0)
        if dt <= 0:
            return None
        self._held.append((msg.k + dt, key, msg))
        self._withheld.setdefault((msg.k, msg.r), set()).add(msg.src)
        return True

    def withheld(self, k: int, r: int) -> set[int] | tuple[()]:
        """The senders whose payloads of round (k, r) are held for whole ticks (they will miss it)."""
        return self._withheld.get((k, r), ())

    def release(self, k: int) -> None:
        """Tick ``k`` begins: deliver the payloads held for whole ticks whose time has come (late ones)."""
        self._k = k
        for kr in [kr for kr in self._withheld if kr[0] < k]:
            del self._withheld[kr]
        due = [h for h in self._held if h[0] <= k]
        if due:
            self._held = [h for h in self._held if h[0] > k]
            for _, key, msg in due:
                self.deliver(key, msg)

    def _release_ms(self, now: float | None) -> bool:
        """Deliver the payloads delayed in ms whose time has come (all of them when ``now`` is None)."""
        n = 0
        while self._held_ms and (now is None or self._held_ms[0][0] <= now):
            _, _, key, msg = heapq.heappop(self._held_ms)
            self.deliver(key, msg)
            n += 1
        return n > 0

    def on_timer(self, now: float) -> None:
        """A process driver's wall clock: payloads delayed in ms go in when their time comes."""
        self._clocked = True
        if self._held_ms:
            self._release_ms(now)

    def next_release(self) -> float | None:
        """When the next payload delayed in ms is due (None: none held)."""
        return self._held_ms[0][0] if self._held_ms else None

    def on_idle(self) -> bool:
        """Nothing else is arriving: a payload held back by a reorder goes in now; without a wall clock (the
        in-process engine) so do the payloads delayed in ms. True if something was delivered."""
        if self._slot is None:
            return bool(self._held_ms) and not self._clocked and self._release_ms(None)
        prev, self._slot = self._slot, None
        self.deliver(*prev)
        return True

    # ------------------------------------------------------------------ sender side
    def corrupt(self, r: int, payload: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The exchange payload of round ``r`` as a Byzantine sender sends it: NaN, huge (×1e6), or stale
        (what it sent in round r when the fault began). ("bias" lies about the measurement: :meth:`perturb`.)"""
        for ev in self._sending("byzantine"):
            if ev.mode == "nan":
                payload = {k: np.full_like(v, np.nan) for k, v in payload.items()}
            elif ev.mode == "huge":
                payload = {k: v * 1e6 for k, v in payload.items()}
            elif ev.mode == "stale":
                payload = self._stale.setdefault(r, {k: v.copy() for k, v in payload.items()})
            elif ev.mode == "noise":
                s = ev.magnitude / 100.0
                payload = {k: v * (1.0 + s * self._fault_rng.standard_normal(v.shape)) for k, v in payload.items()}
            elif ev.mode == "mimic" and self._heard is not None and self._heard.keys() == payload.keys():
                payload = mimic(self._heard, ev.magnitude / 10.0)
            self.counters["byzantine_payloads"] += 1
        return payload

    def perturb(self, y: np.ndarray) -> np.ndarray:
        """The measurement with this sensor's faults: noise × scale, impulsive outliers, a Byzantine bias,
        then an outlier burst's outlier."""
        if self.faults:
            y = self._measurement_faults(y)
        if self._burst_ticks > 0:
            y = y + self._outlier(self._burst_rng, y.size, self._burst_mag)
            self._burst_ticks -= 1
        return y

    def _measurement_faults(self, y: np.ndarray) -> np.ndarray:
        rng = self._fault_rng
        for ev in self._sending("noise"):
            s = ev.noise_scale
            if s > 1:   # v + √(s²−1)·F·N(0, I) has covariance s²·cov(v)
                F = np.eye(y.size) if self.noise is None else self.noise
                y = y + np.sqrt(s * s - 1.0) * (F @ rng.standard_normal(F.shape[1]))
        for ev in self._sending("outliers"):
            if rng.random() < ev.p:
                y = y + self._outlier(rng, y.size, ev.magnitude)
        for ev in self._sending("byzantine"):
            if ev.mode == "bias":
                bias = ev.bias or [ev.magnitude] * y.size
                y = y + np.asarray(bias, float)[: y.size]
            elif ev.mode == "drift":
                rate = np.asarray(ev.bias or [ev.magnitude / 1000.0] * y.size, float)[: y.size]
                y = y + rate * (self._k - self._began.get(ev.id, self._k))
        return y

    def _outlier(self, rng: np.random.Generator, size: int, magnitude: float) -> np.ndarray:
        """An outlier of norm ``magnitude`` in a uniformly random direction (counted)."""
        d = rng.standard_normal(size)
        self.counters["outliers_injected"] += 1
        return magnitude * d / max(np.linalg.norm(d), 1e-12)


def mimic(heard: dict[str, np.ndarray], offset: float) -> dict[str, np.ndarray]:
    """A neighbour's payload passed off as one's own, its estimate moved by ``offset`` in every coordinate:
    for an information payload (χ¹, χ², χ³) χ² ← χ² + χ¹ δ moves the estimate it implies by δ; other payloads
    are shifted as they are."""
    out = {k: v.copy() for k, v in heard.items()}
    if "chi1" in out and "chi2" in out:
        out["chi2"] = out["chi2"] + out["chi1"] @ np.full(out["chi2"].shape, offset)
    else:
        out = {k: v + offset for k, v in out.items()}
    return out
