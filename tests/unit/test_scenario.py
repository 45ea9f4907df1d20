"""Scenario loading: the shipped scenarios validate; bad ones are rejected naming file, key and fix."""

import tomllib
from pathlib import Path

import pytest

from agent.scenario import ScenarioError, load_scenario

SCEN = Path(__file__).resolve().parents[2] / "scenarios"
SHIPPED = sorted(SCEN.glob("*.toml"))


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_shipped_scenarios_validate(path):
    sc = load_scenario(path)
    assert sc.sensors.n >= 1 and sc.run.ticks >= 1


def _write(tmp_path, base: str, edit) -> Path:
    text = (SCEN / base).read_text()
    text = edit(text)
    p = tmp_path / "bad.toml"
    p.write_text(text)
    return p


BAD = [
    # (base scenario, edit, expected key, words in the message)
    ("gu_hu_intelligent.toml", lambda t: t.replace("[sensors]\n", "[sensors]\ncolour = \"red\"\n"),
     "sensors.colour", "unknown key"),
    ("gu_hu_intelligent.toml", lambda t: t.replace("ticks = 1500", "ticks = \"many\""),
     "run.ticks", "expected an integer"),
    ("gu_hu_intelligent.toml", lambda t: t.replace("R = [[0.04, 0.0], [0.0, 0.04]]", "R = [[0.04, 0.0, 0.0]]"),
     "sensors.R", "2×2"),
    ("gu_hu_intelligent.toml", lambda t: t.replace("S = [[0.09, 0.0], [0.0, 0.09]]", "S = [[0.09, 0.0], [0.0, -0.09]]"),
     "estimator.S", "positive definite"),
    ("gu_hu_intelligent.toml", lambda t: t.replace("R = [[0.04, 0.0], [0.0, 0.04]]", "R = [[0.04, 0.1], [0.1, 0.04]]"),
     "sensors.R", "positive definite"),
    ("gu_hu_intelligent.toml", lambda t: t.replace("x0 = [0.0, 0.0, 1.0, 0.5]", "x0 = [0.0, 0.0, 1.0]"),
     "target.x0", "4 states"),
    ("gu_hu_intelligent.toml", lambda t: t.replace("[topology]", "[topologie]"), "topologie", "unknown table"),
    ("chen_switching.toml", lambda t: t.replace("b = [1.0, 1.0, 1.0]", "b = [0.0, 0.0, 0.0]")
     .replace("b = [1.0, 0.0, 0.0]", "b = [0.0, 0.0, 0.0]").replace("b = [1.0, 1.0, 0.0]", "b = [0.0, 0.0, 0.0]")
     .replace("b = [0.0, 0.0, 1.0]", "b = [0.0, 0.0, 0.0]"), "topology.graphs", "no graph of the schedule"),
    ("chen_switching.toml", lambda t: t.replace("edges = [[0, 1], [0, 2]]", "edges = [[0, 1], [0, 7]]"),
     "topology.graphs[1].edges[1]", "two different sensors"),
    ("chen_switching.toml", lambda t: t.replace("A = [[1.0, 0.1], [0.0, 1.0]]", "A = [[1.0, 0.1]]"),
     "target.A", "2×2"),
]


@pytest.mark.parametrize("base,edit,key,words", BAD, ids=[b[2] + ":" + b[3] for b in BAD])
def test_bad_scenarios_are_rejected_with_file_key_and_fix(tmp_path, base, edit, key, words):
    p = _write(tmp_path, base, edit)
    with pytest.raises(ScenarioError) as e:
        load_scenario(p)
    msg = str(e.value)
    assert e.value.key == key, msg
    assert str(p) in msg and f"[{key}]" in msg and words in msg, msg
    assert "fix:" in msg or "expected" in msg, msg


def test_missing_file_and_invalid_toml(tmp_path):
    with pytest.raises(ScenarioError, match="cannot read"):
        load_scenario(tmp_path / "nope.toml")
    p = tmp_path / "x.toml"
    p.write_text("[run\n")
    with pytest.raises(ScenarioError, match="not valid TOML"):
        load_scenario(p)


def test_shipped_scenarios_are_valid_toml_with_comments_on_choices():
    for p in SHIPPED:
        tomllib.loads(p.read_text())
        assert "#" in p.read_text(), f"{p.name} must record why its parameters were chosen"
