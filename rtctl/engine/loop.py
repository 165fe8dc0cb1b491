"""The polled engine: the loop thread runs the blocks, and nothing else.

Per block the loop thread hands the block's parameter changes to the block function, waits for
the block's absolute deadline (paced runs, :mod:`rtctl.engine.pace`), calls the backend's
``read``, the block function and the backend's ``write`` (:meth:`Rig.advance`), and hands the
block's trace record to the ring (:mod:`rtctl.engine.ring`) in the same compiled call that
does the block's accounting. The trace file, the progress bar and any console output belong to
the drain thread. Backends ``sim`` (paced with ``--realtime``), ``serial`` (always paced) and
``daq`` (clocked by its device) all run here; ``audio`` runs its blocks in the device's thread
(:func:`rtctl.engine.run._run_callback`).

A real-time run (paced, or clocked by its device) never waits for the drain: a full ring drops
the record and counts it. A simulation run as fast as it goes waits for room instead.

A trace that cannot be written (a full disk, an I/O error) ends the run like a fault: the drain
stops writing and the loop thread, between runs of blocks, sees its error and fades the outputs
to zero over one block. The trace keeps what was written (:class:`rtctl.trace.TraceWriter`).
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from .. import safety
from .._codegen import fence
from .._numba import kernel
from ..trace import FLUSH_S, TraceWriteError
from . import pace, realtime
from .chunk import FAULT, ROOM, BlockRuns
from .pace import settle
from .ring import DROPPED, READ, WRITE, Drain, TraceRing, published, push, release, slots_for

#: The per-block trace field with each block's wake-up lateness (paced runs).
LATE_FIELD = "wake_late_us"


@kernel
def end_block(st, k, period_ns, paced, times_us, late_us, missed, status, plan, scales, f32, u32, heads, late_col):
    """Block ``k`` is done: its accounting (:func:`rtctl.engine.pace.settle`) and its trace record
    into the ring (:func:`rtctl.engine.ring.push`). Returns its status bits."""
    bits, took, late = settle(st, k, period_ns, paced, times_us, late_us, missed)
    status |= bits
    push(plan, scales, f32, u32, heads, late_col, k, status, took, late)
    return status


@kernel
def end_untraced(st, k, period_ns, paced, times_us, late_us, missed, status):
    """:func:`end_block` for a run without a trace."""
    bits, took, late = settle(st, k, period_ns, paced, times_us, late_us, missed)
    return status | bits


@kernel
def commit(heads, w):
    """Publish the slots below ``w`` after filling them from Python (the ring's fallback path)."""
    fence()
    heads[WRITE] = w


@dataclass
class LoopResult:
    blocks: int
    status_seen: int
    interrupted: bool
    wall: float
    late_wakeups: int = 0
    overruns: int = 0
    dropped: int = 0
    os: dict = field(default_factory=dict)
    cpu: float = 0.0  # CPU time of the loop's thread over the run's blocks, s
    #: the trace's write failure (:meth:`rtctl.trace.TraceWriter.failure`), '' when it had none
    trace_error: str = ""
    #: whether that failure ended the run (it faded the outputs as a fault does); else it came after
    trace_stopped: bool = False


def _compile() -> None:
    """Compile (or load) the loop's kernels now, on scratch arrays of the loop's types, not in
    its first block."""
    st = pace.new_state()
    t = np.zeros(1)
    pace.start(st)
    pace.mark(st)
    while pace.wait(st, 0, 1.0):
        pass
    m = np.zeros(1, dtype=np.bool_)
    end_untraced(st, 0, 1.0, True, t, t, m, 0)
    f32, u32 = np.zeros((1, 4), dtype=np.float32), np.zeros((1, 4), dtype=np.uint32)
    end_block(st, 0, 1.0, True, t, t, m, 0, np.zeros((0, 6), dtype=np.int64), np.ones(1, dtype=np.float32), f32, u32,
              np.zeros(4, dtype=np.int64), -1)
    heads = np.zeros(4, dtype=np.int64)
    commit(heads, 0)
    release(heads, published(heads))  # the drain's, compiled here: a first call holds the GIL


def trace_sources(rig, dtype) -> list | None:
    """Per field of the trace record, the rig buffer it copies (what :meth:`Rig.record` writes),
    as ``(field, float64 array, factor)``; None when a field has no known source (the loop then
    fills records with :meth:`Rig.record` from Python)."""
    truth = rig.truth
    known = {"drive": (rig.out, 1.0), "sensed": (rig.sensed, 1.0), "target_um": (rig.targets_um, 1.0),
             "estimated_um": (rig.estimated_amp, 1e6), "estimated_tip_um": (rig.estimated, 1e6),
             "temperature": (rig.limiter.temperature, 1.0)}
    if truth is not None:
        for i, (name, scale) in enumerate((("tip_um", 1e6), ("tip_velocity", 1.0), ("tip_force", 1.0),
                                           ("voltage", 1.0))):
            known[name] = (truth[:, i, :], scale)
    for name, _, dev, r in rig.probes:
        known[name] = (dev.probe[r, :rig.block], 1.0)
    out = []
    for name in dtype.names[3:]:
        if name == LATE_FIELD:
            continue
        if name not in known:
            return None
        arr, scale = known[name]
        out.append((name, arr, scale))
    return out


def fault_message(rig, k, status, period) -> str:
    """The one line a fault ends a run with: when, what, and that the outputs were faded."""
    what = safety.describe(status & safety.FAULTS)
    if status & (safety.DEVICE_LOST | safety.XRUN_BURST):
        err = rig.device.stats().get("error") if hasattr(rig.device, "stats") else None
        if err:  # the backend's own words replace the generic name of its fault bit
            own = {safety.STATUS_NAMES[safety.DEVICE_LOST]: f"I/O device lost: {err}",
                   safety.STATUS_NAMES[safety.XRUN_BURST]: f"audio xrun burst: {err}"}
            what = [own.get(w, w) for w in what]
    return f"at {k * period:.4f} s: " + "; ".join(what) + "; outputs faded to 0 V"


class Loop:
    """One polled run: ``Loop(rig, writer, ...).run(n_blocks, times, lates, missed, faults)``.

    Parameters
    ----------
    rig : Rig
    writer : TraceWriter or None
    bar : progress bar (``update(blocks done)``, ``close()``), updated by the drain thread
    paced : bool
        Pace blocks to the wall clock (``--realtime``, or a device whose clock is the wall's).
    strict : bool
        Never wait for the drain (real time): a full ring drops records.
    ask_os : bool
        Ask for SCHED_FIFO, mlockall and CPU affinity (``--realtime``; :mod:`rtctl.engine.realtime`).
    say : callable
        Where the refused requests' lines go.
    """

    def __init__(self, rig, writer, bar, paced: bool, strict: bool, ask_os: bool, timing, say=None):
        self.rig, self.writer, self.bar = rig, writer, bar
        self.paced, self.strict, self.ask_os = bool(paced), bool(strict), bool(ask_os)
        self.priority, self.cpu, self.spin_s = int(timing.priority), int(timing.cpu), float(timing.spin) * 1e-6
        self.say = say or (lambda text: print(f"rtctl: {text}", file=sys.stderr))
        self.period_ns = rig.block / rig.fs * 1e9
        self.ring = self.drain = None
        self.python_record = False
        if writer is not None:
            sources = trace_sources(rig, writer.dtype)
            self.python_record = sources is None
            late = LATE_FIELD if LATE_FIELD in writer.dtype.names else None
            slots = slots_for(writer.dtype.itemsize, rig.fs, rig.block, strict)
            self.ring = TraceRing(writer.dtype, sources or [], slots, late)
        _compile()
        # runs of blocks in one compiled call, where no block needs Python (rtctl.engine.chunk)
        self.runs = None
        if BlockRuns.usable(rig) and not self.python_record and os.environ.get("RTCTL_BLOCK_RUNS", "1") != "0":
            self.runs = BlockRuns(rig, self.period_ns, paced, strict, self.ring.args if self.ring is not None else None)
            self.runs.compile()

    def run(self, n_blocks: int, times: np.ndarray, lates: np.ndarray, missed: np.ndarray, faults: list) -> LoopResult:
        rig, paced, period_ns = self.rig, self.paced, self.period_ns
        st = pace.new_state(self.spin_s if paced else 0.0)
        if self.ring is not None:
            # started before this thread asks for a real-time priority or a CPU: it inherits neither
            pinned = self.cpu if self.ask_os else -1
            below = max(1, self.priority - 10) if self.ask_os and self.priority > 0 else 0
            # a pass at least every FLUSH_S: a killed process loses at most about that much trace;
            # a run as fast as it goes fills a ring piece in about a millisecond: look that often
            self.drain = Drain(self.ring, self.writer, self.bar, realtime.other_cpus(pinned), below,
                               FLUSH_S if self.strict else 0.001, st[pace.START:pace.START + 1] if paced else None)
            self.drain.start()
        session = realtime.enter(paced, self.ask_os, self.priority, self.cpu)
        for note in session.notes:
            self.say(f"realtime: {note}")
        ring = self.ring
        if ring is not None:
            args = ring.args
        status_seen, k, run_blocks, interrupted = 0, 0, n_blocks, False
        drain = self.drain
        trace_stopped = False  # the trace could not be written: the run ends as on a fault
        wait, mark, strict = pace.wait, pace.mark, self.strict
        advance, apply_schedule = rig.advance, rig.apply_schedule
        runs = self.runs
        if runs is not None:
            runs.start(0)
        cpu0 = time.thread_time()
        try:
            apply_schedule(0)  # before the clock starts: block 0 starts with parameters to publish
            pace.start(st)
            scheduled = 0  # the last block whose schedule was applied
            while runs is not None and k < n_blocks:
                if k > scheduled:
                    apply_schedule(k)
                    scheduled = k
                k, seen, status, why = runs(k, min(n_blocks, rig.next_busy(k)), st, times, lates, missed)
                status_seen |= seen
                if why == FAULT:
                    faults.append(fault_message(rig, k, status, rig.block / rig.fs))
                    run_blocks = k
                    break
                if why == ROOM:
                    self._room()
                    if not self.drain.is_alive():  # its error is raised after the run; go on dropping
                        runs = self.runs = None
                if drain is not None and drain.error is not None:  # seen within a slice of blocks
                    trace_stopped, run_blocks = True, k
                    break
            while runs is None and k < n_blocks and not trace_stopped:
                if k > scheduled:
                    apply_schedule(k)
                    scheduled = k
                if paced:
                    while wait(st, k, period_ns):
                        pass
                else:
                    mark(st)
                status = advance()
                if ring is None:
                    status = end_untraced(st, k, period_ns, paced, times, lates, missed, status)
                else:
                    if not strict:
                        self._room()
                    if self.python_record:
                        status = self._record(st, k, status, times, lates, missed)
                    else:
                        status = end_block(st, k, period_ns, paced, times, lates, missed, status, *args)
                status_seen |= status
                k += 1
                if status & safety.FAULTS:
                    faults.append(fault_message(rig, k, status, rig.block / rig.fs))
                    run_blocks = k
                    break
                if drain is not None and drain.error is not None:
                    trace_stopped, run_blocks = True, k
                    break
        except KeyboardInterrupt:
            interrupted = True
            if runs is not None:  # what the compiled runs did, even if Ctrl-C cut off their return
                k = max(k, runs.sync())
                status_seen |= runs.status_seen
            run_blocks = k
        finally:
            wall = (pace.now_ns(st) - st[pace.START]) * 1e-9 if st[pace.START] else 0.0
            cpu = time.thread_time() - cpu0
            try:
                k = self._fade(st, k, times, lates, missed, requested=not (faults or trace_stopped), faults=faults)
            finally:
                session.restore()
                if self.drain is not None:
                    self.drain.stop(k)
                self.bar.close()
                if self.writer is not None:
                    self.writer.close(check=False)  # a write failure is this run's to report, below
                if rig.device is not None:
                    rig.device.close()
        if self.drain is not None and self.drain.error is not None and not isinstance(self.drain.error,
                                                                                      TraceWriteError):
            raise self.drain.error  # not the file's: a bug in the drain
        trace_error = self.writer.failure(n_blocks * self.period_ns * 1e-9) if self.writer is not None else ""
        return LoopResult(run_blocks, status_seen, interrupted, wall, int(st[pace.LATE_WAKEUPS]),
                          int(st[pace.OVERRUNS]), self.ring.dropped if self.ring is not None else 0,
                          session.summary(), cpu, trace_error, trace_stopped)

    def _fade(self, st, k, times, lates, missed, requested: bool, faults=None) -> int:
        """Whatever ended the run, fade every output to zero, paced like the run, recording the
        fade blocks; returns the blocks recorded.

        A fault fades linearly over one block (longer if the slew limit needs it). A requested
        stop (the run's end, Ctrl-C) fades over ``rig.stop_fade`` samples (``timing.stop_fade``)
        as a raised cosine, then runs on with 0 V for ``rig.settle_blocks`` while the tips
        settle; a fault in its blocks cuts the fade to one block and ends the run when it is done.
        """
        rig = self.rig
        lim = rig.limiter
        if requested:
            rig.hold_control()
            lim.shutdown(rig.stop_fade, smooth=True)
        else:
            lim.shutdown(rig.block)
        tail = rig.settle_blocks if requested else 0  # blocks to run on once the fade is done
        while True:
            if self.paced:
                while pace.wait(st, k, self.period_ns):
                    pass
            else:
                pace.mark(st)
            status = rig.advance()
            if self.ring is not None:
                if not self.strict:
                    self._room()
                if self.python_record:
                    self._record(st, k, status, times, lates, missed)
                else:
                    end_block(st, k, self.period_ns, self.paced, times, lates, missed, status, *self.ring.args)
            k += 1
            if status & safety.FAULTS and lim.smooth_stop:
                lim.shutdown(rig.block)  # a fault during a requested stop: its own, quick fade
                tail = 0
                if faults is not None:
                    faults.append(fault_message(rig, k, status, rig.block / rig.fs))
            if lim.done:
                if tail <= 0:
                    return k
                if self.runs is None:
                    tail -= 1
                    continue
                # the outputs are at 0 V: the settle tail needs nothing from Python, block by block
                k, status, tail = self._tail(st, k, tail, times, lates, missed, faults)
                if tail <= 0 and lim.done:
                    return k

    def _tail(self, st, k, tail, times, lates, missed, faults) -> tuple:
        """The settle tail's ``tail`` blocks in compiled runs; returns ``(next block, last status,
        blocks of the tail left)``: none, or those after a fault (whose quick fade the caller runs
        from Python, as any fault's, ending the run)."""
        end = k + tail
        status = 0
        while k < end:
            k, _, status, why = self.runs(k, end, st, times, lates, missed)
            if why == FAULT:
                if self.rig.limiter.smooth_stop:
                    self.rig.limiter.shutdown(self.rig.block)
                    if faults is not None:
                        faults.append(fault_message(self.rig, k, status, self.rig.block / self.rig.fs))
                return k, status, 0
            if why == ROOM:
                self._room()
                if not self.drain.is_alive():
                    self.runs = None
                    return k, status, end - k
        return k, status, 0

    def _room(self) -> None:
        """Wait until the ring has a free slot (runs that are not real time only)."""
        h, n = self.ring.heads, self.ring.slots
        while h[WRITE] - h[READ] >= n and self.drain.is_alive():  # a dead drain: drop (its error is raised)
            self.drain.kick()
            time.sleep(5e-5)

    def _record(self, st, k, status, times, lates, missed) -> int:
        """The fallback: a record filled by :meth:`Rig.record` from Python, then published."""
        status = end_untraced(st, k, self.period_ns, self.paced, times, lates, missed, status)
        ring, h = self.ring, self.ring.heads
        w = int(h[WRITE])
        if w - int(h[READ]) >= ring.slots:
            h[DROPPED] += 1
            return status
        rec = ring.records[w % ring.slots]
        took = float(times[k]) if k < len(times) else 0.0
        self.rig.record(rec, status, took)
        rec["block"] = k
        if ring.late_col >= 0:
            rec[LATE_FIELD] = lates[k] if k < len(lates) else 0.0
        commit(h, w + 1)
        return status
