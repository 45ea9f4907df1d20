"""A bus's bulk subscription (agent/inbox.py): its samples stay in a Zenoh channel until the role's thread
polls, and everything else that must wake that thread — a sample of another subscription, a poll's timeout,
:func:`agent.bus.wake_all` — rings the inbox's doorbell. Over a real router."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from agent.bus import ZenohBus, wake_all
from agent.inbox import Alarm, wake_key
from agent.wire import Tick, Xchg, encode
from flocktrack.launch.launcher import free_port, open_router


@pytest.fixture
def pair():
    port = free_port()
    router = open_router(port)
    ep = f"tcp/127.0.0.1:{port}"
    sender, receiver = ZenohBus("inbox", connect=ep), ZenohBus("inbox", connect=ep)
    got: list = []
    receiver.subscribe("agent/*/to/1/xchg", lambda key, msg: got.append((key, msg)), bulk=True)
    receiver.subscribe("world/tick", lambda key, msg: got.append((key, msg)))
    assert receiver._inbox is not None
    assert sender.await_subscriber("agent/0/to/1/xchg", 15) and sender.await_subscriber("world/tick", 15)
    yield sender, receiver, got
    sender.close()
    receiver.close()
    router.close()


def _xchg(r: int) -> Xchg:
    return Xchg(src=0, k=0, r=r, payload={"x": np.array([float(r)])})


def _tick() -> Tick:
    return Tick(k=0, n=2, links=[[1], [0]], weights=[[0.5], [0.5]], b=[1.0, 1.0], delta_max=1, alive=[True, True],
                positions=np.zeros((2, 2)))


def _poll_until(bus, until, timeout=15.0) -> None:
    end = time.monotonic() + timeout
    while not until() and time.monotonic() < end:
        bus.poll(0.05)


def test_the_bulk_subscription_delivers_every_payload_in_order(pair):
    sender, receiver, got = pair
    for r in range(200):
        sender.publish("agent/0/to/1/xchg", _xchg(r % 10))
    _poll_until(receiver, lambda: len(got) == 200)
    assert [m.r for _, m in got] == [r % 10 for r in range(200)]
    assert receiver.stats.received == 200 and not receiver.stats.dropped


def test_a_poll_waits_out_its_timeout_and_no_more(pair):
    _, receiver, _ = pair
    t0 = time.monotonic()
    assert receiver.poll(0.3) == 0
    waited = time.monotonic() - t0
    assert 0.3 <= waited < 5.0, waited


def test_a_sample_of_another_subscription_wakes_a_poll_waiting_in_the_inbox(pair):
    sender, receiver, got = pair
    threading.Timer(0.3, lambda: sender.publish("world/tick", _tick())).start()
    t0 = time.monotonic()
    n = receiver.poll(30.0)
    assert n == 1 and got and got[0][0] == "world/tick"
    assert time.monotonic() - t0 < 15.0


def test_the_deadline_of_a_poll_a_sample_ended_rings_nothing(pair):
    """A poll that a payload ends before its timeout leaves its deadline armed: when that deadline comes, the
    role's thread is not waiting, and no doorbell is put into the inbox for its next poll to skip."""
    sender, receiver, got = pair
    threading.Timer(0.05, lambda: sender.publish("agent/0/to/1/xchg", _xchg(0))).start()
    t0 = time.monotonic()
    assert receiver.poll(1.0) == 1 and len(got) == 1
    time.sleep(max(0.0, t0 + 1.5 - time.monotonic()))  # past the first poll's deadline, the thread not waiting
    assert receiver._inbox.take() is None         # nothing rang: no doorbell in the channel
    t0 = time.monotonic()                         # and a poll after it still waits out its own timeout
    assert receiver.poll(0.3) == 0
    assert time.monotonic() - t0 >= 0.3


def test_wake_all_wakes_a_poll_waiting_in_the_inbox(pair):
    _, receiver, _ = pair
    threading.Timer(0.3, wake_all).start()
    t0 = time.monotonic()
    assert receiver.poll(30.0) == 0
    assert time.monotonic() - t0 < 15.0


def test_bytes_put_on_the_doorbell_key_are_a_bad_key_dropped_and_counted(pair):
    sender, receiver, got = pair
    sender.publish_raw("agent/wake/to/1/xchg", encode(_xchg(0)))
    sender.publish("agent/0/to/1/xchg", _xchg(1))
    _poll_until(receiver, lambda: len(got) == 1 and receiver.stats.dropped)
    assert [m.r for _, m in got] == [1]
    assert receiver.stats.dropped == {"bad_key": 1}


def test_the_wake_key_names_the_first_wildcard_chunk():
    assert wake_key("agent/*/to/3/xchg") == "agent/wake/to/3/xchg"
    assert wake_key("agent/*/state") == "agent/wake/state"
    assert wake_key("**") == "wake"
    assert wake_key("world/tick") is None


def test_the_alarm_rings_once_at_the_deadline_armed_last():
    rings: list[float] = []
    alarm = Alarm(lambda: rings.append(time.monotonic()))
    try:
        t0 = time.monotonic()
        alarm.arm(t0 + 0.2)
        alarm.arm(t0 + 0.5)        # later: the thread wakes at 0.2, finds 0.5 and sleeps on
        end = time.monotonic() + 10
        while not rings and time.monotonic() < end:
            time.sleep(0.01)
        time.sleep(0.3)
        assert len(rings) == 1 and rings[0] >= t0 + 0.5, (rings, t0)
        alarm.arm(time.monotonic() + 0.05)    # earlier than "never": wakes the thread
        end = time.monotonic() + 10
        while len(rings) < 2 and time.monotonic() < end:
            time.sleep(0.01)
        assert len(rings) == 2
    finally:
        alarm.close()
