"""The paced loop's clock: absolute deadlines on CLOCK_MONOTONIC, and cyclictest's accounting.

Block ``k`` of a paced run is due at ``start + k * period`` and must be finished by ``start +
(k + 1) * period``, whatever happened before: a late block shifts no later one (no drift), and
after a stall the loop catches up by running the overdue blocks back to back, as cyclictest's
timer thread does. The wait is ``clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)`` called from
compiled code that has released the GIL: a relative ``time.sleep(deadline - now)`` loses the
time between reading the clock and going to sleep whenever the thread is preempted in that gap,
and holds the GIL while it computes. An optional spin (``timing.spin``) sleeps until that long
before the deadline and then reads the clock until it passes, for a wake-up that does not depend
on the scheduler's timer path; it burns a core for that long every block.

Accounting per block (:func:`settle`): the *wake-up lateness* is when the block started minus
when it was due; the block time is from its start to the moment its trace record is handed
over. A block whose deadline passed is a *late wake-up* when its lateness was the larger share
of the overshoot, a *compute overrun* when its block time was. A stall of several periods costs
the block it delayed and every block that fell due meanwhile (the catch-up): each is a deadline
miss, where cyclictest, which skips the periods it overslept, counts one late wake-up.
:func:`wake_stats` sorts that out: the lateness of the blocks that were woken (not caught up,
cyclictest's samples) and the number of stalls (runs of consecutive misses).

Linux: the kernels call glibc's ``clock_gettime`` and ``clock_nanosleep`` (``CLOCK_MONOTONIC``,
the clock of Python's ``time.monotonic`` and ``time.perf_counter`` there).
"""

from __future__ import annotations

import numpy as np
from numba import types

from .. import safety
from .._numba import kernel

CLOCK_MONOTONIC = 1
TIMER_ABSTIME = 1
NS = 1_000_000_000

_clock_gettime = types.ExternalFunction("clock_gettime", types.int32(types.int32, types.voidptr))
_clock_nanosleep = types.ExternalFunction(
    "clock_nanosleep", types.int32(types.int32, types.int32, types.voidptr, types.voidptr))

#: Fields of the int64 state array (:func:`new_state`): the run's start, the current block's
#: start (ns), the spin (ns), the deadline counts, and a timespec (seconds, nanoseconds).
START, WAKE, SPIN, LATE_WAKEUPS, OVERRUNS, TS = 0, 1, 2, 3, 4, 5
N_STATE = 8
#: Longest single sleep: a wait returns to Python at least this often, so Ctrl-C is seen within
#: it even when a block is seconds long (clock_nanosleep resumes after a signal another thread took).
SLICE_NS = 50_000_000


def new_state(spin_s: float = 0.0) -> np.ndarray:
    """The clock state for one run (see the field names above)."""
    st = np.zeros(N_STATE, dtype=np.int64)
    st[SPIN] = int(round(spin_s * NS))
    return st


@kernel
def now_ns(st):
    """CLOCK_MONOTONIC, ns."""
    ts = st[TS:TS + 2]
    _clock_gettime(CLOCK_MONOTONIC, ts.ctypes.data)
    return ts[0] * NS + ts[1]


@kernel
def due_ns(st, k, period_ns):
    """When block ``k`` is due: start + k periods (float periods, rounded once: no drift)."""
    return st[START] + np.int64(k * period_ns + 0.5)


@kernel
def start(st):
    """The run starts now: block 0 is due now, and starts now."""
    st[START] = now_ns(st)
    st[WAKE] = st[START]
    st[LATE_WAKEUPS] = 0
    st[OVERRUNS] = 0


@kernel
def mark(st):
    """An unpaced block starts now."""
    st[WAKE] = now_ns(st)


@kernel
def wait(st, k, period_ns):
    """Sleep until block ``k`` is due (less ``SPIN``, then spin to it), then mark its start.
    Returns 0 when done, 1 when woken early (a signal, or a sleep longer than ``SLICE_NS``): the
    caller handles its signals and calls again, with the same absolute deadline."""
    due = due_ns(st, k, period_ns)
    target = due - st[SPIN]
    t = now_ns(st)
    if t < target:
        until = target if target - t <= SLICE_NS else t + SLICE_NS
        ts = st[TS:TS + 2]
        ts[0] = until // NS
        ts[1] = until % NS
        r = _clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, ts.ctypes.data, ts.ctypes.data)
        if r != 0 or until < target:
            return 1
    while st[SPIN] > 0 and now_ns(st) < due:
        pass
    st[WAKE] = now_ns(st)
    return 0


@kernel
def settle(st, k, period_ns, paced, times_us, late_us, missed):
    """Block ``k`` is done: its block time, lateness and whether it missed its deadline into
    ``times_us[k]``, ``late_us[k]`` and ``missed[k]`` (when ``k`` is in range), the deadline
    counts, and ``DEADLINE_MISSED`` when it passed (paced runs only). Returns ``(status bits,
    block time us, lateness us)``."""
    t = now_ns(st)
    took = t - st[WAKE]
    late = st[WAKE] - due_ns(st, k, period_ns) if paced else 0
    bits = 0
    if paced and late + took > period_ns:
        bits = safety.DEADLINE_MISSED
        if late >= took:
            st[LATE_WAKEUPS] += 1
        else:
            st[OVERRUNS] += 1
    if k < times_us.shape[0]:
        times_us[k] = took * 1e-3
        late_us[k] = late * 1e-3
        missed[k] = bits != 0
    return bits, took * 1e-3, late * 1e-3


def wake_stats(late_us: np.ndarray, missed: np.ndarray) -> dict:
    """The lateness distribution of the blocks that waited for their time (whose predecessor
    met its deadline: cyclictest's samples), us, and ``miss_bursts``, the runs of consecutive
    deadline misses (a stall and its catch-up count once, as in cyclictest)."""
    missed = np.asarray(missed, dtype=bool)
    woken = np.ones(missed.size, dtype=bool)
    woken[1:] = ~missed[:-1]
    x = np.asarray(late_us, dtype=float)[woken] if woken.any() else np.zeros(1)
    bursts = int(np.count_nonzero(missed & woken))
    return {"wake_late_us": {"p50": float(np.percentile(x, 50)), "p99": float(np.percentile(x, 99)),
                             "p999": float(np.percentile(x, 99.9)), "max": float(x.max())},
            "miss_bursts": bursts}
