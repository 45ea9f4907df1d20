"""Hostile input never crashes anything: ≥ 10⁵ random and mutated messages thrown at a live sensor
process over a real Zenoh router. Every one is either dropped and counted (per reason) or handled;
no exception escapes a handler and the process keeps running and exits cleanly."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest

from agent import wire
from agent.bus import ZenohBus
from flocktrack.launch.launcher import free_port, open_router

ROOT = Path(__file__).resolve().parents[2]
N_MESSAGES = 100_000


def _seeds(n: int):
    """Valid messages of every kind a sensor subscribes to."""
    pos = np.zeros((n, 2))
    return [
        ("world/tick", wire.Tick(k=0, t=0.0, n=n, links=[[1]] + [[0]] + [[] for _ in range(n - 2)],
                                 weights=[[1.0]] + [[1.0]] + [[] for _ in range(n - 2)], b=[1.0] * n, delta_max=1,
                                 alive=[True] * n, positions=pos)),
        ("target/truth", wire.Truth(k=0, t=0.0, x=np.array([0.0, 0.0, 1.0, 0.5]))),
        ("target/truth", wire.Truth(k=0, t=0.0, x=np.array([0.0, 0.0, 1.0]))),
        ("world/tick", wire.Tick(k=0, t=0.0, n=n, links=[[] for _ in range(n)], weights=[[] for _ in range(n)],
                                 b=[1.0] * n, delta_max=0, alive=[True] * n, positions=np.zeros((n, 3)))),
        ("agent/2/estimate", wire.Estimate(src=2, k=0, x=np.zeros(3), x_next=np.zeros(3))),
        ("agent/1/to/0/xchg", wire.Xchg(src=1, k=0, r=0, payload={"chi1": np.eye(4), "chi2": np.ones(4),
                                                             "chi3": np.eye(4)})),
        ("control/outlier_burst", wire.Control(verb="outlier_burst", args={"agent": 0, "ticks": 2, "magnitude": 5.0})),
        ("world/event", wire.Control(k=0, verb="fault", args={"id": 0, "kind": "duplicate", "phase": "start",
                                                              "agents": [0.0], "links": [], "p": 1.0})),
    ]


def _mutate(rng: np.random.Generator, data: bytes) -> bytes:
    b = bytearray(data)
    op = rng.integers(0, 6)
    if op == 0 and b:                                   # flip bytes
        for _ in range(rng.integers(1, 8)):
            b[rng.integers(0, len(b))] = rng.integers(0, 256)
    elif op == 1 and b:                                 # truncate
        b = b[: rng.integers(0, len(b))]
    elif op == 2:                                       # random garbage
        b = bytearray(rng.bytes(int(rng.integers(0, 300))))
    elif op == 3:                                       # structurally valid msgpack, wrong content
        d = msgpack.unpackb(bytes(data), raw=False)
        key = list(d)[rng.integers(0, len(d))]
        d[key] = [None, -1, 2**40, "x" * 50, 1e308, {"s": [1, 2], "d": b"\x00" * 16}, [[-5]], True][rng.integers(0, 8)]
        b = bytearray(msgpack.packb(d, use_bin_type=True))
    elif op == 4:                                       # valid type, hostile numbers
        d = msgpack.unpackb(bytes(data), raw=False)
        for k, v in d.items():
            if isinstance(v, int) and not isinstance(v, bool):
                d[k] = int(rng.choice([0, 1, 7, 2**31, 10**9]))
        b = bytearray(msgpack.packb(d, use_bin_type=True))
    else:                                               # extend with junk
        b += rng.bytes(int(rng.integers(1, 64)))
    return bytes(b)


@pytest.mark.slow
def test_fuzz_live_sensor_process(tmp_path):
    port = free_port()
    router = open_router(port)
    ep = f"tcp/127.0.0.1:{port}"
    env = dict(os.environ, FLOCKTRACK_STATS_DIR=str(tmp_path / "stats"), PYTHONPATH=str(ROOT))
    run = "fuzz"
    proc = subprocess.Popen([sys.executable, "-m", "agent", "sensor", "--id", "0", "--scenario",
                             str(ROOT / "scenarios" / "gu_hu_normal.toml"), "--connect", ep, "--run", run,
                             "--mode", "lockstep"], env=env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    bus = ZenohBus(run, connect=ep)
    try:
        alive = []
        bus.watch_members(lambda name, a: alive.append(name) if a else None)
        t0 = time.time()
        while "agent/0" not in alive and time.time() - t0 < 60:
            bus.poll(0.1)
        assert "agent/0" in alive, "sensor process never came up"
        rng = np.random.default_rng(1234)
        seeds = [(k, wire.encode(m)) for k, m in _seeds(10)]
        keys_extra = ["agent/0/to/0/xchg", "agent/7/to/0/xchg", "agent/99999/to/0/xchg", "agent/x/to/0/xchg",
                      "world/tick", "control/outlier_burst"]
        subscribed = 0
        for i in range(N_MESSAGES):
            key, data = seeds[rng.integers(0, len(seeds))]
            if rng.random() < 0.1:
                key = keys_extra[rng.integers(0, len(keys_extra))]
            bus.publish_raw(key, _mutate(rng, data) if rng.random() < 0.97 else data)
            subscribed += not key.endswith("/estimate")  # a sensor that is not rejoining ignores estimates
            if i % 5000 == 0:
                assert proc.poll() is None, f"sensor died after {i} messages"
        time.sleep(3.0)
        assert proc.poll() is None, "sensor process crashed"
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=60)
        (tmp_path / "sensor.log").write_bytes(out)
        assert proc.returncode == 0, out.decode()[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
        bus.close()
        router.close()
    stats = json.loads((tmp_path / "stats" / "agent-0.json").read_text())
    handled = stats["received"] + sum(stats["dropped"].values())
    assert handled >= 0.99 * subscribed, (handled, subscribed, stats)
    assert stats["handler_errors"] == 0, (stats, out.decode()[-6000:])
    assert "Traceback" not in out.decode(), out.decode()[-3000:]
    assert sum(stats["dropped"].values()) > N_MESSAGES // 2
    print("dropped per reason:", stats["dropped"], "role:", stats.get("role"))
