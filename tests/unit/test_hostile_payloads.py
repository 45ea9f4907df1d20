"""A Byzantine neighbour's unusable payloads never reach an honest sensor's estimate or covariance.

Hypothesis writes what a Byzantine sensor could send in place of its exchange payloads — NaN, inf, arrays of
the wrong shape or too many, keys missing or foreign, values of other types, a header naming another sender,
round or tick — and the flock runs in process with it. An unusable payload is exactly a lost link: every
sensor's estimate and covariance is bit-identical to the run in which those payloads were lost on the way.
A rejoining sensor takes up no covariance from a peer that is not symmetric positive definite.
"""

from __future__ import annotations

from pathlib import Path

import msgpack
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agent import wire
from agent.bus import LocalBus
from agent.estimators.base import is_covariance
from agent.scenario import parse_scenario, scenario_data
from flocktrack.engine.inproc import run_inproc

SCEN = Path(__file__).resolve().parents[2] / "scenarios"
TICKS = 25
LIAR = 3

_bad_numbers = st.sampled_from([np.nan, np.inf, -np.inf])
_arrays = st.one_of(
    st.tuples(st.sampled_from([(4, 4), (4,)]), _bad_numbers).map(lambda t: wire._enc_array(np.full(t[0], t[1]))),
    st.sampled_from([(3, 3), (5,), (4, 4, 1), (0,), (2, 8)]).map(lambda s: wire._enc_array(np.ones(s))),
    st.builds(lambda n: {"s": [n], "d": b"\x00" * (8 * n - 1)}, st.integers(1, 16)),
    st.one_of(st.none(), st.integers(-5, 5), st.text(max_size=20), st.lists(st.floats(), max_size=4)),
)


@st.composite
def hostile_payloads(draw):
    """A payload map with at least one unusable entry, or no usable shape at all."""
    keys = draw(st.lists(st.sampled_from(["chi1", "chi2", "chi3", "x", "P", "zz"]), min_size=1, max_size=4,
                         unique=True))
    out = {k: draw(_arrays) for k in keys}
    return out


def _scenario():
    data = scenario_data(str(SCEN / "gu_hu_normal.toml"), [], **{"run.ticks": TICKS, "estimator.resilient_f": 1})
    return parse_scenario(data, "gu_hu_normal.toml")


class LyingBus(LocalBus):
    """Sensor ``LIAR`` sends ``payload`` (under ``header``'s fields) in place of each exchange payload it
    addresses to a neighbour; with ``payload=None`` those payloads are lost on the way."""

    def __init__(self, payload: dict | None, header: dict | None = None):
        super().__init__()
        self.lie, self.header = payload, header or {}

    def publish_raw(self, key: str, data: bytes) -> None:
        if key.startswith(f"agent/{LIAR}/to/"):
            if self.lie is None:
                return
            d = msgpack.unpackb(data, raw=False)
            d.update(self.header)
            d["payload"] = self.lie
            data = msgpack.packb(d, use_bin_type=True)
        super().publish_raw(key, data)


def _estimates(roles) -> list:
    return [(r.est.x.copy(), None if r.est.P is None else r.est.P.copy()) for r in roles.sensors]


_LOST: dict = {}


def _lost():
    """The run in which the liar's addressed payloads are lost."""
    if not _LOST:
        _, roles, _ = run_inproc(_scenario(), bus=LyingBus(None))
        _LOST["est"] = _estimates(roles)
    return _LOST["est"]


@settings(max_examples=20, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(payload=hostile_payloads(),
       header=st.fixed_dictionaries({}, optional={"src": st.sampled_from([0, 7, -1, "3"]),
                                                   "r": st.sampled_from([0, 99, -2, 1.5]),
                                                   "k": st.sampled_from([0, 10**9, None])}))
def test_a_byzantine_neighbours_unusable_payload_changes_no_honest_estimate(payload, header):
    bus = LyingBus(payload, header)
    _, roles, _ = run_inproc(_scenario(), bus=bus)
    got, want = _estimates(roles), _lost()
    for i, ((x, P), (x0, P0)) in enumerate(zip(got, want)):
        assert np.array_equal(x, x0), i
        assert (P is None and P0 is None) or np.array_equal(P, P0), i
    # each lie is dropped by the bus, or by the estimator as a malformed payload (a dropped link)
    assert sum(bus.stats.dropped.values()) + sum(r.counters["dropped_links"] for r in roles.sensors) > 0


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.lists(st.floats(-1e3, 1e3), min_size=16, max_size=16))
def test_a_peers_covariance_is_taken_up_only_when_it_is_one(values):
    """``Estimator.reinitialise`` (a rejoining sensor) averages its peers' covariances, leaving out any that
    is not symmetric positive definite."""
    from agent.estimators.distributed_minimax import DistributedKalman

    M = np.array(values).reshape(4, 4)
    est = DistributedKalman(np.eye(4), np.eye(4), np.eye(2, 4), np.eye(2), 3, np.zeros(4), np.eye(4), 1)
    good = 2.0 * np.eye(4)
    est.reinitialise({0: np.zeros(4), 1: np.ones(4)}, {0: good, 1: M})
    assert is_covariance(est.P)
    want = (good + M) / 2 if is_covariance(M) else good
    assert np.allclose(est.P, want)
    skew = np.triu(np.ones((4, 4)), 1)
    for bad in (-np.eye(4), np.full((4, 4), np.nan), np.eye(4) + skew, np.diag([1.0, 1.0, 0.0, 1.0])):
        assert not is_covariance(bad)
