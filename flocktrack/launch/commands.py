"""The command line of each of a host's nodes: what the launcher spawns for the run plan.

A node's command is its plan entry's ``python -m MODULE ARGS`` with the run's input files (``--scenario``,
``--design``, ``--meta``, the plan), this host's router (``--connect``), the run's name (``--run``) and, in a
secure run, the node's own identity (``--config``); a child is that command with its log file, its restart
policy and, for a sensor, the flag a restart adds (``--rejoin``).
"""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from flocktrack.plan.model import Node, RestartPolicy, RunPlan
from flocktrack.resources import config_file

MESH_CLIENT = "mesh/client.json5"   # a mesh host's processes (broker_cfg/mesh/client.json5)


@dataclass(frozen=True)
class RunInputs:
    """The files a run's nodes read (``flocktrack.engine.run.write_inputs``): the resolved scenario, the
    pre-run design, the recorder's metadata and the plan itself."""

    scenario: Path
    design: Path | None = None
    meta: Path | None = None
    plan: Path | None = None


@dataclass(frozen=True)
class LaunchOptions:
    """How one launcher runs its host's share of a plan. ``host``: which host of the plan this is (default
    its first); ``port``: its router's port (default: a free one; with a placement: the host's);
    ``keys``: a :class:`flocktrack.deploy.keys.KeySet` — TLS + mTLS + user/password with the ACL, every
    child with its own identity's config; ``startup_timeout_s``: how long the run waits for every host's
    members before it gives up."""

    run_dir: Path
    inputs: RunInputs
    host: str | None = None
    port: int | None = None
    quiet: bool = False
    verbose: bool = False
    dashboard_port: int | None = None
    dashboard_token: str | None = None
    keys: object | None = None
    startup_timeout_s: float = 90.0


@dataclass
class Child:
    name: str
    argv: list[str]
    policy: RestartPolicy
    log_path: Path
    proc: subprocess.Popen | None = None
    restarts: int = 0
    exits: list[int] = field(default_factory=list)
    restart_at: float | None = None
    rejoin_flag: str | None = None
    seen_exit: int | None = None
    hold: bool = False  # killed on request (control/kill): stays down until control/restart
    service: bool = False  # runs until stopped (a mesh host's router): the end of the run does not wait for it

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc else None


@dataclass(frozen=True)
class Commands:
    """The commands of the nodes the plan places on ``host``, dialling ``endpoint``."""

    plan: RunPlan
    opts: LaunchOptions
    host: str
    endpoint: str

    def _common(self) -> list[str]:
        return ["--connect", self.endpoint, "--run", self.plan.run]

    def argv(self, node: Node) -> list[str]:
        """The command line of one of the plan's nodes on this host."""
        ins = self.opts.inputs
        files = {"scenario": ins.scenario, "design": ins.design, "meta": ins.meta}
        argv = [sys.executable, "-m", node.module, *node.args]
        for what in node.inputs:
            if what == "mode":
                argv += ["--mode", self.plan.mode]
            elif files.get(what) is not None:
                argv += [f"--{what}", str(files[what])]
        if node.kind == "recorder":
            argv += ["--out", str(self.opts.run_dir / "recording.mcap"), "--name", node.name]
        if node.kind in ("recorder", "dashboard") and ins.plan is not None:
            argv += ["--plan", str(ins.plan)]
        if node.kind == "world":
            argv += ["--startup-timeout", str(self.opts.startup_timeout_s + 30)]
        if node.kind == "dashboard":
            argv += ["--port", str(self.opts.dashboard_port), *self._dashboard_access()]
        argv += self._common()
        if self.opts.keys is not None:
            cfg = self.opts.keys.client(node.slug)
            if cfg.exists():
                argv += ["--config", str(cfg)]
        elif self.plan.multi_host:   # a mesh host's processes: short leases, so a cut host is noticed
            argv += ["--config", str(config_file(MESH_CLIENT))]
        return argv

    def _dashboard_access(self) -> list[str]:
        who = ["--viewer-only"]
        if self.opts.dashboard_token:
            from dashboards.operator import write_token

            write_token(self.opts.run_dir / "dashboard_token", self.opts.dashboard_token)
            who = ["--operator-token-file", str(self.opts.run_dir / "dashboard_token")]
        if self.opts.keys is not None:   # a secure run's page is HTTPS with a certificate of the run's CA
            who += [a for flag, f in zip(("--tls-cert", "--tls-key"), self.opts.keys.web_cert()) for a in (flag, str(f))]
        return who

    def children(self) -> list[Child]:
        """This host's children, one per process of the plan on it (the dashboard only with a port)."""
        kids = []
        for node in self.plan.processes(self.host):
            if node.kind == "dashboard" and self.opts.dashboard_port is None:
                continue
            kids.append(Child(node.name, self.argv(node), node.restart, self.opts.run_dir / "logs" / f"{node.slug}.log",
                              rejoin_flag="--rejoin" if node.kind == "agent" else None,
                              service=node.kind == "dashboard"))
        return kids

