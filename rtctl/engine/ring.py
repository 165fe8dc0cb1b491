"""The trace ring: the loop thread hands each block's trace record over, another thread writes.

The ring is an array of whole trace records (the trace's own dtype), so the thread that drains
it appends runs of slots to the file as they are, with no per-record Python. The loop thread
fills a slot with one compiled call (:func:`push`): a copy *plan* names, per traced signal, the
rig buffer it comes from (address, rows, columns, row stride) and where it lands in the record
(as float32, scaled); then it publishes the slot by advancing the write index. One writer per
index, a fence before each publishing store, no lock and no allocation: the same contract as
the parameter queue (:mod:`rtctl.engine.queue`).

A full ring never blocks a real-time loop: the record is dropped and counted (``heads[DROPPED]``),
and the drain writes a placeholder in its place (NaN data, status ``TRACE_DROPPED``), so the
trace keeps one record per block and says which are missing. A run that is not real time (the
simulated rig as fast as it goes) waits for room instead: its trace is always complete.
"""

from __future__ import annotations

import math
import os
import threading

import numpy as np
from numba import carray

from .._codegen import fence, voidptr_at
from .._numba import kernel

#: ``heads``: records published (producer), records written out (consumer), records dropped
#: (producer), the block index the next published record will carry (producer).
WRITE, READ, DROPPED = 0, 1, 2
#: Plan columns: source address, rows, columns, source row stride (elements), destination
#: offset (float32 index into the record), index into the scales.
N_PLAN = 6
#: Seconds of records a real-time run's ring holds: the drain thread may stall that long (a busy
#: disk, a loaded machine) before a record is dropped. Bounded by :data:`MAX_BYTES`.
RING_SECONDS = 2.0
#: Largest ring, bytes (a many-channel scene with long blocks holds fewer seconds).
MAX_BYTES = 512 << 20
#: The drain writes and hands back at most this many bytes of records at a time (at least one
#: record, at most half the ring), so that a producer waiting for room goes on while the rest is
#: written.
PIECE_BYTES = 1 << 20


@kernel
def push(plan, scales, f32, u32, heads, late_col, k, status, compute_us, late_us):
    """Copy block ``k``'s record into the next free slot and publish it; when the ring is full,
    count it as dropped instead. Returns 1 if published, 0 if dropped."""
    w = heads[WRITE]
    r = heads[READ]
    fence()  # the consumer's reads of the slots it freed happen before we overwrite them
    n = f32.shape[0]
    if w - r >= n:
        heads[DROPPED] += 1
        return 0
    s = w % n
    u32[s, 0] = np.uint32(k & 0xFFFFFFFF)
    u32[s, 1] = np.uint32(k >> 32)
    u32[s, 2] = np.uint32(status & 0xFFFFFFFF)
    f32[s, 3] = compute_us
    if late_col >= 0:
        f32[s, late_col] = late_us
    rec = f32[s]
    for p in range(plan.shape[0]):
        rows, cols, stride, dst = plan[p, 1], plan[p, 2], plan[p, 3], plan[p, 4]
        scale = scales[plan[p, 5]]
        src = carray(voidptr_at(plan[p, 0]), ((rows - 1) * stride + cols,), np.float64)
        # One loop per case, each over a row as 1-D views: the copy then runs as vector
        # conversions (a loop with the scale's test and 2-D indexing inside ran ~1 ns per value).
        # To float32 first, then scaled in float32: what Rig.record's in-place *= gives.
        for i in range(rows):
            a = src[i * stride:i * stride + cols]
            b = rec[dst + i * cols:dst + (i + 1) * cols]
            if scale != 1.0:
                for j in range(cols):
                    b[j] = np.float32(a[j]) * scale
            else:
                for j in range(cols):
                    b[j] = np.float32(a[j])
    fence()  # the record is complete before the index that publishes it
    heads[WRITE] = w + 1
    return 1


@kernel
def published(heads):
    """Records published so far (consumer side: the slots below it are complete)."""
    w = heads[WRITE]
    fence()
    return w


@kernel
def release(heads, r):
    """Hand the slots below ``r`` back to the producer (after they were written out)."""
    fence()
    heads[READ] = r


class TraceRing:
    """Slots of trace records and the plan that fills them.

    Parameters
    ----------
    dtype : numpy.dtype
        The trace's record dtype (:attr:`rtctl.trace.TraceWriter.dtype`): header
        ``block <i8, status <i4, compute_us <f4``, then float32 fields.
    sources : list of (field, array, scale)
        Per traced field, a float64 array holding exactly the field's values (same element count,
        rows of contiguous columns; strided views allowed) and a factor applied on the copy.
    slots : int
    late_field : str or None
        A per-block float32 field that gets the block's wake-up lateness, us.
    """

    def __init__(self, dtype, sources, slots: int, late_field: str | None = None):
        self.dtype = np.dtype(dtype)
        if self.dtype.itemsize % 4 or list(self.dtype.names[:3]) != ["block", "status", "compute_us"]:
            raise TypeError("not an rtctl trace record dtype")
        self.records = np.zeros(int(slots), dtype=self.dtype)
        self.records.view(np.uint8)[...] = 0  # touch every page now, not in the loop's first pass
        self.f32 = self.records.view(np.float32).reshape(len(self.records), -1)
        self.u32 = self.records.view(np.uint32).reshape(len(self.records), -1)
        self.heads = np.zeros(4, dtype=np.int64)
        self.late_col = self._col(late_field) if late_field else -1
        plan, scales, self._keep = [], [], []
        for field, arr, scale in sources:
            if math.prod(self.dtype.fields[field][0].shape) == 0:  # e.g. no sensed rows: nothing to copy
                continue
            plan.append(self._plan_row(field, arr))
            if float(scale) not in scales:
                scales.append(float(scale))
            plan[-1][5] = scales.index(float(scale))
            self._keep.append(arr)
        self.plan = np.array(plan, dtype=np.int64).reshape(-1, N_PLAN)
        self.scales = np.array(scales or [1.0], dtype=np.float32)

    def _col(self, field: str) -> int:
        return self.dtype.fields[field][1] // 4

    def _plan_row(self, field: str, a: np.ndarray) -> list:
        sub = self.dtype.fields[field][0]
        if sub.base != np.float32:
            raise TypeError(f"trace field {field!r} is not float32")
        a2 = a.reshape(1, -1) if a.ndim == 1 else a
        if a.dtype != np.float64 or a2.ndim != 2 or a2.strides[1] != 8 or a2.strides[0] % 8 or a2.size != math.prod(
                sub.shape):
            raise TypeError(f"trace field {field!r}: its source is not float64 rows of "
                            f"{math.prod(sub.shape)} values in all")
        return [a2.__array_interface__["data"][0], a2.shape[0], a2.shape[1],
                a2.strides[0] // 8 if a2.shape[0] > 1 else a2.shape[1], self._col(field), 0]

    @property
    def slots(self) -> int:
        return len(self.records)

    @property
    def dropped(self) -> int:
        return int(self.heads[DROPPED])

    def push(self, k: int, status: int, compute_us: float = 0.0, late_us: float = 0.0) -> bool:
        """Python's way to :func:`push` (the loop calls the kernel itself, from compiled code)."""
        return bool(push(self.plan, self.scales, self.f32, self.u32, self.heads, self.late_col, k, status,
                         compute_us, late_us))

    @property
    def args(self) -> tuple:
        """:func:`push`'s leading arguments."""
        return self.plan, self.scales, self.f32, self.u32, self.heads, self.late_col


def slots_for(itemsize: int, fs: float, block: int, realtime: bool) -> int:
    """Ring slots for a run: :data:`RING_SECONDS` of blocks when real time (at least 64), else a
    quarter second's (the loop waits for room); at most :data:`MAX_BYTES`, at least 4 slots."""
    per_s = fs / block
    want = math.ceil((RING_SECONDS if realtime else 0.25) * per_s)
    return int(max(4, min(max(64, want), MAX_BYTES // max(1, itemsize))))


class Drain(threading.Thread):
    """The ring's consumer: appends published records to the trace (a placeholder for each
    dropped one), updates the progress bar, and never touches the loop's state but ``heads[READ]``.

    Parameters
    ----------
    ring : TraceRing
    writer : rtctl.trace.TraceWriter
    bar : object with ``update(blocks done)``
    cpus : set of int or None
        CPUs this thread runs on (all but the loop's, when the loop has one).
    priority : int
        SCHED_FIFO priority of this thread (0: stay SCHED_OTHER), below the loop's. Its Python
        holds the GIL, which the loop needs after every wait: a normal thread preempted while it
        holds it would keep a real-time loop waiting for as long as other processes run. At a
        real-time priority only the loop preempts it, and then gets the GIL within the switch
        interval. Refused: it stays SCHED_OTHER.
    poll_s : float
        Sleep between passes while the ring is empty (fewer passes: fewer moments with the GIL).
        Every pass appends what is published, so a record reaches the file (and survives a killed
        process) at most about this long after the loop published it.
    clock : int64 array of one element, optional
        The loop's clock start (CLOCK_MONOTONIC ns, 0 until it starts), noted in the trace
        (:meth:`rtctl.trace.TraceWriter.started`) once it is set: what a reader measures lost
        blocks against.
    """

    def __init__(self, ring: TraceRing, writer, bar, cpus=None, priority: int = 0, poll_s: float = 0.02,
                 clock=None):
        super().__init__(name="rtctl-trace-drain", daemon=True)
        self.ring, self.writer, self.bar, self.cpus, self.poll_s = ring, writer, bar, cpus, poll_s
        self.clock = clock
        self.priority = int(priority)
        self.read = 0          # slots consumed
        self.next_block = 0    # the block index the next record written must carry
        self.error = None
        self._stop_at = None
        self._wake = threading.Event()
        # at most half the ring: a pass of a piece then means more may be waiting
        self._piece = max(1, min(ring.slots // 2, PIECE_BYTES // ring.records.dtype.itemsize))

    def kick(self) -> None:
        """Make a pass now (a producer that waits for room; never a real-time loop)."""
        self._wake.set()

    def stop(self, blocks: int) -> None:
        """The loop has ended after ``blocks`` blocks: write everything, then placeholders for
        any dropped at the end, and end the thread."""
        self._stop_at = int(blocks)
        self._wake.set()
        self.join()

    def run(self) -> None:
        try:
            if self.cpus and hasattr(os, "sched_setaffinity"):
                try:
                    os.sched_setaffinity(0, self.cpus)
                except OSError:  # then anywhere: the loop's own CPU was the point, not this
                    pass
            if self.priority > 0 and hasattr(os, "sched_setscheduler"):
                try:
                    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.priority))
                except OSError:  # not permitted: the loop's own request says so
                    pass
            while True:
                stop = self._stop_at
                if self.clock is not None and self.clock[0]:
                    self.writer.started(int(self.clock[0]))
                    self.clock = None
                # a whole piece written: more may be waiting; less: wait for more (or a kick)
                # rather than write the records one by one as the producer publishes them
                if self._pass() >= self._piece:
                    continue
                if stop is not None:
                    self._pass()
                    self.writer.gap(stop - self.next_block)
                    self.next_block = max(self.next_block, stop)
                    self.bar.update(self.next_block)
                    return
                self._wake.wait(self.poll_s)
                self._wake.clear()
        except BaseException as e:  # noqa: BLE001 - handed to the loop's thread, raised there after the run
            self.error = e
            # keep consuming so a waiting producer is not stuck behind a dead writer
            self.ring.heads[READ] = self.ring.heads[WRITE]

    def _pass(self) -> int:
        """Write out what is published; returns the records written."""
        ring, n = self.ring, self.ring.slots
        w = int(published(ring.heads))
        r0 = r = self.read
        if w == r:
            return 0
        piece = self._piece
        while r < w:
            s = r % n
            e = min(w, r + (n - s), r + piece)
            self._write(ring.records[s:s + (e - r)])
            r = e
            release(ring.heads, r)
            self.read = r
        self.bar.update(self.next_block)
        return r - r0

    def _write(self, recs) -> None:
        blocks = recs["block"]
        first, last = int(blocks[0]), int(blocks[-1])
        if first == self.next_block and last - first == len(recs) - 1:  # no record missing
            self.writer.append(recs)
            self.next_block = last + 1
            return
        cuts = np.flatnonzero(np.diff(blocks) != 1) + 1
        for part in np.split(recs, cuts):
            self.writer.gap(int(part["block"][0]) - self.next_block)
            self.writer.append(part)
            self.next_block = int(part["block"][-1]) + 1
