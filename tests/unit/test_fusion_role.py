"""agent/roles/fusion.py on a real LocalBus with real wire messages and a real fusion estimator: what it holds
back, in which order it fuses, and what it publishes on ``fusion/estimate``."""

import numpy as np
import pytest
from wire_messages import Heard, send, tick

from agent.bus import LocalBus
from agent.estimators.fusion_baselines import KalmanCV
from agent.estimators.relative_measurement import RelativeMeasurement
from agent.roles.fusion import FusionRole
from agent.wire import End, Meas

R, G = np.eye(2) * 0.5 ** 2, np.eye(2) * 0.1 ** 2
LINKS = [[1], [0]]


def to_record(m: Meas) -> RelativeMeasurement:
    """As the runtime builds it: UAV i is the paper's agent i + 1 (agent 0 is the reference)."""
    return RelativeMeasurement(m.src + 1, m.t, m.y, R, m.pos, G)


def fusion(estimators=None, record=to_record) -> tuple[FusionRole, LocalBus, Heard]:
    role = FusionRole(10, estimators or {"kalman": KalmanCV(q=1.0)}, record)
    bus = LocalBus()
    role.attach(bus)
    return role, bus, Heard(bus, "fusion/estimate")


def meas(src: int, k: int, t: float, y, pos) -> Meas:
    return Meas(src=src, k=k, t=t, y=np.asarray(y, float), pos=np.asarray(pos, float))


def test_measurements_are_held_until_the_next_tick_then_fused_in_time_stamp_order():
    role, bus, heard = fusion()
    send(bus, "agent/1/meas", meas(1, 0, 0.08, [5.0, 0.0], [10.0, 0.0]))
    send(bus, "agent/0/meas", meas(0, 0, 0.02, [1.0, 1.0], [2.0, 3.0]))
    assert heard.got == []
    send(bus, "world/tick", tick(1, LINKS))
    first, second = heard.on("fusion/estimate")
    assert (first.k, first.name, second.k) == (0, "kalman", 0)
    assert first.aux["t"][0] == pytest.approx(0.02) and second.aux["t"][0] == pytest.approx(0.08)
    np.testing.assert_allclose(first.x[:2], [3.0, 4.0])   # a Kalman filter starts at the first gps + z
    np.testing.assert_allclose(first.x[2:], [0.0, 0.0])
    assert role.counters["measurements"] == 2


def test_measurements_with_the_same_time_stamp_are_fused_in_order_of_sender():
    role, bus, heard = fusion()
    send(bus, "agent/1/meas", meas(1, 0, 0.05, [5.0, 0.0], [10.0, 0.0]))
    send(bus, "agent/0/meas", meas(0, 0, 0.05, [1.0, 1.0], [2.0, 3.0]))
    send(bus, "world/tick", tick(1, LINKS))
    np.testing.assert_allclose(heard.on("fusion/estimate")[0].x[:2], [3.0, 4.0])   # sender 0's, though it came last


def test_a_tick_releases_only_the_measurements_of_the_ticks_before_it_and_the_end_releases_the_rest():
    role, bus, heard = fusion()
    send(bus, "agent/0/meas", meas(0, 0, 0.02, [1.0, 1.0], [2.0, 3.0]))
    send(bus, "agent/0/meas", meas(0, 1, 0.12, [1.0, 1.0], [2.5, 3.0]))
    send(bus, "world/tick", tick(1, LINKS))
    assert [e.k for e in heard.on("fusion/estimate")] == [0]
    assert not role.finished
    send(bus, "world/end", End(k=2))
    assert [e.k for e in heard.on("fusion/estimate")] == [0, 1]
    assert role.finished


def test_every_estimator_publishes_its_own_estimate_of_every_measurement_under_its_name():
    role, bus, heard = fusion({"loose": KalmanCV(q=5000.0), "tight": KalmanCV(q=1.0)})
    send(bus, "agent/0/meas", meas(0, 0, 0.02, [1.0, 1.0], [2.0, 3.0]))
    send(bus, "agent/0/meas", meas(0, 0, 0.30, [1.5, 1.0], [2.0, 3.0]))
    send(bus, "world/end", End(k=1))
    got = heard.on("fusion/estimate")
    assert [e.name for e in got] == ["loose", "tight", "loose", "tight"]
    assert not np.allclose(got[2].x, got[3].x)     # two tunings, two answers to the same second measurement
    for e in got:
        np.testing.assert_array_equal(e.x, e.x_next)   # a filter has no mid-window state: x_next = x
        assert e.aux["t_mid"][0] == e.aux["t"][0]


def test_a_measurement_that_is_not_planar_is_refused_and_counted():
    role, bus, heard = fusion()
    send(bus, "agent/0/meas", meas(0, 0, 0.02, [1.0, 1.0, 1.0], [2.0, 3.0]))
    send(bus, "world/end", End(k=1))
    assert heard.got == [] and role.counters["rejected_meas"] == 1


def test_a_measurement_its_record_refuses_is_counted_and_the_others_are_still_fused():
    def reference_is_uav_0(m: Meas) -> RelativeMeasurement:
        # UAV 0 taken as the paper's reference agent: its measurement carries a GPS fix, which (4) refuses
        return RelativeMeasurement(m.src, m.t, m.y, R, m.pos, G)

    role, bus, heard = fusion(record=reference_is_uav_0)
    send(bus, "agent/0/meas", meas(0, 0, 0.02, [1.0, 1.0], [2.0, 3.0]))
    send(bus, "agent/1/meas", meas(1, 0, 0.04, [5.0, 0.0], [10.0, 0.0]))
    send(bus, "world/end", End(k=1))
    (only,) = heard.on("fusion/estimate")
    np.testing.assert_allclose(only.x[:2], [15.0, 0.0])
    assert role.counters["rejected_meas"] == 1 and role.counters["measurements"] == 1
