"""Where the nodes of a run go: a placement file (``hosts.toml``) names the hosts and assigns nodes to them.

::

    run = "lab"                 # the run's name on every host (default: the scenario's run.name)

    [hosts.a]
    address = "10.0.0.1"        # what the other hosts' routers dial (an address or a host name)
    port = 7447                 # its router's port (default 7447)
    listen = "0.0.0.0"          # where its router listens (default: every interface)

    [hosts.b]
    address = "10.0.0.2"

    [place]
    "agent/0-3" = "a"           # a range of sensors
    "agent/4-9" = "b"
    "world/0" = "a"             # one node by name
    "*" = "a"                   # every node not named otherwise

A node is matched by its name, a range (``agent/0-3``), its kind (``agent/*``) or ``*``; the most specific
pattern wins, two patterns of the same kind that both name a node are an error, and so is a node that no
pattern names. Every host gets a router, a launcher and a recorder of its own (``router/a``, ``launcher/a``,
``recorder/a``): those are not placed. Every error names the file, the key and the fix
(:class:`agent.scenario.ScenarioError`).
"""

from __future__ import annotations

import ipaddress
import re
import socket
import tomllib
from dataclasses import dataclass
from pathlib import Path

from agent.scenario import ScenarioError
from agent.wire import HOST_NAME

from .model import Host

PER_HOST = ("router", "launcher", "recorder")   #: the kinds every host has one of (not placed)
_DNS = re.compile(r"(?=.{1,253}$)([A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}"
                  r"[A-Za-z0-9])?)*")
_PATTERN = re.compile(r"(?P<kind>[a-z_]+)/(?:(?P<one>\d+)|(?P<lo>\d+)-(?P<hi>\d+)|(?P<all>\*))|(?P<any>\*)")
_HOST_KEYS = {"address", "port", "listen"}


@dataclass(frozen=True)
class Placement:
    """A parsed placement file: its hosts (in file order), the run name and the assignment patterns."""

    source: str
    hosts: tuple[Host, ...]
    place: tuple[tuple[str, str], ...]     #: (pattern, host) in file order
    run: str | None = None

    def host_names(self) -> list[str]:
        return [h.name for h in self.hosts]

    def assign(self, names: list[str]) -> dict[str, str]:
        """Node name → host for every name in ``names`` (see the module docstring for the rules)."""
        known = set(names)
        chosen: dict[str, tuple[int, str, str]] = {}    # name → (specificity, pattern, host)
        for pattern, host in self.place:
            hits, rank = _matches(pattern, names)
            key = f"place.{pattern!r}"
            if not hits:
                raise ScenarioError(self.source, key, f"names no node of this run (its nodes: {_summary(names)})",
                                    "name a node of the scenario, a range such as \"agent/0-3\", or \"*\"")
            m = _PATTERN.fullmatch(pattern)
            if m["lo"] is not None:
                absent = [i for i in range(int(m["lo"]), int(m["hi"]) + 1) if f"{m['kind']}/{i}" not in known]
                if absent:
                    raise ScenarioError(self.source, key, f"names {m['kind']}/{absent[0]}"
                                                          f"{f'–{absent[-1]}' if len(absent) > 1 else ''}, which this "
                                                          f"run does not have", "end the range at the last one there is")
            for n in hits:
                if n in chosen and chosen[n][0] == rank and chosen[n][2] != host:
                    raise ScenarioError(self.source, key, f"places {n} on {host!r}, but {chosen[n][1]!r} places it on "
                                                          f"{chosen[n][2]!r}", "place each node once")
                if n not in chosen or rank > chosen[n][0]:
                    chosen[n] = (rank, pattern, host)
        missing = [n for n in names if n not in chosen]
        if missing:
            raise ScenarioError(self.source, "place", f"places no host for {_summary(missing)}",
                                f"add them (e.g. \"{missing[0]}\" = \"{self.hosts[0].name}\") or a default \"*\" = "
                                f"\"{self.hosts[0].name}\"")
        return {n: chosen[n][2] for n in names if n in known}

    def check_reachable(self) -> None:
        """Every host's address resolves (a name the other hosts can dial)."""
        for h in self.hosts:
            try:
                socket.getaddrinfo(h.address, h.port)
            except OSError as exc:
                raise ScenarioError(self.source, f"hosts.{h.name}.address", f"{h.address!r} does not resolve here "
                                                                          f"({exc.strerror or exc})",
                                    "give an address, or a host name every host can resolve") from None


def _summary(names: list[str]) -> str:
    return ", ".join(names[:6]) + (f" … ({len(names)} in all)" if len(names) > 6 else "")


def _matches(pattern: str, names: list[str]) -> tuple[list[str], int]:
    """The names ``pattern`` matches and its specificity (3 a name, 2 a range, 1 a kind, 0 everything)."""
    m = _PATTERN.fullmatch(pattern)
    if m is None:   # (checked at parse time)
        return [], -1
    if m["any"]:
        return list(names), 0
    kind = m["kind"]
    if m["all"]:
        return [n for n in names if n.split("/")[0] == kind], 1
    if m["one"] is not None:
        return [n for n in names if n == f"{kind}/{int(m['one'])}"], 3
    lo, hi = int(m["lo"]), int(m["hi"])
    return [n for n in names if n.split("/")[0] == kind and n.split("/")[1].isdigit()
            and lo <= int(n.split("/")[1]) <= hi], 2


def _address(source: str, key: str, value) -> str:
    if not isinstance(value, str) or not value:
        raise ScenarioError(source, key, f"{value!r} is not an address", 'write an address or a host name, e.g. '
                                                                          '"10.0.0.1" or "lab-a.local"')
    try:
        ipaddress.ip_address(value)
        return value
    except ValueError:
        if _DNS.fullmatch(value):
            return value
    raise ScenarioError(source, key, f"{value!r} is neither an IP address nor a host name",
                        'write an address or a host name, e.g. "10.0.0.1" or "lab-a.local"')


def parse_placement(data: dict, source: str) -> Placement:
    """A placement from a parsed ``hosts.toml`` (``source``: its path, for the errors)."""
    unknown = set(data) - {"run", "hosts", "place"}
    if unknown:
        raise ScenarioError(source, sorted(unknown)[0], "is not a key of a placement", "use run, [hosts.NAME] and "
                                                                                     "[place]")
    hosts_t = data.get("hosts")
    if not isinstance(hosts_t, dict) or not hosts_t:
        raise ScenarioError(source, "hosts", "no hosts", 'add a table per host: [hosts.a] address = "10.0.0.1"')
    hosts, seen = [], {}
    for name, t in hosts_t.items():
        key = f"hosts.{name}"
        if not HOST_NAME.fullmatch(name):
            raise ScenarioError(source, key, f"{name!r} is not a host name of a placement",
                                "use lower-case letters, digits and _ (it names the host's nodes: router/NAME)")
        if not isinstance(t, dict):
            raise ScenarioError(source, key, "is not a table", f'write [hosts.{name}] address = "…"')
        bad = set(t) - _HOST_KEYS
        if bad:
            raise ScenarioError(source, f"{key}.{sorted(bad)[0]}", "is not a key of a host",
                                f"use {', '.join(sorted(_HOST_KEYS))}")
        if "address" not in t:
            raise ScenarioError(source, f"{key}.address", "missing", "the address the other hosts dial it by")
        address = _address(source, f"{key}.address", t["address"])
        port = t.get("port", 7447)
        if not isinstance(port, int) or isinstance(port, bool) or not 1 <= port <= 65535:
            raise ScenarioError(source, f"{key}.port", f"{port!r} is not a port", "an integer in 1..65535")
        listen = t.get("listen", "0.0.0.0")
        _address(source, f"{key}.listen", listen)
        if (address, port) in seen:
            raise ScenarioError(source, f"{key}.address", f"{address}:{port} is host {seen[(address, port)]!r}'s too",
                                "give every host its own address (or port)")
        seen[(address, port)] = name
        hosts.append(Host(name, address, port, listen))
    place_t = data.get("place", {})
    if not isinstance(place_t, dict):
        raise ScenarioError(source, "place", "is not a table", '[place] "agent/0-3" = "a"')
    place = []
    for pattern, host in place_t.items():
        key = f"place.{pattern!r}"
        kind = pattern.split("/")[0]
        if kind in PER_HOST:
            raise ScenarioError(source, key, f"every host has its own {kind} ({kind}/HOST)", "remove the line")
        m = _PATTERN.fullmatch(pattern)
        if m is None:
            raise ScenarioError(source, key, "is not a node pattern", 'write a name ("world/0"), a range ("agent/0-3"), '
                                                                      'a kind ("agent/*") or "*"')
        if m["lo"] is not None and int(m["lo"]) > int(m["hi"]):
            raise ScenarioError(source, key, "is an empty range", "write the lower id first")
        if host not in hosts_t:
            raise ScenarioError(source, key, f"places on {host!r}, which is not a host of [hosts]",
                                f"use one of {', '.join(hosts_t)}")
        place.append((pattern, host))
    run = data.get("run")
    if run is not None and (not isinstance(run, str) or not re.fullmatch(r"[A-Za-z0-9_.-]+", run)):
        raise ScenarioError(source, "run", f"{run!r} is not a run name", "letters, digits, _ . - (a key chunk)")
    return Placement(source, tuple(hosts), tuple(place), run)


def load_placement(path: str | Path) -> Placement:
    """Read and parse a placement file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ScenarioError(str(path), "-", "no such file", "give the path of a hosts.toml") from None
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(str(path), "-", f"is not TOML ({exc})", "fix the syntax at the line it names") from None
    return parse_placement(data, str(path))
