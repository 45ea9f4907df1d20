"""Who suspected whom: the resilient consensus's discards scored against the run's Byzantine faults.

A sensor whose estimator discards neighbours' payloads publishes them beside its estimate
(``Estimate.aux["suspected"]``, :mod:`agent.estimators.information_gate`). Held against the fault plan's
``byzantine`` starts and heals (as the world announced them on ``world/event``), ``summary.json`` →
``suspicion`` gives

* ``false_suspicion_rate``: the share of node-ticks in which an honest sensor discarded an honest neighbour
  (the gate's price in a fault-free run);
* per attacker: ``detected_tick`` — the first tick of its attack at which a majority of its neighbours
  that tick discarded it — and ``latency_ticks`` from the attack's start; ``discarded_share``, the share of
  its neighbour-ticks under attack in which it was discarded.

And ``robustness``: W-MSR with f tolerates f Byzantine neighbours on a (2f + 1)-robust graph
(:mod:`topology.robustness`). Each tick's link graph is checked — exactly for flocks of up to 16 sensors, by
the degrees beyond — and the report counts the ticks verified robust enough (``ticks_robust``), certainly not
(``ticks_not_robust``, the first of them ``first_tick``, with a warning) and undecided (``ticks_unknown``).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Mapping

import numpy as np

from topology.graph import lists_adjacency
from topology.robustness import is_r_robust

log = logging.getLogger(__name__)


def attack_ticks(windows: Mapping[int, list], ticks: int) -> dict[int, set[int]]:
    """Agent → the ticks it was Byzantine, from its (start, heal) windows (heal None: to the end)."""
    return {a: {k for s, h in ws for k in range(s, ticks if h is None else h)} for a, ws in windows.items()}


def suspicion_report(suspected: Mapping[int, Mapping[int, np.ndarray]], links: Mapping[int, tuple],
                     attacks: Mapping[int, set[int]]) -> dict:
    """``suspected``: tick → node → the neighbours it discarded; ``links``: tick → each node's neighbours;
    ``attacks``: agent → the ticks it was Byzantine."""
    node_ticks = wrong = 0
    for k, by_node in suspected.items():
        for i, sus in by_node.items():
            if k in attacks.get(i, ()):
                continue                       # (what an attacker suspects says nothing)
            node_ticks += 1
            wrong += any(k not in attacks.get(int(j), ()) for j in sus)
    out: dict = {"node_ticks": node_ticks, "false_suspicions": wrong,
                 "false_suspicion_rate": wrong / node_ticks if node_ticks else None, "attackers": {}}
    for a, ks in sorted(attacks.items()):
        detected, hits, tries = None, 0, 0
        for k in sorted(ks):
            if k not in links or k not in suspected:
                continue
            nbrs = [i for i in _neighbours(links[k], a) if i in suspected[k]]
            if not nbrs:
                continue
            n_sus = sum(a in {int(j) for j in suspected[k][i]} for i in nbrs)
            hits, tries = hits + n_sus, tries + len(nbrs)
            if detected is None and 2 * n_sus > len(nbrs):
                detected = k
        start = min(ks) if ks else None
        out["attackers"][str(a)] = {"start": start, "detected_tick": detected,
                                    "latency_ticks": None if detected is None else detected - start,
                                    "discarded_share": hits / tries if tries else None}
    return out


def _neighbours(links: tuple, a: int) -> list[int]:
    """The sensors that hear ``a`` (whose inbox its payloads reach)."""
    return [i for i, heard in enumerate(links) if i != a and a in heard]


def robustness_report(links: Mapping[int, tuple], f: int) -> dict:
    """Which ticks' graphs (``links``: tick → each node's neighbours) are (2f + 1)-robust, as W-MSR with f needs."""
    need = 2 * f + 1
    verdict = {k: _robust(tuple(map(tuple, ls)), need) for k, ls in links.items()}
    low = sorted(k for k, v in verdict.items() if v is False)
    if low:
        log.warning("the link graph is not %d-robust, as W-MSR with f = %d needs, at %d ticks (the first: tick %d)",
                    need, f, len(low), low[0])
    return {"f": f, "required_r": need, "ticks_robust": sum(v is True for v in verdict.values()),
            "ticks_not_robust": len(low), "ticks_unknown": sum(v is None for v in verdict.values()),
            "first_tick": low[0] if low else None}


@functools.lru_cache(maxsize=256)
def _robust(links: tuple[tuple[int, ...], ...], r: int) -> bool | None:
    """:func:`topology.robustness.is_r_robust` of a tick's neighbour lists (cached: the graph changes far less
    often than every tick); None for an empty graph."""
    if not links:
        return None
    A = lists_adjacency(links) > 0
    return is_r_robust(A | A.T, r)
