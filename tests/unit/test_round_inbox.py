"""agent/roles/rounds.py RoundInbox alone: what is kept for its round, what is refused and counted, what a
round's ``take`` hands the estimator."""

from collections import Counter

import numpy as np

from agent.roles.rounds import RoundInbox


def payload(v: float) -> dict[str, np.ndarray]:
    return {"chi2": np.array([v, v])}


def inbox() -> RoundInbox:
    return RoundInbox(Counter())


def test_a_payload_of_a_tick_not_begun_yet_is_kept_for_it_whoever_sent_it():
    ib = inbox()
    assert not ib.refused(7, 5, 0, (4, 1), neighbours=[1, 2])   # at tick 4, round 1: sensor 7's tick 5 is ahead
    ib.put(7, 5, 0, payload(1.0))
    assert ib.complete(5, 0, [7], held=[])
    assert list(ib.take(5, 0, [7])) == [7]
    assert ib.counters == Counter(dropped_links=0)


def test_a_payload_of_a_later_round_of_the_tick_under_way_is_kept_for_its_round():
    ib = inbox()
    assert not ib.refused(1, 3, 2, (3, 0), neighbours=[1])
    ib.put(1, 3, 2, payload(2.0))
    assert not ib.complete(3, 0, [1], held=[])      # round 0 still lacks it: the early one is not round 0's
    assert ib.complete(3, 2, [1], held=[])
    np.testing.assert_array_equal(ib.take(3, 2, [1])[1]["chi2"], [2.0, 2.0])


def test_a_payload_of_a_round_already_closed_is_refused_as_late_and_counted():
    ib = inbox()
    assert ib.refused(1, 3, 0, (3, 1), neighbours=[1])       # round 0 of the tick under way
    assert ib.refused(1, 2, 4, (3, -1), neighbours=[1])      # any round of a past tick, also between ticks
    assert ib.counters["late_payloads"] == 2
    assert ib.counters["non_neighbour_payloads"] == 0


def test_in_the_tick_under_way_a_payload_from_a_sensor_that_is_not_a_neighbour_is_refused_and_counted():
    ib = inbox()
    assert ib.refused(9, 3, 1, (3, 1), neighbours=[1, 2])
    assert ib.counters == Counter(non_neighbour_payloads=1)


def test_between_ticks_a_payload_of_the_next_tick_is_kept_before_its_neighbours_are_known():
    ib = inbox()
    # (3, -1): the tick is not begun, so who the neighbours are is not known yet — the payload waits
    assert not ib.refused(9, 3, 0, (3, -1), neighbours=[])
    assert sum(ib.counters.values()) == 0


def test_a_duplicate_payload_replaces_the_first_copy_and_is_not_counted_twice():
    ib = inbox()
    ib.put(1, 0, 0, payload(1.0))
    ib.put(1, 0, 0, payload(5.0))
    got = ib.take(0, 0, [1])
    assert len(got) == 1
    np.testing.assert_array_equal(got[1]["chi2"], [5.0, 5.0])
    assert ib.counters["dropped_links"] == 0


def test_take_hands_over_only_the_neighbours_payloads_and_counts_each_missing_one_as_a_dropped_link():
    ib = inbox()
    ib.put(1, 0, 0, payload(1.0))
    ib.put(8, 0, 0, payload(8.0))           # kept while it was early; no neighbour of this tick
    got = ib.take(0, 0, [1, 2, 3])
    assert list(got) == [1]
    assert ib.counters["dropped_links"] == 2


def test_take_lists_the_payloads_in_the_neighbour_lists_order_not_in_order_of_arrival():
    ib = inbox()
    ib.put(3, 0, 0, payload(3.0))
    ib.put(1, 0, 0, payload(1.0))
    assert list(ib.take(0, 0, [1, 3])) == [1, 3]


def test_a_round_is_complete_once_every_neighbour_has_sent_or_is_held_back_for_a_later_tick():
    ib = inbox()
    ib.put(1, 4, 0, payload(1.0))
    assert ib.missing(4, 0, [1, 2, 3], held=[]) == [2, 3]
    assert ib.missing(4, 0, [1, 2, 3], held=[3]) == [2]
    assert not ib.complete(4, 0, [1, 2, 3], held=[3])
    assert ib.complete(4, 0, [1, 2, 3], held=[2, 3])


def test_a_round_without_neighbours_is_complete_at_once_and_drops_nothing():
    ib = inbox()
    assert ib.complete(0, 0, [], held=[])
    assert ib.take(0, 0, []) == {}
    assert ib.counters["dropped_links"] == 0


def test_take_closes_the_round_so_a_second_take_finds_nothing():
    ib = inbox()
    ib.put(1, 0, 0, payload(1.0))
    assert ib.take(0, 0, [1])
    assert ib.take(0, 0, [1]) == {}
    assert ib.counters["dropped_links"] == 1


def test_forget_before_drops_the_payloads_of_past_ticks_and_keeps_the_rest():
    ib = inbox()
    for k in (2, 3, 4):
        ib.put(1, k, 0, payload(float(k)))
    ib.forget_before(3)
    assert ib.missing(2, 0, [1], held=[]) == [1]
    assert ib.missing(3, 0, [1], held=[]) == []
    assert ib.missing(4, 0, [1], held=[]) == []
