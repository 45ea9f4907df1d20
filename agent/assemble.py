"""Scenario → the agent-side roles (sensor i, target). Used by ``python -m agent`` and by the runtime.

Graph-wide designs (Chen's gain K) arrive precomputed in ``design`` (a JSON-able dict) — this module
never looks at the whole graph itself (DESIGN.md floors).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .control.flocking import FlockingController
from .estimators.registry import make_estimator
from .models import DisturbedSensor, IntelligentTarget, LinearSensor, LinearTarget
from .roles.sensor import SensorRole
from .roles.target import TargetRole
from .scenario import Scenario
from .seeding import rng_for


_STREAMS: dict = {}


def uav_stream(sc: Scenario):
    """The seeded measurement stream of a UAV scenario (identical in every process that asks)."""
    key = (sc.source, sc.run.seed, repr(sc.uav))
    if key not in _STREAMS:
        _STREAMS.clear()
        _STREAMS[key] = sc.uav.sim().generate(sc.uav.duration, rng_for(sc.run.seed, "uav_stream"))
    return _STREAMS[key]


def build_fusion(sc: Scenario):
    """The fusion role of a UAV scenario: sum-of-norms + baselines on every agent's measurements."""
    from .estimators.sum_of_norms import RelativeMeasurement
    from .roles.fusion import FusionRole

    u = sc.uav.uav
    R, G = np.eye(2) * u.sigma_rel ** 2, np.eye(2) * u.sigma_gps ** 2

    def to_record(m):
        return RelativeMeasurement(m.src + 1, m.t, m.y, R, m.pos, G)

    ests = sc.uav.make_estimators()
    _warm_up(sc.uav.make_estimators(), to_record)  # compile the numba solver before joining the run
    return FusionRole(sc.run.ticks, ests, to_record)


def _warm_up(estimators, to_record) -> None:
    """Run the estimators once on a few synthetic measurements (numba compiles or loads its cache)."""
    from types import SimpleNamespace

    for k in range(4):
        m = SimpleNamespace(src=k % 2, t=0.1 * k, y=np.array([10.0, 5.0]), pos=np.array([1.0 * k, 0.0]), k=0)
        rec = to_record(m)
        for est in estimators.values():
            est.add(rec)
            if hasattr(est, "solve"):
                est.solve()


def build_target(sc: Scenario) -> TargetRole:
    t = sc.target
    if sc.uav is not None:
        from .models_uav import StreamTarget

        return TargetRole(sc.run.ticks, StreamTarget(uav_stream(sc), sc.run.T), False, 2, T=sc.run.T)
    x0 = np.array(t.x0, float)
    rng = rng_for(sc.run.seed, "target", 0, "process_noise")
    if t.kind == "intelligent":
        Q = None if t.Q is None else sc.Qw
        model = IntelligentTarget(sc.A, t.ke, x0, B=sc.B if Q is not None else None, Q=Q,
                                  rng=rng if Q is not None else None)
    else:
        model = LinearTarget(sc.A, sc.B, sc.Qw, x0, rng)
    return TargetRole(sc.run.ticks, model, t.kind == "intelligent", sc.pos_dims, t.estimate_source, T=sc.run.T)


def build_sensor(sc: Scenario, i: int, design: dict[str, Any] | None = None, rejoin: bool = False):
    if sc.uav is not None:
        from .roles.uav import UavRole

        return UavRole(i, sc.run.ticks, sc.run.T, uav_stream(sc))
    est = make_estimator(sc, i, design or {})
    ctrl = None
    if sc.sensors.motion == "flocking":
        c = sc.control
        ctrl = FlockingController(c.kc, c.kr, c.kd, c.h1, c.h2, c.l1, c.l2, c.u_max)
    q0 = sc.initial_positions()[i]
    D = sc.D_of(i)
    meas = LinearSensor(sc.C_of(i), sc.R_of(i)) if D is None else DisturbedSensor(sc.C_of(i), D, sc.sensors.v_std)
    return SensorRole(i, sc.run.ticks, sc.run.T, est, meas,
                      rng_for(sc.run.seed, "agent", i, "measurement"), q0, None, ctrl, sc.pos_dims, rejoin,
                      seed=sc.run.seed)
