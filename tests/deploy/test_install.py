"""The product as a user installs it: a wheel built from this tree, installed into a fresh virtual
environment (the core dependencies only, no extras), run from an empty directory — nothing of the
checkout is on its path. Over Zenoh (real router, real processes), secured, as compose files, the
pre-run design; the one-line errors of a wrong name and of a missing extra; and an estimator from a
package outside the tree (``tests/plugin/``, built on the fly) found through its entry point, in one
process and over Zenoh."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from compose_schema import validate

ROOT = Path(__file__).resolve().parents[2]
PLUGIN = ROOT / "tests" / "plugin"

pytestmark = pytest.mark.slow


def _pip(venv: Path, *args: str, timeout: float = 900) -> None:
    r = subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q", "--disable-pip-version-check", *args],
                       capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, r.stdout + r.stderr


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(venv, empty working directory): the wheel of this tree, installed with its core dependencies."""
    base = tmp_path_factory.mktemp("install")
    dist = base / "dist"
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(dist), str(ROOT)],
                       capture_output=True, text=True, timeout=600, cwd=base)
    assert r.returncode == 0, r.stdout + r.stderr
    (wheel,) = dist.glob("flocktrack-*.whl")
    venv = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    _pip(venv, str(wheel))
    work = base / "work"
    work.mkdir()
    return venv, work


def ft(installed, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """``flocktrack ARGS`` of the installed package, in the empty directory, with no trace of the checkout."""
    venv, work = installed
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    return subprocess.run([str(venv / "bin" / "flocktrack"), *args], cwd=work, env=env, capture_output=True,
                          text=True, timeout=timeout, stdin=subprocess.DEVNULL)


def listed_outputs(r: subprocess.CompletedProcess, work: Path) -> tuple[Path, list[str]]:
    """The run directory and the files its final line names (``results in DIR/: a, b, …``)."""
    m = re.search(r"^results in (.+?)/: (.+)$", r.stdout, flags=re.M)
    assert m, r.stdout + r.stderr
    return work / m.group(1), m.group(2).split(", ")


def test_version_is_the_package_metadata(installed):
    venv, _ = installed
    r = ft(installed, "--version")
    assert r.returncode == 0 and re.fullmatch(r"flocktrack \d+\.\d+\.\d+\S*\n", r.stdout), r.stdout + r.stderr
    meta = subprocess.run([str(venv / "bin" / "python"), "-c", "import flocktrack, importlib.metadata as m; "
                           "print(flocktrack.__version__, m.version('flocktrack'))"],
                          capture_output=True, text=True, check=True).stdout.split()
    assert meta[0] == meta[1] == r.stdout.split()[1]


def test_the_bundled_scenarios_are_listed_and_shown(installed):
    r = ft(installed, "scenarios")
    assert r.returncode == 0
    names = [line.split()[0] for line in r.stdout.splitlines() if line.strip()]
    assert {"demo", "gu_hu_normal", "chen_switching", "zamani_chua", "carrillo_uav"} <= set(names)
    assert all(len(line.split(maxsplit=1)) == 2 for line in r.stdout.splitlines() if line.strip())   # a description each
    shown = ft(installed, "scenarios", "show", "demo")
    assert shown.returncode == 0 and "[sensors]" in shown.stdout
    (installed[1] / "mine.toml").write_text(shown.stdout)
    assert ft(installed, "validate", "mine.toml").returncode == 0   # what `show NAME > my.toml` starts from


def test_main_job_over_zenoh_from_an_empty_directory(installed):
    _, work = installed
    r = ft(installed, "run", "demo", "--ticks", "20", "--quiet")   # the main job as it is: realtime, 25 ticks/s
    assert r.returncode == 0, r.stdout + r.stderr
    out, listed = listed_outputs(r, work)
    assert out.parent == work / "runs" and out.name.startswith("demo-")
    assert {"summary.json", "recording.mcap", "events.json", "logs/", "stats/"} <= set(listed)
    assert all((out / name.rstrip("/")).exists() for name in listed), listed
    assert json.loads((out / "summary.json").read_text())["ticks_seen"] == 20
    assert len(list((out / "logs").glob("agent-*.log"))) == 12


def test_realtime_run_secured(installed):
    _, work = installed
    r = ft(installed, "run", "demo", "--secure", "--ticks", "10", "--out", "secure", "--quiet")
    assert r.returncode == 0, r.stdout + r.stderr
    out, listed = listed_outputs(r, work)
    assert all((out / name.rstrip("/")).exists() for name in listed), listed
    assert (work / "secure" / "keys" / "ca.pem").is_file()
    assert json.loads((out / "run.json").read_text())["transport"] == "zenoh"


def test_in_process_run_names_only_what_it_wrote(installed):
    _, work = installed
    r = ft(installed, "run", "gu_hu_normal", "--transport", "inproc", "--ticks", "10", "--out", "inproc")
    assert r.returncode == 0, r.stdout + r.stderr
    out, listed = listed_outputs(r, work)
    assert "events.json" not in listed and "logs/" not in listed and "summary.json" in listed
    assert all((out / name.rstrip("/")).exists() for name in listed), listed


def test_compose_outside_a_checkout_writes_a_release_deployment(installed):
    _, work = installed
    r = ft(installed, "compose", "demo", "--out", "c")
    assert r.returncode == 0, r.stdout + r.stderr
    doc = yaml.safe_load((work / "c" / "docker-compose.yml").read_text())
    validate(doc)
    assert len([s for s in doc["services"] if s.startswith("agent-")]) == 12
    assert all(s["build"]["context"] == "." for s in doc["services"].values())
    dockerfile = (work / "c" / "Dockerfile").read_text()
    version = ft(installed, "--version").stdout.split()[1]
    assert f'flocktrack[fusion]=={version}' in dockerfile and "COPY agent" not in dockerfile
    assert (work / "c" / "wheels" / "README").is_file()   # the Dockerfile's COPY has its directory
    assert doc["services"]["router-0"]["command"][-1] == "compose_router.json5"


def test_design_of_a_bundled_scenario(installed):
    _, work = installed
    r = ft(installed, "design", "chen_switching", "--out", "chen_design.json")
    assert r.returncode == 0, r.stdout + r.stderr
    K = json.loads((work / "chen_design.json").read_text())["K"]
    assert [round(v, 4) for v in sum(K, [])] == [0.9376, 0.5884]   # Chen et al., Theorem 3.3


@pytest.mark.parametrize("argv, extra", [(["design", "zamani_chua", "--out", "z.json"], "design"),
                                         (["validate", "carrillo_uav"], "fusion"),
                                         (["sweep", "gu_hu_normal", "--seeds", "1", "--out", "sw"], "figures"),
                                         (["export", "a-run", "--out", "tables"], "analysis")])
def test_a_missing_extra_is_one_line_naming_it(installed, argv, extra):
    r = ft(installed, *argv)
    assert r.returncode == 2
    assert f"pip install 'flocktrack[{extra}]'" in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_an_unknown_scenario_name_lists_the_bundled_ones(installed):
    r = ft(installed, "run", "demoo")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert "did you mean 'demo'?" in r.stderr and "gu_hu_normal" in r.stderr and "a path" in r.stderr


def test_a_missing_package_data_file_is_one_line(installed):
    """A broken install (its router config deleted): one line naming the file and the command that mends it."""
    venv, _ = installed
    cfg = next(venv.glob("lib/python*/site-packages/flocktrack/data/broker_cfg/local.json5"))
    saved = cfg.read_bytes()
    cfg.unlink()
    try:
        r = ft(installed, "run", "demo", "--ticks", "2", "--out", "broken")
    finally:
        cfg.write_bytes(saved)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert "broker_cfg/local.json5" in r.stderr and "pip install --force-reinstall flocktrack" in r.stderr


def test_an_estimator_from_an_installed_plug_in_package(installed):
    """tests/plugin/ (the toy estimator with a ``flocktrack.estimators`` entry point), built and installed:
    ``--estimator toy_average`` runs in one process and over Zenoh with the same numbers, and its
    parameters are checked like a built-in estimator's."""
    venv, work = installed
    src = work.parent / "plugin"   # built from a copy: pip's build leaves build/ beside the sources
    shutil.copytree(PLUGIN, src, ignore=shutil.ignore_patterns("__pycache__", "build", "*.egg-info"))
    _pip(venv, "--no-deps", str(src))
    runs = {}
    for transport in ("inproc", "zenoh"):
        r = ft(installed, "run", "gu_hu_normal", "--estimator", "toy_average", "--transport", transport, "--mode",
               "lockstep", "--ticks", "30", "--out", f"toy_{transport}", "--quiet")
        assert r.returncode == 0, r.stdout + r.stderr
        runs[transport] = json.loads((work / f"toy_{transport}" / "summary.json").read_text())
    assert runs["inproc"]["network_rmse"] == runs["zenoh"]["network_rmse"]
    bad = ft(installed, "scenarios", "show", "gu_hu_normal").stdout.replace("[estimator]", "[estimator]\ngain = 2.5", 1)
    (work / "toy_bad.toml").write_text(bad)
    r = ft(installed, "run", "toy_bad.toml", "--estimator", "toy_average", "--transport", "inproc", "--ticks", "2")
    assert r.returncode == 2 and "estimator.gain" in r.stderr and "(0, 1]" in r.stderr, r.stderr
