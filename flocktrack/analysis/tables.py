"""A recording's messages as pandas tables: ticks, estimates, links, events, faults.

Time is simulated time, t = k·T (the message's tick k, the scenario's period T): a recording's log times
are not used. The per-tick scores are :class:`flocktrack.record.metrics.MetricsCollector`'s — the very rows
of ``metrics.csv`` — so a table and ``summary.json`` never disagree.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import dataclass, field, fields
from typing import Any

import pandas as pd

from agent import wire
from agent.recording import Recording
from agent.scenario import FaultEventCfg, Scenario

from flocktrack.record.metrics import MetricsCollector

#: the tables of a run, in the order ``flocktrack export`` writes them
TABLES = ("ticks", "estimates", "links", "events", "faults")

#: a fault's parameters (the ``[[faults.events]]`` keys beyond kind, targets, start and heal)
FAULT_PARAMS = tuple(f.name for f in fields(FaultEventCfg) if f.name not in ("kind", "targets", "start", "heal"))
FAULT_COLUMNS = ("id", "source", "kind", "targets", "start", "heal", "started", "healed", "agents", "links",
                 "groups", *FAULT_PARAMS)
EVENT_COLUMNS = ("k", "t", "key", "verb", "kind", "phase", "fault_id", "agents", "args")
LINK_COLUMNS = ("k", "t", "src", "dst", "weight")


def needed(key: str) -> bool:
    """Whether the tables read the messages on ``key`` (the reader's ``decode``: the exchange payloads, the
    measurements and the agents' states, most of a recording, are left undecoded)."""
    if key in ("world/tick", "target/truth") or _own_estimate(key):
        return True
    return not key.startswith(("agent/", "target/", "fusion/"))   # the events' keys: world/event, control/…


def state_names(sc: Scenario) -> list[str]:
    """The names of the state's components: ``px, py, vx, vy`` for a 2-D double integrator (``px, py, pz,
    vx, vy, vz`` in 3-D), else ``x0, x1, …``."""
    m, d = sc.m, sc.target.dim
    if sc.target.model == "double_integrator" and m == 2 * d and d <= 3:
        axes = "xyz"[:d]
        return [f"p{a}" for a in axes] + [f"v{a}" for a in axes]
    return [f"x{i}" for i in range(m)]


@dataclass
class _Messages:
    """A recording's messages sorted by what the tables need of them."""

    ticks: dict[int, wire.Tick] = field(default_factory=dict)
    truth: dict[int, wire.Truth] = field(default_factory=dict)
    estimates: dict[tuple[int, int], wire.Estimate] = field(default_factory=dict)
    events: list[tuple[int, str, wire.Message]] = field(default_factory=list)   #: (k, key, Control | End)


def _sort(rec: Recording, metrics: MetricsCollector) -> _Messages:
    """One pass over the messages in sequence order: every one to the metrics, and bucketed. A control request
    carries no tick of its own (its sender does not know it): it is put at the last tick recorded before it."""
    out = _Messages()
    last_k = 0
    for key, msg, _log_time in rec.messages:
        if msg is None:
            continue
        metrics.ingest(key, msg)
        if isinstance(msg, wire.Tick):
            out.ticks[msg.k] = msg
            last_k = msg.k
        elif isinstance(msg, wire.Truth):
            out.truth[msg.k] = msg
        elif isinstance(msg, wire.Estimate) and _own_estimate(key):
            out.estimates[(msg.k, msg.src)] = msg
        elif isinstance(msg, (wire.Control, wire.End)):
            out.events.append((last_k if key.startswith("control/") else msg.k, key, msg))
    return out


def _own_estimate(key: str) -> bool:
    """``agent/<i>/estimate``: a sensor's estimate (not the fusion solver's)."""
    parts = key.split("/")
    return len(parts) == 3 and parts[0] == "agent" and parts[2] == "estimate"


def build(rec: Recording, sc: Scenario, design: dict[str, Any]) -> dict[str, pd.DataFrame]:
    """The five tables (:data:`TABLES`) of recording ``rec`` of scenario ``sc`` with pre-run ``design``."""
    metrics = MetricsCollector.for_scenario(sc, design)
    msgs = _sort(rec, metrics)
    scores = {r["k"]: r for r in metrics.rows()}
    T = sc.run.T
    return {"ticks": tick_table(msgs, scores, sc), "estimates": estimate_table(msgs, scores, sc),
            "links": link_table(msgs.ticks.values(), T), "events": event_table(msgs.events, sc),
            "faults": fault_table(msgs.events, sc)}


def tick_table(msgs: _Messages, scores: dict[int, dict], sc: Scenario) -> pd.DataFrame:
    """A row per tick: k, t, the target's true state ``truth_<name>``, the tick's scores (the columns of
    ``metrics.csv``: ``err_<i>``, rmse, tmsee, mean_err, disagreement, reporting, links (undirected), lambda2,
    connected, min_dist, visible, tmsee_lower where the design has it), ``links_directed`` and ``alive`` (the
    sensors the world counts as members)."""
    names = [f"truth_{n}" for n in state_names(sc)]
    metric_cols = [c for r in scores.values() for c in r if c not in ("k", "t")]
    cols = ["k", "t", *names, *dict.fromkeys(metric_cols), "links_directed", "alive"]
    rows = []
    for k in sorted(set(msgs.ticks) | set(msgs.truth) | set(scores)):
        row: dict[str, Any] = {"k": k, "t": k * sc.run.T}
        truth = msgs.truth.get(k)
        if truth is not None:
            row.update(_named(names, truth.x, "truth_x"))
        row.update({c: v for c, v in scores.get(k, {}).items() if c not in ("k", "t")})
        tick = msgs.ticks.get(k)
        if tick is not None:
            row["links_directed"] = sum(map(len, tick.links))
            row["alive"] = sum(tick.alive)
        rows.append(row)
    return _frame(rows, cols, ints=("k", "links", "links_directed", "alive", "reporting", "connected", "visible"))


def estimate_table(msgs: _Messages, scores: dict[int, dict], sc: Scenario) -> pd.DataFrame:
    """A row per tick per sensor that estimated: k, t, node, estimator (the name the node reports), its
    x̂ₖ by component (the state's names), err = ‖position error‖ (``err_<node>`` of the tick's scores) and,
    where the node reports its covariance P (of x̂ₖ₊₁, after this tick's update), ``P_trace`` and the
    diagonal ``P_<name>``."""
    names = state_names(sc)
    with_P = any(e.P is not None for e in msgs.estimates.values())
    cols = ["k", "t", "node", "estimator", *names, "err", *(["P_trace", *(f"P_{n}" for n in names)] if with_P else [])]
    rows = []
    for (k, node), e in sorted(msgs.estimates.items()):
        row: dict[str, Any] = {"k": k, "t": k * sc.run.T, "node": node, "estimator": e.name}
        row.update(_named(names, e.x, "x"))
        row["err"] = scores.get(k, {}).get(f"err_{node}", math.nan)
        if e.P is not None:
            row["P_trace"] = float(e.P.trace())
            row.update(_named([f"P_{n}" for n in names], e.P.diagonal(), "P_x"))
        rows.append(row)
    return _frame(rows, cols, ints=("k", "node"))


def link_table(ticks: Iterable[wire.Tick], T: float) -> pd.DataFrame:
    """A row per tick per directed link src → dst (dst hears src this tick, after range, faults and
    membership) with its consensus weight; an undirected link in both directions is two rows."""
    rows = [{"k": tk.k, "t": tk.k * T, "src": j, "dst": i, "weight": w}
            for tk in sorted(ticks, key=lambda tk: tk.k)
            for i, (nb, ws) in enumerate(zip(tk.links, tk.weights)) for j, w in zip(nb, ws)]
    return _frame(rows, LINK_COLUMNS, ints=("k", "src", "dst"))


def event_table(events: list[tuple[int, str, wire.Message]], sc: Scenario) -> pd.DataFrame:
    """A row per message on a key that is not per tick, in recording order: the world's fault transitions and
    answers (``world/event``), the launcher's acknowledgements and answers (``launcher/event``), the control
    requests (``control/<verb>``) and the run's end (``world/end``). ``args`` holds the message's arguments
    as JSON; kind, phase, fault_id and agents are read from them where they say (an inject's answer and a
    heal_fault request carry the live fault's id)."""
    rows = []
    for k, key, msg in events:
        args = dict(msg.args) if isinstance(msg, wire.Control) else {"reason": msg.reason}
        verb = msg.verb if isinstance(msg, wire.Control) else "end"
        fault = _fault_event(args, sc) if verb in ("fault", "ack") else None
        agents = fault.agents if fault else wire.int_list(args.get("agents", [args.get("agent")]), 0, sc.sensors.n)
        rows.append({"k": k, "t": k * sc.run.T, "key": key, "verb": verb,
                     "kind": fault.kind if fault else args.get("kind"), "phase": fault.phase if fault else None,
                     "fault_id": fault.id if fault else _whole(args.get("id")), "agents": _joined(agents),
                     "args": json.dumps(args, sort_keys=True)})
    return _frame(rows, EVENT_COLUMNS, ints=("k", "fault_id"))


def fault_table(events: list[tuple[int, str, wire.Message]], sc: Scenario) -> pd.DataFrame:
    """A row per fault: the scenario's schedule (source ``scenario``: ``[[faults.events]]`` in order, id = its
    index; ``link_loss``: the ``faults.link_loss`` shorthand, all run long, no id) and the faults injected live
    (source ``live``), with the ticks the world started and healed each (``started``, ``healed``) and the
    agents, links and groups its targets resolved to, from the recorded ``world/event`` transitions."""
    rows: dict[Any, dict[str, Any]] = {}
    if sc.faults.link_loss > 0:
        rows["link_loss"] = {"source": "link_loss", "kind": "link_loss", "targets": "all", "start": 0,
                             "p": sc.faults.link_loss}
    for i, e in enumerate(sc.faults.events):
        rows[i] = {"id": i, "source": "scenario", "kind": e.kind, "targets": e.targets, "start": e.start,
                   "heal": e.heal, **{p: _cell(getattr(e, p)) for p in FAULT_PARAMS}}
    for k, key, msg in events:
        if key != "world/event" or msg.verb != "fault":
            continue
        f = _fault_event(msg.args, sc)
        if f is None:
            continue
        row = rows.setdefault(f.id, {"id": f.id, "source": "live", "kind": f.kind,
                                     **{p: _cell(getattr(f, p, None)) for p in FAULT_PARAMS}})
        row["started" if f.phase == "start" else "healed"] = k
        row.update(agents=_joined(f.agents), links=_joined(f"{a}-{b}" for a, b in f.links), groups=_joined(f.groups))
    return _frame(list(rows.values()), FAULT_COLUMNS,
                  ints=("id", "start", "heal", "started", "healed", "delay_ticks", "jitter_ticks"))


def _fault_event(args: dict, sc: Scenario) -> wire.FaultEvent | None:
    try:
        return wire.fault_event(args, sc.sensors.n)
    except wire.WireError:
        return None


def _whole(v) -> int | None:
    """An id argument (an inject's answer, a heal_fault's request) where it is one."""
    return v if isinstance(v, int) and not isinstance(v, bool) else None


def _named(names: list[str], values, fallback: str) -> dict[str, float]:
    """``{name: value}`` over a vector; components beyond ``names`` are ``<fallback><i>``."""
    return {(names[i] if i < len(names) else f"{fallback}{i}"): float(v) for i, v in enumerate(values)}


def _joined(values) -> str | None:
    """A list of ids as ``1,2`` (the targets selectors' spelling); None for none."""
    return None if values is None else ",".join(map(str, values)) or None


def _cell(v):
    """A fault parameter as a table cell: a vector (a bias) as ``1.0,2.0``."""
    return _joined(v) if isinstance(v, (list, tuple)) else v


def _frame(rows: list[dict], columns, ints: tuple[str, ...] = ()) -> pd.DataFrame:
    """The rows as a DataFrame with ``columns`` (in that order; columns a row has beyond them appended);
    ``ints``: integer columns, nullable where a row has none."""
    cols = list(dict.fromkeys([*columns, *(c for r in rows for c in r)]))
    df = pd.DataFrame(rows, columns=cols)
    for c in ints:
        if c in df:
            df[c] = df[c].astype("Int64") if df[c].isna().any() else df[c].astype("int64")
    return df
