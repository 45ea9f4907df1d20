"""The run plan: every node of a run, where it runs, what it writes and reads, how it is restarted.

A :class:`RunPlan` is one frozen value built from a scenario and an optional placement
(:func:`flocktrack.plan.build.build_plan`). The launcher spawns its nodes, the in-process engine wires the
same roles on one bus, ``flocktrack compose`` writes one service per node, the secure mode's access-control
list grants each node exactly its declared keys, the recorder subscribes to the union of the writes, and
``flocktrack plan`` prints it.

A node has one name, ``KIND/ID`` (``agent/3``, ``world/0``, ``router/a``): its liveliness token
(``ft/<run>/alive/agent/3``), its key prefix (``ft/<run>/agent/3/…``), its dashboard label. Where a slash is
not allowed — a compose service, a log or stats file, a certificate's common name and the ACL subject — it is
written ``KIND-ID`` (:attr:`Node.slug`: ``agent-3``, ``world-0``).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field

from agent.ports import slug


@dataclass(frozen=True)
class RestartPolicy:
    """What happens when a node's process exits (dora-rs style, declared rather than coded):

    * ``never``       — a process that dies stays dead (the world treats it as a node with no links);
    * ``on-failure``  — a process that exits non-zero or is killed is restarted, at most ``max_restarts``
      times, after ``backoff_s`` × 2^(attempt−1) seconds (a restarted sensor rejoins the running flock);
    * ``always``      — a service (a router): restarted whenever it exits until the run is stopped."""

    mode: str = "never"          # "never" | "on-failure" | "always"
    max_restarts: int = 3
    backoff_s: float = 0.5

    def delay(self, attempt: int) -> float:
        return self.backoff_s * (2 ** max(0, attempt - 1))


@dataclass(frozen=True)
class Host:
    """A machine of the run: its name, the address the other hosts' routers dial it by, its router's port,
    and the address its router listens on (default every interface with a placement, loopback without)."""

    name: str
    address: str = "127.0.0.1"
    port: int = 7447
    listen: str | None = None

    @property
    def endpoint(self) -> str:
        return f"tcp/{self.address}:{self.port}"


@dataclass(frozen=True)
class Node:
    """One process of the run (see the module docstring for its name)."""

    name: str
    kind: str                      #: agent | target | world | fusion | recorder | dashboard | launcher | router
    host: str
    writes: tuple[str, ...] = ()   #: key expressions it puts, relative to ft/<run>/
    reads: tuple[str, ...] = ()    #: key expressions it subscribes to
    restart: RestartPolicy = field(default_factory=RestartPolicy)
    module: str = ""               #: ``python -m MODULE`` (empty: not a process of its own — the launcher)
    args: tuple[str, ...] = ()     #: the role's own arguments (``sensor --id 3``)
    inputs: tuple[str, ...] = ()   #: the run inputs it reads: scenario, design, meta
    member: bool = True            #: it declares a liveliness token (and the world's start waits for it)
    observer: bool = False         #: a read-only observer, run at a lower scheduling priority

    @property
    def id(self) -> str:
        return self.name.split("/", 1)[1]

    @property
    def slug(self) -> str:
        return slug(self.name)


@dataclass(frozen=True)
class RunPlan:
    """Every node of a run, on its hosts (the first host is the one without a placement: ``local``)."""

    run: str
    scenario: str
    mode: str
    nodes: tuple[Node, ...]
    hosts: tuple[Host, ...]
    placement: str | None = None   #: the placement file it was built with

    def node(self, name: str) -> Node:
        for n in self.nodes:
            if n.name == name:
                return n
        raise KeyError(name)

    def names(self) -> list[str]:
        return [n.name for n in self.nodes]

    def of_kind(self, kind: str) -> list[Node]:
        return [n for n in self.nodes if n.kind == kind]

    def on(self, host: str) -> list[Node]:
        """The nodes placed on ``host``."""
        return [n for n in self.nodes if n.host == host]

    def host(self, name: str) -> Host:
        for h in self.hosts:
            if h.name == name:
                return h
        raise KeyError(name)

    @property
    def multi_host(self) -> bool:
        return len(self.hosts) > 1

    def processes(self, host: str | None = None) -> list[Node]:
        """The nodes a launcher spawns (on ``host``; all hosts when None): each with a module of its own,
        routers aside (the launcher's router is embedded)."""
        return [n for n in self.nodes if n.module and n.kind != "router" and (host is None or n.host == host)]

    def observed(self, host: str | None = None) -> list[str]:
        """What an observer subscribes to so that it sees every payload once: the union of the writes (of the
        nodes on ``host``), without the addressed copies (``…/to/<j>/…``, ``…/via/<host>/…``) of what a node
        also puts for observers."""
        from agent.wire import addressed

        keys: dict[str, None] = {}
        for n in self.nodes:
            if host is None or n.host == host:
                keys.update((w, None) for w in n.writes if not addressed(w))
        return list(keys)

    def world_expects(self) -> list[str]:
        """The members the world waits for before tick 0 beyond the sensors and the target (which it always
        waits for): launchers, recorders, the fusion solver."""
        return [n.name for n in self.nodes if n.member and n.kind not in ("agent", "target", "world", "dashboard",
                                                                           "router")]

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict:
        nodes = []
        for n in self.nodes:
            d = asdict(n)
            d["restart"] = asdict(n.restart)
            d["writes"], d["reads"], d["args"], d["inputs"] = list(n.writes), list(n.reads), list(n.args), list(n.inputs)
            nodes.append(d)
        return {"run": self.run, "scenario": self.scenario, "mode": self.mode, "placement": self.placement,
                "hosts": [asdict(h) | {"endpoint": h.endpoint} for h in self.hosts], "nodes": nodes}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1) + "\n"

    @classmethod
    def from_dict(cls, d: dict) -> RunPlan:
        nodes = tuple(Node(**{**n, "restart": RestartPolicy(**n["restart"]), "writes": tuple(n["writes"]),
                                 "reads": tuple(n["reads"]), "args": tuple(n["args"]), "inputs": tuple(n["inputs"])})
                      for n in d["nodes"])
        hosts = tuple(Host(**{k: v for k, v in h.items() if k != "endpoint"}) for h in d["hosts"])
        return cls(d["run"], d["scenario"], d["mode"], nodes, hosts, d.get("placement"))

    @classmethod
    def from_json(cls, text: str) -> RunPlan:
        return cls.from_dict(json.loads(text))
