"""Run metrics from the message stream alone (so a recording can be re-scored).

:class:`MetricsCollector` is a read-only subscriber: it ingests ``tick``, ``truth``, ``estimate`` and
``state`` messages and produces, per tick k,

* eᵢ(k) = ‖x̂ᵢ,ₖ − xₖ‖ over the position components (per node) and the network RMSE √(mean eᵢ²);
* TMSEE(k) = Σᵢ ‖x̂ᵢ,ₖ − xₖ‖² over the full state (Chen et al.), and its lower bound (12) where the
  runtime computed one;
* the consensus disagreement √(mean ‖x̂ᵢ − x̄‖²) of the node estimates around their mean;
* the error of the mean estimate ‖x̄ₖ − xₖ‖ (position);
* the minimum inter-agent distance, the algebraic connectivity λ₂ of the tick's graph, the number of links.

``summary()`` condenses them into ``summary.json``; ``rows()`` gives ``metrics.csv``. Nothing in either
depends on wall-clock time, so the same scenario and seed give byte-identical files.
"""

from __future__ import annotations

import csv
import json
import functools
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from agent.estimators.registry import specs
from agent.estimators.spec import RunTrace
from agent.wire import (Control, Estimate, Meas, Message, State, Tick, Truth, WireError, fault_event,
                        valid_suspects)
from topology.graph import algebraic_connectivity, is_connected, lists_adjacency


def summary_identity(sc) -> dict:
    """What identifies a run in ``summary.json`` (transport-independent by design)."""
    return {"scenario": sc.run.name, "estimator": sc.estimator.name, "seed": sc.run.seed,
            "ticks": sc.run.ticks, "n_sensors": sc.sensors.n, "rounds": sc.estimator.rounds}


SummaryHook = Callable[[Mapping[str, Any], RunTrace | None], dict]


class MetricsCollector:
    """Per-tick metrics of one run; ``summary_hook`` adds the estimator's own summary fields (its spec's
    ``summary``) computed from the run's :class:`agent.estimators.spec.RunTrace`."""

    def __init__(self, n: int, ticks: int, pos_dims: int, burn_in: int = 0,
                 tmsee_lower: Sequence[float] | None = None, *, design: dict | None = None, T: float | None = None,
                 summary_hook: SummaryHook | None = None, reference=None, resilient_f: int = 0):
        """``reference``: the centralized model the estimates are held against
        (:class:`flocktrack.record.credibility.Reference`; None: no efficiency); ``resilient_f``: the W-MSR f
        the graph is checked against (flocktrack/record/suspicion.py)."""
        self.summary_hook = summary_hook
        self.n, self.ticks, self.d, self.burn_in = int(n), int(ticks), int(pos_dims), int(burn_in)
        self.tmsee_lower = None if tmsee_lower is None else [float(v) for v in tmsee_lower]
        self._truth: dict[int, np.ndarray] = {}
        self._est: dict[int, dict[int, np.ndarray]] = {}
        self._ticks: dict[int, Tick] = {}
        self._target_pos: dict[int, np.ndarray] = {}
        self.design, self.T = design or {}, T
        self._w: dict[int, np.ndarray] = {}
        self._v: dict[int, dict[int, np.ndarray]] = {}
        self._eps: dict[int, dict[int, dict[str, np.ndarray]]] = {}
        #: name → (t newest, t mid, x newest, x mid, P newest, P mid) per estimate (P None: not sent)
        self._fusion: dict[str, list[tuple]] = {}
        self._meas_pos: list[tuple[float, np.ndarray]] = []
        self._cov: dict[int, dict[int, np.ndarray]] = {}          #: tick → node → the P reported for its x̂
        self._meas: dict[int, dict[int, tuple[float, np.ndarray]]] = {}   #: tick → node → (b, y)
        self.reference = reference
        self.resilient_f = int(resilient_f)
        self._byzantine: dict[int, list[list]] = {}   #: agent → its Byzantine [start, heal] windows

    @classmethod
    def for_scenario(cls, sc, design: Mapping[str, Any]) -> "MetricsCollector":
        """The collector of scenario ``sc`` with the runtime's pre-run ``design``."""
        spec = specs().get(sc.estimator.name)
        from .credibility import Reference

        return cls(sc.sensors.n, sc.run.ticks, sc.pos_dims, sc.run.burn_in, design.get("tmsee_lower"),
                   design=dict(design), T=sc.run.T, summary_hook=None if spec is None else spec.summary,
                   reference=Reference.of(sc) if sc.kind == "flock" else None,
                   resilient_f=sc.estimator.resilient_f if sc.kind == "flock" else 0)

    def subscribe(self, bus) -> None:
        for pat in ("world/tick", "target/truth", "agent/*/estimate", "target/state", "agent/*/meas",
                    "fusion/estimate", "world/event"):
            bus.subscribe(pat, self.ingest)

    def ingest(self, key: str, msg: Message) -> None:
        if isinstance(msg, Tick):
            self._ticks[msg.k] = msg
        elif isinstance(msg, Truth):
            self._truth[msg.k] = msg.x
        elif isinstance(msg, Estimate) and key.startswith("agent/"):
            self._est.setdefault(msg.k, {})[msg.src] = msg.x
            if msg.P is not None and msg.P.shape == (msg.x.size, msg.x.size):
                self._cov.setdefault(msg.k + 1, {})[msg.src] = msg.P     # (of x_next: the next tick's x̂)
            if msg.aux:
                self._eps.setdefault(msg.k, {})[msg.src] = msg.aux
                t, x = msg.aux.get("t_newest"), msg.aux.get("newest")
                if t is not None and x is not None and t.shape == (1,) and x.shape == (4,):
                    # a distributed-fusion UAV's estimate at its window's newest node, scored like the fusion's
                    self._fusion.setdefault(f"admm/{msg.src}", []).append((float(t[0]), float(t[0]), x, x,
                                                                               None, None))
        elif isinstance(msg, State) and key == "target/state":
            self._target_pos[msg.k] = msg.pos
            if msg.w is not None:
                self._w[msg.k] = msg.w
        elif isinstance(msg, Estimate) and key == "fusion/estimate":
            t, tm = msg.aux.get("t"), msg.aux.get("t_mid")
            if t is not None and tm is not None:
                Pn = msg.aux.get("P_newest")          # (a filter's x is its x_next: P is both)
                if Pn is None and np.array_equal(msg.x, msg.x_next):
                    Pn = msg.P
                self._fusion.setdefault(msg.name, []).append((float(t[0]), float(tm[0]), msg.x, msg.x_next, Pn,
                                                              msg.P))
        elif isinstance(msg, Control) and key == "world/event" and msg.verb == "fault":
            self._note_fault(msg)
        elif isinstance(msg, Meas):
            self._meas.setdefault(msg.k, {})[msg.src] = (msg.b, msg.y)
            if msg.v is not None:
                self._v.setdefault(msg.k, {})[msg.src] = msg.v
            if self.T is not None and msg.y.shape == msg.pos.shape == (2,):
                self._meas_pos.append((msg.t, msg.pos + msg.y))

    def _note_fault(self, msg: Control) -> None:
        """A Byzantine fault's start or heal, as the world announced it (the agents it resolved to)."""
        try:
            ev = fault_event(msg.args)
        except WireError:
            return
        if ev.kind != "byzantine":
            return
        for a in ev.agents:
            ws = self._byzantine.setdefault(a, [])
            if ev.phase == "start":
                ws.append([msg.k, None])
            elif ws and ws[-1][1] is None:
                ws[-1][1] = msg.k

    # ------------------------------------------------------------------ per tick
    def rows(self) -> list[dict]:
        """``metrics.csv``: :meth:`row` of every tick with a truth."""
        return [r for r in map(self.row, range(self.ticks)) if r is not None]

    def row(self, k: int) -> dict | None:
        """Tick ``k``'s metrics (None before its truth is known): per-node errors, RMSE, TMSEE, the mean
        estimate's error, disagreement, links, λ₂, connectivity, the closest two agents."""
        if k not in self._truth:
            return None
        x = self._truth[k]
        est = self._est.get(k, {})
        row: dict = {"k": k}
        tick = self._ticks.get(k)
        row["t"] = tick.t if tick else math.nan
        errs = {i: float(np.linalg.norm(est[i][: self.d] - x[: self.d])) for i in sorted(est)}
        for i in range(self.n):
            row[f"err_{i}"] = errs.get(i, math.nan)
        if errs:
            ev = np.array([errs[i] for i in sorted(errs)])
            row["rmse"] = float(np.sqrt(np.mean(ev ** 2)))
            X = np.array([est[i] for i in sorted(est)])
            row["tmsee"] = float(np.sum((X - x[None, :]) ** 2))
            xbar = X.mean(axis=0)
            row["mean_err"] = float(np.linalg.norm(xbar[: self.d] - x[: self.d]))
            row["disagreement"] = float(np.sqrt(np.mean(np.sum((X - xbar[None, :]) ** 2, axis=1))))
            row["reporting"] = len(est)
        else:
            row.update(rmse=math.nan, tmsee=math.nan, mean_err=math.nan, disagreement=math.nan, reporting=0)
        if self.tmsee_lower is not None and k < len(self.tmsee_lower):
            row["tmsee_lower"] = self.tmsee_lower[k]
        if tick is not None:
            row["links"], row["lambda2"], row["connected"] = _graph_metrics(tuple(map(tuple, tick.links)))
            P = tick.positions
            if P.shape[0] > 1:
                D = np.linalg.norm(P[:, None, :] - P[None, :, :], axis=2)
                row["min_dist"] = float(D[np.triu_indices(P.shape[0], 1)].min())
            else:
                row["min_dist"] = math.nan
            row["visible"] = int(sum(1 for b in tick.b if b > 0))
        return row

    # ------------------------------------------------------------------ summary
    def summary(self, extra: dict | None = None) -> dict:
        rows = self.rows()
        scored = [r for r in rows if r["k"] >= self.burn_in]

        def col(name: str, rs=scored) -> np.ndarray:
            return np.array([r[name] for r in rs if name in r and not math.isnan(r[name])], float)

        per_node = []
        for i in range(self.n):
            e = col(f"err_{i}")
            per_node.append(float(np.sqrt(np.mean(e ** 2))) if e.size else None)
        rm = col("rmse")
        s: dict = {
            "ticks_scored": len(scored),
            "ticks_seen": len(rows),
            "burn_in": self.burn_in,
            "per_node_rmse": per_node,
            "network_rmse": float(np.sqrt(np.mean(rm ** 2))) if rm.size else None,
            "final_rmse": float(rows[-1]["rmse"]) if rows and not math.isnan(rows[-1]["rmse"]) else None,
            "max_error": _max(np.array([r[f"err_{i}"] for r in scored for i in range(self.n)
                                        if not math.isnan(r[f"err_{i}"])])),
            "mean_estimate_rmse": _rms(col("mean_err")),
            "tmsee_mean": _mean(col("tmsee")),
            "disagreement_mean": _mean(col("disagreement")),
            "disagreement_max": _max(col("disagreement")),
            "min_inter_agent_distance": _min(col("min_dist", rows)),
            "lambda2_min": _min(col("lambda2", rows)),
            "lambda2_mean": _mean(col("lambda2", rows)),
            "connected_fraction": _mean(col("connected", rows)),
        }
        if self.tmsee_lower is not None:
            lo = col("tmsee_lower")
            s["tmsee_lower_mean"] = _mean(lo)
            tm = np.array([r["tmsee"] for r in scored if "tmsee_lower" in r])
            lb = np.array([r["tmsee_lower"] for r in scored if "tmsee_lower" in r])
            s["tmsee_below_bound_ticks"] = int(np.sum(tm < lb))
        s["tmsee"] = [r["tmsee"] for r in rows]
        if self.tmsee_lower is not None:
            s["tmsee_lower"] = [r.get("tmsee_lower") for r in rows]
        s["lambda2"] = [r.get("lambda2") for r in rows]
        if self.summary_hook is not None:
            s.update(self.summary_hook(self.design, self.run_trace()))
        if self._fusion:
            s["fusion"] = self.fusion_report()
        s["credibility"] = self.credibility([r["k"] for r in scored])
        s.update(self.resilience())
        if extra:
            s.update(extra)
        return s

    def resilience(self) -> dict:
        """``suspicion`` (where estimators report whom they discarded) and ``robustness`` (with W-MSR)."""
        from .suspicion import attack_ticks, robustness_report, suspicion_report

        out: dict = {}
        links = {k: t.links for k, t in self._ticks.items()}
        suspected: dict[int, dict[int, np.ndarray]] = {}
        invalid = 0         # values of aux["suspected"] that name no possible suspect (dropped, as the dashboard does)
        for k, by in self._eps.items():
            for i, aux in by.items():
                if "suspected" in aux:
                    ids, bad = valid_suspects(i, aux["suspected"], self.n)
                    suspected.setdefault(k, {})[i] = ids
                    invalid += bad
        if suspected:
            attacks = attack_ticks(self._byzantine, self.ticks)
            out["suspicion"] = suspicion_report(suspected, links, attacks) | {"invalid_suspects": invalid}
        if self.resilient_f > 0 and links:
            out["robustness"] = robustness_report(links, self.resilient_f)
        return out

    def credibility(self, scored: list[int]) -> dict:
        """NEES/ANEES, COIN and the efficiency against the centralized reference
        (flocktrack/record/credibility.py) over the ``scored`` ticks."""
        from .credibility import report

        central = None
        if self.reference is not None and self._meas:
            central = self.reference.run(self._meas, self.ticks)
        return report(self._truth, self._est, self._cov, scored, central, meas=self._meas, ref=self.reference)

    def forget(self, upto: int) -> None:
        """Drop what is kept of the ticks up to ``upto`` (a live consumer done with them: the recorder's
        views keep a few ticks, not the run)."""
        for d in (self._truth, self._est, self._ticks, self._target_pos, self._w, self._v, self._eps, self._cov,
                  self._meas):
            for k in [k for k in d if k <= upto]:
                del d[k]
        self._meas_pos.clear()

    def truth_at(self, k: int) -> np.ndarray | None:
        """The target's true state at tick ``k`` (None: not recorded)."""
        return self._truth.get(k)

    def truth_position(self, t: float) -> np.ndarray | None:
        """The target position at time t: cubic Hermite between the tick truths (position, velocity)."""
        if self.T is None:
            return None
        k0 = int(np.floor(t / self.T))
        if k0 not in self._truth or k0 + 1 not in self._truth:
            return self._truth[k0][:2] if k0 in self._truth and abs(t - k0 * self.T) < 1e-9 else None
        x0, x1 = self._truth[k0], self._truth[k0 + 1]
        s = (t - k0 * self.T) / self.T
        h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
        return h00 * x0[:2] + h10 * self.T * x0[2:4] + h01 * x1[:2] + h11 * self.T * x1[2:4]

    def fusion_report(self) -> dict:
        """García Carrillo et al. Table I quantities on this run: the RMSE of the raw measurements and of
        every fusion estimator, scored at the newest window node (filtering) and at the mid-window node
        (smoothing, lagged) against the true position at that node's time stamp."""
        out: dict = {}
        meas = sorted(self._meas_pos, key=lambda tp: (tp[0], tuple(tp[1])))  # arrival order must not matter
        me = [p - self.truth_position(t) for t, p in meas if self.truth_position(t) is not None]
        out["measurement_rmse"] = float(np.sqrt(np.mean(np.sum(np.square(me), axis=1)))) if me else None
        from .credibility import consistency

        for name in sorted(self._fusion):
            en, em, cn, cm = [], [], [], []     # errors; (error, P) pairs for the NEES
            for t, tm, x, xm, Pn, Pm in self._fusion[name]:
                pt, pm = self.truth_position(t), self.truth_position(tm)
                if pt is not None:
                    en.append(x[:2] - pt)
                    if Pn is not None and Pn.shape == (4, 4):
                        cn.append((en[-1], Pn[:2, :2]))
                if pm is not None:
                    em.append(xm[:2] - pm)
                    if Pm is not None and Pm.shape == (4, 4):
                        cm.append((em[-1], Pm[:2, :2]))
            out[name] = {"estimates": len(self._fusion[name]),
                         "rmse_newest": float(np.sqrt(np.mean(np.sum(np.square(en), axis=1)))) if en else None,
                         "rmse_midwindow": float(np.sqrt(np.mean(np.sum(np.square(em), axis=1)))) if em else None}
            # the position's NEES against the covariance each estimate was sent with (m = 2)
            for key, pairs in (("nees_newest", cn), ("nees_midwindow", cm)):
                c = consistency(np.array([e for e, _ in pairs]), np.array([P for _, P in pairs])) if pairs else None
                if c is not None:
                    out[name][key] = c
        return out

    def run_trace(self) -> RunTrace | None:
        """The run's errors, disturbances and reported extras over the ticks 0…K every node estimated
        (None when those ticks are not 0…K in a row, or the tick period is unknown)."""
        ks = [k for k in range(self.ticks) if k in self._truth and len(self._est.get(k, {})) == self.n]
        if len(ks) < 2 or ks != list(range(len(ks))) or self.T is None:
            return None
        K = len(ks) - 1
        E = np.array([[self._est[k][i] - self._truth[k] for i in range(self.n)] for k in ks])
        m = len(self._w.get(0, [0.0]))
        w = np.array([self._w.get(k, np.zeros(m)) for k in range(K)])
        v = [np.array([self._v.get(k, {}).get(i, np.zeros(1)) for k in range(K)]) for i in range(self.n)]

        def extra(k: int, i: int, name: str) -> np.ndarray | None:
            return self._eps.get(k, {}).get(i, {}).get(name)

        return RunTrace(T=float(self.T), errors=E, w=w, v=v, extra=extra)

    def write(self, out_dir: str | Path, extra: dict | None = None) -> dict:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        rows = self.rows()
        summary = self.summary(extra)
        (out / "summary.json").write_text(json.dumps(_nan_to_none(summary), indent=2, sort_keys=True, allow_nan=False,
                                                     default=_json_default) + "\n")
        cols: list[str] = []
        for r in rows:
            for c in r:
                if c not in cols:
                    cols.append(c)
        with (out / "metrics.csv").open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=cols)
            w.writeheader()
            for r in rows:
                w.writerow({c: _fmt(r.get(c, "")) for c in cols})
        return summary


@functools.lru_cache(maxsize=256)
def _graph_metrics(links: tuple[tuple[int, ...], ...]) -> tuple[int, float, int]:
    """(undirected links, λ₂, connected) of a tick's neighbour lists — the graph changes far less often
    than every tick, so the eigen-solve is cached by the lists."""
    adj = lists_adjacency(links)
    return int(adj.sum() // 2), float(algebraic_connectivity(adj)), int(is_connected(adj))


def _nan_to_none(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _nan_to_none(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_nan_to_none(x) for x in v]
    return v


def _fmt(v):
    return repr(v) if isinstance(v, float) else v


def _json_default(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    raise TypeError(type(v))


def _mean(a: np.ndarray) -> float | None:
    return float(np.mean(a)) if a.size else None


def _rms(a: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(a ** 2))) if a.size else None


def _min(a: np.ndarray) -> float | None:
    return float(np.min(a)) if a.size else None


def _max(a: np.ndarray) -> float | None:
    return float(np.max(a)) if a.size else None
