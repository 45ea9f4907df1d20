"""A sensor's inbox of exchange payloads, by (tick, round): what arrived early is kept for its round, what
comes too late or from a sensor that is not a neighbour this tick is dropped and counted, and a round is
complete once every current neighbour's payload is in — or held back by the link emulator for a later
tick (agent/link_emulation.py), which the round need not wait for. A payload that came unusable (its arrays
dropped by the bus: :class:`agent.wire.UnusableXchg`) is put as ``None``: it completes the round and is a lost
link when the round closes (``unusable_payloads``).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Collection

import numpy as np


class RoundInbox:
    """Exchange payloads (``{name: array}``) by (k, r) and sender; ``counters`` shared with the role."""

    def __init__(self, counters: Counter):
        self.counters = counters
        self._buf: dict[tuple[int, int], dict[int, dict[str, np.ndarray]]] = {}

    def refused(self, j: int, k: int, r: int, at: tuple[int, int], neighbours: Collection[int]) -> bool:
        """Is a payload (k, r) from j late (its round is over at ``at`` = (tick, round; −1 between ticks))
        or, in the tick under way, not from one of its ``neighbours``? Counted if so. (A payload of a tick
        not begun yet is kept: its sender addressed it by that tick's link table.)"""
        k_now, r_now = at
        if k < k_now or (k == k_now and 0 <= r_now and r < r_now):
            self.counters["late_payloads"] += 1
            return True
        if k == k_now and r_now >= 0 and j not in neighbours:
            self.counters["non_neighbour_payloads"] += 1
            return True
        return False

    def put(self, j: int, k: int, r: int, payload: dict[str, np.ndarray] | None) -> None:
        got = self._buf.setdefault((k, r), {})
        if payload is not None or j not in got:    # (an unusable copy never replaces a usable one)
            got[j] = payload

    def complete(self, k: int, r: int, neighbours: Collection[int], held: Collection[int]) -> bool:
        """Has every neighbour's payload of (k, r) arrived, or been ``held`` for later by the link emulator?
        (Asked at every arrival: while fewer payloads are in than neighbours not held, the answer is no without
        looking at who sent them — a round of d neighbours costs O(d), not O(d²).)"""
        if len(self._buf.get((k, r), ())) < len(neighbours) - len(held):
            return False
        return not self.missing(k, r, neighbours, held)

    def missing(self, k: int, r: int, neighbours: Collection[int], held: Collection[int]) -> list[int]:
        """The neighbours whose payload of (k, r) has neither arrived nor been ``held`` for later."""
        got = self._buf.get((k, r), {})
        return [j for j in neighbours if j not in got and j not in held]

    def take(self, k: int, r: int, neighbours: Collection[int]) -> dict[int, dict[str, np.ndarray]]:
        """The neighbours' payloads of (k, r) (the round closes: a missing one is a dropped link, counted)."""
        got = self._buf.pop((k, r), {})
        heard = {j: got[j] for j in neighbours if got.get(j) is not None}
        unusable = sum(1 for j in neighbours if j in got and got[j] is None)
        if unusable:
            self.counters["unusable_payloads"] += unusable
        self.counters["dropped_links"] += len(neighbours) - len(heard)
        return heard

    def forget_before(self, k: int) -> None:
        self._buf = {kr: got for kr, got in self._buf.items() if kr[0] >= k}
