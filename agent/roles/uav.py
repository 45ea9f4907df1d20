"""The UAV roles (García Carrillo et al., Section IV-A): UAVs that report time-stamped relative measurements of
the target — to the central fusion solver (:class:`UavRole`, ``[fusion] mode = "central"``), or, each fusing its
own, to the other UAVs' solvers by consensus ADMM (:class:`UavFusionNodeRole`, ``mode = "distributed"``).

Every process regenerates the scenario's measurement stream from the seed (``agent.models_uav``:
unicycle target, orbiting UAVs, asynchronous ~5 Hz each, Gaussian noise, 40–70 m outliers, GPS noise),
so the UAVs, the target and the scorer agree on one world without sharing memory. At tick k a UAV
publishes, as ``meas``, the records of its own agent whose *arrival* time falls in [kT, (k+1)T)
(``t`` = the measurement time, ``y`` = z, ``pos`` = its GPS position), then its position as ``state``.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from ..bus import Bus
from ..ports import Ports
from ..estimators.relative_measurement import RelativeMeasurement
from ..wire import Meas, Message, State, Tick, Truth
from .common import Role
from .sensor import SensorRole


class UavTrack:
    """UAV ``i``'s share of the seeded stream: its records by arrival time, and where it flies."""

    def __init__(self, stream, i: int, T: float):
        self.s, self.i, self.T = stream, int(i), float(T)
        mine = np.flatnonzero(stream.agent == self.i + 1)
        order = np.argsort(stream.arrival[mine], kind="stable")
        self.idx = mine[order]
        self.arrival = stream.arrival[mine][order]

    def in_tick(self, k: int) -> np.ndarray:
        """Stream indices of the records arriving in [kT, (k+1)T)."""
        lo, hi = np.searchsorted(self.arrival, [k * self.T, (k + 1) * self.T], side="left")
        return self.idx[lo:hi]

    def meas(self, j: int, k: int) -> Meas:
        s = self.s
        return Meas(src=self.i, k=k, t=float(s.t[j]), y=s.z[j].copy(), b=1.0, pos=s.gps[j].copy())

    def position(self, t: float) -> np.ndarray:
        """True UAV position at time t (orbit around the target), for the world and the dashboard."""
        s = self.s
        mine = s.agent == self.i + 1
        ts = s.t[mine]
        if ts.size == 0:
            return np.zeros(2)
        return np.array([np.interp(t, ts, s.uav_pos[mine, 0]), np.interp(t, ts, s.uav_pos[mine, 1])])


class UavRole(Role):
    name = "uav"
    PORTS = Ports(writes=("agent/{i}/meas", "agent/{i}/state"), reads=("world/tick",))

    def __init__(self, i: int, ticks: int, T: float, stream):
        super().__init__(ticks)
        self.i, self.T = int(i), float(T)
        self.k = 0
        self.track = UavTrack(stream, i, T)
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
        tr = self.track
        while self._next < len(tr.idx) and tr.arrival[self._next] < t_end:
            self.publish(f"agent/{self.i}/meas", tr.meas(int(tr.idx[self._next]), self.k))
            self.counters["measurements"] += 1
            self._next += 1
        self.publish(f"agent/{self.i}/state", State(src=self.i, k=self.k, pos=tr.position(t_end), vel=np.zeros(2)))
        self.k += 1


class UavFusionNodeRole(SensorRole):
    """A UAV that fuses its own measurements (:class:`agent.estimators.admm_fusion.AdmmFusionNode`) and agrees
    with the other UAVs over the sensor role's exchange rounds — so membership, deadlines, the link emulator,
    sitting out and rejoining are the sensor's. Its measurements of tick k are those of :class:`UavRole`
    (published as ``meas``, for the recording and a central fusion process beside it); it flies its orbit."""

    def __init__(self, i: int, ticks: int, T: float, estimator, sensor, *, track: UavTrack, rng,
                 rejoin: bool = False, seed: int = 0, catch_up: bool = False):
        super().__init__(i, ticks, T, estimator, sensor, rng=rng, q0=track.position(0.0), pos_dims=2, rejoin=rejoin,
                         seed=seed, catch_up=catch_up)
        self.track = track

    def _measure(self, tick: Tick, truth: Truth, b: float) -> np.ndarray:
        for j in self.track.in_tick(self.k):
            self.publish(f"agent/{self.i}/meas", self.track.meas(int(j), self.k))
            self.counters["measurements"] += 1
        return np.zeros(2)

    def _finish(self) -> None:
        self.q = self.track.position((self.k + 1) * self.T)
        super()._finish()


def track_records(track: UavTrack, R: np.ndarray, G: np.ndarray):
    """``records(k)`` of :class:`AdmmFusionNode`: the UAV's relative measurements arriving in tick k."""
    s = track.s

    def records(k: int) -> list[RelativeMeasurement]:
        return [RelativeMeasurement(track.i + 1, float(s.t[j]), s.z[j], R, s.gps[j], G) for j in track.in_tick(k)]
    return records
