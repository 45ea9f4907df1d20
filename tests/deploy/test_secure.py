"""Per-process credentials, TLS + mTLS + user/password and the router ACL — shown on the live system:
a real router opened with the generated config, real clients with the generated configs, and a real
secure run with an impostor publishing under other processes' keys."""

import argparse
import dataclasses
import json
import os
import stat
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec

from agent.scenario import parse_scenario
from agent import wire
from agent.scenario import scenario_data
from flocktrack.deploy.keys import acl, identities, issue, load_keys, make_ca, make_keys, register, cert_pem, key_pem
from flocktrack.launch.launcher import free_port, open_router
from flocktrack.plan import build_plan
from flocktrack.record.reader import read_recording
from flocktrack.engine.run import run_inproc_to_dir, run_zenoh_to_dir

ROOT = Path(__file__).resolve().parents[2]
SCEN = ROOT / "scenarios"
RUN = "sec"


# ============================================================================ helpers

def plan_of(run: str, n: int, scenario: str = "gu_hu_normal.toml"):
    """The run plan of a scenario with ``n`` sensors (and the dashboard) under run name ``run``."""
    data = scenario_data(str(SCEN / scenario), [f"sensors.n={n}"])
    return build_plan(parse_scenario(data, scenario), run=run, dashboard=True)


@pytest.fixture(scope="module")
def keyset(tmp_path_factory):
    return make_keys(tmp_path_factory.mktemp("keys"), plan_of(RUN, 6))


@pytest.fixture
def router(keyset):
    port = free_port()
    r = open_router(port, config_file=keyset.router(), proto="tls")
    yield f"tls/localhost:{port}"
    r.close()


def client_conf(keyset, ident: str, endpoint: str, **overrides) -> zenoh.Config:
    c = zenoh.Config.from_file(str(keyset.client(ident)))
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    for path, value in overrides.items():
        c.insert_json5(path, json.dumps(value))
    return c


def can_connect(conf: zenoh.Config) -> bool:
    try:
        s = zenoh.open(conf)
    except zenoh.ZError:
        return False
    s.close()
    return True


class Tap:
    """A subscriber session (default: the recorder's identity, subscribed to what it reads: every node's writes
    but the addressed copies)."""

    def __init__(self, keyset, endpoint, ident="recorder-0", patterns=None):
        self.got: list[tuple[str, bytes]] = []
        self.tokens: list[tuple[str, bool]] = []
        self.s = zenoh.open(client_conf(keyset, ident, endpoint))
        patterns = patterns or [f"ft/{RUN}/{k}" for k in keyset.plan().node("recorder/0").reads]
        self.subs = [self.s.declare_subscriber(pat, lambda smp: self.got.append((str(smp.key_expr),
                                                                                 smp.payload.to_bytes())))
                     for pat in patterns]
        self.lsub = self.s.liveliness().declare_subscriber(
            f"ft/{RUN}/alive/**", lambda smp: self.tokens.append((str(smp.key_expr), smp.kind == zenoh.SampleKind.PUT)),
            history=True)

    def keys(self) -> set[str]:
        return {k for k, _ in self.got}

    def close(self):
        for sub in self.subs:
            sub.undeclare()
        self.lsub.undeclare()
        self.s.close()


def settle(t=0.6):
    time.sleep(t)


# ============================================================================ the key set

def test_keys_command_writes_a_complete_key_set(tmp_path):
    ap = argparse.ArgumentParser()
    register(ap.add_subparsers())
    out = tmp_path / "k"
    args = ap.parse_args(["keys", str(SCEN / "gu_hu_normal.toml"), "--out", str(out), "--run", "demo1",
                          "--host", "10.9.8.7", "--host", "hub.example"])
    assert args.fn(args) == 0
    ks = load_keys(out)
    assert ks.run == "demo1" and ks.identities == identities(ks.plan())
    assert {f"agent-{i}" for i in range(10)} | {"router-0", "launcher-0", "world-0", "target-0", "recorder-0",
                                               "dashboard-0"} == set(ks.identities)
    ca = x509.load_pem_x509_certificate((out / "ca.pem").read_bytes())
    for ident in ks.identities:
        cert = x509.load_pem_x509_certificate(ks.cert(ident)[0].read_bytes())
        assert cert.subject.get_attributes_for_oid(x509.oid.NameOID.COMMON_NAME)[0].value == ident
        assert cert.issuer == ca.subject
        ca.public_key().verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(cert.signature_hash_algorithm))
        assert stat.S_IMODE(os.stat(ks.cert(ident)[1]).st_mode) == 0o600  # private keys are private
        if ident != "router-0":
            conf = json.loads("\n".join(ks.client(ident).read_text().splitlines()[1:]))
            assert conf["transport"]["auth"]["usrpwd"]["user"] == ident
            assert conf["transport"]["link"]["tls"]["enable_mtls"] is True
    sans = x509.load_pem_x509_certificate(ks.cert("router-0")[0].read_bytes()).extensions.get_extension_for_class(
        x509.SubjectAlternativeName).value
    assert {"localhost", "hub.example"} <= set(sans.get_values_for_type(x509.DNSName))
    assert {"127.0.0.1", "10.9.8.7"} <= {str(a) for a in sans.get_values_for_type(x509.IPAddress)}
    assert stat.S_IMODE(os.stat(out / "passwords.txt").st_mode) == 0o600
    assert len({ks.password(i) for i in ks.identities}) == len(ks.identities)
    # the router's config is a valid Zenoh config and carries the ACL
    zenoh.Config.from_file(str(ks.router()))


def test_acl_rules_are_the_nodes_declared_ports():
    """Each identity may put exactly what its node declares it writes and read exactly what it reads."""
    from agent.roles.sensor import SensorRole
    from topology.world import WorldRole

    plan = plan_of("r", 5)
    a = acl(plan)
    rules = {r["id"]: r for r in a["rules"]}
    assert a["default_permission"] == "deny" and a["enabled"]
    assert rules["agent-3-write"]["key_exprs"] == [f"ft/r/{k}" for k in SensorRole.PORTS.of(3).writes]
    assert rules["agent-3-read"]["key_exprs"] == [f"ft/r/{k}" for k in SensorRole.PORTS.of(3).reads]
    assert "ft/r/agent/*/to/3/xchg" in rules["agent-3-read"]["key_exprs"]      # its own inbox, no other
    assert rules["agent-3-write"]["messages"] == ["put"] and rules["agent-3-write"]["flows"] == ["ingress"]
    assert rules["world-0-write"]["key_exprs"] == [f"ft/r/{k}" for k in WorldRole.PORTS.writes]
    assert rules["target-0-write"]["key_exprs"] == ["ft/r/target/truth", "ft/r/target/state"]
    assert rules["dashboard-0-write"]["key_exprs"] == ["ft/r/control/**"]
    assert "recorder-0-write" not in rules
    assert rules["launcher-0-write"]["key_exprs"] == ["ft/r/launcher/event"]   # its fault acks, nothing else
    assert "ft/r/launcher/event" in rules["world-0-read"]["key_exprs"]
    for n in plan.nodes:     # every node's rules are its plan entry's
        if n.kind != "router":
            assert rules.get(f"{n.slug}-write", {}).get("key_exprs", []) == [f"ft/r/{k}" for k in n.writes], n.name
            assert rules.get(f"{n.slug}-read", {}).get("key_exprs", []) == [f"ft/r/{k}" for k in n.reads], n.name
    assert rules["agent-3-token"]["key_exprs"] == ["ft/r/alive/agent/3"]
    subj = {s["id"]: s for s in a["subjects"]}
    assert subj["agent-3"] == {"id": "agent-3", "cert_common_names": ["agent-3"], "usernames": ["agent-3"]}
    for p in a["policies"]:
        if p["id"] == "agent-3":
            assert "agent-4-write" not in p["rules"] and "world-write" not in p["rules"]


def test_committed_acl_template_is_the_generated_one():
    text = (ROOT / "broker_cfg" / "acl.json5").read_text()
    body = "\n".join(l for l in text.splitlines() if not l.startswith("//"))
    c = zenoh.Config()
    c.insert_json5("access_control", body)  # a valid access_control block for Zenoh
    assert json.loads(body.replace(",\n  ]", "\n  ]").replace("],\n}", "]\n}")) == acl(
        plan_of("demo", 12, "demo.toml")), \
        "regenerate broker_cfg/acl.json5 (see its header)"
    zenoh.Config.from_file(str(ROOT / "broker_cfg" / "secure.json5"))


# ============================================================================ who may connect

def test_only_clients_with_the_ca_a_certificate_and_their_password_connect(keyset, router, tmp_path):
    assert can_connect(client_conf(keyset, "agent-3", router))
    assert can_connect(client_conf(keyset, "agent-3", router.replace("localhost", "127.0.0.1")))  # IP SAN
    # no credentials at all / a wrong password / another identity's name with this password
    assert not can_connect(client_conf(keyset, "agent-3", router,
                                       **{"transport/auth/usrpwd/user": None, "transport/auth/usrpwd/password": None}))
    assert not can_connect(client_conf(keyset, "agent-3", router, **{"transport/auth/usrpwd/password": "guess"}))
    assert not can_connect(client_conf(keyset, "agent-3", router, **{"transport/auth/usrpwd/user": "agent-4"}))
    # without the CA the router's certificate is not trusted
    assert not can_connect(client_conf(keyset, "agent-3", router, **{"transport/link/tls/root_ca_certificate": None}))
    # without a client certificate (no mTLS)
    assert not can_connect(client_conf(keyset, "agent-3", router, **{"transport/link/tls/connect_private_key": None,
                                                                       "transport/link/tls/connect_certificate": None}))
    # a certificate with the right name from another CA
    k2, c2 = make_ca()
    lk, lc = issue(k2, c2, "agent-3")
    (tmp_path / "f.key").write_bytes(key_pem(lk))
    (tmp_path / "f.pem").write_bytes(cert_pem(lc))
    assert not can_connect(client_conf(keyset, "agent-3", router,
                                       **{"transport/link/tls/connect_private_key": str(tmp_path / "f.key"),
                                          "transport/link/tls/connect_certificate": str(tmp_path / "f.pem")}))
    # plain tcp on the TLS port
    c = zenoh.Config()
    c.insert_json5("mode", '"client"')
    c.insert_json5("connect/endpoints", json.dumps([router.replace("tls/localhost", "tcp/127.0.0.1")]))
    c.insert_json5("scouting/multicast/enabled", "false")
    assert not can_connect(c)


# ============================================================================ who may say what

def test_each_identity_puts_only_under_its_own_keys(keyset, router):
    tap = Tap(keyset, router)
    inbox4 = Tap(keyset, router, "agent-4", [f"ft/{RUN}/agent/*/to/4/xchg"])   # what is addressed to agent 4
    sessions = {i: zenoh.open(client_conf(keyset, i, router)) for i in ("agent-3", "world-0", "target-0",
                                                                        "dashboard-0", "recorder-0", "launcher-0")}
    settle()
    p = f"ft/{RUN}/"
    attempts = {
        "agent-3": ["agent/3/estimate", "agent/4/estimate", "agent/4/xchg", "agent/3x/estimate", "world/tick",
                    "world/end", "target/truth", "control/kill", "alive/agent/4", "agent/3/to/4/xchg",
                    "agent/4/to/3/xchg", "agent/4/to/5/xchg"],
        "world-0": ["world/tick", "world/event", "agent/1/state", "target/truth", "control/pause"],
        "target-0": ["target/truth", "target/state", "world/tick", "agent/0/estimate"],
        "dashboard-0": ["control/pause", "control/kill", "world/tick", "agent/0/xchg"],
        "recorder-0": ["world/tick", "agent/0/estimate", "control/pause"],
        "launcher-0": ["control/kill", "world/event", "launcher/other"],
    }
    for ident, keys in attempts.items():
        for k in keys:
            sessions[ident].put(p + k, ident.encode())
    sessions["agent-3"].put("ft/otherrun/agent/3/estimate", b"agent-3")  # the ACL is bound to its run
    settle()
    got = Counter((k[len(p):], v.decode()) for k, v in tap.got + inbox4.got)
    assert set(got) == {("agent/3/estimate", "agent-3"), ("agent/3/to/4/xchg", "agent-3"),
                        ("world/tick", "world-0"), ("world/event", "world-0"),
                        ("target/truth", "target-0"), ("target/state", "target-0"), ("control/pause", "dashboard-0"),
                        ("control/kill", "dashboard-0")}, got
    for s in sessions.values():
        s.close()
    tap.close()
    inbox4.close()


def test_liveliness_tokens_only_for_oneself(keyset, router):
    tap = Tap(keyset, router)
    s3 = zenoh.open(client_conf(keyset, "agent-3", router))
    toks = [s3.liveliness().declare_token(f"ft/{RUN}/alive/{n}") for n in ("agent/3", "agent/4", "world/0")]
    settle()
    assert {k for k, alive in tap.tokens if alive} == {f"ft/{RUN}/alive/agent/3"}
    for t in toks:
        t.undeclare()
    s3.close()
    tap.close()


def test_subscriptions_only_to_what_the_role_reads(keyset, router):
    """agent-3 cannot eavesdrop on what a sensor does not read (other agents' measurements and states,
    the target's state, the exchange payloads addressed to others or to observers), not even with a
    catch-all subscription; it does get what it reads (its own inbox)."""
    spy: list[str] = []
    s3 = zenoh.open(client_conf(keyset, "agent-3", router))
    subs = [s3.declare_subscriber(pat, lambda smp: spy.append(str(smp.key_expr)))
            for pat in (f"ft/{RUN}/**", f"ft/{RUN}/agent/4/meas", f"ft/{RUN}/target/state", f"ft/{RUN}/world/tick",
                        f"ft/{RUN}/agent/*/xchg", f"ft/{RUN}/agent/*/to/5/xchg", f"ft/{RUN}/agent/*/to/3/xchg")]
    w = zenoh.open(client_conf(keyset, "world-0", router))
    t = zenoh.open(client_conf(keyset, "target-0", router))
    a4 = zenoh.open(client_conf(keyset, "agent-4", router))
    settle()
    w.put(f"ft/{RUN}/world/tick", b"1")
    t.put(f"ft/{RUN}/target/state", b"1")
    a4.put(f"ft/{RUN}/agent/4/meas", b"1")
    a4.put(f"ft/{RUN}/agent/4/state", b"1")
    for k in ("agent/4/xchg", "agent/4/to/5/xchg", "agent/4/to/3/xchg"):
        a4.put(f"ft/{RUN}/{k}", b"1")
    settle()
    assert set(spy) == {f"ft/{RUN}/world/tick", f"ft/{RUN}/agent/4/to/3/xchg"}, spy   # its inbox, no other
    for sub in subs:
        sub.undeclare()
    for s in (s3, w, t, a4):
        s.close()


def test_a_mismatched_certificate_and_password_get_no_rights(keyset, router):
    """agent-4's certificate with agent-3's user and password: admitted by TLS and by the dictionary,
    but no ACL subject matches (certificate name AND user name), so it may do nothing."""
    tap = Tap(keyset, router)
    cert, key = keyset.cert("agent-4")
    c = client_conf(keyset, "agent-3", router, **{"transport/link/tls/connect_certificate": str(cert),
                                                  "transport/link/tls/connect_private_key": str(key)})
    s = zenoh.open(c)
    settle()
    for k in ("agent/3/estimate", "agent/4/estimate"):
        s.put(f"ft/{RUN}/{k}", b"x")
    settle()
    assert tap.got == []
    s.close()
    tap.close()


# ============================================================================ a live secure run with an impostor

class Impostor:
    """on_poll hook: a client with agent 3's credentials that forges, for every message it may read,
    messages under keys that are not its own — other sensors' estimates, exchange payloads and states,
    the world's tick and end, the target's truth and state, kill/pause controls — and declares other
    processes' liveliness tokens."""

    def __init__(self, keyset):
        self.keyset = keyset
        self.bus = None
        self.forged = Counter()
        self.seen_ticks = 0
        self.controls_sent = False
        self.read_estimates = 0

    def _put(self, key: str, msg) -> None:
        self.bus.publish(key, msg)
        self.forged[key.split("/")[0] + "/" + key.split("/")[-1]] += 1

    def _read_estimate(self, key: str, data: bytes) -> None:
        if key != "agent/4/estimate":       # (its own forgeries come back to it inside its session)
            self.read_estimates += 1

    def _forge(self, key: str, data: bytes) -> None:
        try:
            msg = wire.decode(key, data)
        except wire.WireError:
            return
        if key == "world/tick":
            self.seen_ticks += 1
            self._put("world/tick", dataclasses.replace(msg, links=[[] for _ in msg.links],
                                                        positions=msg.positions + 50.0))
            self._put("target/truth", wire.Truth(k=msg.k, t=msg.t, x=np.full(4, 1e3)))
            self._put("agent/4/state", wire.State(src=4, k=msg.k, pos=np.array([1e3, 1e3]), vel=np.zeros(2)))
            self._put("target/state", wire.State(k=msg.k, pos=np.array([1e3, 1e3]), vel=np.zeros(2)))
            # sensor 4's estimate, to the observers and handed to sensor 1 as if it had restarted (agent 3
            # reads no one's estimates: it cannot copy them, only make them up)
            forged = wire.Estimate(src=4, k=msg.k, x=np.full(4, 1e3), x_next=np.full(4, 1e3))
            self._put("agent/4/estimate", forged)
            self._put("agent/4/to/1/estimate", forged)
            if msg.k >= 20 and not self.controls_sent:
                self.controls_sent = True
                self._put("control/kill", wire.Control(verb="kill", args={"agent": 1}))
                self._put("control/pause", wire.Control(verb="pause", args={}))
                self._put("world/end", wire.End(k=msg.k, reason="impostor"))
        elif key.endswith("/xchg") and msg.src in (2, 4):
            j = 5 if msg.src == 2 else 4    # (as the sender, to the observers and to sensor 1's inbox)
            forged = dataclasses.replace(msg, src=j, payload={k: v + 1e3 for k, v in msg.payload.items()})
            self._put(f"agent/{j}/xchg", wire.Rounds(src=j, k=msg.k, payloads=[forged.payload]))
            self._put(f"agent/{j}/to/1/xchg", forged)

    def __call__(self, launcher) -> None:
        if self.bus is None:
            from agent.bus import ZenohBus

            self.bus = ZenohBus(launcher.run, connect=launcher.endpoint,
                                config_file=str(self.keyset.client("agent-3")))
            for pat in ("world/tick", "agent/*/to/3/xchg"):
                self.bus.subscribe_raw(pat, self._forge)
            self.bus.subscribe_raw("agent/*/estimate", self._read_estimate)
            for name in ("agent/9", "world/1"):
                self.bus.declare_token(name)
        self.bus.poll(0)

    def close(self):
        if self.bus is not None:
            self.bus.close()


def test_an_impostor_with_agent_3s_credentials_has_no_effect_on_a_live_run(tmp_path):
    data = scenario_data(str(SCEN / "gu_hu_intelligent.toml"), [], **{"run.ticks": 60, "run.mode": "lockstep"})
    sc = parse_scenario(data, "gu_hu_intelligent.toml")
    clean, _ = run_inproc_to_dir(sc, data, tmp_path / "in")
    keys = make_keys(tmp_path / "keys", build_plan(sc, run="impostor-run", dashboard=True))
    imp = Impostor(keys)
    try:
        summary, info = run_zenoh_to_dir(sc, data, tmp_path / "z", quiet=True, on_poll=imp, timeout_s=300,
                                         secure_dir=tmp_path / "keys")
    finally:
        imp.close()
    assert info["rc"] == 0 and info["secure"] and info["run"] == "impostor-run", info
    assert info["router"].startswith("tls/")
    # the impostor was connected (it read the ticks) and forged plenty
    assert imp.seen_ticks >= 20 and imp.controls_sent, imp.seen_ticks
    assert imp.read_estimates == 0      # a sensor reads only what is addressed to it: no one's estimates
    assert sum(imp.forged.values()) > 150 and {"world/tick", "agent/estimate", "agent/xchg", "world/end",
                                               "control/kill"} <= set(imp.forged), imp.forged
    # ... and nobody noticed: the same numbers as the clean in-process run
    assert summary == clean
    assert (tmp_path / "z" / "metrics.csv").read_bytes() == (tmp_path / "in" / "metrics.csv").read_bytes()
    # every recorded message was published by its legitimate owner (the processes' own counters)
    sent: Counter = Counter()
    for f in (tmp_path / "z" / "stats").glob("*.json"):
        sent.update(json.loads(f.read_text()).get("sent_by_key", {}))
    sent = Counter({k: v for k, v in sent.items() if not wire.addressed(k)})   # (recorded once, unaddressed)
    recorded = json.loads((tmp_path / "z" / "stats" / "recorder-0.json").read_text())["recorded_by_key"]
    assert dict(sent) == recorded
    rec = read_recording(tmp_path / "z" / "recording.mcap")
    assert rec.complete and [m.reason for k, m, _ in rec.messages if k == "world/end"] == ["done"]
    # no process was killed or paused, no message was dropped as invalid anywhere
    events = json.loads((tmp_path / "z" / "events.json").read_text())
    assert not [e for e in events if e["event"] in ("signal", "restart")], events
    assert all(v == [0] for v in info["exits"].values()), info["exits"]
    for f in (tmp_path / "z" / "stats").glob("agent-*.json"):
        assert not json.loads(f.read_text()).get("dropped"), f
