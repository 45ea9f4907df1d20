"""What a published package holds, checked against the source tree: one version everywhere, the license,
every router config and scenario in the package data (and read from there, not from the checkout), the
bundled scenarios by name, and the one-line errors of the resource look-ups."""

from __future__ import annotations

import argparse
import fnmatch
import re
import tomllib
from pathlib import Path

import pytest
import yaml

import flocktrack
from flocktrack import resources
from flocktrack.cli import RUN_OUTPUTS, main

ROOT = Path(__file__).resolve().parents[2]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
PRODUCT = ("agent", "topology", "dashboards", "flocktrack")


def test_one_version_everywhere():
    version = PYPROJECT["project"]["version"]
    assert flocktrack.__version__ == version
    assert yaml.safe_load((ROOT / "CITATION.cff").read_text())["version"] == version
    assert f"## [{version}]" in (ROOT / "CHANGELOG.md").read_text()


def test_license_is_declared_as_an_spdx_expression():
    assert PYPROJECT["project"]["license"] == "MIT"
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    assert PYPROJECT["project"]["license-files"] == ["LICENSE"]


def test_citation_references_the_four_papers():
    refs = yaml.safe_load((ROOT / "CITATION.cff").read_text())["references"]
    titles = " | ".join(r["title"] for r in refs)
    for words in ("Minimax Filter for Tracking and Flocking", "Cooperative Robust Estimation",
                  "Switching Multi-agent Network", "Impulsive Noise"):
        assert words in titles


def test_every_config_and_scenario_is_package_data():
    """The package-data globs of pyproject.toml cover every file of broker_cfg/ and scenarios/, and the
    package's data folders are the top-level ones (links), so the wheel ships what the checkout has."""
    globs = PYPROJECT["tool"]["setuptools"]["package-data"]["flocktrack"]
    for top in ("broker_cfg", "scenarios"):
        link = ROOT / "flocktrack" / "data" / top
        assert link.is_symlink() and link.resolve() == (ROOT / top).resolve()
        for f in (ROOT / top).rglob("*"):
            if f.is_file():
                rel = f"data/{top}/{f.relative_to(ROOT / top).as_posix()}"
                assert any(fnmatch.fnmatch(rel, g) for g in globs), f"{rel} is not package data"


def test_no_product_module_reads_files_relative_to_the_checkout():
    bad = []
    for pkg in PRODUCT:
        for p in (ROOT / pkg).rglob("*.py"):
            for n, line in enumerate(p.read_text().splitlines(), 1):
                if re.search(r"__file__\)\.resolve\(\)\.parents\[|parents\[1\]", line):
                    bad.append(f"{p.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not bad, "\n".join(bad)


def test_resources_come_from_the_package():
    assert resources.broker_config("local.json5").read_text() == (ROOT / "broker_cfg" / "local.json5").read_text()
    assert set(resources.scenario_names()) == {p.stem for p in (ROOT / "scenarios").glob("*.toml")}
    assert resources.config_file("mesh/client.json5").name == "client.json5"
    with pytest.raises(FileNotFoundError, match="it ships: .*local.json5"):
        resources.config_file("nonesuch.json5")
    with pytest.raises(resources.MissingDataError, match="pip install --force-reinstall flocktrack"):
        resources.broker_config("nonesuch.json5")


@pytest.mark.parametrize("given", ["demo", "demo.toml", "scenarios/demo.toml"])
def test_a_bundled_scenario_by_name(given, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)   # nothing called demo here: the package's
    assert Path(resources.resolve_scenario(given)) == resources.scenario_dir() / "demo.toml"
    (tmp_path / "demo.toml").write_text("# mine\n")
    if given == "demo.toml":      # a file that exists wins over the bundled name
        assert resources.resolve_scenario(given) == "demo.toml"


def test_an_unknown_scenario_names_the_bundled_ones():
    with pytest.raises(argparse.ArgumentTypeError) as e:
        resources.scenario_arg("gu_hu_normall")
    msg = str(e.value)
    assert "did you mean 'gu_hu_normal'?" in msg and "demo" in msg and "a path to a .toml file works too" in msg


def test_every_bundled_scenario_describes_itself_in_one_line(capsys):
    assert main(["scenarios"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.strip()]
    assert [ln.split()[0] for ln in lines] == resources.scenario_names()
    for name in resources.scenario_names():
        d = resources.scenario_description(name)
        assert 20 < len(d) <= 120 and not d.endswith((",", ":")), (name, d)


def test_scenarios_show_prints_the_file(capsys):
    assert main(["scenarios", "show", "chen_switching"]) == 0
    assert capsys.readouterr().out == (ROOT / "scenarios" / "chen_switching.toml").read_text()
    assert main(["scenarios", "show", "nonesuch"]) == 2
    assert "bundled:" in capsys.readouterr().err


def test_the_run_outputs_named_are_the_readmes():
    text = (ROOT / "README.md").read_text()
    table = text[text.index("### Outputs"):text.index("With `--dashboard` the directory also holds")]
    named = set(re.findall(r"^\| `([^`]+)` \|", table, flags=re.M))
    assert named | {"dashboard_token"} == set(RUN_OUTPUTS)
