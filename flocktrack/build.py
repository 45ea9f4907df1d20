"""Scenario → role objects. The only place that knows every role's constructor (floor 3).

:func:`design` computes, before the run, what needs the whole graph (Chen's gain K from λ₀ over all
switching graphs, the TMSEE lower bound (12)); :func:`build_roles` then makes the world, the target and
the sensors (and :func:`build_role` one of them, for a process of its own).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent.assemble import build_fusion, build_sensor, build_target
from agent.roles.common import Role
from agent.roles.sensor import SensorRole
from agent.roles.target import TargetRole
from agent.scenario import Scenario
from topology.world import WorldRole, build_world, schedule_of


def design(sc: Scenario) -> dict[str, Any]:
    """Graph-wide, pre-run design parameters handed to every sensor (JSON-serialisable)."""
    e = sc.estimator
    out: dict[str, Any] = {}
    if e.name == "min_energy":
        out["min_energy"] = min_energy_design(sc).to_dict()
    if e.name == "hinf_switching":
        from agent.estimators.hinf_switching import constant_gain, tmsee_lower_bound

        sch = schedule_of(sc)
        if sch is not None:
            H = sch.H_list()
        else:
            H = [np.eye(1) * float(e.lambda0)]
        Rd = np.eye(sc.C.shape[0]) if e.R_design is None else np.array(e.R_design, float)
        Qd = sc.filter_Q() if e.Q_design is None else np.array(e.Q_design, float)
        K = constant_gain(sc.A, sc.C, Qd, Rd, e.gamma, H)
        out["K"] = np.asarray(K, float).tolist()
        if sch is not None:
            Rn = sc.R + (np.zeros_like(sc.R) if e.comm_noise is None else np.array(e.comm_noise, float))
            Qw = sc.B @ sc.Qw @ sc.B.T
            off = np.zeros((sc.sensors.n, sc.m)) if e.x0_offsets is None else np.array(e.x0_offsets, float)
            Z0 = np.zeros((sc.sensors.n * sc.m, sc.sensors.n * sc.m))
            for i in range(sc.sensors.n):
                sl = slice(i * sc.m, (i + 1) * sc.m)
                Z0[sl, sl] = np.outer(off[i], off[i])
            H_seq = [sch.at(k).H() for k in range(sc.run.ticks)]
            out["tmsee_lower"] = np.asarray(
                tmsee_lower_bound(sc.A, sc.C, Qw, Rn, e.gamma, H_seq, Z0), float)[: sc.run.ticks].tolist()
    return out


def min_energy_design(sc: Scenario):
    """The SDP (29) design of Zamani & Ugrinovskii for the scenario: loaded from estimator.design_file
    (checked against the scenario's problem data) or solved now (supremum γ*², then a well-centred
    point at γ² = gamma2_factor·γ*² that the filters run on)."""
    import json
    from pathlib import Path

    from agent.estimators.min_energy import MinEnergyDesign, design_network, make_problem

    e, s = sc.estimator, sc.sensors
    Cs = [sc.C_of(i) for i in range(s.n)]
    Ds = [sc.D_of(i) for i in range(s.n)]
    edges = [tuple(x) for x in e.edges]
    Ac, Bc = np.array(sc.target.A, float), np.array(sc.target.B, float)
    W = np.array(e.W, float)
    F = np.array(e.F, float)
    W = list(W) if W.ndim == 3 else W
    F = list(F) if F.ndim == 3 else F
    if e.design_file:
        path = Path(e.design_file)
        if not path.is_absolute():
            path = Path(sc.source).parent / path
        dsg = MinEnergyDesign.from_dict(json.loads(path.read_text()))
        prob = make_problem(Ac, Bc, Cs, Ds, W, F, edges, P=e.P)
        if not dsg.problem.matches(prob):
            from agent.scenario import ScenarioError

            raise ScenarioError(sc.source, "estimator.design_file", f"{path} was designed for other problem data",
                                "re-run `flocktrack design` for this scenario")
        return dsg
    return design_network(Ac, Bc, Cs, Ds, W, F, edges, P=e.P, zbar_min=e.zbar_min, margin=e.margin,
                          solver=e.solver, gamma2_factor=e.gamma2_factor, centre=e.centre)


@dataclass
class Roles:
    world: WorldRole
    target: TargetRole
    sensors: list[SensorRole]
    design: dict[str, Any] = field(default_factory=dict)
    extra: list[Role] = field(default_factory=list)   #: fusion

    def all(self) -> list[Role]:
        return [self.world, self.target, *self.sensors, *self.extra]


def build_roles(sc: Scenario, dsg: dict[str, Any] | None = None) -> Roles:
    dsg = design(sc) if dsg is None else dsg
    extra = [build_fusion(sc)] if sc.uav is not None else []
    return Roles(build_world(sc), build_target(sc), [build_sensor(sc, i, dsg) for i in range(sc.sensors.n)], dsg,
                 extra)
