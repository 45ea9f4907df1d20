"""The fusion role (García Carrillo et al.): a centralized solver fed by asynchronous, time-stamped
relative measurements from any agents (``agent/*/meas``), publishing ``fusion/estimate`` for each of
its estimators — the sum-of-norms estimator (10) on a sliding window, and the Kalman and batched
least-squares baselines on the same stream.

Determinism: measurements are buffered per tick and processed when the next tick (or the end) is
announced, sorted by (time stamp, sender) — so the estimates do not depend on how two UAVs' messages
interleave on the network, and a lockstep run over Zenoh equals the in-process one.

Each published ``Estimate`` has ``name`` = the estimator, ``x`` = the target state [p, v] at the newest
window node, ``x_next`` = the mid-window (smoothed) state, ``P`` = the covariance of ``x_next`` and
``aux`` = {"t": [t_newest], "t_mid": [t_mid], "outliers": [number flagged in the window], "P_newest": the
covariance of ``x``}. A window's covariances are those its own information implies
(:mod:`agent.estimators.son_covariance`); the Kalman baselines send their P (``x`` = ``x_next``).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Mapping

import numpy as np

from ..bus import Bus
from ..ports import Ports
from ..wire import End, Estimate, Meas, Message, Tick
from .common import Role


class FusionRole(Role):
    name = "fusion"
    PORTS = Ports(writes=("fusion/estimate",), reads=("agent/*/meas", "world/tick", "world/end"))

    def __init__(self, ticks: int, estimators: Mapping[str, object], to_record: Callable[[Meas], object]):
        super().__init__(ticks)
        self.estimators = dict(estimators)
        self.to_record = to_record     # Meas → RelativeMeasurement (covariances from the scenario)
        self._buf: dict[int, list[Meas]] = {}
        self._done = False
        self.counters: Counter = Counter()

    def subscribe(self, bus: Bus) -> None:
        bus.subscribe("agent/*/meas", self._on_meas)
        bus.subscribe("world/tick", self._on_tick)
        bus.subscribe("world/end", self._on_end)

    @property
    def finished(self) -> bool:
        return self._done

    def _on_meas(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Meas)
        if msg.y.shape != (2,) or msg.pos.shape != (2,):
            self.counters["rejected_meas"] += 1
            return
        self._buf.setdefault(msg.k, []).append(msg)

    def _on_tick(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Tick)
        self._flush(below=msg.k)

    def _on_end(self, key: str, msg: Message) -> None:
        assert isinstance(msg, End)
        self._flush(below=None)
        self._done = True

    def _flush(self, below: int | None) -> None:
        for k in sorted(kk for kk in self._buf if below is None or kk < below):
            for m in sorted(self._buf.pop(k), key=lambda m: (m.t, m.src)):
                self._process(m)

    def _process(self, m: Meas) -> None:
        try:
            rec = self.to_record(m)
        except ValueError:
            self.counters["rejected_meas"] += 1
            return
        self.counters["measurements"] += 1
        for name, est in self.estimators.items():
            if hasattr(est, "solve"):      # window estimators (sum-of-norms, BLS)
                est.add(rec)
                r = est.solve()
                x, xm = np.asarray(r.newest, float), np.asarray(r.midwindow, float)
                aux = {"t": np.array([r.t_newest]), "t_mid": np.array([r.t_mid]),
                       "outliers": np.array([float(np.sum(r.outliers))])}
                cov, P = est.covariances() if hasattr(est, "covariances") else None, None
                if cov is not None:
                    aux["P_newest"], P = cov
            else:                           # Kalman on every measurement
                est.add(rec)
                x = np.asarray(est.estimate(), float)
                xm = x
                aux = {"t": np.array([float(est.t)]), "t_mid": np.array([float(est.t)])}
                P = None if getattr(est, "P", None) is None else np.array(est.P, float)
            if not np.all(np.isfinite(x)) or not np.all(np.isfinite(xm)):
                self.counters[f"non_finite_{name}"] += 1
                continue
            if P is not None and (P.shape != (x.size, x.size) or not np.all(np.isfinite(P))):
                P = None
            self.publish("fusion/estimate", Estimate(k=m.k, x=x, x_next=xm, P=P, name=name, aux=aux))
