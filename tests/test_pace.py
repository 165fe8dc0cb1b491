"""The paced loop's clock: absolute deadlines on a grid that a stall does not move, never an early
wake-up, and the deadline accounting against a plain recomputation from the recorded times."""

import time
from fractions import Fraction

import numpy as np

from rtctl import safety
from rtctl.engine import pace


def _run(n, period_ns, spin_s=0.0, stall_at=None, stall_s=0.0, busy_at=None, busy_s=0.0):
    """``n`` paced blocks: a sleep of ``stall_s`` before waiting for block ``stall_at`` (the
    thread kept from its wake-up), a busy ``busy_s`` inside block ``busy_at`` (a long block)."""
    st = pace.new_state(spin_s)
    times, lates, missed = np.zeros(n), np.zeros(n), np.zeros(n, dtype=np.bool_)
    wakes, bits = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
    pace.start(st)
    for k in range(n):
        if k == stall_at:
            time.sleep(stall_s)
        while pace.wait(st, k, period_ns):
            pass
        wakes[k] = st[pace.WAKE]
        if k == busy_at:
            t = time.perf_counter()
            while time.perf_counter() - t < busy_s:
                pass
        bits[k] = pace.settle(st, k, period_ns, True, times, lates, missed)[0]
    return st, times, lates, missed, wakes, bits


def _grid(start, k, period_ns):
    """Block k's due time, from exact rationals: start + k periods, rounded half up."""
    return start + int(Fraction(k) * Fraction(period_ns) + Fraction(1, 2))


def test_blocks_are_due_on_a_fixed_grid_that_a_stall_does_not_move():
    period = 2e6 / 3  # 666666.67 ns: block 32 at 48 kHz, not a whole number of nanoseconds
    n = 120
    st, _, lates, missed, wakes, _ = _run(n, period, stall_at=10, stall_s=0.05)
    start = int(st[pace.START])
    due = np.array([_grid(start, k, period) for k in range(n)])
    np.testing.assert_array_equal([pace.due_ns(st, k, period) for k in range(n)], due)
    assert np.all(wakes >= due)  # never early
    np.testing.assert_allclose(lates, (wakes - due) * 1e-3)
    # the stall (at least 75 periods) made block 10 and every block due meanwhile miss ...
    assert missed[10:84].all()
    # ... and the blocks after the catch-up are due where they were: a loop that slept relative
    # to its last wake-up would be a whole stall (50 ms) late at the end
    assert lates[-1] < 25e3


def test_a_late_start_is_a_late_wakeup_and_a_long_block_an_overrun():
    period = 1e6  # 1 ms
    st, times, lates, missed, _, bits = _run(30, period, stall_at=5, stall_s=0.02, busy_at=20, busy_s=0.02)
    # every count is what the recorded times say (the rule: a miss is the larger share's)
    ref_miss = (lates + times) * 1e3 > period
    np.testing.assert_array_equal(missed, ref_miss)
    np.testing.assert_array_equal(bits != 0, ref_miss)
    assert set(np.unique(bits)) <= {0, safety.DEADLINE_MISSED}
    late = ref_miss & (lates >= times)
    assert st[pace.LATE_WAKEUPS] == late.sum() and st[pace.OVERRUNS] == (ref_miss & ~late).sum()
    assert late[5] and not late[20] and ref_miss[20]  # the stall is a late wake-up, the long block an overrun
    assert st[pace.OVERRUNS] >= 1 and st[pace.LATE_WAKEUPS] >= 1


def test_a_spin_still_never_wakes_early():
    period = 1e6
    st, _, lates, _, wakes, _ = _run(20, period, spin_s=200e-6)
    start = int(st[pace.START])
    assert all(wakes[k] >= _grid(start, k, period) for k in range(20))
    assert np.all(lates >= 0)


def test_wake_stats_count_a_stall_once_and_sample_only_woken_blocks():
    late = np.array([5.0, 7.0, 900.0, 300.0, 4.0, 6.0, 800.0, 3.0])
    missed = np.array([0, 0, 1, 1, 0, 0, 1, 0], dtype=bool)
    w = pace.wake_stats(late, missed)
    assert w["miss_bursts"] == 2  # blocks 2-3 (one stall and its catch-up) and block 6
    # blocks 3, 4 and 7 each followed a missed block: they were due before it ended (caught up)
    woken = late[[0, 1, 2, 5, 6]]
    assert w["wake_late_us"]["max"] == 900.0
    assert w["wake_late_us"]["p50"] == np.percentile(woken, 50)
