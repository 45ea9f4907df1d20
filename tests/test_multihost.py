"""Several hosts without Docker: network namespaces joined by a switch (tests/netns.py), one Zenoh router
per host (broker_cfg/mesh/), each host's processes on their local router, the routers meshed — a
lockstep run across them gives the single-host numbers, and a host whose cable is pulled for a few
seconds is noticed, carried on without, and rejoins.

Needs root and iproute2 (tests/provision.py installs iproute2 as root when it is absent); skipped with
the reason otherwise, and failed instead under CI.
"""

import json
import sys
from pathlib import Path

import pytest

from agent.scenario import parse_scenario
from agent.scenario import scenario_data
from flocktrack.record.reader import read_recording
from flocktrack.engine.run import run_inproc_to_dir
from flocktrack.deploy.mesh import mesh_configs

sys.path.insert(0, str(Path(__file__).resolve().parent))
import netns
from provision import network_namespaces, require

ROOT = Path(__file__).resolve().parents[1]
SCEN = ROOT / "scenarios"
MESH_DIR = ROOT / "broker_cfg" / "mesh"
HOSTS = ("a", "b", "c")
# gu_hu_normal has 10 sensors: host a runs the world, the target, the recorder and sensors 0-3,
# host b sensors 4-6, host c sensors 7-9
WHERE = {f"agent/{i}": ("a" if i < 4 else "b" if i < 7 else "c") for i in range(10)}
VICTIMS = [4, 5, 6]



@pytest.fixture
def net():
    require(network_namespaces)   # iproute2 installed as root if absent; skipped with the reason, failed under CI
    n = netns.Network(len(HOSTS))
    try:
        yield n
    finally:
        n.close()
        assert not any(ns in netns._ip("netns", "list").stdout for ns in [n.switch, *n.hosts])


def mesh_run(net, tmp_path: Path, sets: list[str], cut: dict | None = None, timeout_s: float = 150,
             sample_at: list[int] | None = None) -> dict:
    """Run gu_hu_normal across the three hosts (``sets`` over the scenario); ``cut``: pull a cable
    (tests/netns.py CutAndWatch); ``sample_at``: ticks at which the switch ports' byte counters are read
    into the timeline (bench/bench_mesh_traffic.py)."""
    cfgs = mesh_configs(list(zip(HOSTS, net.addrs)), tmp_path / "cfg")
    spec = {"out": str(tmp_path / "run"), "scenario": str(SCEN / "gu_hu_normal.toml"), "set": sets,
            "hosts": [{"name": h, "wrap": net.wrap(i) if i else [], "router": str(cfgs[h]) if i else None}
                      for i, h in enumerate(HOSTS)],
            "where": WHERE, "hub_config": str(cfgs["a"]), "timeout_s": timeout_s}
    if cut:
        spec["cut"] = {"switch": net.switch, **cut}
    if sample_at:
        spec["sample"] = {"switch": net.switch, "ports": [f"p{i}" for i in range(len(HOSTS))], "at_ticks": sample_at}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    # the launcher runs on host a: its embedded router is host a's router
    r = net.run(0, sys.executable, str(ROOT / "tests" / "netns.py"), "mesh-run", str(tmp_path / "spec.json"),
                cwd=str(ROOT), capture_output=True, text=True, timeout=timeout_s + 270)   # the run, then its scoring
    assert r.returncode == 0, (r.stdout[-3000:], r.stderr[-3000:])
    return json.loads((tmp_path / "run" / "run.json").read_text())


def test_committed_mesh_configs_are_the_generated_ones(tmp_path):
    import zenoh

    paths = mesh_configs([("a", "192.0.2.1"), ("b", "192.0.2.2"), ("c", "192.0.2.3")], tmp_path)
    for p in paths.values():
        assert (MESH_DIR / p.name).read_text() == p.read_text(), f"regenerate broker_cfg/mesh/{p.name}"
        zenoh.Config.from_file(str(MESH_DIR / p.name))
    c = json.loads("\n".join(paths["c"].read_text().splitlines()[1:]))
    assert c["connect"]["endpoints"] == ["tcp/192.0.2.1:7447", "tcp/192.0.2.2:7447"]  # c dials a and b
    assert c["transport"]["link"]["tx"]["lease"] == 1000
    zenoh.Config.from_file(str(MESH_DIR / "client.json5"))


def test_lockstep_across_hosts_equals_single_host(net, tmp_path):
    sets = ["run.ticks=60", 'run.mode="lockstep"']
    info = mesh_run(net, tmp_path, sets)
    assert info["rc"] == 0 and info["recording_complete"], info
    assert {"router/b", "router/c"} <= set(info["exits"])
    data = scenario_data(str(SCEN / "gu_hu_normal.toml"), sets)
    run_inproc_to_dir(parse_scenario(data, "gu_hu_normal.toml"), data, tmp_path / "in")
    assert json.loads((tmp_path / "run" / "summary.json").read_text()) == \
        json.loads((tmp_path / "in" / "summary.json").read_text())
    assert (tmp_path / "run" / "metrics.csv").read_bytes() == (tmp_path / "in" / "metrics.csv").read_bytes()


@pytest.mark.slow
def test_cut_a_hosts_link_and_heal_it(net, tmp_path):
    # enough ticks after the heal for host b to reconnect (~0.5 s) even when the world, not waiting for the
    # dead, runs through the 3 s cut at full lockstep speed (~25–40 ticks/s)
    ticks, down_s = 400, 3.0
    # lockstep with a short per-wait deadline: waiting on a vanished host costs ≤ 0.3 s per wait
    info = mesh_run(net, tmp_path, [f"run.ticks={ticks}", 'run.mode="lockstep"', "run.deadline_s=0.3"],
                    cut={"port": "p1", "at_tick": 40, "down_s": down_s})
    assert info["rc"] == 0 and info["recording_complete"], info
    assert all(v == [0] for n, v in info["exits"].items() if n.startswith(("agent", "world", "target"))), info
    tl = json.loads((tmp_path / "run" / "timeline.json").read_text())
    cut = next(e for e in tl if e["event"] == "cut")
    heal = next(e for e in tl if e["event"] == "heal")
    victims = {f"agent/{i}" for i in VICTIMS}

    def member_times(alive: bool, after: float, before: float = float("inf")) -> dict[str, float]:
        out: dict[str, float] = {}
        for e in tl:
            if e["event"] == "member" and e["name"] in victims and e["alive"] is alive and after < e["t"] < before:
                out.setdefault(e["name"], e["t"])
        return out

    lost = member_times(False, cut["t"], heal["t"])
    back = member_times(True, heal["t"])
    assert set(lost) == victims and set(back) == victims, (lost, back)
    # only host b's processes were lost during the cut
    assert not [e for e in tl if e["event"] == "member" and not e["alive"] and e["name"] not in victims
                and cut["t"] < e["t"] < heal["t"]]
    detect = max(lost.values()) - cut["t"]
    recover = max(back.values()) - heal["t"]

    # the recording: the world's ticks mark host b's sensors dead during the cut and alive after it,
    # their estimates stop at the cut and resume after the heal, everyone finishes the run
    rec = read_recording(tmp_path / "run" / "recording.mcap")
    assert rec.complete
    alive = {m.k: m.alive for k, m, _ in rec.messages if k == "world/tick"}
    assert sorted(alive) == list(range(ticks))
    dead_ticks = [k for k, a in alive.items() if not all(a[i] for i in VICTIMS)]
    assert dead_ticks and dead_ticks == list(range(dead_ticks[0], dead_ticks[-1] + 1))  # one gap
    assert all(not any(alive[k][i] for i in VICTIMS) for k in dead_ticks)
    assert all(all(alive[k][j] for j in range(10) if j not in VICTIMS) for k in alive)
    est: dict[int, dict[int, float]] = {}
    for key, m, t in rec.messages:
        if key.startswith("agent/") and key.endswith("/estimate"):
            est.setdefault(m.src, {})[m.k] = t / 1e9
    for i in VICTIMS:
        missing = sorted(set(range(ticks)) - set(est[i]))
        assert missing and missing == list(range(missing[0], missing[-1] + 1)), (i, missing)
        assert set(dead_ticks) <= set(missing)
        assert ticks - 1 in est[i]                                   # rejoined and finished
    for j in set(range(10)) - set(VICTIMS):
        assert sorted(est[j]) == list(range(ticks)), j               # the others never stopped
    rejoin = min(t for i in VICTIMS for k, t in est[i].items() if t > heal["t"]) - heal["t"]
    result = {"cut_detected_s": round(detect, 3), "recovered_s": round(recover, 3),
              "first_estimate_after_heal_s": round(rejoin, 3), "gap_ticks": [dead_ticks[0], dead_ticks[-1]],
              "down_s": down_s}
    (tmp_path / "timings.json").write_text(json.dumps(result))
    print("multi-host cut/heal:", result)
    # prompt, not a benchmark: on an idle machine ~1.0 s to detect (lease 1 s + keep-alive 250 ms) and
    # ~0.3 s to recover (re-dial every ≤ 250 ms, each attempt given 500 ms); two loaded copies at once took
    # 1.14 s to recover (bench/flake_hunt.py) — the timings are in timings.json, the bounds leave room
    assert detect <= 3.0, result
    assert recover <= 3.0, result
