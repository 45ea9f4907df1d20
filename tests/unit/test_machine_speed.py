"""The benchmarks' machine-speed probe (bench/machine_gaps.py): its summary, and a run's missed deadlines split
between the machine's slow phases and the rest — what tells a miss the machine caused from one the flock caused."""

from __future__ import annotations

import json

import pytest


@pytest.fixture(scope="module")
def gaps(bench_module):
    return bench_module("machine_gaps")


def _result(samples):
    return {"speed": [[float(t), float(us)] for t, us in samples]}


def test_summary_finds_the_fastest_and_the_share_of_slow_samples(gaps):
    # 100 samples: 70 at full speed (1000 µs, with jitter), 30 at half speed
    res = _result([(t, 1000 + t % 7) for t in range(70)] + [(t, 2000) for t in range(70, 100)])
    s = gaps.speed_summary(res)
    assert s["samples"] == 100
    assert 1000 <= s["fastest_us"] <= 1006
    assert s["slow_share"] == pytest.approx(0.30)
    assert s["median_slowdown"] < 1.1
    assert gaps.speed_summary({"speed": []}) is None
    assert gaps.speed_summary(None) is None


def test_misses_go_to_the_phase_of_the_nearest_probe(gaps):
    # fast from t = 0 to 9.9, slow from 10 to 19.9 (probes every 0.1 s)
    res = _result([(i / 10, 1000 if i < 100 else 2100) for i in range(200)])
    ticks = {k: k * 0.04 for k in range(500)}          # 25 ticks/s for 20 s
    missed = {10: 2, 260: 5, 400: 1, 499: 3}           # one tick with misses in the fast phase, three in the slow
    split = gaps.by_speed(res, ticks, missed)
    # tick 249 (t = 9.96) is nearer the first slow probe (10.0) than the last fast one (9.9)
    assert split == {"fast": {"ticks": 249, "missed": 2}, "slow": {"ticks": 251, "missed": 9}}
    assert gaps.by_speed(res, {}, missed) is None
    assert gaps.by_speed(None, ticks, missed) is None


def test_missed_by_tick_reads_the_sensors_logs(gaps, tmp_path):
    (tmp_path / "agent-0.log").write_text("INFO agent.runner: agent/0: deadline on (7, 2) — no payload from agent/1\n"
                                          "INFO agent.runner: agent/0: deadline on (9, 0) — no payload from agent/3\n")
    (tmp_path / "agent-1.log").write_text("INFO agent.runner: agent/1: deadline on (7, 1) — no payload from agent/0\n"
                                          "some other line (7, 1)\n")
    assert gaps.missed_by_tick(tmp_path) == {7: 2, 9: 1}


def test_the_probe_costs_cpu_time_and_the_watch_records_it(gaps):
    assert gaps.probe_us() > 0
    res = gaps.watch(0.3, 20.0)
    assert len(res["speed"]) >= 3                      # one every 50 ms
    assert all(us > 0 for _, us in res["speed"])
    json.dumps(res)                                    # what the monitor prints to its parent
