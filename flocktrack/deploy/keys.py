"""Credentials for a secure deployment: a CA, one certificate and one password per process, the router's
access-control list and one Zenoh config per process — ``flocktrack keys SCENARIO --out DIR``.

Every node of the run plan (:mod:`flocktrack.plan`) has an *identity*: its name written with a dash
(``router-0``, ``launcher-0``, ``world-0``, ``target-0``, ``recorder-0``, ``dashboard-0``, ``agent-0`` …,
``fusion-0``; with a placement ``router-a``, ``launcher-a``, ``recorder-a`` … per host). An identity is
(certificate common name = user name = identity). The router admits a client only over TLS with a
client certificate signed by the run's CA (mTLS) *and* the identity's user/password; its access
control then matches the link to the identity by both (``cert_common_names`` AND ``usernames``) and
applies that identity's rules, ``default_permission: deny`` for everything else. The rules are the node's
declared ports, nothing more:

* ``put`` in: exactly the keys the node declares it writes (``agent-3``: ``agent/3/meas``, ``agent/3/state``,
  ``agent/3/to/*/xchg`` …; ``world-0``: ``world/tick``, ``world/event``, ``world/end``);
* ``declare_subscriber`` in and ``put`` out: exactly the keys it declares it reads (``agent-3``: the tick,
  the truth, its own inbox ``agent/*/to/3/xchg`` …);
* its own liveliness token ``ft/<run>/alive/<name>`` (``agent-3`` → ``alive/agent/3``), while everyone may
  watch ``ft/<run>/alive/**``.

Nobody may ``delete``, query or declare a queryable. Router-to-router links of a mesh (the plan's routers)
are trusted with ``ft/<run>/**``.

Files written to DIR (see :class:`KeySet`)::

    keys.json              manifest: run name, identities, endpoint, hosts
    plan.json              the run plan the identities and the ACL are made from
    ca.pem  ca.key         the CA (keep ca.key off the hosts: it is needed only to issue more certs)
    certs/<id>.pem/.key    one certificate + private key per identity (CN = identity)
    passwords.txt          the router's user:password dictionary (mode 0600)
    acl.json5              the access_control block
    router.json5           the router's full config (broker_cfg/secure.json5 + TLS + auth + ACL)
    clients/<id>.json5     one client config per process (TLS + mTLS + user/password)
"""

from __future__ import annotations

import datetime as _dt
import ipaddress
import json
import os
import secrets
import sys
from dataclasses import dataclass, field
from pathlib import Path

from flocktrack.resources import add_scenario_argument, load_json5

SECURE_TEMPLATE = "secure.json5"   # the secure router's template: broker_cfg/secure.json5 of the package

ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
                "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"]
DEFAULT_HOSTS = ("localhost", "127.0.0.1", "::1")

def identities(plan) -> list[str]:
    """Every identity of a run plan: its routers first, then every other node's (``agent/3`` → ``agent-3``)."""
    routers = [n.slug for n in plan.nodes if n.kind == "router"]
    return routers + [n.slug for n in plan.nodes if n.kind != "router"]


# ============================================================================ the ACL

def acl(plan) -> dict:
    """The router's ``access_control`` block for a run plan (default deny): each node may put what it declares
    it writes and read what it declares it reads (:mod:`agent.ports`), and nothing else."""
    p = f"ft/{plan.run}/"
    rules: list[dict] = []
    subjects: list[dict] = []
    policies: list[dict] = []

    def rule(rid: str, messages: list[str], flows: list[str], keys) -> str:
        rules.append({"id": rid, "permission": "allow", "flows": flows, "messages": messages,
                      "key_exprs": [p + k for k in keys]})
        return rid

    # shared by every client: see who is alive, and see others' subscriptions (a publisher's write
    # filtering needs the subscribers' declarations)
    common = [rule("watch-members", ["declare_liveliness_subscriber", "liveliness_query"], ["ingress"], ["alive/**"]),
              rule("see-members", ["liveliness_token", "reply"], ["egress"], ["alive/**"]),
              rule("see-subscribers", ["declare_subscriber"], ["egress"], ["**"])]
    for node in plan.nodes:
        if node.kind == "router":
            continue
        ident = node.slug
        own = []
        if node.reads:
            own.append(rule(f"{ident}-read", ["declare_subscriber"], ["ingress"], node.reads))
            own.append(rule(f"{ident}-recv", ["put"], ["egress"], node.reads))
        if node.writes:
            own.append(rule(f"{ident}-write", ["put"], ["ingress"], node.writes))
        if node.member:
            own.append(rule(f"{ident}-token", ["liveliness_token"], ["ingress"], [f"alive/{node.name}"]))
        subjects.append({"id": ident, "cert_common_names": [ident], "usernames": [ident]})
        policies.append({"id": ident, "rules": own + common, "subjects": [ident]})
    # router-to-router links of a mesh: trusted with the whole run (they carry everyone's traffic;
    # each router enforces the rules above on its own clients)
    trusted = rule("mesh-all", ALL_MESSAGES, ["ingress", "egress"], ["**"])
    alive = rule("mesh-alive", ["liveliness_token", "declare_liveliness_subscriber", "liveliness_query", "reply"],
                 ["ingress", "egress"], ["alive/**"])
    rids = [n.slug for n in plan.nodes if n.kind == "router"]
    for r in rids:
        subjects.append({"id": r, "cert_common_names": [r], "usernames": [r]})
    policies.append({"id": "routers", "rules": [trusted, alive], "subjects": rids})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


# ============================================================================ certificates

def write_private(path: Path, data: bytes | str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(data, str):
        data = data.encode()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _new_key():
    try:
        from cryptography.hazmat.primitives.asymmetric import ec
    except ImportError as exc:  # pragma: no cover - a dependency of the package
        raise SystemExit("flocktrack keys needs the `cryptography` package: pip install cryptography") from exc

    return ec.generate_private_key(ec.SECP256R1())


def key_pem(key) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def make_ca(days: int = 365, cn: str = "flocktrack CA"):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import NameOID

    key = _new_key()
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])
    now = _dt.datetime.now(_dt.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - _dt.timedelta(days=1)).not_valid_after(now + _dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    return key, cert


def issue(ca_key, ca_cert, cn: str, hosts: list[str] = (), days: int = 365):
    """A leaf certificate with CN = ``cn`` for both TLS server and client use. Its SANs are DNS:cn plus
    ``hosts`` (names → DNS, addresses → IP): a client checks the router's certificate against the host
    name of the endpoint it dials (``tls/localhost:7447`` → DNS:localhost, ``tls/10.0.0.1:7447`` →
    IP:10.0.0.1)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    key = _new_key()
    sans: list = [x509.DNSName(cn)]
    for h in hosts:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            if x509.DNSName(h) not in sans:
                sans.append(x509.DNSName(h))
    now = _dt.datetime.now(_dt.timezone.utc)
    cert = (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)]))
            .issuer_name(ca_cert.subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - _dt.timedelta(days=1)).not_valid_after(now + _dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=False,
                                         crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))
    return key, cert


def cert_pem(cert) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return cert.public_bytes(serialization.Encoding.PEM)


# ============================================================================ configs

def _merge(base: dict, extra: dict) -> dict:
    out = dict(base)
    for k, v in extra.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def tls_block(ks_dir: Path, ident: str, listen: bool, connect: bool) -> dict:
    d = ks_dir.resolve()
    tls: dict = {"root_ca_certificate": str(d / "ca.pem"), "enable_mtls": True, "verify_name_on_connect": True}
    if listen:
        tls["listen_private_key"] = str(d / "certs" / f"{ident}.key")
        tls["listen_certificate"] = str(d / "certs" / f"{ident}.pem")
    if connect:
        tls["connect_private_key"] = str(d / "certs" / f"{ident}.key")
        tls["connect_certificate"] = str(d / "certs" / f"{ident}.pem")
    return tls


def client_config(ks_dir: Path, ident: str, password: str, endpoint: str, *, lease_ms: int = 2000,
                  keep_alive: int = 4) -> dict:
    return {
        "mode": "client",
        "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {
            "link": {"protocols": ["tls"], "tx": {"lease": lease_ms, "keep_alive": keep_alive},
                     "tls": tls_block(ks_dir, ident, listen=False, connect=True)},
            "auth": {"usrpwd": {"user": ident, "password": password}},
        },
    }


def router_config(ks_dir: Path, ident: str, password: str, listen: list[str], *, connect: list[str] = (),
                  acl_block: dict | None = None, template: str | Path = SECURE_TEMPLATE) -> dict:
    conf = load_json5(template)
    conf = _merge(conf, {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "connect": {"endpoints": list(connect)},
        "transport": {
            "link": {"protocols": ["tls"], "tls": tls_block(ks_dir, ident, listen=True, connect=bool(connect))},
            "auth": {"usrpwd": {"user": ident, "password": password,
                                "dictionary_file": str((ks_dir / "passwords.txt").resolve())}},
        },
    })
    if acl_block is not None:
        conf["access_control"] = acl_block
    return conf


def _dump(path: Path, conf: dict, header: str) -> None:
    write_private(path, f"// {header}\n" + json.dumps(conf, indent=2) + "\n")


def format_acl(block: dict, header: str) -> str:
    """The ``access_control`` block as json5 text, one rule / subject / policy per line."""
    lines = [f"// {h}" for h in header.splitlines()]
    lines.append("{")
    lines.append(f'  "enabled": {json.dumps(block["enabled"])},')
    lines.append(f'  "default_permission": {json.dumps(block["default_permission"])},')
    for part in ("rules", "subjects", "policies"):
        lines.append(f'  "{part}": [')
        lines += [f"    {json.dumps(item)}," for item in block[part]]
        lines.append("  ],")
    lines.append("}")
    return "\n".join(lines) + "\n"


# ============================================================================ key sets

@dataclass
class KeySet:
    """A directory made by :func:`make_keys`."""

    dir: Path
    run: str
    identities: list[str]
    endpoint: str
    hosts: list[str] = field(default_factory=list)
    routers: list[str] = field(default_factory=lambda: ["router-0"])

    def client(self, ident: str) -> Path:
        return self.dir / "clients" / f"{ident}.json5"

    def router(self, ident: str | None = None) -> Path:
        """The config of router ``ident`` (default: the plan's first router)."""
        return self.dir / f"{ident or self.routers[0]}.json5"

    def plan(self):
        """The run plan the key set was made for."""
        from flocktrack.plan.model import RunPlan

        return RunPlan.from_json((self.dir / "plan.json").read_text())

    def covers(self, plan) -> list[str]:
        """The identities of ``plan`` this key set has no credentials for (empty: it covers the plan)."""
        have = set(self.identities)
        return [i for i in identities(plan) if i not in have]

    def password(self, ident: str) -> str:
        for line in (self.dir / "passwords.txt").read_text().splitlines():
            user, _, pw = line.partition(":")
            if user == ident:
                return pw
        raise KeyError(ident)

    def cert(self, ident: str) -> tuple[Path, Path]:
        return self.dir / "certs" / f"{ident}.pem", self.dir / "certs" / f"{ident}.key"

    @property
    def ca(self) -> Path:
        return self.dir / "ca.pem"

    def web_cert(self) -> tuple[Path, Path]:
        """The dashboard's HTTPS certificate and key (``certs/dashboard-web.*``, a server certificate of the
        run's CA for its host names), made now if this key set predates it."""
        pem, key = self.cert(WEB_IDENT)
        if not pem.exists():
            from cryptography import x509
            from cryptography.hazmat.primitives import serialization

            ca_key = serialization.load_pem_private_key((self.dir / "ca.key").read_bytes(), None)
            ca_cert = x509.load_pem_x509_certificate(self.ca.read_bytes())
            _issue_to(self.dir, ca_key, ca_cert, WEB_IDENT, hosts=list(self.hosts or DEFAULT_HOSTS))
        return pem, key


#: the dashboard page's HTTPS identity (a server certificate; not a Zenoh identity, it has no password)
WEB_IDENT = "dashboard-web"


def _issue_to(out: Path, ca_key, ca_cert, ident: str, *, hosts: list[str], days: int = 365) -> None:
    key, cert = issue(ca_key, ca_cert, ident, hosts=hosts, days=days)
    write_private(out / "certs" / f"{ident}.key", key_pem(key))
    (out / "certs" / f"{ident}.pem").write_bytes(cert_pem(cert))


def make_keys(out: str | Path, plan, endpoint: str = "tls/localhost:7447", hosts: list[str] = DEFAULT_HOSTS, *,
               lease_ms: int = 2000, days: int = 365) -> KeySet:
    """Write a complete key set for the run plan ``plan`` to ``out``: a certificate and a password per node,
    the ACL of :func:`acl`, one config per router (each valid for ``hosts``) and one per client."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    routers = [n.slug for n in plan.nodes if n.kind == "router"]
    ca_key, ca_cert = make_ca(days)
    write_private(out / "ca.key", key_pem(ca_key))
    (out / "ca.pem").write_bytes(cert_pem(ca_cert))
    passwords: dict[str, str] = {}
    idents = identities(plan)
    for ident in idents:
        _issue_to(out, ca_key, ca_cert, ident, hosts=list(hosts) if ident in routers else [], days=days)
        passwords[ident] = secrets.token_urlsafe(24)
    _issue_to(out, ca_key, ca_cert, WEB_IDENT, hosts=list(hosts), days=days)
    write_private(out / "passwords.txt", "".join(f"{u}:{p}\n" for u, p in passwords.items()))
    block = acl(plan)
    (out / "acl.json5").write_text(format_acl(block, f"access_control for run {plan.run} ({len(idents)} identities), "
                                                     f"generated by `flocktrack keys`; it is also in each router's config"))
    (out / "plan.json").write_text(plan.to_json())
    port = endpoint.rsplit(":", 1)[-1]
    for r in routers:
        conf = router_config(out, r, passwords[r], [f"tls/[::]:{port}"], acl_block=block)
        _dump(out / f"{r}.json5", conf, f"router {r} of run {plan.run} (generated by flocktrack keys)")
    for ident in idents:
        if ident in routers:
            continue
        _dump(out / "clients" / f"{ident}.json5", client_config(out, ident, passwords[ident], endpoint, lease_ms=lease_ms),
              f"client {ident} of run {plan.run} (generated by flocktrack keys)")
    manifest = {"run": plan.run, "endpoint": endpoint, "hosts": list(hosts), "routers": routers, "identities": idents}
    (out / "keys.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return KeySet(out, plan.run, idents, endpoint, list(hosts), routers)


class KeySetError(ValueError):
    """A key set that does not fit the run; the message says how to make one that does."""


def load_keys(path: str | Path) -> KeySet:
    path = Path(path)
    m = json.loads((path / "keys.json").read_text())
    if "identities" not in m or "n_sensors" in m:
        raise KeySetError(f"{path}: a key set of an older flocktrack (identities named otherwise); make a new one with "
                         f"`flocktrack keys SCENARIO --out DIR`")
    return KeySet(path, m["run"], list(m["identities"]), m["endpoint"], m.get("hosts", []), m["routers"])


# ============================================================================ CLI

def cmd_keys(args) -> int:
    from agent.scenario import parse_scenario, scenario_data

    from flocktrack.plan import build_plan, load_placement

    data = scenario_data(args.scenario, args.set or [])
    sc = parse_scenario(data, args.scenario)
    placement = load_placement(args.placement) if args.placement else None
    plan = build_plan(sc, run=args.run, placement=placement, dashboard=True)
    hosts = list(DEFAULT_HOSTS) + [h for h in (args.host or []) if h not in DEFAULT_HOSTS]
    if placement is not None:
        hosts += [h.address for h in placement.hosts if h.address not in hosts]
    ks = make_keys(args.out, plan, endpoint=f"tls/{args.endpoint_host}:{args.port}", hosts=hosts)
    print(f"wrote {ks.dir}: CA, {len(ks.identities)} certificates and passwords (one per node of the run plan), "
          f"acl.json5 and the routers' configs for run {plan.run!r}; clients/<id>.json5 connect to "
          f"{ks.endpoint}.\nrun it: flocktrack run {args.scenario} --secure --keys {ks.dir} --out DIR",
          file=sys.stderr)
    return 0


def register(subparsers) -> None:
    """Add ``flocktrack keys SCENARIO --out DIR`` to the CLI."""
    k = subparsers.add_parser("keys", help="make a CA, per-process certificates/passwords, the router ACL and configs")
    add_scenario_argument(k)
    k.add_argument("--out", required=True, help="directory for the key set")
    k.add_argument("--run", help="run name the ACL is written for (key prefix ft/<run>/); default: the scenario's")
    k.add_argument("--port", type=int, default=7447, help="router TLS port the client configs connect to")
    k.add_argument("--endpoint-host", default="localhost", help="host name the clients dial (must be in the SANs)")
    k.add_argument("--host", action="append", metavar="NAME|IP",
                   help="extra router SAN (repeat): a host name or address the clients dial the router by")
    k.add_argument("--placement", metavar="HOSTS.toml",
                   help="a placement: one router identity per host (router-HOST), its address among the SANs")
    k.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override a scenario key")
    k.set_defaults(fn=cmd_keys)




def prepare_keys(path: str | Path, plan) -> KeySet:
    """The key set in ``path`` (it must cover every node of ``plan``), or a new one for ``plan`` there."""
    path = Path(path)
    if (path / "keys.json").exists():
        ks = load_keys(path)
        missing = ks.covers(plan)
        if missing:
            raise KeySetError(f"{path} has no credentials for {', '.join(missing[:5])}"
                             f"{' …' if len(missing) > 5 else ''} of this run: make a new set with "
                             f"`flocktrack keys SCENARIO --out DIR`")
        return ks
    return make_keys(path, plan)


__all__ = ["make_keys", "load_keys", "prepare_keys", "KeySet", "acl", "identities", "register",
           "issue", "make_ca"]
