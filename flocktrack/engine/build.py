"""Scenario → role objects. The only place that knows every role's constructor (floor 3).

:func:`design` computes, before the run, what needs the whole graph — the chosen estimator's design hook
given :func:`graph_facts` (e.g. Chen's gain K from λ₀ over all switching graphs and the TMSEE lower bound
(12), Zamani's SDP (29)); :func:`build_roles` then makes the world, the target and the sensors.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agent.assemble import build_extra, build_sensor, build_target, extra_processes
from agent.estimators.registry import specs
from agent.estimators.spec import GraphFacts
from agent.roles.common import Role
from agent.roles.sensor import SensorRole
from agent.roles.target import TargetRole
from agent.scenario import Scenario, ScenarioError
from topology.world import WorldRole, build_world, schedule_of


def graph_facts(sc: Scenario) -> GraphFacts:
    """What the runtime knows of the whole graph before the run (a schedule's H = L + B per graph and
    per tick), and how a design hook reads a stored design (relative to the scenario's directory)."""
    def stored(name: str) -> dict[str, Any]:
        path = Path(name) if Path(name).is_absolute() else Path(sc.source).parent / name
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise ScenarioError(sc.source, "estimator.design_file", f"cannot read {path} ({exc})",
                                "write it with `flocktrack design SCENARIO --out FILE`") from None

    sch = schedule_of(sc)
    if sch is None:
        return GraphFacts(stored=stored)
    H = sch.H_list()
    return GraphFacts(H_graphs=H, H_per_tick=[H[sch.index_at(k)] for k in range(sc.run.ticks)], stored=stored)


def design(sc: Scenario) -> dict[str, Any]:
    """Graph-wide, pre-run design parameters handed to every sensor (JSON-serialisable): the chosen
    estimator's design hook (its spec), if it has one."""
    spec = specs().get(sc.estimator.name)
    if spec is None or spec.design is None:
        return {}
    return spec.design(sc, sc.estimator.params, graph_facts(sc))


@dataclass
class Roles:
    world: WorldRole
    target: TargetRole
    sensors: list[SensorRole]
    design: dict[str, Any] = field(default_factory=dict)
    extra: list[Role] = field(default_factory=list)   #: fusion

    def all(self) -> list[Role]:
        return [self.world, self.target, *self.sensors, *self.extra]


def build_roles(sc: Scenario, dsg: dict[str, Any] | None = None, plan=None) -> Roles:
    """The role objects of the run plan's flock nodes (its sensors, target, world and extra roles), for one
    process on LocalBus: the same nodes the launcher spawns one process each for."""
    from flocktrack.plan.build import flock_nodes

    dsg = design(sc) if dsg is None else dsg
    nodes = plan.nodes if plan is not None else flock_nodes(sc)
    extras = set(extra_processes(sc))
    sensors = [build_sensor(sc, int(n.id), dsg) for n in nodes if n.kind == "agent"]
    extra = [build_extra(sc, n.kind) for n in nodes if n.kind in extras]
    return Roles(build_world(sc), build_target(sc), sensors, dsg, extra)
