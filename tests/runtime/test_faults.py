"""The fault plan ([faults] in a scenario; topology/faults.py): every kind injected in a real
multi-process run over Zenoh with its effect and heal checked in the recording, plus the in-process
claims of the fault plan (link loss, partition and re-merge, immunity to duplication and reordering)."""

import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from agent.scenario import ScenarioError, parse_scenario
from agent.scenario import scenario_data
from flocktrack.record.reader import read_recording
from flocktrack.engine.run import run_inproc_to_dir, run_zenoh_to_dir

SCEN = Path(__file__).resolve().parents[2] / "scenarios"


def _scenario(name, events, **over):
    data = scenario_data(str(SCEN / name), [], **over)
    data["faults"] = {"events": events}
    return data, parse_scenario(data, name)


def _links(t):
    return {(i, j) for i, nb in enumerate(t.links) for j in nb}


WORLD_SENSOR_TARGET_PLAN = [
    {"kind": "link_loss", "targets": "agents:0", "direction": "in", "p": 1.0, "start": 10, "heal": 30},
    {"kind": "partition", "targets": "halves", "start": 40, "heal": 60},
    {"kind": "blind", "targets": "agents:1", "start": 70, "heal": 80},
    {"kind": "delay", "targets": "agents:2", "direction": "in", "delay_ticks": 1, "start": 85, "heal": 95},
    {"kind": "duplicate", "targets": "all", "p": 1.0, "start": 100, "heal": 110},
    {"kind": "reorder", "targets": "all", "p": 0.5, "start": 110, "heal": 120},
    {"kind": "byzantine", "targets": "agents:3", "mode": "huge", "start": 120, "heal": 130},
    {"kind": "outliers", "targets": "agents:4", "p": 1.0, "magnitude": 50.0, "start": 130, "heal": 135},
    {"kind": "noise", "targets": "agents:5", "noise_scale": 10.0, "start": 140, "heal": 160},
    {"kind": "evade", "accel": 3.0, "start": 165, "heal": 180},
]


def test_world_sensor_and_target_faults_over_zenoh(tmp_path):
    # lockstep with a long deadline: on a loaded machine a deadline firing would change the numbers
    data, sc = _scenario("gu_hu_normal.toml", WORLD_SENSOR_TARGET_PLAN,
                         **{"run.ticks": 200, "run.mode": "lockstep", "run.deadline_s": 30.0})
    summary, info = run_zenoh_to_dir(sc, data, tmp_path, quiet=True, timeout_s=600)
    assert info["rc"] == 0
    rec = read_recording(tmp_path / "recording.mcap")
    ev = defaultdict(dict)
    for key, m, _ in rec.messages:
        if key == "world/event" and m.verb == "fault":
            ev[m.args["kind"]][m.args["phase"]] = m.k
    for e in WORLD_SENSOR_TARGET_PLAN:  # every start and heal is on the timeline, at its tick
        assert ev[e["kind"]] == {"start": e["start"], "heal": e["heal"]}, (e["kind"], ev[e["kind"]])
    ticks = {m.k: m for key, m, _ in rec.messages if key == "world/tick"}
    # link loss, direction "in": agent 0 hears nobody, others still hear it; healed afterwards
    for k in range(10, 30):
        assert ticks[k].links[0] == [] and any(0 in ticks[k].links[j] for j in range(1, 10))
    assert ticks[30].links[0]
    # partition into two halves, then re-merged
    groups = None
    for key, m, _ in rec.messages:
        if key == "world/event" and m.args.get("kind") == "partition" and m.args["phase"] == "start":
            groups = [int(g) for g in m.args["groups"]]
    for k in range(40, 60):
        assert all(groups[i] == groups[j] for i, j in _links(ticks[k]))
    assert any(groups[i] != groups[j] for i, j in _links(ticks[60]))
    # blind sensor: b = 0 in the window, its measurement is pure noise there
    assert all(ticks[k].b[1] == 0 for k in range(70, 80)) and ticks[80].b[1] > 0
    meas = defaultdict(dict)
    truth = {m.k: m.x for key, m, _ in rec.messages if key == "target/truth"}
    for key, m, _ in rec.messages:
        if key.endswith("/meas"):
            meas[m.src][m.k] = m.y
    assert all(np.linalg.norm(meas[1][k]) < 1.5 for k in range(70, 80))
    # Byzantine "huge" payloads from agent 3 in its window only
    big = {m.k for key, m, _ in rec.messages if key == "agent/3/xchg"
           and max(np.abs(v).max() for p in m.payloads for v in p.values()) > 1e4}
    assert big and min(big) >= 120 and max(big) < 130
    # outliers at agent 4, larger noise at agent 5
    res4 = {k: np.linalg.norm(meas[4][k] - truth[k][:2]) for k in meas[4]}
    assert all(res4[k] > 40 for k in range(130, 135)) and all(res4[k] < 5 for k in range(135, 140))
    res5 = np.array([meas[5][k] - truth[k][:2] for k in sorted(meas[5])])
    assert np.std(res5[140:160]) > 4 * np.std(res5[:100])
    # evasive manoeuvre: the target's heading turns in the window, not before
    v = {k: truth[k][2:4] for k in truth}
    ang = lambda a, b: abs(np.arctan2(a[0] * b[1] - a[1] * b[0], a @ b))
    assert ang(v[165], v[180]) > 5 * max(ang(v[145], v[160]), 1e-3)
    # receiver-side counters: delayed, duplicated, reordered payloads were really delayed/duplicated/reordered
    stats = {p.stem: json.loads(p.read_text()).get("role", {}) for p in (tmp_path / "stats").glob("agent-*.json")}
    assert stats["agent-2"].get("delayed_payloads", 0) > 0
    assert sum(s.get("duplicated_payloads", 0) for s in stats.values()) > 0
    assert sum(s.get("reordered_payloads", 0) for s in stats.values()) > 0
    assert summary["network_rmse"] is not None


@pytest.mark.slow
def test_process_faults_crash_pause_router_restart_over_zenoh(tmp_path):
    events = [{"kind": "crash", "targets": "agents:1", "start": 20, "heal": 40},
              {"kind": "pause", "targets": "agents:2", "start": 80, "heal": 90},
              {"kind": "router_restart", "start": 120}]
    data, sc = _scenario("chen_switching.toml", events, **{"run.ticks": 200, "run.mode": "lockstep",
                                                           "run.deadline_s": 0.5})
    summary, info = run_zenoh_to_dir(sc, data, tmp_path, quiet=True, timeout_s=600)
    assert info["rc"] == 0
    rec = read_recording(tmp_path / "recording.mcap")
    est = defaultdict(set)
    for key, m, _ in rec.messages:
        if key.startswith("agent/") and key.endswith("/estimate"):
            est[m.src].add(m.k)
    missing = {i: sorted(set(range(200)) - est[i]) for i in range(3)}
    # crash: agent 1 disappears after tick 20 and is back before the end (restarted at heal, rejoined)
    assert missing[1] and 20 <= missing[1][0] < 40 and max(est[1]) == 199
    assert info["exits"]["agent/1"][0] == -9
    # pause: agent 2 falls silent from the pause until the heal (SIGCONT) while the others go on, then
    # catches up (its buffered ticks, or coasting over the lost ones) and finishes
    t_ev = {m.args["phase"]: t for (key, m, _), t in zip(rec.messages, rec.wall)     # (recorded: wall clock)
            if key == "world/event" and m.verb == "fault" and m.args.get("kind") == "pause"}
    window = (t_ev["start"] + 0.3e9, t_ev["heal"])
    during = defaultdict(int)
    for (key, m, _), t in zip(rec.messages, rec.wall):
        if key.startswith("agent/") and window[0] < t < window[1]:
            during[m.src] += 1
    assert during[2] == 0 and during[0] > 0 and during[1] > 0, dict(during)
    assert max(est[2]) == 199
    # router restart: everyone misses a few ticks after 120, then all resume
    assert all(any(120 <= k < 160 for k in missing[i]) for i in range(3))
    assert all(len([k for k in missing[i] if k >= 160]) == 0 for i in range(3))
    ev = json.loads((tmp_path / "events.json").read_text())
    assert any(e["event"] == "router" and e["name"] == "up" for e in ev)


@pytest.mark.slow
def test_a_restarted_sensor_starts_from_its_neighbours_estimates_not_its_prior(tmp_path):
    """The demo's adversarial target has moved ~12 m from x̂₀ by the heal: a sensor that rejoined with its
    prior x̂₀ was that far off at its first tick, dragged its neighbours' consensus and the target (which
    reacts to the mean estimate) after it, and a crash every two minutes made the error grow without bound
    (bench/soak.py, docs/reliability.md). Restarted, it starts from the estimates its peers hand it."""
    events = [{"kind": "crash", "targets": "agents:1", "start": 150, "heal": 260}]
    data, sc = _scenario("demo.toml", events, **{"run.ticks": 320, "run.mode": "lockstep"})
    summary, info = run_zenoh_to_dir(sc, data, tmp_path, quiet=True, timeout_s=600)
    assert info["rc"] == 0 and info["exits"]["agent/1"][0] == -9
    import csv

    rows = {int(r["k"]): r for r in csv.DictReader(open(tmp_path / "metrics.csv"))}
    assert rows[259]["err_1"] in ("", "nan") and rows[260]["err_1"] not in ("", "nan")   # back at the heal
    truth = {m.k: m.x for key, m, _ in read_recording(tmp_path / "recording.mcap").messages if key == "target/truth"}
    assert np.linalg.norm(truth[260][:2] - sc.estimator.x0[:2]) > 8.0         # x̂₀ would be metres off ...
    first = float(rows[260]["err_1"])
    others = [float(rows[260][f"err_{i}"]) for i in range(sc.sensors.n) if i != 1]
    assert first < 3 * max(others) + 0.05, (first, others)                     # ... it starts where they are
    assert max(float(r["rmse"]) for k, r in rows.items() if k >= 10) < 0.3     # and nobody is dragged off
    bus = {p.stem: json.loads(p.read_text()) for p in (tmp_path / "stats").glob("agent-*.json")}
    stats = {name: b.get("role", {}) for name, b in bus.items()}
    assert stats["agent-1"].get("reinitialised_from", 0) >= 1 and not stats["agent-1"].get("join_deadline")
    assert sum(s.get("estimates_handed", 0) for s in stats.values()) >= 2
    # while it was dead nobody addressed payloads to it (they would pile up, held for a subscriber, and spill)
    assert not any(b.get("dropped", {}).get("unmatched") for b in bus.values()), {n: b.get("dropped") for n, b in bus.items()}


def _inproc(tmp_path, name, events, **over):
    data, sc = _scenario(name, events, **over)
    return run_inproc_to_dir(sc, data, tmp_path)


def test_duplication_and_reordering_change_nothing(tmp_path):
    """The protocol keys payloads by (tick, round, sender): duplicated or reordered delivery gives
    bit-identical results."""
    base, _ = _inproc(tmp_path / "a", "gu_hu_normal.toml", [], **{"run.ticks": 120})
    noisy, info = _inproc(tmp_path / "b", "gu_hu_normal.toml",
                          [{"kind": "duplicate", "p": 1.0, "start": 5, "heal": 60},
                           {"kind": "reorder", "p": 0.7, "start": 30, "heal": 110}], **{"run.ticks": 120})
    assert (tmp_path / "a" / "metrics.csv").read_bytes() == (tmp_path / "b" / "metrics.csv").read_bytes()
    assert sum(c.get("duplicated_payloads", 0) for c in info["sensor_counters"]) > 0
    assert sum(c.get("reordered_payloads", 0) for c in info["sensor_counters"]) > 0


@pytest.mark.slow
def test_minimax_bounded_under_30pct_link_loss_on_intelligent_target(tmp_path):
    s, info = _inproc(tmp_path, "gu_hu_intelligent.toml", [], **{"run.ticks": 1500, "faults.link_loss": 0.3})
    dropped = sum(c.get("dropped_links", 0) for c in info["sensor_counters"])
    assert dropped == 0  # lost links are absent from the tick's link table, not waited for
    assert s["max_error"] < 1.0 and s["network_rmse"] < 0.3, (s["max_error"], s["network_rmse"])


def test_partition_halves_keep_tracking_and_remerge(tmp_path):
    events = [{"kind": "partition", "targets": "groups:0,0,0,0,0,1,1,1,1,1", "start": 100, "heal": 300}]
    s, _ = _inproc(tmp_path, "gu_hu_normal.toml", events, **{"run.ticks": 500})
    import csv

    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    during = [float(r["rmse"]) for r in rows[150:300]]
    after = [float(r["lambda2"]) for r in rows[320:500]]
    assert max(during) < 0.5                 # each half keeps tracking (both see the target)
    assert min(float(r["lambda2"]) for r in rows[150:300]) == 0.0   # really partitioned
    assert min(after) > 0.0                  # and re-merged into one connected flock


def test_fault_plan_validation_names_key_and_fix():
    bad = [({"kind": "link_loss", "start": 10, "heal": 5}, "faults.events[0].heal"),
           ({"kind": "crash", "targets": "agents:99", "start": 1}, "faults.events[0].targets"),
           ({"kind": "partition", "targets": "all", "start": 1}, "faults.events[0].targets"),
           ({"kind": "link_loss", "p": 1.5, "start": 1}, "faults.events[0].p"),
           ({"kind": "meteor", "start": 1}, "faults.events[0].kind")]
    for ev, key in bad:
        with pytest.raises(ScenarioError) as e:
            _scenario("gu_hu_normal.toml", [ev])
        assert e.value.key == key, (ev, str(e.value))


def _honest_rmse(tmp_path, f: int, byz_mode: str = "huge") -> float:
    import csv

    events = [{"kind": "byzantine", "targets": "agents:3", "mode": byz_mode, "start": 50}]
    _inproc(tmp_path, "gu_hu_normal.toml", events, **{"run.ticks": 300, "estimator.resilient_f": f})
    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    e = np.array([[float(r[f"err_{i}"]) for i in range(10) if i != 3] for r in rows[60:]])
    return float(np.sqrt(np.mean(e ** 2)))


@pytest.mark.parametrize("mode", ["huge", "bias"])
def test_one_byzantine_sensor_ruins_plain_consensus_not_the_resilient_one(tmp_path, mode):
    plain = _honest_rmse(tmp_path / "plain", 0, mode)
    resilient = _honest_rmse(tmp_path / "wmsr", 1, mode)
    base, _ = _inproc(tmp_path / "base", "gu_hu_normal.toml", [], **{"run.ticks": 300, "estimator.resilient_f": 1})
    assert plain > 20 * resilient, (plain, resilient)
    assert resilient < 3 * max(base["network_rmse"], 0.05), (resilient, base["network_rmse"])


# ------------------------------------------------------------------ delays in ms, live injection

def test_delay_in_ms_changes_nothing_in_lockstep_inproc(tmp_path):
    """Lockstep waits for every payload: a wall-clock delay (with jitter) on every link only holds
    payloads back, so the estimates are bit-identical to the run without it."""
    from flocktrack.engine.inproc import run_inproc

    plan = [{"kind": "delay", "targets": "all", "delay_ms": 20.0, "jitter_ms": 15.0, "start": 5, "heal": 25}]
    _, base = _scenario("gu_hu_normal.toml", [], **{"run.ticks": 40})
    _, sc = _scenario("gu_hu_normal.toml", plan, **{"run.ticks": 40})
    m0, _, _ = run_inproc(base)
    m1, roles, _ = run_inproc(sc)
    assert m1.summary() == m0.summary()
    delayed = [r.counters["delayed_payloads"] for r in roles.sensors]
    assert all(d > 0 for d in delayed)
    assert sum(r.counters["dropped_links"] for r in roles.sensors) == 0   # every round got every payload


def test_delay_in_ticks_with_jitter_spreads_the_lateness():
    from flocktrack.engine.inproc import run_inproc

    def counters(jitter):
        plan = [{"kind": "delay", "targets": "agents:2", "direction": "in", "delay_ticks": 1,
                 "jitter_ticks": jitter, "start": 5, "heal": 35}]
        _, sc = _scenario("gu_hu_normal.toml", plan, **{"run.ticks": 40})
        return run_inproc(sc)[1].sensors[2].counters

    c0, c1 = counters(0), counters(1)
    # held 1 tick: always late, counted and dropped; with jitter ±1 a third arrive at once (0 ticks)
    assert c0["delayed_payloads"] > 100 and c0["late_payloads"] >= c0["delayed_payloads"]
    assert c1["late_payloads"] >= c1["delayed_payloads"]
    assert 0.5 < c1["delayed_payloads"] / c0["delayed_payloads"] < 0.85
    assert 0 < c1["dropped_links"] < c0["dropped_links"]    # rounds that missed a neighbour's payload


@pytest.mark.parametrize("bad, key", [({"delay_ms": -5.0}, "delay_ms"), ({"jitter_ms": float("inf")}, "jitter_ms"),
                                      ({"delay_ms": 10.0, "jitter_ticks": 2}, "jitter_ticks"),
                                      ({"delay_ticks": 5000}, "delay_ticks")])
def test_bad_delays_are_named_in_the_error(bad, key):
    ev = {"kind": "delay", "targets": "all", "start": 1, **bad}
    with pytest.raises(ScenarioError) as ei:
        _scenario("gu_hu_normal.toml", [ev])
    assert f"faults.events[0].{key}" in str(ei.value)


def test_live_injection_through_the_world():
    from agent.bus import LocalBus
    from agent.wire import Control
    from topology.faults import LIVE_ID0
    from topology.world import build_world

    _, sc = _scenario("gu_hu_normal.toml", [])
    w = build_world(sc)
    bus = LocalBus()
    w.attach(bus)
    events = []
    bus.subscribe("world/event", lambda key, m: events.append(m))
    w.start()                                         # tick 0 is open: controls take effect on tick 1
    for bad in ({"kind": "delay", "targets": "agents:99"}, {"kind": "no_such_kind"}, {"kind": "delay", "delay_ms": -1.0},
                {"kind": "delay", "colour": "red"}, {"kind": "delay", "ticks": 0}, {"kind": "partition", "targets": "all"}):
        bus.publish("control/inject", Control(verb="inject", args=bad))
        bus.drain()
    assert w.stats["rejected_injections"] == 6
    assert [e.verb for e in events] == ["rejected"] * 6      # each said why, on the timeline
    reasons = [e.args["reason"] for e in events]
    for r, key in zip(reasons, ("inject.targets", "inject.kind", "inject.delay_ms", "inject.colour", "inject.ticks",
                                "inject.targets")):
        assert key in r, (key, r)
    events.clear()
    bus.publish("control/inject", Control(verb="inject", args={"kind": "link_loss", "targets": "agents:0", "p": 1.0,
                                                                "direction": "in", "ticks": 3}))
    bus.publish("control/inject", Control(verb="inject", args={"kind": "blind", "targets": "agents:1"}))
    bus.drain()
    assert [(e.verb, e.k, e.args["id"]) for e in events] == [("inject", 1, LIVE_ID0), ("inject", 1, LIVE_ID0 + 1)]
    starts = {}
    for k in range(1, 8):
        if k == 5:
            bus.publish("control/heal_fault", Control(verb="heal_fault", args={"id": LIVE_ID0 + 1}))
            bus.drain()
        w.on_deadline()                               # close tick k−1, open tick k
        bus.drain()
        t = w.last_tick
        assert (t.links[0] == []) == (1 <= k < 4), k  # the link loss lasted its 3 ticks
        assert (t.b[1] == 0) == (1 <= k < 5), k       # blind until healed (the tick after the control)
    for e in events:
        if e.verb == "fault":
            starts[(e.args["id"], e.args["phase"])] = e.k
    assert starts == {(LIVE_ID0, "start"): 1, (LIVE_ID0 + 1, "start"): 1, (LIVE_ID0, "heal"): 4,
                      (LIVE_ID0 + 1, "heal"): 5}
    assert not w.apply_control("heal_fault", {"id": LIVE_ID0 + 1})   # already healed


def test_delay_in_ms_in_realtime_and_live_injection_over_zenoh(tmp_path):
    """Realtime: a wall-clock delay longer than a tick makes every delayed payload miss its round (lost,
    counted late); a live control/inject starts a fault plan event mid-run, heal_fault ends it."""
    import subprocess
    import sys
    import time

    from agent.bus import ZenohBus
    from agent.wire import Control
    from topology.faults import LIVE_ID0

    plan = [{"kind": "delay", "targets": "agents:2", "direction": "in", "delay_ms": 400.0, "jitter_ms": 100.0,
             "start": 20, "heal": 50}]
    # 200 ticks: the CLI process that injects may take ~12 s (75 ticks) to start on a loaded machine
    data, sc = _scenario("gu_hu_normal.toml", plan, **{"run.ticks": 200, "run.mode": "realtime", "run.speed": 0.25})
    st = {"bus": None, "k": -1, "sent": set(), "injected": None}

    def on_event(key, m):
        if m.verb == "inject":
            st["injected"] = m.k

    def hook(launcher):
        if st["bus"] is None:
            st["bus"] = ZenohBus(launcher.run, connect=launcher.endpoint)
            st["bus"].subscribe("world/tick", lambda key, m: st.__setitem__("k", max(st["k"], m.k)))
            st["bus"].subscribe("world/event", on_event)
        st["bus"].poll(0)
        if st["k"] >= 40 and "inject" not in st["sent"]:   # through the CLI, as a user would
            st["cli"] = subprocess.Popen([sys.executable, "-m", "flocktrack", "fault", "inject", "kind=delay",
                                          "targets=agents:5", "direction=in", "delay_ms=1.0", "jitter_ms=1.0",
                                          "--run", launcher.run, "--connect", launcher.endpoint],
                                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            st["sent"].add("inject")
        # heal it once the world has acknowledged it and it has run 15 ticks (a CLI process starting on a
        # loaded machine may take many ticks to get its message out: a heal sent before would be refused)
        if st["injected"] is not None and st["k"] >= st["injected"] + 15 and "heal" not in st["sent"]:
            assert st["bus"].await_subscriber("control/heal_fault", 10.0)   # (a put before the routes is dropped)
            st["bus"].publish("control/heal_fault", Control(verb="heal_fault", args={"id": LIVE_ID0}))
            st["sent"].add("heal")
        time.sleep(0.005)

    try:
        summary, info = run_zenoh_to_dir(sc, data, tmp_path, quiet=True, on_poll=hook, timeout_s=600)
    finally:
        if st["bus"] is not None:
            st["bus"].close()
    assert info["rc"] == 0
    out, _ = st["cli"].communicate(timeout=60)
    assert st["cli"].returncode == 0 and "applied: inject at tick" in out, out
    rec = read_recording(tmp_path / "recording.mcap")
    fault = {(m.args["id"], m.args["phase"]): m.k for key, m, _ in rec.messages
             if key == "world/event" and m.verb == "fault"}
    assert fault[(0, "start")] == 20 and fault[(0, "heal")] == 50
    inj = [m for key, m, _ in rec.messages if key == "world/event" and m.verb == "inject"]
    assert len(inj) == 1 and inj[0].args["id"] == LIVE_ID0 and inj[0].args["delay_ms"] == 1.0
    assert fault[(LIVE_ID0, "start")] == inj[0].k >= 40
    assert fault[(LIVE_ID0, "heal")] >= inj[0].k + 15
    stats = {p.stem: json.loads(p.read_text()).get("role", {}) for p in (tmp_path / "stats").glob("agent-*.json")}
    s2, s5 = stats["agent-2"], stats["agent-5"]
    # 400 ± 100 ms ≫ the 23 ms round slot: every payload delayed to agent 2 came too late for its round
    assert s2["delayed_payloads"] > 50
    assert s2.get("late_payloads", 0) >= 0.95 * s2["delayed_payloads"]
    assert s5["delayed_payloads"] > 50                  # the live one was applied, at agent 5 only
    assert all(s.get("delayed_payloads", 0) == 0 for name, s in stats.items() if name not in ("agent-2", "agent-5"))


def _world_on_localbus(events, **over):
    from agent.bus import LocalBus
    from topology.world import build_world

    _, sc = _scenario("chen_switching.toml", events, **over)
    w = build_world(sc, ack_timeout_s=5.0)
    bus = LocalBus()
    w.attach(bus)
    seen = {"tick": [], "event": []}
    bus.subscribe("world/tick", lambda key, m: seen["tick"].append(m))
    bus.subscribe("world/event", lambda key, m: seen["event"].append(m))
    return w, bus, seen


def _ack(bus, k, fid, kind, phase, agents=()):
    from agent.wire import Control

    bus.publish("launcher/event", Control(k=k, verb="ack", args={"id": fid, "kind": kind, "phase": phase,
                                                                 "agents": [float(a) for a in agents]}))
    bus.drain()


def test_lockstep_world_holds_a_process_fault_tick_for_the_launcher():
    """A crash scheduled for tick k lands at tick k: the world holds tick k until the launcher acks (the
    crashed sensor is dead in tick k's membership); the heal tick waits for the ack and the restarted
    sensor's return; a router restart's tick is released into the outage and the next one waits for every
    member's return (topology/fault_hold.py)."""
    events = [{"kind": "crash", "targets": "agents:1", "start": 3, "heal": 6},
              {"kind": "router_restart", "start": 9}]
    w, bus, seen = _world_on_localbus(events)
    members = [("launcher", 0), ("agent", 0), ("agent", 1), ("agent", 2), ("target", 0), ("recorder", 0)]
    for m in members:
        w.on_member(*m, True)
    w.start()
    bus.drain()
    ks = lambda: [t.k for t in seen["tick"]]
    for _ in range(3):
        w.on_deadline()
        bus.drain()
    assert ks() == [0, 1, 2] and seen["event"][-1].args["kind"] == "crash"   # tick 3 held: its fault is out
    w.on_deadline()
    bus.drain()
    assert ks() == [0, 1, 2]                     # nothing to close: still held
    _ack(bus, 3, 0, "crash", "start", [1])
    assert ks()[-1] == 3 and seen["tick"][-1].alive == [True, False, True] and 1 not in seen["tick"][-1].links[0]
    w.on_member("agent", 1, False)               # its token goes a moment later: nothing changes
    for _ in range(3):
        w.on_deadline()
        bus.drain()
    assert ks()[-1] == 5                         # the heal tick 6 waits for the ack ...
    _ack(bus, 6, 0, "crash", "heal", [1])
    assert ks()[-1] == 5                         # ... and for the restarted sensor
    w.on_member("agent", 1, True)
    bus.drain()
    assert ks()[-1] == 6 and seen["tick"][-1].alive == [True, True, True]
    for _ in range(3):
        w.on_deadline()
        bus.drain()
    assert ks()[-1] == 8
    _ack(bus, 9, 1, "router_restart", "start")
    assert ks()[-1] == 8                         # held until the outage shows ...
    w.on_member("launcher", 0, False)            # a closing router drops the launcher's link first ...
    bus.drain()
    assert ks()[-1] == 8                         # ... which does not show the others are cut off yet
    for m in members[1:]:
        w.on_member(*m, False)                   # the router is down: every token has gone
    bus.drain()
    assert ks()[-1] == 9                         # ... then tick 9 goes out (into the outage, lost)
    w.on_deadline()
    bus.drain()
    assert ks()[-1] == 9                         # tick 10 waits for everyone's return
    for m in members[:-1]:
        w.on_member(*m, True)
    bus.drain()
    assert ks()[-1] == 9                         # the recorder is not back yet
    w.on_member("recorder", 0, True)
    bus.drain()
    assert ks()[-1] == 10 and w.stats.get("fault_hold_timeouts", 0) == 0


def test_process_fault_hold_gives_up_after_its_timeout_and_needs_a_launcher():
    events = [{"kind": "pause", "targets": "agents:2", "start": 1, "heal": 2}]
    w, bus, seen = _world_on_localbus(events)
    w.start()                                    # no launcher: nobody would answer, nothing is held
    w.on_deadline()
    bus.drain()
    assert [t.k for t in seen["tick"]] == [0, 1]
    w, bus, seen = _world_on_localbus(events)
    w.on_member("launcher", 0, True)
    w.start()
    w.on_deadline()
    bus.drain()
    assert [t.k for t in seen["tick"]] == [0]
    w.on_timer(100.0)
    w.on_timer(104.0)
    assert [t.k for t in seen["tick"]] == [0]
    w.on_timer(105.5)                            # held longer than ack_timeout_s = 5: go on, counted
    bus.drain()
    assert [t.k for t in seen["tick"]] == [0, 1] and w.stats["fault_hold_timeouts"] == 1


def test_a_sensor_sits_out_a_tick_whose_membership_marks_it_dead():
    """The world's membership is authoritative: a sensor publishes nothing for a tick that marks it dead
    (cut off, or not yet seen back), and takes part again from the next tick that marks it alive."""
    from agent.assemble import build_sensor, build_target
    from agent.bus import LocalBus
    from topology.world import build_world

    _, sc = _scenario("gu_hu_normal.toml", [], **{"run.ticks": 6})
    bus = LocalBus()
    w, tgt, s0 = build_world(sc), build_target(sc), build_sensor(sc, 0)
    others = [build_sensor(sc, i) for i in range(1, sc.sensors.n)]
    for r in (w, tgt, s0, *others):
        r.attach(bus)
    pubs = []
    bus.subscribe("agent/0/**", lambda key, m: pubs.append((key, m.k)))
    # sensor 0 is dead in ticks 0–2 (the world flips it back while tick 2 is under way)
    bus.subscribe("world/tick", lambda key, m: w.alive.__setitem__(0, m.k >= 2))
    w.alive[0] = False
    w.start()
    bus.drain()
    assert s0.counters["sat_out_ticks"] == 3 and s0.k == 6
    assert {k for _, k in pubs} == {3, 4, 5}
    assert {key.split("/")[-1] for key, _ in pubs} >= {"meas", "xchg", "estimate", "state"}


def test_a_nan_sending_sensor_costs_its_neighbours_no_deadline_and_the_flock_keeps_its_clock(tmp_path):
    """Byzantine NaN payloads are dropped at every receiver, and each round closes as soon as the rest
    have come (the NaN payload is a lost link): no round waits out a deadline, the world closes every tick
    on every state, and every sensor reports to the end."""
    import csv

    events = [{"kind": "byzantine", "targets": "agents:3", "mode": "nan", "start": 50}]
    s, info = _inproc(tmp_path, "gu_hu_normal.toml", events, **{"run.ticks": 300, "estimator.resilient_f": 1})
    c = info["sensor_counters"]
    assert sum(x.get("deadline_rounds", 0) for x in c) == 0
    assert sum(x.get("unusable_payloads", 0) for x in c) > 0
    assert info["world"]["missing_states"] == 0 and info["world"]["late_states"] == 0
    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    assert len(rows) == 300 and all(r["reporting"] == "10" for r in rows)
    assert s["network_rmse"] < 0.2, s["network_rmse"]


def test_in_process_deadlines_fire_innermost_first_so_the_world_never_runs_ahead(tmp_path):
    """A payload that never comes: the waiting sensors' rounds end by deadline before the world's wait, so
    the world closes each tick on every sensor's state instead of running ahead of the flock."""
    from agent import wire
    from agent.bus import LocalBus
    from flocktrack.engine.inproc import run_inproc

    class Lossy(LocalBus):
        def publish_raw(self, key, data):
            if key.startswith("agent/3/to/") and wire.decode(key, data).k >= 20:
                return
            super().publish_raw(key, data)

    _, sc = _scenario("gu_hu_normal.toml", [], **{"run.ticks": 60})
    metrics, roles, _ = run_inproc(sc, bus=Lossy())
    assert sum(r.counters["deadline_rounds"] for r in roles.sensors) > 0
    assert roles.world.stats["missing_states"] == 0 and roles.world.stats["late_states"] == 0
    assert metrics.summary()["ticks_seen"] == 60


def _per_node_rmse(run_dir: Path, skip: int = 60) -> np.ndarray:
    import csv

    rows = list(csv.DictReader(open(run_dir / "metrics.csv")))
    n = sum(1 for c in rows[0] if c.startswith("err_"))
    e = np.array([[float(r[f"err_{i}"]) for i in range(n)] for r in rows[skip:]])
    return np.sqrt(np.mean(e ** 2, axis=0))


@pytest.fixture(scope="module")
def fault_free_f1(tmp_path_factory):
    out = tmp_path_factory.mktemp("fault_free_f1")
    _inproc(out, "gu_hu_normal.toml", [], **{"run.ticks": 250, "estimator.resilient_f": 1})
    return _per_node_rmse(out)


@pytest.mark.parametrize("mode,node,start,magnitude",
                         [(m, 3, 50, None) for m in ("nan", "huge", "stale", "bias", "drift", "noise", "mimic")]
                         + [("huge", 0, 150, None), ("stale", 7, 150, None), ("bias", 7, 20, None),
                            ("mimic", 0, 100, None),
                            # lies near what one test resolves: half the noise's σ, and less
                            ("mimic", 3, 50, 1.0), ("mimic", 7, 0, 0.5), ("bias", 3, 50, 0.5), ("drift", 3, 50, 5.0)])
def test_a_byzantine_sensor_is_contained_by_the_gate_and_w_msr(tmp_path, fault_free_f1, mode, node, start, magnitude):
    """With resilient_f = 1 every Byzantine mode, at the hub (agent 3) or at the edge, from early or late on,
    large or small, keeps the honest sensors' worst per-node RMSE within 1.5 × the fault-free run's."""
    events = [{"kind": "byzantine", "targets": f"agents:{node}", "mode": mode, "start": start}]
    if magnitude is not None:
        events[0]["magnitude"] = magnitude
    s, _ = _inproc(tmp_path, "gu_hu_normal.toml", events, **{"run.ticks": 250, "estimator.resilient_f": 1})
    got = _per_node_rmse(tmp_path)
    honest = [i for i in range(len(got)) if i != node]
    ratio = max(got[honest]) / max(fault_free_f1[honest])
    assert ratio <= 1.5, (mode, node, start, ratio)
    # suspicion as an output: a majority of its neighbours discards it soon (NaN never reaches the estimators:
    # the bus drops it), and honest sensors are rarely suspected
    seen = s["suspicion"]["attackers"][str(node)]
    if mode != "nan":      # a small lie takes longer to tell from the noise
        assert seen["detected_tick"] is not None and seen["latency_ticks"] <= (30 if magnitude is None else 60), seen
    assert s["suspicion"]["false_suspicion_rate"] <= 0.01


#: Gu & Hu's normal target with a link range that spans the flock: the complete graph on 10 sensors, 5-robust
DENSE = {"run.ticks": 250, "estimator.resilient_f": 2, "topology.range": 40.0}


@pytest.fixture(scope="module")
def fault_free_f2_dense(tmp_path_factory):
    out = tmp_path_factory.mktemp("fault_free_f2")
    s, _ = _inproc(out, "gu_hu_normal.toml", [], **DENSE)
    assert s["robustness"]["ticks_robust"] == 250 and s["suspicion"]["false_suspicion_rate"] <= 0.01
    return _per_node_rmse(out)


@pytest.mark.parametrize("mode,nodes,magnitude", [("bias", "3,5", None), ("stale", "0,7", None),
                                                  ("drift", "0,7", None), ("mimic", "3,5", 1.0)])
def test_two_colluding_sensors_are_contained_on_a_graph_verified_5_robust(tmp_path, fault_free_f2_dense, mode,
                                                                          nodes, magnitude):
    """With resilient_f = 2 on a graph the run verifies (2f + 1)-robust at every tick, two sensors lying the same
    way from tick 50 keep the honest sensors' worst per-node RMSE within 2 × the fault-free run's."""
    events = [{"kind": "byzantine", "targets": f"agents:{nodes}", "mode": mode, "start": 50}]
    if magnitude is not None:
        events[0]["magnitude"] = magnitude
    s, _ = _inproc(tmp_path, "gu_hu_normal.toml", events, **DENSE)
    assert s["robustness"] == {"f": 2, "required_r": 5, "ticks_robust": 250, "ticks_not_robust": 0,
                               "ticks_unknown": 0, "first_tick": None}
    got = _per_node_rmse(tmp_path)
    bad = [int(a) for a in nodes.split(",")]
    honest = [i for i in range(len(got)) if i not in bad]
    ratio = max(got[honest]) / max(fault_free_f2_dense[honest])
    assert ratio <= 2.0, (mode, nodes, ratio)
    assert all(s["suspicion"]["attackers"][str(a)]["detected_tick"] is not None for a in bad), s["suspicion"]


def test_a_graph_too_sparse_for_f_is_reported_with_its_first_tick(tmp_path, caplog):
    """gu_hu_normal's range graph has sensors with 4 neighbours or fewer: never the 5-robust f = 2 needs."""
    s, _ = _inproc(tmp_path, "gu_hu_normal.toml", [], **{"run.ticks": 40, "estimator.resilient_f": 2})
    r = s["robustness"]
    assert r["ticks_not_robust"] == 40 and r["first_tick"] == 0 and r["ticks_robust"] == 0
    assert "not 5-robust" in caplog.text


def test_the_gate_rarely_suspects_an_honest_sensor():
    """Fault-free, the consistency gate discards at most 1 % of the payloads a sensor takes in (a neighbour's
    payload of each round) and an honest neighbour in at most 1 % of the node-ticks, also on the manoeuvring
    intelligent target (its prediction errors are common to the flock and cancel) and in the flocking demo."""
    from flocktrack.engine.inproc import run_inproc

    for name in ("gu_hu_normal.toml", "gu_hu_intelligent.toml", "demo.toml"):
        _, sc = _scenario(name, [], **{"run.ticks": 200, "estimator.resilient_f": 1})
        metrics, roles, _ = run_inproc(sc)
        suspicions = sum(r.est.suspicions for r in roles.sensors)
        assert suspicions <= 0.01 * 200 * len(roles.sensors) * sc.estimator.rounds, (name, suspicions)
        s = metrics.summary()["suspicion"]
        assert s["false_suspicion_rate"] <= 0.01 and s["attackers"] == {}, (name, s)
