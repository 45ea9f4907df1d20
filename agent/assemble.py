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


def build_target(sc: Scenario) -> TargetRole:
    t = sc.target
    x0 = np.array(t.x0, float)
    rng = rng_for(sc.run.seed, "target", 0, "process_noise")
    if t.kind == "intelligent":
        Q = None if t.Q is None else sc.Qw
        model = IntelligentTarget(sc.A, t.ke, x0, B=sc.B if Q is not None else None, Q=Q,
                                  rng=rng if Q is not None else None)
    else:
        model = LinearTarget(sc.A, sc.B, sc.Qw, x0, rng)
    return TargetRole(sc.run.ticks, model, t.kind == "intelligent", sc.pos_dims, t.estimate_source, T=sc.run.T)


def build_sensor(sc: Scenario, i: int, design: dict[str, Any] | None = None, rejoin: bool = False) -> SensorRole:
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
