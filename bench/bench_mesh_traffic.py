"""What crosses each host link of a 3-host mesh per tick: measured on the switch, predicted from the recording.

    python bench/bench_mesh_traffic.py [--ticks 300] [--out bench/results/mesh_traffic.json]

The multi-host test's set-up (flocktrack.testbed.netns): three "hosts" (network namespaces on a switch), each
running `flocktrack run gu_hu_normal --placement hosts.toml --host NAME` — its own router of the mesh, launcher
and recorder shard — with the 10 sensors split a: 0–3 (with the world and the target), b: 4–6, c: 7–9, in
lockstep. Between two ticks of
the run (``--from``, ``--to``), the switch's port counters give what each host sent (port rx) and received
(port tx), in bytes and Ethernet frames — everything: Zenoh framing, TCP/IP headers, keep-alives, liveliness.

The prediction reads the run's merged recording: every message of those ticks, its msgpack size
(``wire.encode``), its publisher's host, and the hosts with a subscriber for its key (the run plan's reads of
the nodes on each host), one copy per remote router (Zenoh routes a put once to each router with a matching
subscription). Exchange payloads go three ways, each predicted: ``per_host`` (what the runtime does: sensor
i sends each sensor j of its own host that hears it by tick k's link table a copy on ``agent/i/to/j/xchg``,
and every other host with hearers one copy on ``agent/i/via/<host>/xchg`` naming them), ``per_hearer`` (one
copy per hearer wherever it is) and ``broadcast`` (every sensor subscribed to ``agent/*/xchg``: one copy to
every other host); and one observer copy a tick ``agent/i/xchg`` (its rounds) to the recorder's host.

Writes per directed host link and per host: predicted messages and payload bytes per tick (each way),
measured bytes and frames per tick, the measured / predicted byte ratio (the wire's overhead over the msgpack
payloads), and ``crossing``: everything that crossed a host link against the payloads that had to.
docs/scaling.md extrapolates from these numbers.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent import wire  # noqa: E402 - after the sys.path line above
from agent.bus import key_matches  # noqa: E402 - same
from flocktrack.plan import RunPlan  # noqa: E402 - same
from flocktrack.record.reader import read_recording  # noqa: E402 - same
from flocktrack.testbed import netns  # noqa: E402 - same

HOSTS = ["a", "b", "c"]
WHERE = {"agent/0-3": "a", "agent/4-6": "b", "agent/7-9": "c", "*": "a"}


def host_of(plan: RunPlan, topic: str) -> str:
    """The host of a recorded message's publisher: the node whose declared writes hold the key."""
    return next(n.host for n in plan.nodes if any(key_matches(w, topic) for w in n.writes))


def subscriber_hosts(plan: RunPlan, topic: str) -> set[str]:
    """Hosts with a subscriber for an observed (not addressed) key: the hosts of the nodes that read it."""
    return {n.host for n in plan.nodes if any(key_matches(r, topic) for r in n.reads)}


SCHEMES = ("per_host", "per_hearer", "broadcast")


def predict(recording: Path, plan: RunPlan, k0: int, k1: int) -> dict:
    """Messages and msgpack bytes per directed host link over ticks [k0, k1), for each way of sending the
    exchange payloads (:data:`SCHEMES`): ``per_host`` (what runs), ``per_hearer``, ``broadcast``."""
    rec = read_recording(recording)
    ticks = {m.k: m for topic, m, _ in rec.messages if topic == "world/tick"}
    links: dict[str, dict[str, dict[str, float]]] = {s: defaultdict(lambda: defaultdict(float)) for s in SCHEMES}
    sizes: dict[str, list[int]] = defaultdict(list)

    def add(kinds: tuple[str, ...], src: str, dst: str, size: int) -> None:
        if src != dst:
            for kind in kinds:
                links[kind][f"{src}->{dst}"]["messages"] += 1
                links[kind][f"{src}->{dst}"]["bytes"] += size

    for topic, msg, _ in rec.messages:
        if not k0 <= msg.k < k1:
            continue
        size = len(wire.encode(msg))
        kind = topic.split("/")[-1]
        sizes[kind].append(size)
        src = host_of(plan, topic)
        for dst in subscriber_hosts(plan, topic):   # observers' copies, and every other message
            add(SCHEMES if kind != "xchg" else ("per_host", "per_hearer"), src, dst, size)
        if kind == "xchg":                         # the observers' copy of the tick: its rounds, each sent
            tick = ticks[msg.k]
            hearers = [j for j in range(tick.n) if j != msg.src and msg.src in tick.links[j]]
            where = {j: plan.node(f"agent/{j}").host for j in hearers}
            remote = [j for j in hearers if where[j] != src]
            for r, payload in enumerate(msg.payloads):
                x = wire.Xchg(src=msg.src, k=msg.k, r=r, payload=payload)
                one = len(wire.encode(x))
                for j in hearers:                  # one addressed copy per sensor that hears the sender
                    add(("per_hearer",), src, where[j], one)
                if remote:                         # one copy per other host with hearers, naming them all
                    via = len(wire.encode(wire.ViaXchg(src=x.src, k=x.k, r=r, payload=payload, to=remote)))
                    for dst in dict.fromkeys(where[j] for j in remote):
                        add(("per_host",), src, dst, via)
                for dst in HOSTS:                  # before addressing: to every host (sensors or recorder)
                    add(("broadcast",), src, dst, one)
    n = k1 - k0
    out = {kind: {lk: {"messages_per_tick": v["messages"] / n, "bytes_per_tick": v["bytes"] / n}
                  for lk, v in sorted(d.items())} for kind, d in links.items()}
    out["message_bytes"] = {k: {"median": sorted(v)[len(v) // 2], "max": max(v)} for k, v in sorted(sizes.items())}
    return out


def measured(timeline: list[dict]) -> tuple[int, int, dict]:
    """(k0, k1, per host bytes/frames sent and received per tick) between the two counter samples."""
    c0, c1 = [e for e in timeline if e["event"] == "counters"][:2]
    n = c1["k"] - c0["k"]
    per_host = {}
    for i, h in enumerate(HOSTS):
        a, b = c0["ports"][f"p{i}"], c1["ports"][f"p{i}"]
        per_host[h] = {"sent_bytes_per_tick": (b["rx_bytes"] - a["rx_bytes"]) / n,
                       "sent_frames_per_tick": (b["rx_packets"] - a["rx_packets"]) / n,
                       "received_bytes_per_tick": (b["tx_bytes"] - a["tx_bytes"]) / n,
                       "received_frames_per_tick": (b["tx_packets"] - a["tx_packets"]) / n}
    return c0["k"], c1["k"], per_host


def per_host(pred: dict[str, dict]) -> dict[str, dict[str, float]]:
    out = {h: {"sent_bytes_per_tick": 0.0, "received_bytes_per_tick": 0.0, "sent_messages_per_tick": 0.0,
               "received_messages_per_tick": 0.0} for h in HOSTS}
    for lk, v in pred.items():
        src, dst = lk.split("->")
        out[src]["sent_bytes_per_tick"] += v["bytes_per_tick"]
        out[src]["sent_messages_per_tick"] += v["messages_per_tick"]
        out[dst]["received_bytes_per_tick"] += v["bytes_per_tick"]
        out[dst]["received_messages_per_tick"] += v["messages_per_tick"]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ticks", type=int, default=300)
    ap.add_argument("--from", dest="k0", type=int, default=50, help="first tick counted (after start-up)")
    ap.add_argument("--to", dest="k1", type=int, default=250, help="tick the count ends at")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "mesh_traffic.json")
    a = ap.parse_args(argv)
    why = netns.available()
    if why:
        sys.exit(f"bench_mesh_traffic: {why}")
    print(f"[mesh] gu_hu_normal on 3 hosts, {a.ticks} lockstep ticks; counting ticks {a.k0}–{a.k1}", flush=True)
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="meshtraffic_") as d, netns.Network(len(HOSTS)) as net:
        r = netns.placed_run(net, WHERE, "gu_hu_normal", Path(d), "--ticks", str(a.ticks), "--mode", "lockstep",
                             names=HOSTS, sample_at=[a.k0, a.k1], timeout_s=600)
        info = {"rc": max((rc if rc is not None else 124) for rc in r["rcs"])}
        timeline = json.loads((Path(d) / "timeline.json").read_text())
        plan = RunPlan.from_json((Path(d) / "a" / "plan.json").read_text())
        k0, k1, meas = measured(timeline)
        pred = predict(r["merged"] / "recording.mcap", plan, k0, k1)
    by_host = {s: per_host(pred[s]) for s in SCHEMES}
    hosts = {h: {"measured": meas[h], **{f"predicted_{s}": by_host[s][h] for s in SCHEMES},
                 "measured_over_predicted_bytes": {
                     d: round(meas[h][f"{d}_bytes_per_tick"] / max(by_host["per_host"][h][f"{d}_bytes_per_tick"], 1e-9), 2)
                     for d in ("sent", "received")}}
             for h in HOSTS}
    crossing = {"measured_bytes_per_tick": round(sum(meas[h]["sent_bytes_per_tick"] for h in HOSTS), 1),
                **{f"{s}_payload_bytes_per_tick": round(sum(v["bytes_per_tick"] for v in pred[s].values()), 1)
                   for s in SCHEMES}}
    crossing["measured_over_per_host_payloads"] = round(
        crossing["measured_bytes_per_tick"] / max(crossing["per_host_payload_bytes_per_tick"], 1e-9), 3)
    res = {"date": time.strftime("%Y-%m-%d"), "scenario": "gu_hu_normal", "n_sensors": len(plan.of_kind("agent")),
           "placement": {h: [n.name for n in plan.on(h)] for h in HOSTS},
           "ticks_counted": [k0, k1], "rc": info.get("rc"), "wall_s": round(time.monotonic() - t0, 1),
           **{f"links_{s}": pred[s] for s in SCHEMES}, "message_bytes": pred["message_bytes"], "hosts": hosts,
           "crossing": crossing}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1))
    for h, v in hosts.items():
        m, p, e, b = v["measured"], v["predicted_per_host"], v["predicted_per_hearer"], v["predicted_broadcast"]
        print(f"[mesh] host {h}: sent {m['sent_bytes_per_tick']:.0f} B/tick in {m['sent_frames_per_tick']:.1f} frames "
              f"(payloads {p['sent_bytes_per_tick']:.0f} B in {p['sent_messages_per_tick']:.1f} messages; one copy per "
              f"hearer would be {e['sent_bytes_per_tick']:.0f} B, broadcast {b['sent_bytes_per_tick']:.0f} B); "
              f"received {m['received_bytes_per_tick']:.0f} B/tick (payloads {p['received_bytes_per_tick']:.0f} B)",
              flush=True)
    print(f"[mesh] across host links: {crossing['measured_bytes_per_tick']:.0f} B/tick measured, "
          f"{crossing['measured_over_per_host_payloads']:.3f} × the payloads that must cross", flush=True)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
