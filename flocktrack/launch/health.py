"""Health probes for containers: ``python -m flocktrack.launch.health CHECK ...`` exits 0 when every check
passes and 1 otherwise (one line on stderr says which check failed). The docker-compose file uses it
as the ``healthcheck`` of every service; it is also handy by hand.

Checks (any combination; each one given must pass):

* ``--tcp HOST:PORT``  a TCP connection opens (the router's probe: it listens on 7447);
* ``--member NAME`` (with ``--run R --connect EP``)  the Zenoh liveliness token
  ``ft/<R>/alive/<NAME>`` is present on the router — the same membership the world and the
  launcher go by (``agent/3``, ``target/0``, ``world/0``, ``recorder/0``, ``dashboard/0``). A process
  that hangs without dying keeps its token, so this says "connected and registered", which is what
  the runtime itself knows of a member;
* ``--http URL``  the URL answers with a status below 400 (the dashboard's page).

It imports only zenoh (not numpy or the roles), so a probe costs about 0.2 s of CPU.
"""

from __future__ import annotations

import argparse
import socket
import sys
import time


def check_tcp(hostport: str, timeout: float) -> str | None:
    host, sep, port = hostport.rpartition(":")
    if not sep or not port.isdigit():
        return f"--tcp wants HOST:PORT, got {hostport!r}"
    try:
        with socket.create_connection((host.strip("[]") or "localhost", int(port)), timeout=timeout):
            return None
    except OSError as exc:
        return f"tcp {hostport}: {exc}"


def check_http(url: str, timeout: float) -> str | None:
    import urllib.error
    import urllib.request

    try:
        with urllib.request.urlopen(url, timeout=timeout) as resp:
            return None if resp.status < 400 else f"http {url}: status {resp.status}"
    except (urllib.error.URLError, OSError) as exc:
        return f"http {url}: {exc}"


def zenoh_config(connect: str | None = None, listen: str | None = None, mode: str = "client",
                 config_file: str | None = None):
    """The same Zenoh config as :func:`agent.bus.zenoh_config` (json5 file, then mode and endpoints,
    multicast scouting off), without importing ``agent`` — whose message schema pulls in numpy and
    would make every probe cost seconds instead of a fraction of one."""
    import json

    import zenoh

    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect.split(",")))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen.split(",")))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def alive_members(run: str, connect: str, names: list[str], timeout: float, config_file: str | None = None) -> set[str]:
    """Which of ``names`` have a liveliness token under ``ft/<run>/alive/`` (raises if no router)."""
    import zenoh

    zenoh.init_log_from_env_or("error")
    prefix = f"ft/{run}/alive/"
    found: set[str] = set()
    session = zenoh.open(zenoh_config(connect=connect, mode="client", config_file=config_file))
    try:
        deadline = time.monotonic() + timeout
        for name in names:
            left = max(0.1, deadline - time.monotonic())
            for reply in session.liveliness().get(prefix + name, timeout=left):
                sample = reply.ok
                if sample is not None and str(sample.key_expr) == prefix + name:
                    found.add(name)
    finally:
        session.close()
    return found


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m flocktrack.launch.health", description=__doc__.split("\n\n")[0])
    ap.add_argument("--tcp", action="append", default=[], metavar="HOST:PORT", help="a TCP port accepts connections")
    ap.add_argument("--member", action="append", default=[], metavar="NAME",
                    help="the liveliness token ft/<run>/alive/NAME is present (needs --run, --connect)")
    ap.add_argument("--run", help="run name (key prefix ft/<run>/)")
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447", help="Zenoh router endpoint")
    ap.add_argument("--config", default=None,
                    help="Zenoh json5 config (a secure run's: the member's own identity, TLS + password)")
    ap.add_argument("--http", action="append", default=[], metavar="URL", help="the URL answers (status < 400)")
    ap.add_argument("--timeout", type=float, default=3.0, help="seconds per check (default 3)")
    ap.add_argument("--quiet", action="store_true", help="print nothing on success")
    args = ap.parse_args(argv)
    if not (args.tcp or args.member or args.http):
        ap.error("give at least one check: --tcp, --member or --http")
    if args.member and not args.run:
        ap.error("--member needs --run")

    failures: list[str] = []
    for hp in args.tcp:
        if (err := check_tcp(hp, args.timeout)) is not None:
            failures.append(err)
    for url in args.http:
        if (err := check_http(url, args.timeout)) is not None:
            failures.append(err)
    if args.member:
        try:
            found = alive_members(args.run, args.connect, args.member, args.timeout, args.config)
        except Exception as exc:  # zenoh.ZError: no router at that endpoint
            failures.append(f"cannot reach a Zenoh router at {args.connect}: {exc}")
        else:
            failures += [f"no liveliness token ft/{args.run}/alive/{m} on {args.connect}"
                         for m in args.member if m not in found]
    if failures:
        for f in failures:
            print(f"unhealthy: {f}", file=sys.stderr)
        return 1
    if not args.quiet:
        print("healthy: " + ", ".join([f"tcp {t}" for t in args.tcp] + [f"member {m}" for m in args.member]
                                      + [f"http {u}" for u in args.http]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
