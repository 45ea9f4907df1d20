"""agent/roles/rejoin.py Rejoin alone: a restarted sensor's way back into the flock (take up the world's
clock, wait for its neighbours' fresh estimates, restart its filter from them) and the handover of a
sensor's last estimate to a peer that reappears."""

from collections import Counter

import numpy as np
from wire_messages import estimate, tick

from agent.estimators.distributed_minimax import DistributedKalman
from agent.roles.rejoin import JOIN_FRESH_TICKS, Rejoin

ME = 1
#: sensor 1 hears 0 and 2; 3 is in the flock but not its neighbour
LINKS = [[1], [0, 2], [1, 3], [2]]


def joining(at: int = 10) -> Rejoin:
    """Sensor ME restarted, having taken up the world's tick ``at``."""
    rj = Rejoin(ME, restarted=True, counters=Counter())
    assert rj.takes_up(tick(at, LINKS), k=0)
    return rj


def filter_at(x0) -> DistributedKalman:
    return DistributedKalman(np.eye(2), 0.01 * np.eye(2), np.eye(2), np.eye(2), n=4, x0=np.asarray(x0, float),
                             P0=np.eye(2), rounds=1)


def test_a_restarted_sensor_takes_up_the_first_tick_ahead_of_its_clock_and_only_that_one():
    rj = Rejoin(ME, restarted=True, counters=Counter())
    assert not rj.takes_up(tick(0, LINKS), k=0)        # not ahead of its own clock
    assert rj.takes_up(tick(12, LINKS), k=0)
    assert rj.joining
    assert not rj.takes_up(tick(13, LINKS), k=12)


def test_a_sensor_that_was_not_restarted_never_takes_up_a_tick():
    rj = Rejoin(ME, restarted=False, counters=Counter())
    assert not rj.takes_up(tick(12, LINKS), k=0)
    assert not rj.joining


def test_a_tick_of_a_flock_without_this_sensor_is_not_taken_up():
    rj = Rejoin(3, restarted=True, counters=Counter())
    assert not rj.takes_up(tick(12, [[1], [0], [1]]), k=0)     # n = 3: no sensor 3 in that world


def test_a_sensor_hands_its_last_estimate_to_a_peer_whose_token_reappears_and_counts_it():
    rj = Rejoin(ME, restarted=False, counters=Counter())
    rj.last = estimate(ME, 7, [1.0, 2.0])
    assert rj.handover(2, alive=True) is rj.last
    assert rj.counters["estimates_handed"] == 1


def test_nothing_is_handed_before_a_first_estimate_nor_to_itself_nor_to_a_peer_that_vanished():
    rj = Rejoin(ME, restarted=False, counters=Counter())
    assert rj.handover(2, alive=True) is None         # no estimate yet
    rj.last = estimate(ME, 7, [1.0, 2.0])
    assert rj.handover(ME, alive=True) is None
    assert rj.handover(2, alive=False) is None
    assert rj.counters["estimates_handed"] == 0


def test_a_handed_estimate_is_kept_only_by_a_joining_sensor_or_at_the_first_tick():
    settled = Rejoin(ME, restarted=False, counters=Counter())
    settled.offer(estimate(0, 4, [1.0, 1.0]), k=5, shape=(2,))
    assert settled.peers == {}
    settled.offer(estimate(0, 0, [1.0, 1.0]), k=0, shape=(2,))    # tick 0: a restart may not know it is one yet
    assert list(settled.peers) == [0]
    rj = joining()
    rj.offer(estimate(0, 9, [1.0, 1.0]), k=10, shape=(2,))
    assert list(rj.peers) == [0]


def test_an_older_copy_of_a_peers_estimate_does_not_replace_the_newer_one():
    rj = joining()
    rj.offer(estimate(0, 9, [9.0, 9.0]), k=10, shape=(2,))
    rj.offer(estimate(0, 4, [4.0, 4.0]), k=10, shape=(2,))    # held by the bus since an earlier router restart
    assert rj.peers[0].k == 9


def test_an_estimate_of_another_shape_or_its_own_is_not_kept():
    rj = joining()
    rj.offer(estimate(0, 9, [1.0, 2.0, 3.0]), k=10, shape=(2,))
    rj.offer(estimate(ME, 9, [1.0, 2.0]), k=10, shape=(2,))
    assert rj.peers == {}


def test_a_joining_sensor_waits_until_every_live_neighbour_has_handed_a_fresh_estimate():
    rj = joining()
    t = tick(10, LINKS)
    assert rj.awaiting(t, [0, 2], k=10)
    rj.offer(estimate(3, 9, [3.0, 3.0]), k=10, shape=(2,))
    assert rj.awaiting(t, [0, 2], k=10)                      # 3 is no neighbour: still waiting
    assert rj.offer(estimate(0, 9, [0.0, 0.0]), k=10, shape=(2,))   # True: the first tick waits for these
    assert rj.awaiting(t, [0, 2], k=10)
    rj.offer(estimate(2, 9, [2.0, 2.0]), k=10, shape=(2,))
    assert not rj.awaiting(t, [0, 2], k=10)
    assert not rj.pending


def test_a_joining_sensor_without_live_neighbours_waits_for_any_fresh_estimate():
    rj = joining()
    t = tick(10, LINKS)
    assert rj.awaiting(t, [], k=10)
    rj.offer(estimate(3, 9, [3.0, 3.0]), k=10, shape=(2,))
    assert not rj.awaiting(t, [], k=10)


def test_a_joining_sensor_the_world_lists_dead_does_not_wait():
    rj = joining()
    dead = tick(10, LINKS, alive=[True, False, True, True])
    assert not rj.awaiting(dead, [0, 2], k=10)
    assert not rj.pending


def test_estimates_older_than_the_freshness_window_are_not_waited_for():
    rj = joining()
    k = 10
    rj.offer(estimate(0, k - JOIN_FRESH_TICKS - 1, [0.0, 0.0]), k=k, shape=(2,))
    rj.offer(estimate(2, k - JOIN_FRESH_TICKS, [2.0, 2.0]), k=k, shape=(2,))
    assert sorted(rj.fresh(k)) == [2]
    assert rj.awaiting(tick(k, LINKS), [0, 2], k=k)


def test_the_first_tick_back_restarts_the_filter_from_the_mean_of_the_neighbours_estimates():
    rj = joining()
    for j, x in ((0, [0.0, 4.0]), (2, [2.0, 8.0]), (3, [100.0, 100.0])):
        rj.offer(estimate(j, 9, x, P=(j + 1) * np.eye(2)), k=10, shape=(2,))
    est = filter_at([50.0, -50.0])                           # its prior, which the restart must not keep
    rj.start_from(est, [0, 2], k=10)
    np.testing.assert_allclose(est.x, [1.0, 6.0])            # 0's and 2's, not the non-neighbour 3's
    np.testing.assert_allclose(est.P, 2.0 * np.eye(2))       # the mean of 1·I and 3·I
    assert rj.counters["reinitialised_from"] == 2
    assert not (rj.joining or rj.restarted or rj.pending)


def test_a_restart_without_neighbours_starts_from_everyone_who_handed_an_estimate():
    rj = joining()
    rj.offer(estimate(3, 9, [3.0, 1.0]), k=10, shape=(2,))
    est = filter_at([50.0, -50.0])
    rj.start_from(est, [], k=10)
    np.testing.assert_allclose(est.x, [3.0, 1.0])


def test_past_the_deadline_the_sensor_stops_waiting_and_starts_from_the_newest_estimates_there_are():
    rj = joining(at=20)
    rj.offer(estimate(0, 5, [0.0, 0.0]), k=20, shape=(2,))   # all stale
    rj.offer(estimate(2, 6, [6.0, 2.0]), k=20, shape=(2,))
    t = tick(20, LINKS)
    assert rj.awaiting(t, [0, 2], k=20)
    assert rj.give_up_waiting()
    assert rj.counters["join_deadline"] == 1
    assert not rj.awaiting(t, [0, 2], k=20)                  # forced: the tick goes on
    est = filter_at([50.0, -50.0])
    rj.start_from(est, [0, 2], k=20)
    np.testing.assert_allclose(est.x, [6.0, 2.0])            # the newest (tick 6) only
    assert not rj.forced


def test_the_deadline_changes_nothing_when_no_first_tick_is_waiting():
    rj = Rejoin(ME, restarted=False, counters=Counter())
    assert not rj.give_up_waiting()
    assert rj.counters["join_deadline"] == 0
