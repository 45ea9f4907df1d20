"""Absurd but valid TOML is refused with the file/key/fix error while the scenario is read — before anything
is built or any process starts, and fast (agent/schema.py LIMITS)."""

import time

import pytest

from agent.scenario import ScenarioError, load_scenario, parse_scenario, scenario_data
from agent.schema import LIMITS
from flocktrack.cli import main

from conftest import ROOT

DEMO = ROOT / "scenarios" / "demo.toml"


def _refused(data: dict, key: str, words: str) -> ScenarioError:
    t0 = time.perf_counter()
    with pytest.raises(ScenarioError) as e:
        parse_scenario(data, "absurd.toml")
    assert time.perf_counter() - t0 < 2.0, "refused, but only after the work it should have spared"
    assert e.value.key == key and words in e.value.problem and e.value.fix, str(e.value)
    assert str(e.value).startswith("absurd.toml: [")
    return e.value


def _demo(**sections) -> dict:
    data = scenario_data(str(DEMO))
    for dotted, v in sections.items():
        sec, _, k = dotted.partition("__")
        data[sec][k] = v
    return data


def test_a_million_sensors():
    _refused(_demo(sensors__n=10**6), "sensors.n", f"need 1 … {LIMITS['sensors']} sensors")


def test_a_nanosecond_tick_and_a_realtime_tick_no_process_keeps():
    _refused(_demo(run__T=1e-9), "run.T", "sample time must be ≥")
    _refused(_demo(run__T=1e-4, run__mode="realtime", run__speed=1.0), "run.T", "shorter than 1 ms")
    _refused(_demo(run__ticks=10**12), "run.ticks", "must be in [1,")


def test_a_ten_thousand_square_matrix_is_refused_at_its_first_row():
    row = [0.0] * 10_000
    e = _refused(_demo(sensors__R=[row] * 10_000), "sensors.R", "entries; at most 4096")
    assert len(str(e)) < 400                                  # the value is not printed whole
    _refused(_demo(sensors__R=[row] * 2), "sensors.R", "10000 columns; at most 64")


def test_static_sensors_that_are_never_linked():
    data = _demo(sensors__motion="static", sensors__positions=[[100.0 * i, 0.0] for i in range(12)])
    data["topology"]["range"] = 50.0
    _refused(data, "topology.range", "no two of the 12 static sensors are ever linked")
    data["topology"]["range"] = 150.0                         # the neighbours are linked: fine
    parse_scenario(data, "ok.toml")


def test_a_huge_file_is_refused_unread(tmp_path, capsys):
    p = tmp_path / "huge.toml"
    with open(p, "wb") as f:
        f.truncate(LIMITS["file_bytes"] + 1)                  # sparse: nothing is written or read
    with pytest.raises(ScenarioError, match="a scenario is at most 16 MiB"):
        load_scenario(p)
    assert main(["run", str(p), "--transport", "inproc"]) == 2
    assert "a scenario is at most 16 MiB" in capsys.readouterr().err


def test_a_port_in_use_is_named_before_anything_starts(tmp_path, capsys):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        for flags in (["--port", str(port)], ["--dashboard", "--dashboard-port", str(port)]):
            assert main(["run", str(DEMO), "--ticks", "3", *flags, "--out", str(tmp_path / "r")]) == 2
            err = capsys.readouterr().err
            assert f"port {port} is in use by another program; give {flags[-2]}" in err, err
    assert not (tmp_path / "r" / "logs").exists()                # nothing was started
