"""Scenario → the agent-side roles (sensor i, target). Used by ``python -m agent`` and by the runtime.

Graph-wide designs (Chen's gain K) arrive precomputed in ``design`` (a JSON-able dict) — this module
never looks at the whole graph itself (DESIGN.md floors).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .control.flocking import FlockingController
from .estimators.registry import make_estimator
from .ports import Ports
from .models import DisturbedSensor, IntelligentTarget, LinearSensor, LinearTarget
from .roles.common import Role
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
    from .estimators.relative_measurement import RelativeMeasurement
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


def _flock_target(sc: Scenario) -> TargetRole:
    t = sc.target
    x0 = np.array(t.x0, float)
    rng = rng_for(sc.run.seed, "target", 0, "process_noise")
    if t.kind == "intelligent":
        Q = None if t.Q is None else sc.Qw
        model = IntelligentTarget(sc.A, t.ke, x0, B=sc.B if Q is not None else None, Q=Q,
                                  rng=rng if Q is not None else None)
    else:
        model = LinearTarget(sc.A, sc.B, sc.Qw, x0, rng)
    return TargetRole(sc.run.ticks, model, t.kind == "intelligent", sc.pos_dims, estimate_source=t.estimate_source,
                      T=sc.run.T)


def _flock_sensor(sc: Scenario, i: int, design: dict[str, Any], rejoin: bool) -> SensorRole:
    est = make_estimator(sc, i, design)
    ctrl = None
    if sc.sensors.motion == "flocking":
        c = sc.control
        ctrl = FlockingController(c.kc, c.kr, c.kd, c.h1, c.h2, c.l1, c.l2, c.u_max)
    q0 = sc.initial_positions()[i]
    D = sc.D_of(i)
    meas = LinearSensor(sc.C_of(i), sc.R_of(i)) if D is None else DisturbedSensor(sc.C_of(i), D, sc.sensors.v_std)
    return SensorRole(i, sc.run.ticks, sc.run.T, est, meas,
                      rng=rng_for(sc.run.seed, "agent", i, "measurement"), q0=q0, controller=ctrl,
                      pos_dims=sc.pos_dims, rejoin=rejoin, seed=sc.run.seed, catch_up=sc.run.mode == "realtime")


def _uav_target(sc: Scenario) -> TargetRole:
    from .models_uav import StreamTarget

    return TargetRole(sc.run.ticks, StreamTarget(uav_stream(sc), sc.run.T), False, 2, T=sc.run.T)


def _uav_sensor(sc: Scenario, i: int, design: dict[str, Any], rejoin: bool) -> Role:
    from .roles.uav import UavRole

    if sc.uav.fusion_mode == "distributed":
        return _uav_fusion_node(sc, i, rejoin)
    return UavRole(i, sc.run.ticks, sc.run.T, uav_stream(sc))


def _uav_fusion_node(sc: Scenario, i: int, rejoin: bool) -> Role:
    """UAV i of ``[fusion] mode = "distributed"``: its own robust window, agreed by consensus ADMM."""
    from .estimators.registry import fusion_specs
    from .roles.uav import UavFusionNodeRole, UavTrack, track_records

    u = sc.uav.uav
    R, G = np.eye(2) * u.sigma_rel ** 2, np.eye(2) * u.sigma_gps ** 2
    name, est = next(iter(sc.uav.make_estimators(sc.source).items()))   # the [fusion] estimator: its keys
    track = UavTrack(uav_stream(sc), i, sc.run.T)
    a = sc.uav.admm()
    node = fusion_specs()[name].distributed(est, i, track_records(track, R, G), a["iterations"], a["rho"], sc.run.T)
    return UavFusionNodeRole(i, sc.run.ticks, sc.run.T, node, LinearSensor(sc.C_of(i), R), track=track,
                             rng=rng_for(sc.run.seed, "agent", i, "measurement"), rejoin=rejoin, seed=sc.run.seed,
                             catch_up=sc.run.mode == "realtime")


@dataclass(frozen=True)
class WorldKind:
    """How a kind of scenario (:attr:`agent.scenario.Scenario.kind`) becomes roles: its target, its
    sensor i, and the extra processes it needs beyond world, target and sensors (by process name)."""

    target: Callable[[Scenario], TargetRole]
    sensor: Callable[[Scenario, int, dict[str, Any], bool], Role]
    sensor_class: Callable[[Scenario], type[Role]]    #: the class of its sensors (its declared ports)
    extra: tuple[str, ...] = ()


def _uav_sensor_class(sc: Scenario) -> type[Role]:
    from .roles.uav import UavFusionNodeRole, UavRole

    return UavFusionNodeRole if sc.uav.fusion_mode == "distributed" else UavRole


def _extra_class(name: str) -> type[Role]:
    from .roles.fusion import FusionRole

    return {"fusion": FusionRole}[name]


KINDS: dict[str, WorldKind] = {
    "flock": WorldKind(_flock_target, _flock_sensor, lambda sc: SensorRole),
    "uav_fusion": WorldKind(_uav_target, _uav_sensor, _uav_sensor_class, extra=("fusion",)),
}


def build_target(sc: Scenario) -> TargetRole:
    """The target role of scenario ``sc``."""
    return KINDS[sc.kind].target(sc)


def build_sensor(sc: Scenario, i: int, design: dict[str, Any] | None = None, rejoin: bool = False) -> Role:
    """Sensor ``i`` of scenario ``sc`` (its estimator built with the runtime's pre-run ``design``)."""
    return KINDS[sc.kind].sensor(sc, i, design or {}, rejoin)


def extra_processes(sc: Scenario) -> tuple[str, ...]:
    """The roles scenario ``sc`` runs beyond world, target and sensors (e.g. ``("fusion",)``)."""
    return KINDS[sc.kind].extra


def role_ports(sc: Scenario, kind: str) -> Ports:
    """What the agent-side role ``kind`` of scenario ``sc`` declares it writes and reads: ``agent`` (its
    sensors), ``target``, or one of :func:`extra_processes` (``{i}`` not yet filled in)."""
    if kind == "agent":
        return KINDS[sc.kind].sensor_class(sc).PORTS
    if kind == "target":
        return TargetRole.PORTS
    if kind in extra_processes(sc):
        return _extra_class(kind).PORTS
    raise ValueError(f"{sc.source} runs no {kind!r} role")


def role_host_ports(sc: Scenario) -> Ports | None:
    """What scenario ``sc``'s sensors add to their ports in a run placed on several hosts (``HOST_PORTS``:
    ``{i}`` and ``{host}`` not yet filled in), None when they exchange nothing."""
    return getattr(KINDS[sc.kind].sensor_class(sc), "HOST_PORTS", None)


def build_extra(sc: Scenario, name: str) -> Role:
    """One of :func:`extra_processes`' roles."""
    if name == "fusion" and name in extra_processes(sc):
        return build_fusion(sc)
    raise ValueError(f"{sc.source} runs no {name!r} role (its extra roles: {', '.join(extra_processes(sc)) or 'none'})")
