"""Scenario (+ placement) → :class:`~flocktrack.plan.model.RunPlan`.

The reads and writes come from the roles themselves (``PORTS`` next to each role's code:
:mod:`agent.roles`, :mod:`topology.world`, the launcher, the dashboard's operator); this module only
says which roles a scenario runs, how each is started (``python -m MODULE ARGS``, the inputs it reads), its
restart policy, and where it goes.
"""

from __future__ import annotations

from dataclasses import replace

from agent.ports import Ports
from agent.wire import addressed
from agent.scenario import Scenario

from .model import Host, Node, RestartPolicy, RunPlan
from .placement import Placement

#: the host of a run without a placement
LOCAL = Host("local")
NEVER = RestartPolicy("never")
END = "world/end"
CONTROL = "control/**"    #: the control plane (written by the dashboard and by `flocktrack fault`)


def _node(name: str, kind: str, ports: Ports, module: str, *args: str, inputs: tuple[str, ...] = (),
          restart: RestartPolicy = NEVER, member: bool = True, observer: bool = False) -> Node:
    p = ports.of(int(name.split("/")[1])) if name.split("/")[1].isdigit() else ports
    return Node(name, kind, "", p.writes, p.reads, restart, module, tuple(args), inputs, member, observer)


def flock_nodes(sc: Scenario, *, dashboard: bool = False, sensor_restart: RestartPolicy = NEVER) -> list[Node]:
    """The nodes of the scenario itself, each once: its sensors, target, world, extra roles and dashboard."""
    from agent.assemble import extra_processes, role_ports
    from dashboards.operator import PORTS as DASHBOARD_PORTS
    from topology.world import WorldRole

    sensor = role_ports(sc, "agent")
    nodes = [_node(f"agent/{i}", "agent", sensor, "agent", "sensor", "--id", str(i),
                   inputs=("scenario", "design", "mode"), restart=sensor_restart) for i in range(sc.sensors.n)]
    nodes.append(_node("target/0", "target", role_ports(sc, "target"), "agent", "target", inputs=("scenario", "mode")))
    for extra in extra_processes(sc):
        nodes.append(_node(f"{extra}/0", extra, role_ports(sc, extra), "agent", extra, inputs=("scenario", "mode")))
    nodes.append(_node("world/0", "world", WorldRole.PORTS, "topology", inputs=("scenario", "mode")))
    if dashboard:
        nodes.append(_node("dashboard/0", "dashboard", DASHBOARD_PORTS, "dashboards", inputs=("scenario",),
                           restart=RestartPolicy("on-failure", 3), observer=True))
    return nodes


def host_nodes(host: str, single: bool, *, record: bool, supervisor: bool) -> list[Node]:
    """What every host has of its own: a router, a launcher (``supervisor``) and a recorder (``record``);
    named ``KIND/0`` on the one host of a run without a placement, ``KIND/HOST`` else."""
    from flocktrack.launch.launcher import PORTS as LAUNCHER_PORTS

    ident = "0" if single else host
    nodes = [_node(f"router/{ident}", "router", Ports(), "flocktrack.launch.router", restart=RestartPolicy("always"),
                   member=False)]
    if supervisor:
        nodes.append(_node(f"launcher/{ident}", "launcher", LAUNCHER_PORTS, ""))
    if record:
        nodes.append(_node(f"recorder/{ident}", "recorder", Ports(), "flocktrack.record", inputs=("meta",),
                           observer=True))
    return nodes


def build_plan(sc: Scenario, *, run: str | None = None, placement: Placement | None = None, record: bool = True,
               dashboard: bool = False, supervisor: bool = True,
               sensor_restart: RestartPolicy = NEVER) -> RunPlan:
    """The plan of scenario ``sc``: its nodes (:func:`flock_nodes`), placed by ``placement`` (all on one
    host without), and each host's router, launcher (``supervisor``: not in a compose deployment) and
    recorder (``record``). The recorder of a host subscribes to what that host's nodes write; the world's
    start waits for every launcher, recorder and extra role (``--expect``)."""
    from agent.assemble import extra_processes

    hosts = placement.hosts if placement is not None else (LOCAL,)
    flock = flock_nodes(sc, dashboard=dashboard, sensor_restart=sensor_restart)
    where = placement.assign([n.name for n in flock]) if placement is not None else {}
    placed = [replace(n, host=where.get(n.name, hosts[0].name)) for n in flock]
    single = placement is None
    if not single:
        placed = _routed_by_host(sc, placed)
    for h in hosts:
        placed += [replace(n, host=h.name) for n in host_nodes(h.name, single, record=record, supervisor=supervisor)]
    placed = _ordered(_with_observers(placed, multi=not single))
    expects = [n.name for n in placed if n.member and n.kind in ("launcher", "recorder", *extra_processes(sc))]
    placed = [replace(n, args=n.args + tuple(a for e in expects for a in ("--expect", e))) if n.kind == "world" else n
              for n in placed]
    name = run or (placement.run if placement is not None and placement.run else sc.run.name)
    return RunPlan(name, sc.source, sc.run.mode, tuple(placed), tuple(hosts),
                   placement.source if placement is not None else None)



def _routed_by_host(sc: Scenario, nodes: list[Node]) -> list[Node]:
    """A run on several hosts: each sensor is told every sensor's host (``--hosts``) and sends a payload to
    another host once, for all its hearers there (agent/roles/routes.py) — its role's ``HOST_PORTS``, with
    ``{host}`` its own."""
    from agent.assemble import role_host_ports
    from agent.roles.routes import format_hosts

    extra = role_host_ports(sc)
    sensors = {int(n.id): n.host for n in nodes if n.kind == "agent"}
    if extra is None or not sensors:
        return nodes
    spec = format_hosts([sensors[i] for i in range(len(sensors))])
    out = []
    for n in nodes:
        if n.kind == "agent":
            p = extra.of(int(n.id)).on_host(n.host)
            n = replace(n, writes=n.writes + p.writes, reads=n.reads + p.reads, args=n.args + ("--hosts", spec))
        out.append(n)
    return out


def _with_observers(nodes: list[Node], multi: bool) -> list[Node]:
    """Observers read what the others write: a recorder what its own host's nodes write (the recorder shards
    of a placement, merged by ``flocktrack merge``), the dashboard everything."""
    out = []
    for n in nodes:
        if n.kind in ("recorder", "dashboard"):
            mine = [m for m in nodes if m.kind not in ("recorder", "dashboard") and (
                n.kind == "dashboard" or not multi or m.host == n.host)]
            reads: dict[str, None] = {}
            for m in mine + ([n] if n.kind == "dashboard" else []):
                reads.update((w, None) for w in m.writes if not addressed(w))
            if any(m.kind == "world" for m in mine):
                # the control plane: the dashboard's and `flocktrack fault`'s, on the world's timeline
                reads[CONTROL] = None
            reads[END] = None   # every recorder shard stops at the end (the merge keeps one copy)
            n = replace(n, reads=tuple(compact(list(reads), nodes)))
        out.append(n)
    return out


def compact(keys: list[str], nodes: list[Node]) -> list[str]:
    """``keys`` with ``KIND/<id>/rest`` for every node of that kind written once, as ``KIND/*/rest`` (one
    subscription instead of one per sensor)."""
    ids: dict[str, set[str]] = {}
    for n in nodes:
        ids.setdefault(n.kind, set()).add(n.id)
    seen: dict[tuple[str, str], set[str]] = {}
    for k in keys:
        kind, _, rest = k.partition("/")
        ident, _, tail = rest.partition("/")
        if tail and ident in ids.get(kind, ()):
            seen.setdefault((kind, tail), set()).add(ident)
    out: dict[str, None] = {}
    for k in keys:
        kind, _, rest = k.partition("/")
        ident, _, tail = rest.partition("/")
        if tail and seen.get((kind, tail)) == ids.get(kind) and len(ids[kind]) > 1:
            out[f"{kind}/*/{tail}"] = None
        else:
            out[k] = None
    return list(out)


_ORDER = ("router", "launcher", "recorder", "dashboard", "agent", "target", "fusion", "world")


def _ordered(nodes: list[Node]) -> list[Node]:
    """Start order: routers, launchers, recorders and the dashboard first (so they see everything), then the
    flock, the world last (its tick 0 waits for the others anyway)."""
    def key(n: Node):
        kind = _ORDER.index(n.kind) if n.kind in _ORDER else _ORDER.index("fusion")
        return kind, int(n.id) if n.id.isdigit() else 0, n.name
    return sorted(nodes, key=key)

