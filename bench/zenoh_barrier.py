"""A bare Zenoh barrier: the reference the runtime's lockstep ticks/s are compared with.

A coordinator and N worker processes exchange messages of the runtime's sizes with the runtime's
neighbour lists — tick → R exchange rounds with neighbours → state → next tick — with raw Zenoh and
raw bytes: no msgpack, no validation, no estimation. What the runtime does on top of this is its cost.
Addressed like the runtime: a worker puts each round's payload once per neighbour on
``bar/x/<dst>/<src>`` and reads only its own inbox ``bar/x/<id>/*``; at the tick's end it puts the tick's
payloads once for observers (whom nobody plays here), so the comparison stays fair.

    python bench/zenoh_barrier.py coordinator --n N --rounds R --ticks K --connect EP --nbrs FILE
    python bench/zenoh_barrier.py worker --id I ...
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import time

import zenoh


def session(connect: str):
    c = zenoh.Config()
    c.insert_json5("mode", '"client"')
    c.insert_json5("connect/endpoints", json.dumps([connect]))
    c.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(c)


def worker(a) -> None:
    nbrs = json.load(open(a.nbrs))[a.id]
    s = session(a.connect)
    q: queue.SimpleQueue = queue.SimpleQueue()
    s.declare_subscriber("bar/tick", lambda smp: q.put(("tick", smp.payload.to_bytes())))
    s.declare_subscriber(f"bar/x/{a.id}/*", lambda smp: q.put((str(smp.key_expr), smp.payload.to_bytes())))
    pubs_x = [s.declare_publisher(f"bar/x/{j}/{a.id}", congestion_control=zenoh.CongestionControl.BLOCK)
              for j in nbrs]
    pub_obs = s.declare_publisher(f"bar/obs/{a.id}", congestion_control=zenoh.CongestionControl.BLOCK)
    pub_s = s.declare_publisher(f"bar/s/{a.id}", congestion_control=zenoh.CongestionControl.BLOCK)
    tok = s.liveliness().declare_token(f"bar/alive/{a.id}")
    payload = bytes(a.xbytes)
    state = bytes(a.sbytes)
    got: dict[tuple[int, int], set[int]] = {}
    for k in range(a.ticks):
        while True:
            kind, data = q.get()
            if kind == "tick":
                break
            j, kk, r = kind.rsplit("/", 1)[1], data[0] | data[1] << 8, data[2]
            got.setdefault((kk, r), set()).add(int(j))
        for r in range(a.rounds):
            data = bytes([k & 255, k >> 8, r]) + payload
            for pub_x in pubs_x:
                pub_x.put(data)
            need = set(nbrs)
            while not need <= got.get((k & 0xFFFF, r), set()):
                kind, data = q.get()
                if kind == "tick":
                    continue
                j, kk, rr = kind.rsplit("/", 1)[1], data[0] | data[1] << 8, data[2]
                got.setdefault((kk, rr), set()).add(int(j))
            got.pop((k & 0xFFFF, r), None)
        pub_obs.put(payload * a.rounds)
        pub_s.put(state)
    time.sleep(0.3)
    tok.undeclare()
    s.close()


def coordinator(a) -> None:
    s = session(a.connect)
    q: queue.SimpleQueue = queue.SimpleQueue()
    alive: set[str] = set()
    s.liveliness().declare_subscriber("bar/alive/**", lambda smp: alive.add(str(smp.key_expr)), history=True)
    s.declare_subscriber("bar/s/**", lambda smp: q.put(1))
    pub = s.declare_publisher("bar/tick", congestion_control=zenoh.CongestionControl.BLOCK)
    while len(alive) < a.n:
        time.sleep(0.05)
    time.sleep(0.2)
    tick = bytes(a.tbytes)
    t0, w0 = time.perf_counter(), time.time()
    for _k in range(a.ticks):
        pub.put(tick)
        for _ in range(a.n):
            q.get()
    dt = time.perf_counter() - t0
    print(json.dumps({"ticks": a.ticks, "seconds": dt, "ticks_per_s": a.ticks / dt, "t0_wall": w0,
                      "t1_wall": time.time()}))
    s.close()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("role", choices=["coordinator", "worker"])
    ap.add_argument("--id", type=int, default=0)
    ap.add_argument("--n", type=int, required=True)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--ticks", type=int, default=100)
    ap.add_argument("--connect", required=True)
    ap.add_argument("--nbrs", required=True)
    ap.add_argument("--xbytes", type=int, default=400)
    ap.add_argument("--sbytes", type=int, default=120)
    ap.add_argument("--tbytes", type=int, default=600)
    a = ap.parse_args()
    (coordinator if a.role == "coordinator" else worker)(a)


if __name__ == "__main__":
    sys.exit(main())
