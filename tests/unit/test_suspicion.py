"""Who suspected whom, scored against the Byzantine windows (flocktrack/record/suspicion.py)."""

import numpy as np

from flocktrack.record.suspicion import attack_ticks, robustness_report, suspicion_report

# a path 0 - 1 - 2 - 3 and 2 - 4: node i hears the nodes in LINKS[i]
LINKS = ((1,), (0, 2), (1, 3, 4), (2,), (2,))


def test_detection_latency_discarded_share_and_false_suspicions():
    attacks = attack_ticks({2: [(3, 6)]}, ticks=10)
    assert attacks == {2: {3, 4, 5}}
    sus = {k: {i: np.array([]) for i in range(5)} for k in range(10)}
    sus[1][0] = np.array([1.0])                       # an honest node suspected, before the attack
    for i in (1, 3):
        sus[4][i] = np.array([2.0])                   # tick 4: 2 of its 3 neighbours discard it
    sus[5][1] = np.array([2.0])                       # tick 5: 1 of 3
    links = {k: LINKS for k in range(10)}
    r = suspicion_report(sus, links, attacks)
    assert r["false_suspicions"] == 1 and r["node_ticks"] == 47          # 50 node-ticks less node 2's 3
    a = r["attackers"]["2"]
    assert (a["start"], a["detected_tick"], a["latency_ticks"]) == (3, 4, 1)
    assert a["discarded_share"] == 3 / 9


def test_a_graph_with_a_sensor_below_2f_plus_1_neighbours_is_not_robust_enough():
    full = tuple(tuple(j for j in range(5) if j != i) for i in range(5))
    r = robustness_report({0: full, 1: LINKS, 2: full, 3: LINKS}, f=1)
    assert (r["required_r"], r["ticks_not_robust"], r["first_tick"]) == (3, 2, 1)
    assert robustness_report({0: full}, f=1)["ticks_not_robust"] == 0
    assert robustness_report({0: full}, f=2)["ticks_not_robust"] == 1     # 4 neighbours, 5 needed


def test_robustness_is_decided_exactly_not_only_by_the_degrees():
    """Two 5-cliques joined by a perfect matching: every sensor has 5 neighbours (the degree test passes for
    f = 2), but no sensor has more than one neighbour outside its own clique: the graph is only 1-robust, not
    the 5-robust W-MSR with f = 2 needs; the complete graph on 10 is."""
    links = [[j for j in range(5) if j != i] + [i + 5] for i in range(5)]
    links += [[j for j in range(5, 10) if j != i] + [i - 5] for i in range(5, 10)]
    r = robustness_report({0: tuple(map(tuple, links))}, f=2)
    assert (r["ticks_not_robust"], r["ticks_robust"], r["first_tick"]) == (1, 0, 0)
    full = tuple(tuple(j for j in range(10) if j != i) for i in range(10))
    r = robustness_report({0: full, 1: full}, f=2)
    assert (r["ticks_robust"], r["ticks_not_robust"], r["ticks_unknown"]) == (2, 0, 0)


def test_a_hostile_suspect_list_is_dropped_and_counted_not_a_crash_of_the_summary():
    """Whom a sensor says it discarded comes off the wire: NaN, out-of-range ids, itself and repeats are
    left out of the scoring and counted (the same reading as the dashboard's: agent.wire.valid_suspects)."""
    from agent.wire import Estimate, Tick
    from flocktrack.record.metrics import MetricsCollector

    m = MetricsCollector(3, 4, 2, resilient_f=1)
    links = [[1, 2], [0, 2], [0, 1]]
    for k in range(4):
        m.ingest("world/tick", Tick(k=k, t=0.1 * k, n=3, links=links, weights=[[1.0, 1.0]] * 3, b=[1.0] * 3,
                                    delta_max=2, alive=[True] * 3, positions=np.zeros((3, 2))))
        for i in range(3):
            sus = np.array([np.nan, 7.0, float(i), 1.0, 1.0]) if i == 0 else np.zeros(0)
            m.ingest(f"agent/{i}/estimate", Estimate(src=i, k=k, x=np.zeros(4), x_next=np.zeros(4), name="kf",
                                                     aux={"suspected": sus}))
    s = m.resilience()["suspicion"]
    assert s["invalid_suspects"] == 4 * 4          # NaN, 7, itself, a repeat of 1 — each tick
    assert s["false_suspicions"] == 4 and s["node_ticks"] == 12     # sensor 0 suspected honest sensor 1
