"""Recordings that Foxglove opens natively (flocktrack/record/foxglove.py) on the experiment's timeline
(flocktrack/record/writer.py): a fresh recording read by Foxglove's own TypeScript reader with CRCs
validated, every message decoded; log times are the ticks' simulated times in every mode; recordings of the
wall-clock kind still replay and score."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import pytest

from agent import wire
from agent.recording import read_recording
from dashboards.live import replay_model_from_file
from flocktrack.cli import main
from flocktrack.record.reader import metrics_from_recording
from flocktrack.record.writer import McapRecorder

from mcap_js import foxglove_read

ROOT = Path(__file__).resolve().parents[2]
SCEN = ROOT / "scenarios"
VIEWS = {"/tf", "/scene/sensors", "/scene/links", "/scene/ranges", "/scene/target", "/scene/estimates", "/log",
         "/metrics"}


def _T(rec) -> float:
    return float(tomllib.loads(rec.metadata["scenario"])["run"]["T"])


def _on_the_simulated_clock(rec) -> None:
    T = _T(rec)
    assert rec.simulated and rec.messages
    assert all(t == round(max(m.k, 0) * T * 1e9) for _k, m, t in rec.messages)
    assert len(rec.wall) == len(rec.messages)


@pytest.fixture(scope="module")
def fresh(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fox") / "run"
    assert main(["run", str(SCEN / "demo.toml"), "--transport", "inproc", "--record", "--ticks", "50", "--quiet",
                 "--set", "faults.link_loss=0.2", "--out", str(out)]) == 0
    return out


def test_foxglove_reads_a_fresh_recording_whole_with_its_own_schemas(fresh):
    rec = read_recording(fresh / "recording.mcap")
    seen = foxglove_read(fresh / "recording.mcap", "whole")
    assert seen["readError"] is None and seen["complete"], seen["readError"]
    assert {"foxglove.SceneUpdate", "foxglove.FrameTransforms", "foxglove.Log"} <= set(seen["schemas"])
    assert {f"flocktrack.{c.__name__}" for c in wire.MESSAGE_TYPES.values()
            if any(m.TYPE == c.TYPE for _k, m, _t in rec.messages)} <= set(seen["schemas"])
    wire_keys = {k for k, _m, _t in rec.messages}
    assert seen["channels"] == len(wire_keys) + len(VIEWS), (seen["channels"], sorted(seen["perTopic"]))
    assert set(seen["perTopic"]) == wire_keys | VIEWS
    assert seen["decodeErrors"] == 0, seen["firstError"]
    assert seen["messages"] == len(rec.messages) + sum(seen["perTopic"][v] for v in VIEWS)
    # a view per tick: the scene, the target, the estimates, the metrics
    for v in ("/scene/sensors", "/scene/links", "/scene/estimates", "/scene/target", "/metrics"):
        assert seen["perTopic"][v] == 50, (v, seen["perTopic"][v])
    # the timeline is the experiment's: 50 ticks of T, not the machine's seconds
    T = _T(rec)
    span = (seen["logTimeMax"] - seen["logTimeMin"]) / 1e9
    assert abs(span - 50 * T) <= T, span


def test_every_message_is_on_its_ticks_simulated_time_and_the_metrics_view_matches_the_csv(fresh):
    rec = read_recording(fresh / "recording.mcap")
    _on_the_simulated_clock(rec)
    from mcap.reader import make_reader

    rows = []
    with open(fresh / "recording.mcap", "rb") as f:
        for _s, _c, m in make_reader(f).iter_messages(topics=["/metrics"]):
            rows.append(json.loads(m.data))
    T = _T(rec)
    assert [r["k"] for r in rows] == list(range(50))
    assert all(abs(r["t"] - r["k"] * T) < 1e-9 for r in rows)
    csv = {int(line.split(",")[0]): line for line in (fresh / "metrics.csv").read_text().splitlines()[1:]}
    header = (fresh / "metrics.csv").read_text().splitlines()[0].split(",")
    for r in rows:
        live = dict(zip(header, csv[r["k"]].split(",")))
        assert abs(float(live["rmse"]) - r["rmse"]) <= 1e-9 * max(1.0, r["rmse"]), (r["k"], live["rmse"], r["rmse"])
        assert int(live["links"]) == r["links"] and r["messages"] > 0


def test_a_lockstep_zenoh_run_records_on_the_simulated_clock_too(tmp_path):
    assert main(["run", str(SCEN / "gu_hu_normal.toml"), "--transport", "zenoh", "--mode", "lockstep", "--quiet",
                 "--ticks", "40", "--out", str(tmp_path / "z")]) == 0
    rec = read_recording(tmp_path / "z" / "recording.mcap")
    _on_the_simulated_clock(rec)
    seen = foxglove_read(tmp_path / "z" / "recording.mcap", "whole")
    assert seen["decodeErrors"] == 0 and "foxglove.SceneUpdate" in seen["schemas"], seen["firstError"]


def test_an_older_wall_clock_recording_still_replays_and_scores(fresh, tmp_path):
    """A recording of the earlier kind: wall-clock log times, no timeline entry, no views."""
    rec = read_recording(fresh / "recording.mcap")
    old = tmp_path / "old.mcap"
    meta = {k: v for k, v in rec.metadata.items() if k != "timeline"}
    w = McapRecorder(old, {**meta, "timeline": "wall"}, views=False)
    t0 = 1_700_000_000_000_000_000
    for j, (key, msg, _t) in enumerate(rec.messages):
        w.write(key, msg, t0 + j * 1_000_000, wall_ns=t0 + j * 1_000_000)
    w.finish()
    again = read_recording(old)
    assert not again.simulated
    assert [(k, m.to_json_bytes()) for k, m, _t in again.messages] == [(k, m.to_json_bytes()) for k, m, _t in rec.messages]
    assert metrics_from_recording(old) == metrics_from_recording(fresh / "recording.mcap")
    assert len(replay_model_from_file(old)) == len(replay_model_from_file(fresh / "recording.mcap")) == 50


def test_the_shipped_foxglove_layout_names_what_a_recording_holds(fresh):
    """dashboards/foxglove_layout.json: the 3-D panel's topics, the plots' paths (topic.field) and the log
    panel's topic are all in a fresh recording; a plotted field is in every tick's metrics."""
    from importlib.resources import files

    from mcap.reader import make_reader

    layout = json.loads(files("dashboards").joinpath("foxglove_layout.json").read_text())
    with open(fresh / "recording.mcap", "rb") as f:
        reader = make_reader(f)
        topics = {c.topic for c in reader.get_summary().channels.values()}
        metrics = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=["/metrics"])]
    panels = layout["configById"]
    assert set(panels["3D!flock"]["topics"]) <= topics
    assert panels["RosOut!events"]["topicToRender"] in topics
    paths = [p["value"] for name, cfg in panels.items() if name.startswith("Plot!") for p in cfg["paths"]]
    assert paths
    for path in paths:
        topic, field = path.split(".", 1)
        assert topic in topics, path
        assert all(field in row for row in metrics[1:]), path    # (tick 0: no estimate yet for some)
