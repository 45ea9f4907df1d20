"""Addressed payloads (``agent/<i>/to/<j>/xchg``) are held until the receiver's subscription reaches the
sender, then sent in order (agent.bus.ZenohBus): a put before that would be dropped, and lockstep would wait
out a deadline for it (seen in a mesh of routers at tick 0: tests/deploy/test_multihost.py). Over a real router."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from agent.bus import ZenohBus
from agent.wire import Rounds, Xchg
from flocktrack.launch.launcher import free_port

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def router():
    port = free_port()
    p = subprocess.Popen([sys.executable, "-m", "flocktrack.launch.router", "--config", str(ROOT / "broker_cfg" / "compose_router.json5"),
                          "--listen", f"tcp/127.0.0.1:{port}"], cwd=str(ROOT), stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True)
    box: list[str] = []
    t = threading.Thread(target=lambda: box.append(p.stdout.readline()), daemon=True)
    t.start()
    t.join(60)
    assert box and "listening on" in box[0], box
    yield f"tcp/127.0.0.1:{port}"
    p.send_signal(signal.SIGTERM)
    try:
        p.wait(15)
    except subprocess.TimeoutExpired:
        p.kill()
        p.wait()


def _xchg(r: int) -> Xchg:
    return Xchg(src=0, k=0, r=r, payload={"x": np.array([float(r)])})


def _pump(buses, until, timeout=15.0) -> None:
    end = time.monotonic() + timeout
    while not until() and time.monotonic() < end:
        for b in buses:
            b.poll(0.02)


def test_a_payload_put_before_its_receiver_subscribed_arrives_in_order(router):
    sender, receiver = ZenohBus("held", connect=router), ZenohBus("held", connect=router)
    got: list = []
    try:
        sender.subscribe("world/tick", lambda key, msg: None)   # the sender's node loop polls its bus
        for r in range(3):
            sender.publish("agent/0/to/1/xchg", _xchg(r))
        sender.publish("agent/0/xchg", Rounds(src=0, payloads=[_xchg(9).payload]))   # an observers' key: never held
        assert sender.stats.held == 3 and sender.stats.sent == 1
        receiver.subscribe("agent/*/to/1/xchg", lambda key, msg: got.append(msg.r))
        _pump([sender, receiver], lambda: len(got) == 3)
        assert got == [0, 1, 2]
        sender.publish("agent/0/to/1/xchg", _xchg(3))            # matched now: sent at once
        _pump([sender, receiver], lambda: len(got) == 4)
        assert got == [0, 1, 2, 3] and sender.stats.held == 3
        assert sender.stats.sent_by_key["agent/0/to/1/xchg"] == 4
    finally:
        sender.close()
        receiver.close()


def test_a_receiver_that_never_comes_costs_a_bounded_hold(router):
    from agent.bus import HELD_PER_KEY

    sender = ZenohBus("held2", connect=router)
    try:
        for r in range(HELD_PER_KEY + 5):
            sender.publish("agent/0/to/7/xchg", _xchg(r))
        assert sender.stats.held == HELD_PER_KEY + 5
        assert sender.stats.dropped["unmatched"] == 5
        assert len(sender._held["agent/0/to/7/xchg"]) == HELD_PER_KEY
    finally:
        sender.close()
