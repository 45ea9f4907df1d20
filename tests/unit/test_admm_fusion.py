"""Distributed robust moving-horizon fusion by consensus ADMM (agent/estimators/admm_fusion.py):
one node per UAV, each with only its own measurements, against the central RobustMHE on the same data; the
nodes agree; a node that is down leaves the other estimating alone, and a restarted one takes the window
over and agrees again."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.estimators.admm_fusion import AdmmFusionNode, ArrivalRecord, run_lockstep
from agent.estimators.robust_mhe import RobustMHE
from agent.models_uav import UavConfig, UavRelativeSim

T = 0.05


class World:
    """García Carrillo's two UAVs (ids 1, 2; ~5 Hz each, outliers), their records by arrival tick."""

    def __init__(self, frac: float, dur: float = 60.0, seed: int = 0):
        self.st = UavRelativeSim(UavConfig(outlier_fraction=frac)).generate(dur, np.random.default_rng(seed))
        self.ticks = int(math.ceil(dur / T))
        self.recs = [self.st.record(j) for j in range(len(self.st))]
        self.by_tick: dict[int, list[int]] = {}
        for j, a in enumerate(self.st.arrival):
            self.by_tick.setdefault(int(math.floor(a / T)), []).append(j)

    def source(self, agent: int | None):
        """Node input: the records of UAV ``agent`` (None: every UAV's) arriving in tick k, by time."""
        def f(k: int):
            js = [j for j in self.by_tick.get(k, []) if agent is None or self.recs[j].agent == agent]
            return [self.recs[j] for j in sorted(js, key=lambda j: (self.recs[j].t, self.recs[j].agent))]
        return f

    def truth(self, t: float) -> np.ndarray:
        d = self.st.dense
        return np.array([np.interp(t, d["t"], d["pos"][:, 0]), np.interp(t, d["t"], d["pos"][:, 1])])

    def rmse(self, est) -> float:
        e = [p[:2] - self.truth(t) for t, p in est]
        return float(np.sqrt(np.mean(np.sum(np.square(e), axis=1))))

    def central(self) -> list:
        """The fusion role's central RobustMHE (scenarios/carrillo_robust.toml): newest node per measurement."""
        c, out, src = RobustMHE(W=15, q=3.0), [], self.source(None)
        for k in range(self.ticks):
            for rec in src(k):
                c.add(rec)
                r = c.solve()
                out.append((r.t_newest, r.newest.copy()))
        return out


def _track(nodes, rec):
    last = {i: None for i in nodes}

    def on_tick(k):
        for i, n in nodes.items():
            if math.isfinite(n.t_newest) and n.t_newest != last[i]:
                last[i] = n.t_newest
                rec[i].append((n.t_newest, n.newest.copy(), k))
    return on_tick


@pytest.fixture(scope="module")
def worlds():
    return {f: World(f) for f in (0.01, 0.10, 0.20)}


def test_one_node_with_every_measurement_is_the_central_estimator(worlds):
    """M = 1 (no consensus): the node's window solve is the central robust MHE's problem — RMSE within 2 %."""
    w = worlds[0.10]
    node = AdmmFusionNode(0, w.source(None), T=T)
    got: dict = {0: []}
    run_lockstep({0: node}, T, range(w.ticks), on_tick=_track({0: node}, got))
    c = w.rmse(w.central())
    d = w.rmse([(t, x) for t, x, _ in got[0]])
    assert abs(d - c) <= 0.02 * c, (d, c)
    assert node.counters["ticks_alone"] > 0 and node.counters["evicted"] > 0.9 * len(got[0])


@pytest.mark.parametrize("frac", [0.01, 0.10, 0.20])
def test_two_uavs_agree_and_match_the_central_solver(worlds, frac):
    """Each UAV fuses only its own measurements; after the tick's ADMM iterations both hold the same
    estimate, and its RMSE is within 5 % of the central solver's on the same data (or better)."""
    w = worlds[frac]
    nodes = {0: AdmmFusionNode(0, w.source(1), T=T), 1: AdmmFusionNode(1, w.source(2), T=T)}
    got: dict = {0: [], 1: []}
    run_lockstep(nodes, T, range(w.ticks), on_tick=_track(nodes, got))
    assert [t for t, _, _ in got[0]] == [t for t, _, _ in got[1]]
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(got[0], got[1]))
    c = w.rmse(w.central())
    d = w.rmse([(t, x) for t, x, _ in got[0]])
    assert d <= 1.05 * c, (frac, d, c)
    for n in nodes.values():
        assert n.counters["ticks_consensus"] > 0 and n.counters["ticks_alone"] == 0
        assert n.counters["rounds_broken"] == 0 and n.counters["adopted_arrival"] > 0


def test_payloads_carry_no_measurement():
    """What a node sends: its node times and states, the arrival cost, consensus vectors — never one of its
    relative measurements or GPS fixes."""
    w = World(0.10, dur=10.0)
    sent: list = []

    class Spy(AdmmFusionNode):
        def payload(self, r):
            p = super().payload(r)
            sent.append(p)
            return p

    nodes = {0: Spy(0, w.source(1), T=T), 1: Spy(1, w.source(2), T=T)}
    run_lockstep(nodes, T, range(w.ticks))
    assert {tuple(sorted(p)) for p in sent} == {("arrival", "clean", "count", "nodes"), ("sig", "xy")}
    private = {float(v) for r in w.recs for v in (*r.z, *r.gps)}
    values = {float(v) for p in sent for a in p.values() for v in np.ravel(a)}
    assert len(values) > 1000 and not private & values


def test_a_node_down_leaves_the_other_estimating_and_a_restarted_one_agrees_again():
    """UAV 2's process is down for ticks 400–599 (20–30 s) and restarts empty: UAV 1 estimates alone from its
    own data meanwhile; from the restart on the new node takes the window and the arrival cost over from
    round 0 and the two agree again."""
    w = World(0.10)
    nodes = {0: AdmmFusionNode(0, w.source(1), T=T), 1: AdmmFusionNode(1, w.source(2), T=T)}
    got: dict = {0: [], 1: []}
    track = _track(nodes, got)
    run_lockstep(nodes, T, range(0, 400), on_tick=track)
    run_lockstep(nodes, T, range(400, 600), alive=lambda k, i: i == 0, on_tick=track)
    alone = nodes[0].counters["ticks_alone"]
    assert alone >= 150
    during = [(t, x) for t, x, k in got[0] if 400 <= k < 600]
    assert len(during) > 30 and max(t for t, _ in during) > 29.0       # it kept estimating
    assert w.rmse(during) < 2.0 * w.rmse(w.central())
    nodes[1] = AdmmFusionNode(1, w.source(2), T=T)                      # the restarted process
    got[1] = []
    track = _track(nodes, got)
    run_lockstep(nodes, T, range(600, w.ticks), on_tick=track)
    assert nodes[1].counters["adopted_arrival"] >= 1
    assert isinstance(nodes[1].arrival, ArrivalRecord) and nodes[1].arrival.evictions > 0
    late0 = {t: x for t, x, k in got[0] if k >= 620}
    late1 = {t: x for t, x, k in got[1] if k >= 620}
    assert late0 and late0.keys() == late1.keys()
    assert all(np.array_equal(late0[t], late1[t]) for t in late0)
    assert nodes[0].counters["ticks_consensus"] > 400 + 500
    after = [(t, x) for t, x, k in got[0] if k >= 650]
    assert w.rmse(after) < 1.2 * w.rmse(w.central())


@pytest.mark.parametrize("scen, sets, key, hint", [
    ("carrillo_robust", ['fusion.mode="distributd"'], "fusion.mode", "did you mean `distributed`"),
    ("carrillo_uav", ['fusion.mode="distributed"'], "fusion.estimator", 'estimator = "robust_mhe"'),
    ("carrillo_robust", ['fusion.mode="distributed"', "fusion.admm_iterations=0"], "fusion.admm_iterations", "1…100"),
    ("carrillo_robust", ['fusion.mode="distributed"', "fusion.admm_rho=-1.0"], "fusion.admm_rho", "> 0"),
])
def test_the_fusion_mode_is_checked_with_file_key_and_fix(scen, sets, key, hint):
    from pathlib import Path

    from agent.scenario import parse_scenario, scenario_data
    from agent.schema import ScenarioError

    path = Path(__file__).resolve().parents[2] / "scenarios" / f"{scen}.toml"
    with pytest.raises(ScenarioError) as e:
        parse_scenario(scenario_data(str(path), sets), str(path))
    assert e.value.key == key and hint in str(e.value), str(e.value)


def test_the_distributed_mode_links_the_uavs():
    from pathlib import Path

    from agent.scenario import parse_scenario, scenario_data

    path = Path(__file__).resolve().parents[2] / "scenarios" / "carrillo_robust.toml"
    central = parse_scenario(scenario_data(str(path)), str(path))
    dist = parse_scenario(scenario_data(str(path), ['fusion.mode="distributed"']), str(path))
    assert central.topology.graphs[0].edges == [] and dist.topology.graphs[0].edges == [[0, 1]]
    assert dist.uav.admm() == {"iterations": 8, "rho": 0.05}


def test_a_lost_payload_ends_the_ticks_consensus_on_both_sides_and_the_next_tick_agrees_again():
    """UAV 2's round-4 payload of tick 300 never reaches UAV 1: UAV 1 finishes the tick alone, its next
    payload tells UAV 2, which leaves too; both restart their duals at tick 301 and agree from then on."""
    w = World(0.10, dur=20.0)
    nodes = {0: AdmmFusionNode(0, w.source(1), T=T), 1: AdmmFusionNode(1, w.source(2), T=T)}
    got: dict = {0: [], 1: []}
    run_lockstep(nodes, T, range(w.ticks), on_tick=_track(nodes, got),
                 lost=lambda k, r, i, j: (k, r, i, j) == (300, 4, 1, 0))
    assert nodes[0].counters["rounds_broken"] == 1 and nodes[1].counters["rounds_broken"] == 1
    assert nodes[0].counters["ticks_alone"] == 1 and nodes[1].counters["ticks_alone"] == 1
    after0 = {t: x for t, x, k in got[0] if k > 300}
    after1 = {t: x for t, x, k in got[1] if k > 300}
    assert after0 and after0.keys() == after1.keys()
    assert all(np.array_equal(after0[t], after1[t]) for t in after0)
