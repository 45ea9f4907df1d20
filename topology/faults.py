"""The fault plan: a seeded schedule of faults with explicit heal (a Jepsen-style nemesis), executed
per agent pair and per Zenoh key by the roles that own each effect.

A scenario's ``[faults]`` table lists events ``{kind, start, heal, targets, …}`` (ticks). At each tick the
world (the clock) starts and heals them and publishes every transition on ``world/event`` — a
``Control`` with verb ``"fault"`` and args ``{id, kind, phase: "start"|"heal", agents: [...],
links: [a, b, a, b, ...], groups: [...], …parameters}`` — before that tick's ``tick`` message, so the
faults sit on the same timeline as the metrics and every role applies them at the same tick.

Who executes what:

=================  ===========================================================================
world              link_loss (per direction, probability p per tick), partition, blind (bᵢ = 0)
sensor (receiver)  delay: held ``delay_ticks`` (± ``jitter_ticks``) ticks — arrives late → dropped and
                   counted — or ``delay_ms`` (± ``jitter_ms``) of wall-clock time: in realtime what
                   misses its round's deadline is lost, in lockstep the round waits for it,
                   duplicate and reorder of exchange payloads (the protocol must be immune)
sensor (sender)    byzantine (nan | huge | stale | noise | mimic payloads, bias | drift measurements;
                   agent/link_emulation.py), outliers (impulsive noise of
                   paper 004), noise (measurement noise × noise_scale)
target             evade (an extra acceleration ⟂ to its velocity)
launcher           crash (SIGKILL; restart at heal), pause (SIGSTOP / SIGCONT), router_restart
=================  ===========================================================================

Target selectors: ``all``, ``agents:1,2``, ``links:0-1,2-3``, ``random:k`` (k agents drawn from the plan's
seeded generator at start), ``most_connected`` (highest degree in the graph at start), ``halves``
(a seeded random split into two groups), ``groups:0,0,1,…`` (a group id per sensor).

Live faults: ``control/inject`` (args = the keys of one event, ``ticks`` = its duration, none = until
healed) adds an event to the plan from the next tick, with id ``LIVE_ID0 + j``; ``control/heal`` heals
every live fault (and the world's link faults) at the next tick, ``control/heal_fault {id}`` heals one.
Both then go through the same start/heal transitions on ``world/event`` as the scenario's own events.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from agent.scenario import FaultEventCfg, FaultsCfg
from agent.seeding import rng_for

WORLD_KINDS = {"link_loss", "partition", "blind"}
LIVE_ID0 = 1000   #: ids of live-injected faults start here (the scenario's events are 0, 1, …)


@dataclass
class ActiveFault:
    id: int
    cfg: FaultEventCfg
    agents: list[int] = field(default_factory=list)
    links: list[tuple[int, int]] = field(default_factory=list)
    groups: list[int] | None = None

    def event_args(self, phase: str) -> dict[str, Any]:
        c = self.cfg
        a: dict[str, Any] = {"id": self.id, "kind": c.kind, "phase": phase, "agents": [float(x) for x in self.agents],
                             "links": [float(v) for e in self.links for v in e], "p": c.p,
                             "direction": c.direction, "delay_ticks": c.delay_ticks, "mode": c.mode,
                             "jitter_ticks": c.jitter_ticks, "delay_ms": c.delay_ms, "jitter_ms": c.jitter_ms,
                             "magnitude": c.magnitude, "noise_scale": c.noise_scale, "accel": c.accel}
        if self.groups is not None:
            a["groups"] = [float(g) for g in self.groups]
        if c.bias is not None:
            a["bias"] = [float(b) for b in c.bias]
        return a


class FaultPlan:
    """Which faults start and heal at each tick, with targets resolved deterministically."""

    def __init__(self, cfg: FaultsCfg, n: int, seed: int):
        self.cfg, self.n = cfg, int(n)
        self.rng = rng_for(cfg.seed if cfg.seed is not None else seed, "faults", 0, "targets")
        self.loss_rng = rng_for(cfg.seed if cfg.seed is not None else seed, "faults", 0, "link_loss")
        self.active: dict[int, ActiveFault] = {}
        self.events: dict[int, FaultEventCfg] = dict(enumerate(cfg.events))

    @property
    def empty(self) -> bool:
        return not self.events and self.cfg.link_loss == 0

    def inject(self, e: FaultEventCfg, k: int, ticks: int | None = None) -> int:
        """A live fault: ``e`` starts at tick ``k`` and heals ``ticks`` later (never, if None). Returns its id."""
        fid = LIVE_ID0 + sum(1 for i in self.events if i >= LIVE_ID0)
        self.events[fid] = replace(e, start=int(k), heal=None if ticks is None else int(k) + int(ticks))
        return fid

    def heal_at(self, k: int, fid: int | None = None) -> list[int]:
        """Heal the live fault ``fid`` (every live one if None) at tick ``k``; returns the ids concerned."""
        ids = [i for i in self.events if i >= LIVE_ID0 and (fid is None or i == fid)
               and (self.events[i].heal is None or self.events[i].heal > k)]
        for i in ids:
            e = self.events[i]
            if e.start >= k:            # not started yet: it never will
                del self.events[i]
            else:
                self.events[i] = replace(e, heal=int(k))
        return ids

    def transitions(self, k: int, adj: np.ndarray) -> list[tuple[str, ActiveFault]]:
        """Faults that heal and start at tick k (heals first), resolving targets on start."""
        out: list[tuple[str, ActiveFault]] = []
        for i, e in self.events.items():
            if e.heal is not None and e.heal == k and i in self.active:
                out.append(("heal", self.active.pop(i)))
        for i, e in self.events.items():
            if e.start == k:
                f = self.resolve(i, e, adj)
                self.active[i] = f
                out.append(("start", f))
        return out

    def resolve(self, i: int, e: FaultEventCfg, adj: np.ndarray) -> ActiveFault:
        head, _, rest = e.targets.partition(":")
        f = ActiveFault(i, e)
        n = self.n
        if head == "all":
            f.agents = list(range(n))
        elif head == "agents":
            f.agents = sorted({int(x) for x in rest.split(",")})
        elif head == "random":
            f.agents = sorted(int(x) for x in self.rng.choice(n, size=int(rest), replace=False))
        elif head == "most_connected":
            deg = adj.sum(axis=1)
            f.agents = [int(np.argmax(deg))]  # lowest id among the highest degree
        elif head == "links":
            f.links = [(int(a), int(b)) for a, b in (x.split("-") for x in rest.split(","))]
            f.agents = sorted({v for ab in f.links for v in ab})
        elif head == "halves":
            perm = self.rng.permutation(n)
            g = np.zeros(n, int)
            g[perm[n // 2:]] = 1
            f.groups = [int(x) for x in g]
        elif head == "groups":
            f.groups = [int(x) for x in rest.split(",")]
        if f.groups is not None and not f.agents:
            f.agents = list(range(n))
        return f

    # ------------------------------------------------------------------ world-side effects
    def directed_mask(self, adj: np.ndarray) -> np.ndarray:
        """M[i, j] = 1 iff i hears j this tick after link loss and partitions (adj is symmetric)."""
        M = adj.copy()
        n = self.n
        losses: list[tuple[float, np.ndarray]] = []
        if self.cfg.link_loss > 0:
            losses.append((self.cfg.link_loss, np.ones((n, n), bool)))
        for f in self.active.values():
            c = f.cfg
            if c.kind == "partition" and f.groups is not None:
                g = np.array(f.groups)
                M[g[:, None] != g[None, :]] = 0.0
            elif c.kind == "link_loss":
                sel = np.zeros((n, n), bool)
                if f.links:
                    for a, b in f.links:
                        if c.direction in ("both", "in"):
                            sel[a, b] = True   # a does not hear b
                        if c.direction in ("both", "out"):
                            sel[b, a] = True   # b does not hear a
                else:
                    idx = np.array(f.agents, int)
                    if c.direction in ("both", "in"):
                        sel[idx, :] = True     # the agent hears nothing
                    if c.direction in ("both", "out"):
                        sel[:, idx] = True     # nobody hears the agent
                losses.append((c.p, sel))
        for p, sel in losses:
            drop = (self.loss_rng.random((n, n)) < p) & sel
            M[drop] = 0.0
        np.fill_diagonal(M, 0.0)
        return M

    def blind(self) -> set[int]:
        return {a for f in self.active.values() if f.cfg.kind == "blind" for a in f.agents}
