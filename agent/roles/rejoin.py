"""A restarted sensor's way back into the flock: from its neighbours' estimates, not from its prior x̂₀.

Every sensor keeps its newest estimate and hands it to a sensor whose liveliness token (re)appears — a
restarted process, or one back after a router restart — on the addressed key ``agent/i/to/j/estimate``
(one message; ignored unless j is rejoining). A restarted process (``--rejoin``) takes up the world's clock
at the first tick it sees; once the world lists it alive it waits, up to its round deadline, for the
estimates of its current neighbours from the last :data:`JOIN_FRESH_TICKS` ticks (older copies, held by the
bus since an earlier router restart, are not waited for), and starts its filter from their mean
(:meth:`agent.estimators.base.Estimator.reinitialise`). In lockstep every live sensor answers the token
before the world's next tick, so the restart is as deterministic as the rest of the run.

:class:`Rejoin` is the sensor role's state for this (agent/roles/sensor.py calls it at each step).
"""

from __future__ import annotations

import logging
from collections import Counter

from ..estimators.base import Estimator
from ..wire import Estimate, Tick

log = logging.getLogger(__name__)

#: a rejoining sensor starts from peer estimates at most this many ticks older than its first tick
JOIN_FRESH_TICKS = 3


class Rejoin:
    """Sensor ``i``'s side of the handover (module doc); ``restarted``: this process is a restart."""

    def __init__(self, i: int, restarted: bool, counters: Counter):
        self.i, self.counters = int(i), counters
        self.restarted = bool(restarted)   # a restarted process not yet back in the flock
        self.joining = False               # it has taken up the world's clock; the filter starts at its first tick
        self.pending = False               # listed alive, waiting for the neighbours' estimates
        self.forced = False                # the deadline passed while waiting: start from what came
        self.peers: dict[int, Estimate] = {}   # each peer's newest estimate handed to us
        self.last: Estimate | None = None      # our own newest estimate (handed to a sensor that reappears)

    def takes_up(self, tick: Tick, k: int) -> bool:
        """Is ``tick`` the first one a restarted process sees ahead of its own clock ``k``? Then it is joining
        (the caller takes up the tick's clock and its position)."""
        if self.restarted and not self.joining and tick.k > k and tick.n > self.i:
            self.joining = True
            return True
        return False

    def handover(self, ident: int, alive: bool) -> Estimate | None:
        """Our last estimate for sensor ``ident`` whose token (re)appeared, or None."""
        if alive and ident != self.i and self.last is not None:
            self.counters["estimates_handed"] += 1
            return self.last
        return None

    def offer(self, msg: Estimate, k: int, shape: tuple[int, ...]) -> bool:
        """A peer's estimate handed to us, kept (the newest per peer) while it can matter; True if the first
        tick is waiting for it."""
        if msg.src == self.i or not (self.joining or k == 0) or msg.x_next.shape != shape:
            return False
        old = self.peers.get(msg.src)
        if old is None or msg.k >= old.k:   # (a copy held since an earlier router restart may come late)
            self.peers[msg.src] = msg
        return self.pending

    def awaiting(self, tick: Tick, neighbours: list[int], k: int) -> bool:
        """Joining, listed alive, and some of this tick's live ``neighbours`` (of anyone, if it has none) have
        not handed a fresh estimate yet: the first tick waits (bounded by :meth:`give_up_waiting`)."""
        if not self.joining or self.forced or not tick.alive[self.i]:
            self.pending = False
            return False
        fresh = self.fresh(k)
        self.pending = not (all(j in fresh for j in neighbours) if neighbours else fresh)
        return self.pending

    def fresh(self, k: int) -> dict[int, Estimate]:
        """The peers' estimates of the last few ticks before tick ``k`` (in lockstep exactly tick k − 1's)."""
        return {j: e for j, e in self.peers.items() if e.k >= k - JOIN_FRESH_TICKS}

    def start_from(self, est: Estimator, neighbours: list[int], k: int) -> None:
        """The first tick back: restart ``est`` from the neighbours' (else anyone's) estimates; back in."""
        peers = self.fresh(k)
        if not peers and self.peers:     # (none fresh after the deadline: the newest there are)
            newest = max(e.k for e in self.peers.values())
            peers = {j: e for j, e in self.peers.items() if e.k == newest}
        src = [j for j in neighbours if j in peers] or sorted(peers)
        if src:
            est.reinitialise({j: peers[j].x_next for j in src}, {j: peers[j].P for j in src if peers[j].P is not None})
            self.counters["reinitialised_from"] = len(src)
        self.joining = self.restarted = self.forced = False

    def give_up_waiting(self) -> bool:
        """The round deadline passed: if the first tick was waiting, it starts with what came (True)."""
        if not self.pending:
            return False
        log.info("agent/%d: rejoining with the estimates of %s only", self.i, sorted(self.peers))
        self.forced, self.pending = True, False
        self.counters["join_deadline"] += 1
        return True
