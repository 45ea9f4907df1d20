"""The run plan is the one description of a run: the roles' declared ports are what they really subscribe to and
publish (on LocalBus and in a real Zenoh run), the launcher spawns exactly its nodes, a placement is checked
with errors that name the file and the key, and in secure mode the router denies a node what it did not
declare."""

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from agent.bus import LocalBus, ZenohBus, key_matches
from agent.scenario import ScenarioError, load_scenario, parse_scenario, scenario_data
from flocktrack.engine.build import build_roles
from flocktrack.engine.run import run_zenoh_to_dir
from flocktrack.plan import RunPlan, build_plan, load_placement, parse_placement
from flocktrack.plan.cli import as_mermaid, intersects

ROOT = Path(__file__).resolve().parents[2]
SCEN = ROOT / "scenarios"


def _covered(key: str, patterns) -> bool:
    return any(key_matches(p, key) for p in patterns)


# ============================================================================ the plan itself

def test_plan_json_lists_every_node_with_its_name_host_reads_and_writes():
    p = subprocess.run([sys.executable, "-m", "flocktrack", "plan", "scenarios/demo.toml", "--format", "json"],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    doc = json.loads(p.stdout)
    names = [n["name"] for n in doc["nodes"]]
    assert set(names) == {"router/0", "launcher/0", "recorder/0", "dashboard/0", "target/0", "world/0",
                          *(f"agent/{i}" for i in range(12))}
    assert len(names) == len(set(names))
    for n in doc["nodes"]:
        assert {"name", "kind", "host", "writes", "reads", "restart"} <= set(n), n
        assert n["host"] == "local" and doc["hosts"][0]["name"] == "local"
    a3 = next(n for n in doc["nodes"] if n["name"] == "agent/3")
    assert "agent/3/state" in a3["writes"] and "agent/*/to/3/xchg" in a3["reads"]
    assert not any("agent/4" in k for k in a3["writes"])
    assert RunPlan.from_dict(doc).to_dict() == doc        # the JSON is the plan, both ways


def test_every_role_subscribes_to_what_it_declares_and_no_more():
    """On LocalBus, each role's subscriptions are its declared reads (the ACL grants exactly those)."""
    for name, sets in (("gu_hu_intelligent.toml", []), ("carrillo_uav.toml", []), ("carrillo_robust.toml", [])):
        sc = load_scenario(SCEN / name, sets)
        roles = build_roles(sc)
        for role in roles.all():
            bus = LocalBus()
            seen: list[str] = []
            sub = bus.subscribe
            bus.subscribe = lambda pattern, handler, _s=sub, _seen=seen, **kw: (_seen.append(pattern), _s(pattern, handler, **kw))
            role.attach(bus)
            reads = role.ports().reads
            assert seen and all(p in reads for p in seen), (name, type(role).__name__, seen, reads)


def test_the_recorder_reads_what_the_nodes_write_each_key_once():
    plan = build_plan(load_scenario(SCEN / "gu_hu_normal.toml"))
    rec = plan.node("recorder/0")
    writes = {w for n in plan.nodes for w in n.writes if "/to/" not in w}
    assert all(_covered(w.replace("*", "0"), rec.reads) for w in writes)
    assert "agent/*/state" in rec.reads and not any("/to/" in r for r in rec.reads)   # one subscription per family


@pytest.mark.parametrize("scenario", ["demo.toml", "carrillo_uav.toml"])
def test_observers_see_every_published_key_once_and_no_addressed_copy(scenario):
    plan = build_plan(load_scenario(SCEN / scenario), dashboard=True)
    published = {w.replace("*", "7").replace("{i}", "3") for n in plan.nodes for w in n.writes if "**" not in w}
    published |= {"control/pause", "control/kill"}
    for observer in ("recorder/0", "dashboard/0"):
        reads = plan.node(observer).reads
        for key in published:
            hits = sum(key_matches(p, key) for p in reads)
            assert hits == (0 if "/to/" in key else 1), (observer, key, hits)


def test_mermaid_draws_who_feeds_whom():
    text = as_mermaid(build_plan(load_scenario(SCEN / "demo.toml"), dashboard=True))
    assert text.startswith("flowchart LR")
    assert 'agents_local["agent/0–11<br/>12 sensors"]' in text
    assert 'world_0 -->|"world/event, world/tick"| agents_local' in text
    assert 'agents_local -->|"agent/*/state"| world_0' in text
    assert intersects("agent/*/to/3/xchg", "agent/4/to/*/xchg") and not intersects("agent/3/state", "agent/*/meas")
    assert intersects("control/**", "control/kill") and intersects("**", "a/b")


# ============================================================================ placements

HOSTS = """run = "lab"
[hosts.a]
address = "10.0.0.1"
[hosts.b]
address = "10.0.0.2"
port = 7448
[place]
"agent/0-3" = "a"
"agent/4-9" = "b"
"*" = "a"
"""


def test_a_placement_puts_each_node_once_and_gives_every_host_its_own_router_launcher_recorder(tmp_path):
    (tmp_path / "hosts.toml").write_text(HOSTS)
    plan = build_plan(load_scenario(SCEN / "gu_hu_normal.toml"), placement=load_placement(tmp_path / "hosts.toml"))
    assert plan.run == "lab" and [h.name for h in plan.hosts] == ["a", "b"]
    where = {n.name: n.host for n in plan.nodes}
    assert {where[f"agent/{i}"] for i in range(4)} == {"a"} and {where[f"agent/{i}"] for i in range(4, 10)} == {"b"}
    assert where["world/0"] == where["target/0"] == "a"
    for h in ("a", "b"):
        assert {f"router/{h}", f"launcher/{h}", f"recorder/{h}"} <= {n.name for n in plan.on(h)}
    # a host's recorder shard records what its own nodes write
    assert _covered("agent/5/state", plan.node("recorder/b").reads)
    assert not _covered("agent/2/state", plan.node("recorder/b").reads)
    assert not _covered("world/tick", plan.node("recorder/b").reads)
    assert _covered("world/tick", plan.node("recorder/a").reads)
    world = plan.node("world/0").args
    assert [world[i + 1] for i, a in enumerate(world) if a == "--expect"] == [
        "launcher/a", "launcher/b", "recorder/a", "recorder/b"]
    assert plan.host("b").endpoint == "tcp/10.0.0.2:7448"
    # a sensor sends another host one copy of a payload (its hosts' map, its own host's inbox); observers
    # never read those copies
    s5 = plan.node("agent/5")
    assert s5.args[s5.args.index("--hosts") + 1] == "a:0-3,b:4-9"
    assert "agent/5/via/*/xchg" in s5.writes and "agent/*/via/b/xchg" in s5.reads
    assert "agent/*/via/a/xchg" in plan.node("agent/2").reads
    for observer in ("recorder/a", "recorder/b"):
        assert not any("/via/" in r for r in plan.node(observer).reads)
    assert not any("/via/" in k for k in plan.observed())


def test_a_waiting_host_names_its_router_links_by_the_ids_the_routers_are_given(tmp_path):
    from flocktrack.deploy.mesh import host_router_config, router_links

    (tmp_path / "hosts.toml").write_text(HOSTS.replace("[place]", '[hosts.c]\naddress = "10.0.0.3"\n[place]'))
    plan = build_plan(load_scenario(SCEN / "gu_hu_normal.toml"), placement=load_placement(tmp_path / "hosts.toml"))
    ids = {h: host_router_config(plan, h)["id"] for h in ("a", "b", "c")}   # what each router is told to be
    assert router_links(plan, "b", {ids["a"]}) == "router links: a up, c down (c dials this router)"
    assert router_links(plan, "c", {ids["b"], "an unrelated router"}) == \
        "router links: a down (dialling tcp/10.0.0.1:7447), b up"
    assert router_links(plan, "a", set(ids.values())) == "router links: b up, c up"


@pytest.mark.parametrize("text, key, fix", [
    (HOSTS.replace('"agent/4-9" = "b"', '"agent/4-12" = "b"'), "place.'agent/4-12'", None),
    (HOSTS.replace('"agent/4-9" = "b"', '"agent/4-9" = "c"'), "place.'agent/4-9'", "use one of a, b"),
    (HOSTS.replace('"*" = "a"', '"agent/3-5" = "b"'), "place.'agent/3-5'", "place each node once"),
    (HOSTS.replace('"*" = "a"\n', ""), "place", '"*" = "a"'),
    (HOSTS.replace('address = "10.0.0.2"', 'address = "10.0.0.1"\nport = 7447').replace("port = 7448\n", ""),
     "hosts.b.address", "its own address"),
    (HOSTS.replace('address = "10.0.0.2"', "address = 12"), "hosts.b.address", None),
    (HOSTS.replace("[hosts.b]", "[hosts.B]"), "hosts.B", None),
    (HOSTS + '"recorder/a" = "a"\n', "place.'recorder/a'", "remove the line"),
    (HOSTS.replace("port = 7448", "prot = 7448"), "hosts.b.prot", None),
    ('run = "lab"\n', "hosts", None),
])
def test_a_bad_placement_is_one_error_naming_the_file_the_key_and_the_fix(tmp_path, text, key, fix):
    import tomllib

    sc = load_scenario(SCEN / "gu_hu_normal.toml")
    with pytest.raises(ScenarioError) as e:
        build_plan(sc, placement=parse_placement(tomllib.loads(text), "hosts.toml"))
    assert e.value.source == "hosts.toml" and e.value.key == key and e.value.fix, str(e.value)
    if fix:
        assert fix in e.value.fix, str(e.value)


def test_plan_check_says_a_placement_fits_or_names_the_problem(tmp_path):
    (tmp_path / "hosts.toml").write_text(HOSTS)
    ok = subprocess.run([sys.executable, "-m", "flocktrack", "plan", "gu_hu_normal", "--placement",
                         str(tmp_path / "hosts.toml"), "--check"], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and "placed once (a: 10, b: 9 nodes)" in ok.stdout, ok.stdout + ok.stderr
    (tmp_path / "bad.toml").write_text(HOSTS.replace('address = "10.0.0.2"', 'address = "nosuch.invalid"'))
    bad = subprocess.run([sys.executable, "-m", "flocktrack", "plan", "gu_hu_normal", "--placement",
                          str(tmp_path / "bad.toml"), "--check"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "[hosts.b.address] 'nosuch.invalid' does not resolve" in bad.stderr, bad.stderr
    assert "Traceback" not in bad.stderr


# ============================================================================ the contract in a real run

def test_in_a_real_zenoh_run_every_node_publishes_only_what_it_declared_and_the_launcher_spawns_the_plan(tmp_path):
    data = scenario_data(str(SCEN / "gu_hu_intelligent.toml"), [], **{"run.ticks": 30})
    sc = parse_scenario(data, "gu_hu_intelligent.toml")
    summary, info = run_zenoh_to_dir(sc, data, tmp_path, quiet=True, timeout_s=300)
    assert info["rc"] == 0, info
    plan = RunPlan.from_json((tmp_path / "plan.json").read_text())
    events = json.loads((tmp_path / "events.json").read_text())
    spawned = {e["name"] for e in events if e["event"] == "spawn"}
    assert spawned == {n.name for n in plan.processes()} == set(info["exits"])
    published = 0
    for n in plan.processes():
        stats = json.loads((tmp_path / "stats" / f"{n.slug}.json").read_text())
        assert stats.get("undeclared", {}) == {}, n.name
        for key in stats.get("sent_by_key", {}):
            assert _covered(key, n.writes), (n.name, key, n.writes)
            published += 1
    assert published > 30
    # and what was recorded was written by the node whose key prefix it bears, under a declared key
    recorded = json.loads((tmp_path / "stats" / "recorder-0.json").read_text())["recorded_by_key"]
    owners = {n.name: n for n in plan.nodes}
    for key in recorded:
        owner = owners.get("/".join(key.split("/")[:2])) or next(n for n in plan.nodes if _covered(key, n.writes))
        assert _covered(key, owner.writes), key


def test_in_secure_mode_the_router_denies_a_node_what_it_did_not_declare(tmp_path):
    """A deliberately misbehaving sensor: its bus counts and logs the undeclared put; the router drops it
    (a sensor that reads the key never gets it), while the world's own put of the same key arrives."""
    from flocktrack.deploy.keys import make_keys
    from flocktrack.launch.launcher import free_port, open_router

    sc = parse_scenario(scenario_data(str(SCEN / "gu_hu_normal.toml"), ["sensors.n=3"]), "gu_hu_normal.toml")
    plan = build_plan(sc, run="contract", dashboard=True)
    ks = make_keys(tmp_path / "keys", plan)
    port = free_port()
    router = open_router(port, config_file=ks.router(), proto="tls")
    endpoint = f"tls/localhost:{port}"
    got: list[str] = []
    try:
        conf = zenoh.Config.from_file(str(ks.client("agent-1")))
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        listener = zenoh.open(conf)
        sub = listener.declare_subscriber("ft/contract/world/tick", lambda s: got.append(s.payload.to_bytes().decode()))
        rogue = ZenohBus("contract", connect=endpoint, config_file=str(ks.client("agent-2")))
        rogue.restrict_writes(plan.node("agent/2").writes)
        world = ZenohBus("contract", connect=endpoint, config_file=str(ks.client("world-0")))
        time.sleep(0.8)
        for _ in range(3):
            rogue.publish_raw("world/tick", b"rogue")
            world.publish_raw("world/tick", b"world")
        time.sleep(0.8)
        assert rogue.stats.undeclared == {"world/tick": 3}
        assert got == ["world"] * 3, got
        sub.undeclare()
        for b in (rogue, world):
            b.close()
        listener.close()
    finally:
        router.close()


def test_the_architecture_page_draws_the_demos_plan_as_it_is():
    text = (ROOT / "docs" / "architecture.md").read_text()
    block = text.split("```mermaid\n", 1)[1].split("```", 1)[0]
    assert block == as_mermaid(build_plan(load_scenario(SCEN / "demo.toml"), dashboard=True)), \
        "regenerate with `flocktrack plan scenarios/demo.toml --format mermaid`"
