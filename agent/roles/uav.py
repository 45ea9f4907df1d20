"""The UAV role (García Carrillo et al., Section IV-A): a sensor without a distributed estimator that
reports time-stamped relative measurements of the target to the fusion solver.

Every process regenerates the scenario's measurement stream from the seed (``agent.models_uav``:
unicycle target, orbiting UAVs, asynchronous ~5 Hz each, Gaussian noise, 40–70 m outliers, GPS noise),
so the UAVs, the target and the scorer agree on one world without sharing memory. At tick k the UAV
publishes, as ``meas``, the records of its own agent whose *arrival* time falls in [kT, (k+1)T)
(``t`` = the measurement time, ``y`` = z, ``pos`` = its GPS position), then its position as ``state``.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from ..bus import Bus
from ..wire import Meas, Message, State, Tick
from .common import Role


class UavRole(Role):
    name = "uav"

    def __init__(self, i: int, ticks: int, T: float, stream):
        super().__init__(ticks)
        self.i, self.T = int(i), float(T)
        self.k = 0
        mine = np.flatnonzero(stream.agent == self.i + 1)
        self._arr = stream.arrival[mine]
        self._idx = mine[np.argsort(self._arr, kind="stable")]
        self._arr = np.sort(self._arr, kind="stable")
        self._s = stream
        self._next = 0
        self.counters: Counter = Counter()

    def subscribe(self, bus: Bus) -> None:
        bus.subscribe("world/tick", self._on_tick)

    @property
    def finished(self) -> bool:
        return self.k >= self.ticks

    def _on_tick(self, key: str, msg: Message) -> None:
        assert isinstance(msg, Tick)
        if msg.k < self.k:
            return
        self.k = msg.k  # (ticks lost while disconnected are skipped: their records go out now)
        t_end = (self.k + 1) * self.T
        s = self._s
        while self._next < len(self._idx) and self._arr[self._next] < t_end:
            j = self._idx[self._next]
            self.publish(f"agent/{self.i}/meas", Meas(src=self.i, k=self.k, t=float(s.t[j]), y=s.z[j].copy(),
                                                      b=1.0, pos=s.gps[j].copy()))
            self.counters["measurements"] += 1
            self._next += 1
        pos = self._position(t_end)
        self.publish(f"agent/{self.i}/state", State(src=self.i, k=self.k, pos=pos, vel=np.zeros(2)))
        self.k += 1

    def _position(self, t: float) -> np.ndarray:
        """True UAV position at time t (orbit around the target), for the world and the dashboard."""
        s = self._s
        mine = s.agent == self.i + 1
        ts = s.t[mine]
        if ts.size == 0:
            return np.zeros(2)
        return np.array([np.interp(t, ts, s.uav_pos[mine, 0]), np.interp(t, ts, s.uav_pos[mine, 1])])
