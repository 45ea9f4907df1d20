"""A sensor's per-tick timing rows (agent/roles/tick_timing.py), on a clock the test moves."""

import csv

from agent.roles.tick_timing import COLUMNS, TickTiming


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_a_tick_is_split_into_start_compute_publish_and_wait(tmp_path):
    wall, cpu, thread = Clock(), Clock(), Clock()
    tt = TickTiming(tmp_path / "agent-0-ticks.csv", batch=2, clock=wall, cpu=cpu, thread_cpu=thread)
    for k in range(3):
        arrived = wall.t
        wall.t += 0.004                       # 4 ms until the truth came
        tt.begin(k, arrived)
        with tt.spent("compute"):
            wall.t += 0.002
            thread.t += 0.002
        with tt.spent("publish"):
            wall.t += 0.001
            thread.t += 0.001
        wall.t += 0.010                       # waiting for a neighbour
        tt.round_closed(by_deadline=(k == 1))
        cpu.t += 0.005                        # 3 ms of it the role's compute and publish, 2 ms receiving
        row = tt.end()
        assert row[1:8] == (4.0, 2.0, 1.0, 10.0, 2.0, 5.0, 17.0) and row[8] == 1
    assert tt.end() is None                   # no tick open
    with tt.spent("compute"):                 # outside a tick: not counted anywhere
        wall.t += 1
    tt.flush()
    rows = list(csv.DictReader((tmp_path / "agent-0-ticks.csv").open()))
    assert tuple(rows[0]) == COLUMNS and [r["k"] for r in rows] == ["0", "1", "2"]
    assert [r["deadline_rounds"] for r in rows] == ["0", "1", "0"]


def test_without_a_file_only_the_last_rows_are_kept():
    tt = TickTiming(keep=10)
    for k in range(100):
        tt.begin(k, None)
        tt.end()
    assert 10 <= len(tt.rows) <= 20 and tt.rows[-1][0] == 99


def test_a_flock_writes_its_files_at_different_ticks(tmp_path):
    """Sensor i's first batch is i rows shorter: the sensors do not all write in the same tick."""
    written_at = {}
    for i in range(4):
        tt = TickTiming(tmp_path / f"agent-{i}-ticks.csv", batch=10, stagger=i)
        for k in range(25):
            tt.begin(k, None)
            tt.end()
            if not tt.rows and i not in written_at:
                written_at[i] = k
        tt.flush()
        rows = list(csv.DictReader((tmp_path / f"agent-{i}-ticks.csv").open()))
        assert [int(r["k"]) for r in rows] == list(range(25))      # every row once, in order
    assert written_at == {0: 9, 1: 8, 2: 7, 3: 6}
