"""Hosts without Docker: Linux network namespaces joined by a switch (needs root and ``ip``).

:class:`Network` makes ``n`` "hosts" (namespaces ``ft<tag>h<i>``, each with ``lo`` and ``eth0`` =
10.213.0.<i+1>/24) cabled by veth pairs to a bridge that lives in its own namespace ``ft<tag>sw`` — so
no address of the test network exists in the root namespace and none of its traffic leaves the
namespaces. :meth:`Network.cut` / :meth:`Network.heal` take a host's switch port down / up (its cable
is pulled: the host sees no carrier, the others see silence). Names are unique per test run; the
namespaces, and with them every veth and the bridge, are deleted by :meth:`Network.close` (also on
failure and at interpreter exit), after killing what still runs inside them.

Each host runs its share of a placed flock with the user's own command, ``flocktrack run SCENARIO
--placement hosts.toml --host NAME`` (:meth:`Network.flock`). ``python -m flocktrack.testbed.netns watch SPEC.json`` is run
*inside* the first host beside them: it follows the run on that host's router, optionally cuts a host's link at
a tick and heals it, and writes the timeline of what the first host saw (liveliness of every process, ticks,
cut/heal instants, switch counters).
"""

from __future__ import annotations

import atexit
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

SUBNET = "10.213.0"


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], check=check, capture_output=True, text=True)


def available() -> str | None:
    """None if namespaces can be made here, else why not."""
    if shutil.which("ip") is None:
        return "iproute2 (ip) is not installed"
    if os.geteuid() != 0:
        return "needs root (ip netns)"
    name = f"ftprobe{uuid.uuid4().hex[:6]}"
    r = _ip("netns", "add", name, check=False)
    if r.returncode != 0:
        return f"ip netns add failed: {r.stderr.strip()}"
    _ip("netns", "del", name, check=False)
    return None


class Network:
    def __init__(self, n_hosts: int, tag: str | None = None):
        self.tag = tag or uuid.uuid4().hex[:6]
        self.switch = f"ft{self.tag}sw"
        self.hosts = [f"ft{self.tag}h{i}" for i in range(n_hosts)]
        self.addrs = [f"{SUBNET}.{i + 1}" for i in range(n_hosts)]
        self._made: list[str] = []
        atexit.register(self.close)
        try:
            self._build()
        except Exception:
            self.close()
            raise

    def _build(self) -> None:
        for ns in [self.switch, *self.hosts]:
            _ip("netns", "add", ns)
            self._made.append(ns)
            _ip("-n", ns, "link", "set", "lo", "up")
        _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
        _ip("-n", self.switch, "link", "set", "br0", "up")
        for i, ns in enumerate(self.hosts):
            port = f"p{i}"
            _ip("link", "add", "eth0", "netns", ns, "type", "veth", "peer", "name", port, "netns", self.switch)
            _ip("-n", self.switch, "link", "set", port, "master", "br0")
            _ip("-n", self.switch, "link", "set", port, "up")
            _ip("-n", ns, "addr", "add", f"{self.addrs[i]}/24", "dev", "eth0")
            _ip("-n", ns, "link", "set", "eth0", "up")

    def placement(self, path: Path, where: dict[str, str], names: list[str] | None = None, run: str = "mesh") -> Path:
        """Write a placement of the hosts (``h0``, ``h1`` … or ``names``) at their addresses; ``where``:
        node pattern → host name."""
        names = names or [f"h{i}" for i in range(len(self.hosts))]
        lines = [f'run = "{run}"']
        for name, addr in zip(names, self.addrs):
            lines += [f"[hosts.{name}]", f'address = "{addr}"']
        lines.append("[place]")
        lines += [f'"{pat}" = "{host}"' for pat, host in where.items()]
        path.write_text("\n".join(lines) + "\n")
        return path

    def flock(self, placement: Path, names: list[str], scenario: str, out: Path, *args: str) -> list[subprocess.Popen]:
        """Start ``flocktrack run SCENARIO --placement P --host NAME`` on every host (host i = ``names[i]``),
        each writing to ``out/NAME``."""
        procs = []
        for i, name in enumerate(names):
            log = open(out / f"{name}.out", "w")
            procs.append(subprocess.Popen([*self.wrap(i), sys.executable, "-m", "flocktrack", "run", scenario,
                                           "--placement", str(placement), "--host", name, "--out", str(out / name),
                                           "--quiet", *args], cwd=str(out), stdout=log, stderr=subprocess.STDOUT))
        return procs

    def wrap(self, i: int) -> list[str]:
        """argv prefix that runs a command on host i."""
        return ["ip", "netns", "exec", self.hosts[i]]

    def run(self, i: int, *argv: str, **kw) -> subprocess.CompletedProcess:
        return subprocess.run([*self.wrap(i), *argv], **kw)

    def cut(self, i: int) -> None:
        _ip("-n", self.switch, "link", "set", f"p{i}", "down")

    def heal(self, i: int) -> None:
        _ip("-n", self.switch, "link", "set", f"p{i}", "up")

    def close(self) -> None:
        """Kill what still runs in our namespaces (only processes started there by this test), then
        delete them."""
        for ns in reversed(self._made):
            r = _ip("netns", "pids", ns, check=False)
            for pid in r.stdout.split():
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
        for ns in reversed(self._made):
            _ip("netns", "del", ns, check=False)
        self._made.clear()

    def __enter__(self) -> "Network":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def port_counters(switch: str, ports: list[str]) -> dict[str, dict[str, int]]:
    """{port: {rx_bytes, rx_packets, tx_bytes, tx_packets}} of the switch namespace's ports."""
    out = {}
    for port in ports:
        base = Path(f"/sys/class/net/{port}/statistics")
        r = subprocess.run(["ip", "netns", "exec", switch, "cat", *(str(base / f) for f in
                            ("rx_bytes", "rx_packets", "tx_bytes", "tx_packets"))], capture_output=True, text=True)
        vals = [int(v) for v in r.stdout.split()] if r.returncode == 0 else [0, 0, 0, 0]
        out[port] = dict(zip(("rx_bytes", "rx_packets", "tx_bytes", "tx_packets"), vals))
    return out


# ============================================================================ inside the first host

class CutAndWatch:
    """Follows a run from the first host (its router on loopback): liveliness and ticks; at tick ``at_tick``
    takes the switch port ``port`` down, brings it up ``down_s`` later — and, with ``repeat`` > 1, cuts it
    again ``every_s`` after each heal (the cable-pull benchmark's trials)."""

    def __init__(self, spec: dict):
        self.spec = spec
        self.bus = None
        self.timeline: list[dict] = []
        self.seen_k = -1
        self.ended = False
        self.cut_t: float | None = None
        self.heal_t: float | None = None
        self.cuts = 0
        self.samples_taken = 0

    def _note(self, what: str, **kw) -> None:
        self.timeline.append({"t": time.time(), "event": what, **kw})

    def step(self) -> None:
        if self.bus is None:
            from agent.bus import ZenohBus

            import zenoh

            try:   # (the host's router comes up with its launcher: until then, dial again)
                self.bus = ZenohBus(self.spec["run"], connect=self.spec.get("connect", "tcp/127.0.0.1:7447"))
            except zenoh.ZError:
                time.sleep(0.2)
                return
            self.bus.subscribe("world/tick", self._on_tick)
            self.bus.subscribe("world/end", lambda key, msg: setattr(self, "ended", True))
            self.bus.watch_members(lambda name, alive: self._note("member", name=name, alive=alive))
        self.bus.poll(0.02)
        self._sample()
        cut = self.spec.get("cut")
        if not cut:
            return
        again = (self.heal_t is not None and self.cuts < cut.get("repeat", 1)
                 and time.time() - self.heal_t >= cut.get("every_s", 0.0))
        if (self.cut_t is None and self.seen_k >= cut["at_tick"]) or again:
            _ip("-n", cut["switch"], "link", "set", cut["port"], "down")
            self.cut_t, self.heal_t = time.time(), None
            self.cuts += 1
            self._note("cut", k=self.seen_k, port=cut["port"])
        elif self.cut_t is not None and self.heal_t is None and time.time() - self.cut_t >= cut["down_s"]:
            _ip("-n", cut["switch"], "link", "set", cut["port"], "up")
            self.heal_t = time.time()
            self._note("heal", k=self.seen_k, port=cut["port"])

    def _sample(self) -> None:
        """At each tick of ``spec["sample"]["at_ticks"]`` (once seen): the switch ports' counters — rx of
        port p<i> is what host i sent, tx what it received — into the timeline."""
        smp = self.spec.get("sample")
        if not smp or self.samples_taken >= len(smp["at_ticks"]) or self.seen_k < smp["at_ticks"][self.samples_taken]:
            return
        self.samples_taken += 1
        self._note("counters", k=self.seen_k, ports=port_counters(smp["switch"], smp["ports"]))

    def _on_tick(self, key: str, msg) -> None:
        if msg.k > self.seen_k:
            self.seen_k = msg.k
            self._note("tick", k=msg.k, alive=[bool(a) for a in msg.alive])

    def close(self) -> None:
        if self.bus is not None:
            self.bus.close()


def placed_run(net: Network, where: dict[str, str], scenario: str, out: Path, *args: str, names: list[str],
               cut: dict | None = None, sample_at: list[int] | None = None, timeout_s: float = 240,
               run: str = "mesh") -> dict:
    """Run ``scenario`` placed on the network's hosts (``names[i]`` = host i; ``where``: node pattern → host) with
    one ``flocktrack run --placement --host`` per host, then ``flocktrack merge`` of their directories into
    ``out/merged``. ``cut``: pull a cable (:class:`CutAndWatch`, run on host 0 beside the flock; its timeline in
    ``out/timeline.json``); ``sample_at``: ticks at which the watcher reads the switch ports' byte counters into
    that timeline. Returns ``{"rcs", "outputs", "merge_rc", "merged"}``."""
    placement = net.placement(out / "hosts.toml", where, names, run=run)
    watch = None
    if cut is not None or sample_at:
        spec = {"run": run, "out": str(out / "timeline.json"), "timeout_s": timeout_s}
        if cut is not None:
            spec["cut"] = {"switch": net.switch, **cut}
        if sample_at:
            spec["sample"] = {"switch": net.switch, "ports": [f"p{i}" for i in range(len(names))], "at_ticks": sample_at}
        (out / "watch.json").write_text(json.dumps(spec))
        watch = subprocess.Popen([*net.wrap(0), sys.executable, "-m", "flocktrack.testbed.netns", "watch",
                                  str(out / "watch.json")], cwd=str(out))
    procs = net.flock(placement, names, scenario, out, *args)
    rcs: list[int | None] = []
    for p in procs:
        try:
            rcs.append(p.wait(timeout_s + 120))
        except subprocess.TimeoutExpired:
            p.kill()
            rcs.append(None)
    if watch is not None:
        try:
            watch.wait(60)
        except subprocess.TimeoutExpired:
            watch.kill()
    merged = subprocess.run([sys.executable, "-m", "flocktrack", "merge", *(str(out / h) for h in names),
                             "--out", str(out / "merged")], capture_output=True, text=True, timeout=600)
    return {"rcs": rcs, "outputs": {h: (out / f"{h}.out").read_text()[-2000:] for h in names},
            "merge_rc": merged.returncode, "merge_err": merged.stderr[-2000:], "merged": out / "merged"}


def watch(spec_file: str) -> int:
    """Follow the spec's run from this host until its end (or ``timeout_s``); write ``spec["out"]``."""
    spec = json.loads(Path(spec_file).read_text())
    hook = CutAndWatch(spec)
    end = time.monotonic() + spec.get("timeout_s", 240)
    try:
        while not hook.ended and time.monotonic() < end:
            hook.step()
        t_end = time.monotonic() + 1.0
        while time.monotonic() < t_end:   # the last members leaving
            hook.step()
    finally:
        hook.close()
    Path(spec["out"]).write_text(json.dumps(hook.timeline, indent=1))
    return 0 if hook.ended else 1


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "watch":
        sys.exit(watch(sys.argv[2]))
    print("usage: python -m flocktrack.testbed.netns watch SPEC.json", file=sys.stderr)
    sys.exit(2)
