"""The fixed-rate engine: read -> block step -> write, one block at a time, with a trace.

Per block the engine calls the backend's ``read`` (sensed currents, one block late as on an
audio interface), the rig's ``@njit`` block step (synthesis and the final limiter over
preallocated arrays) and the backend's ``write`` (for the ``sim`` backend this advances the
simulated plant); the polled backends' loop is :mod:`rtctl.engine.loop` (its thread runs the
blocks and nothing else: the trace and the progress bar are another thread's). On a fault every
output fades to zero over one block before the run ends; at the run's end or on Ctrl-C under a
raised cosine over ``timing.stop_fade``, and the trace runs on at 0 V until the model's tips
have settled (:mod:`rtctl.engine.settle`). The trace keeps every finished block.

A trace that cannot be written (a full disk, a quota, an I/O error) ends the run as a fault does;
the trace keeps what was written and says why it ends early, and the summary's ``faults`` name
the cause, the file and how much the trace holds. A run whose trace would not fit on the output's
filesystem (its estimate against the free space) is refused before it starts.
"""

from __future__ import annotations

import contextlib
import json
import math
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import _numba, safety
from ..events import duration_blocks
from .loop import LATE_FIELD, Loop, fault_message
from .pace import wake_stats


@dataclass
class RunResult:
    """What :func:`run` returns: the summary (what ``rtctl run --json`` prints), whether Ctrl-C
    ended it, and where the trace, summary.json and plot.png went (None without ``out_dir``)."""

    summary: dict
    interrupted: bool
    out_dir: Path | None


class _Progress:
    """A progress bar (tqdm) on a terminal, for runs longer than a couple of seconds of wall time;
    ``update`` takes the blocks done so far."""

    def __init__(self, total: int, enabled: bool):
        self._bar = None
        if enabled and sys.stderr.isatty():
            from tqdm import tqdm

            self._bar = tqdm(total=total, unit="block", unit_scale=True, delay=2.0, mininterval=0.2,
                             leave=False, file=sys.stderr, dynamic_ncols=True)
        self._done = 0

    def update(self, done: int) -> None:
        if self._bar is not None and done > self._done:
            self._bar.update(done - self._done)
            self._done = done

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


class _Notice:
    """A line on stderr if ``cancel`` has not come within ``after`` seconds (a timer thread:
    compiling releases the GIL often enough for it to print)."""

    def __init__(self, after: float, text: str, enabled: bool):
        self._timer = None
        if enabled:
            import threading

            self._timer = threading.Timer(after, _stderr, (text,))
            self._timer.daemon = True
            self._timer.start()

    def cancel(self) -> None:
        if self._timer is not None:
            self._timer.cancel()


def run(scene, out_dir=None, realtime: bool = False, plot: bool = True, progress: bool = False,
        report: bool = True, rig=None, blocks: int | None = None) -> RunResult:
    """Build the rig for ``scene`` and run it for ``timing.duration``.

    Parameters
    ----------
    scene : rtctl.scene.Scene
    out_dir : str or Path, optional
        Where ``trace/``, ``summary.json`` and ``plot.png`` go, replacing an earlier run's (its
        plot.png is removed even when this run writes none); nothing is written without it.
    realtime : bool
        Pace blocks to the wall clock, count deadline misses and ask the OS for a real-time
        loop (:mod:`rtctl.engine.realtime`); otherwise run as fast as possible and report the
        real-time factor (a device whose clock paces the loop is paced either way).
    report : bool
        The per-channel rows (and plot.png) from the trace; a caller that reads the trace itself
        (the calibration's excitation) leaves them out.
    blocks : int, optional
        Stop after this many blocks, before ``timing.duration`` (``rtctl warm``: the whole
        scene's rig, events included, compiled by a run of a few blocks).

    With ``control.calibrate = "auto"`` the calibration's measurement and fit run first
    (:func:`rtctl.engine.calibrate.auto`, written to ``out_dir/calibration.json``), and the rig is
    built on it.

    ``rig``: a rig built for ``scene`` and run before (a campaign of runs on one rig): it and its
    device are put back to rest and run again, nothing rebuilt.
    """
    from ..outpath import writable_dir
    from ..trace import TraceReader, TraceWriter, why_failed
    from ..validity import check as model_validity
    from .rig import build

    validity = model_validity(scene)  # a model far outside its range is refused here
    created = out_dir is not None and not Path(out_dir).exists()
    if out_dir is not None:  # before anything runs: a bad directory is one line, not a lost run
        writable_dir(out_dir, "--out", subdirs=("trace",), files=RUN_FILES + ("calibration.json",))
    calibrated = None
    try:
        if rig is not None:
            rig.reset()
            rig.device.reset()
        elif scene.control.calibrate == "auto":
            from .calibrate import auto

            scene, calibrated = auto(scene, out_dir, run, say=_stderr if progress else None)
        t_build = time.perf_counter()
        # A build that compiles (an empty or outdated numba cache) takes 20-40 s: say so on a
        # terminal, as the progress bar does, not a silence (piped output keeps its one line per error).
        notice = _Notice(2.0, "compiling the block function and its kernels (the first run after an install or "
                              "a change; numba caches them for the next runs; `rtctl warm` does it ahead) ...",
                         progress and sys.stderr.isatty() and rig is None)
        try:
            rig = build(scene) if rig is None else rig
        finally:
            notice.cancel()
    except BaseException:
        if created:  # refused before anything was written (a bad signal, an image): leave no empty --out
            with contextlib.suppress(OSError):
                Path(out_dir).rmdir()  # (only if empty)
        raise
    build_s = time.perf_counter() - t_build
    if calibrated is not None and out_dir is None:  # auto's temporary file: the rig has read it
        Path(scene.control.calibration).unlink(missing_ok=True)
    fs, block = rig.fs, rig.block
    n_blocks = duration_blocks(scene.timing.duration, fs, block)
    if blocks is not None:
        n_blocks = max(1, min(n_blocks, blocks))
    out = Path(out_dir) if out_dir is not None else None
    dev = rig.device
    # Paced to the wall clock: asked for, or the device's clock is the wall's (hardware). Real
    # time: paced, or clocked by the device itself (read() waits for its buffers); then nothing
    # may make the loop wait, a full trace ring included.
    paced = realtime or dev.paced
    strict = paced or dev.clocked
    writer = None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        signals = rig.trace_signals()
        if paced and not dev.callback:
            signals[LATE_FIELD] = ("us", 1, 0)
        meta = trace_meta(scene, rig)
        # before anything of an earlier run is removed: a refused run leaves it as it was
        check_space(out, signals, rig, n_blocks, meta)
        _remove_earlier_run(out)
        writer = TraceWriter(out / "trace", signals, fs, block, rig.channel_names, meta=meta, reserve=RUN_RESERVE)
    times = np.zeros(n_blocks)
    lates = np.zeros(n_blocks)
    missed = np.zeros(n_blocks, dtype=np.bool_)
    faults: list[str] = []
    bar = _Progress(n_blocks, progress)
    period = block / fs
    timing = {}
    if dev.callback:
        t_start = time.perf_counter()
        run_blocks, status_seen, interrupted, trace_stopped = _run_callback(rig, writer, n_blocks, times, faults, bar)
        wall = time.perf_counter() - t_start
        trace_error = ""
        if writer is not None:
            writer.close(check=False)  # a write failure is reported below, with the run's summary
            trace_error = writer.failure(n_blocks * period)
        dev.close()
        misses = int(dev.stats().get("late_blocks", 0))
    else:
        loop = Loop(rig, writer, bar, paced, strict, realtime, scene.timing)
        res = loop.run(n_blocks, times, lates, missed, faults)
        run_blocks, status_seen, interrupted, wall = res.blocks, res.status_seen, res.interrupted, res.wall
        trace_error, trace_stopped = res.trace_error, res.trace_stopped
        misses = res.late_wakeups + res.overruns
        # on a machine shared with other processes the wall clock measures them too
        cpu_rtf = run_blocks * block / fs / res.cpu if res.cpu > 0 else math.inf
        timing = {"cpu_realtime_factor": cpu_rtf, "late_wakeups": res.late_wakeups, "overruns": res.overruns,
                  "trace_dropped": res.dropped}
        if paced:
            timing.update(wake_stats(lates[:run_blocks], missed[:run_blocks]))
        if res.os:
            timing["realtime"] = res.os
    # the outputs faded as on a fault (an audio device fades any stop this thread asks for smoothly)
    faulted = bool(faults) or (trace_stopped and not dev.callback)
    if trace_error:
        # as a fault's line: when it ended the run, at the block it did; else it came with the close
        faults.append(f"at {run_blocks * period:.4f} s: {trace_error}; outputs faded to 0 V" if trace_stopped
                      else f"{trace_error} (after the run's end)")
    bt = times[:run_blocks] if run_blocks else np.zeros(1)
    summary = {
        "scene": scene.scene.name,
        "fs": fs,
        "block": block,
        "backend": scene.io.backend,
        "duration_s": run_blocks * period,
        "realtime_factor": (run_blocks * period / wall) if wall > 0 else math.inf,
        "block_time_us": _percentiles(bt),
        "deadline_misses": misses,
        **timing,
        "faults": faults,
        "warnings": validity + rig.warnings + [w for w in safety.describe(status_seen & ~safety.FAULTS
                                                                          & ~safety.DEADLINE_MISSED)],
        "build_s": build_s,
        # how the block ran: one composed function or stages from Python; cached kernels or not
        "block_function": rig.compose_note,
        "numba_cache": _numba.CACHE_NOTE or "stamped with the package",
        "interrupted": interrupted,
        # how the outputs went to 0 V: a fault over one block, a requested stop under a raised
        # cosine and then 0 V while the model's tips settle (rtctl.engine.settle)
        "stop": {"by": "fault" if faulted or trace_stopped else ("interrupt" if interrupted else "end"),
                 "fade": "linear" if faulted else "raised cosine",
                 "fade_s": (block if faulted else rig.stop_fade) / fs,
                 "settle_s": 0.0 if faulted else rig.settle_blocks * period},
        # the scene's events, at the block they took effect in
        "events": [{"at": ev.at, "t_s": ev.block * period, "block": ev.block, "set": dict(ev.sets)}
                   for ev in rig.events if ev.block < run_blocks],
        "channels": [],
    }
    if rig.calibration is not None:
        from .calibrate import summary_of

        summary["calibration"] = summary_of(rig.calibration, calibrated)
    if dev is not None and hasattr(dev, "stats"):
        summary["io"] = dev.stats()
    if out is not None:
        from .report import channel_rows

        reader = TraceReader(out / "trace", verify=False)  # just written and closed here: its counts suffice
        if trace_error:
            summary["trace"] = {"blocks": reader.n_blocks, "duration_s": reader.n_blocks * period,
                                "closed": reader.closed, "error": trace_error}
        # the report reads the blocks the trace holds (all of the run's, unless a write failed)
        reported = min(run_blocks, reader.n_blocks)
        if report:
            summary["channels"] = channel_rows(rig, reader, reported)
        _write_summary(out, summary, trace_error)
        if plot and report and reported:
            from .report import plot as make_plot

            try:
                make_plot(summary, reader, out / "plot.png", reported)
            except OSError as e:  # a full disk: the run's results are in the summary already
                (out / "plot.png").unlink(missing_ok=True)
                summary["warnings"].append(f"plot.png not written: {why_failed(e)}")
                _write_summary(out, summary, trace_error)
    return RunResult(summary, interrupted, out)


def _write_summary(out: Path, summary: dict, trace_error: str) -> None:
    """Write ``summary.json`` whole; one that cannot be written is an OutputError naming why (and
    what the trace holds when it failed too), not a half file."""
    from ..errors import OutputError
    from ..trace import why_failed

    p = out / "summary.json"
    try:
        p.write_text(json.dumps(summary, indent=1))
    except OSError as e:
        p.unlink(missing_ok=True)
        raise OutputError(f"{why_failed(e)} writing {p}: the run's summary is not written"
                          + (f"; {trace_error}" if trace_error else "")) from None


#: Bytes a run's trace holds back while it is written (freed on close): room for summary.json
#: and plot.png (about 250 kB) when the trace has filled the disk.
RUN_RESERVE = 512 << 10


def check_space(out: Path, signals: dict, rig, n_blocks: int, meta: dict) -> None:
    """Refuse a run whose trace would not fit on ``out``'s filesystem: its records (bytes per
    block from the trace signals, times the run's blocks with the stop's fade and settling), an
    index entry per block at most, its ``trace.json`` and :data:`RUN_RESERVE`, against the free
    space plus what the earlier run's files there (replaced) hold. An estimate made before
    anything runs; a disk filled during the run still ends it as a fault."""
    from ..errors import OutputError
    from ..trace import CHUNK, RESERVE, record_fields

    itemsize = np.dtype(record_fields(signals, rig.block)[0]).itemsize
    blocks = n_blocks + math.ceil(rig.stop_fade / rig.block) + rig.settle_blocks + 1
    need = blocks * (itemsize + CHUNK.itemsize) + 2 * len(json.dumps(meta, indent=1)) + RUN_RESERVE
    try:
        free = shutil.disk_usage(out).free
    except OSError:  # no figure to check against: the run's own writes will say
        return
    for name in ("trace/blocks.bin", "trace/chunks.bin", f"trace/{RESERVE}", *RUN_FILES):
        try:
            free += (out / name).stat().st_size
        except OSError:
            pass
    if need > free:
        secs = n_blocks * rig.block / rig.fs
        raise OutputError(f"--out {out}: this run's trace needs about {_size(need)} ({secs:g} s: {blocks} blocks "
                          f"of {itemsize} bytes) but its filesystem has {_size(free)} free; shorten the run "
                          f"(--duration, timing.duration) or give --out a filesystem with room")


def _size(n: int) -> str:
    """Bytes in decimal units, three figures ("5.92 GB")."""
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n} bytes"


def trace_meta(scene, rig) -> dict:
    """What a trace records about its run, for readers and ``rtctl replay``: the scene (validated,
    overrides applied; its file's text and SHA-256 as they were), overrides, seed, backend,
    device, latency, the sensed rows' names, the limiter's bounds (for the trace checker) and the
    versions (:mod:`rtctl.provenance`)."""
    import hashlib

    from ..provenance import provenance

    try:
        text = Path(scene.source).read_text()
    except (OSError, ValueError):  # a scene made from a string has no file
        text = None
    io = scene.io
    return {"scene": scene.to_dict(), "scene_name": scene.scene.name, "source": scene.source,
            "scene_text": text, "scene_sha256": hashlib.sha256(text.encode()).hexdigest() if text is not None else None,
            "overrides": list(scene.overrides), "seed": io.seed, "backend": io.backend,
            "device": io.port if io.backend == "serial" else io.device,
            "sensed_rows": rig.sensed_names,
            "latency_blocks": io.latency_blocks or int(rig.device.latency_blocks),
            "limits": rig.limiter.bounds(), "rtctl": provenance()}


def _percentiles(x: np.ndarray) -> dict:
    return {"p50": float(np.percentile(x, 50)), "p99": float(np.percentile(x, 99)),
            "p999": float(np.percentile(x, 99.9)), "max": float(x.max())}


def _stderr(text: str) -> None:
    print(f"rtctl: {text}", file=sys.stderr)


#: The files a run writes into its ``out_dir`` besides ``trace/`` (which TraceWriter replaces).
RUN_FILES = ("summary.json", "plot.png")


def _remove_earlier_run(out: Path) -> None:
    """Remove an earlier run's summary and plot from ``out``: otherwise a run without a plot
    (``--no-plot``, or one that ends before it) leaves the old plot.png, perhaps of another
    scene, beside its own summary. Only the names a run writes go; other files stay."""
    for name in RUN_FILES:
        (out / name).unlink(missing_ok=True)


def _run_callback(rig, writer, n_blocks, times, faults, bar):
    """The device's thread runs the block step; this thread writes the trace from its snapshot
    ring and schedules parameter changes (they land one or two blocks after their block, as the
    device runs ahead). Returns ``(blocks run, status seen, interrupted, whether a trace write
    failure ended the run)``."""
    from ..trace import TraceWriteError

    dev = rig.device
    period = rig.block / rig.fs
    st = {"run": n_blocks, "seen": 0, "stopping": False, "trace": writer is not None, "trace_stopped": False}
    rig.apply_schedule(0)

    def on_block(k, slot):
        snaps = dev.snaps
        status = int(snaps.status[slot])
        if st["trace"]:
            try:
                rig.record(writer.next(), status, float(snaps.compute_us[slot]), snaps, slot)
            except TraceWriteError:  # the writer keeps its error for the summary; nothing more is written
                st["trace"] = False
                if not st["stopping"]:  # the run ends here, as on a fault
                    st["run"], st["stopping"], st["trace_stopped"] = k + 1, True, True
                    return True
        if st["stopping"]:
            return True
        times[k] = snaps.compute_us[slot]
        st["seen"] |= status
        if status & safety.FAULTS:
            faults.append(fault_message(rig, k + 1, status, period))
            st["run"], st["stopping"] = k + 1, True
            return True
        if k + 1 >= n_blocks:
            st["stopping"] = True
            return True
        rig.apply_schedule(k + 1)
        bar.update(k + 1)
        return False

    interrupted = False
    try:
        status = dev.run(rig, n_blocks, on_block)
    except KeyboardInterrupt:
        interrupted = True
        status = 0
    finally:
        bar.close()
    if status & safety.FAULTS and not faults:
        done = min(dev.snaps.done, n_blocks)
        faults.append(fault_message(rig, done, status, period))
        st["run"] = done
    if interrupted:
        st["run"] = min(dev.snaps.done, n_blocks)
    st["seen"] |= status
    return st["run"], st["seen"], interrupted, st["trace_stopped"]
