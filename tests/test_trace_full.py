"""A full disk (or any failing write) under a trace: the writer keeps its whole chunks and closes
the trace saying why it ends early; a run stops as on a fault with one line naming the cause, the
file and what the trace holds, and still writes its summary; a run whose trace would not fit is
refused before it starts.

The disk fills at the writer's one seam to the files (``rtctl.trace._write_all``): past a budget
of bytes in ``blocks.bin`` and ``chunks.bin`` a write puts what fits and then fails with ENOSPC,
as a filesystem does.
"""

import errno
import json
import os
import shutil
import time
from collections import namedtuple

import numpy as np
import pytest

from rtctl import cli
from rtctl import scene as scenes
from rtctl import trace as tracemod
from rtctl.engine import run as runmod
from rtctl.engine.run import run
from rtctl.errors import OutputError
from rtctl.trace import TraceReader, TraceWriter


def _fill_after(monkeypatch, budget: int, err: int = errno.ENOSPC) -> dict:
    """Make the trace's record and index files fail after ``budget`` bytes between them; returns
    where the monotonic time of the failure goes (``"at"``)."""
    real = tracemod._write_all
    left = [budget]
    seen = {}

    def write_all(fd, data):
        name = os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))
        if name not in ("blocks.bin", "chunks.bin"):
            return real(fd, data)
        view = memoryview(data).cast("B")
        if len(view) > left[0]:
            real(fd, view[:left[0]])  # what fits, as a short write does
            left[0] = 0
            seen.setdefault("at", time.monotonic())
            raise OSError(err, os.strerror(err))
        left[0] -= len(view)
        real(fd, view)

    monkeypatch.setattr(tracemod, "_write_all", write_all)
    return seen


def test_a_failed_write_leaves_a_closed_trace_of_its_whole_chunks(tmp_path, monkeypatch):
    w = TraceWriter(tmp_path, {"drive": ("V", 2)}, fs=1000.0, block=4, channels=["a", "b"], chunk=8)
    _fill_after(monkeypatch, 2 * 8 * w.dtype.itemsize + 2 * 16 + 40)  # two whole chunks, then part of one
    with pytest.raises(OSError, match="No space left|no space left"):
        for k in range(100):
            r = w.next()
            r["drive"][:] = k
            r["status"] = 0
    with pytest.raises(OSError, match="no space left on device writing .*blocks.bin"):
        w.close()
    r = TraceReader(tmp_path)
    assert r.closed and r.n_blocks == 16 and r.torn_bytes == 0
    np.testing.assert_array_equal(r.signal("drive")[0], np.repeat(np.arange(16.0), 4))
    assert r.layout["write_error"] == "no space left on device writing blocks.bin"
    assert "closed by its writer early (no space left on device writing blocks.bin)" in r.recovery()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blocks.bin", "chunks.bin", "trace.json"]


def test_an_io_error_at_close_is_said_too(tmp_path, monkeypatch):
    w = TraceWriter(tmp_path, {"drive": ("V", 1)}, fs=1000.0, block=4, channels=["a"])
    for _ in range(3):
        w.next()["status"] = 0
    _fill_after(monkeypatch, 0, errno.EIO)
    with pytest.raises(OSError, match="input/output error writing .*blocks.bin: the trace holds the first 0.000 s"):
        w.close()
    assert TraceReader(tmp_path).closed


@pytest.mark.parametrize("realtime,block_runs", [(False, "1"), (True, "1"), (False, "0")])
def test_a_disk_full_during_a_run_ends_it_as_a_fault(tmp_path, monkeypatch, realtime, block_runs):
    monkeypatch.setenv("RTCTL_BLOCK_RUNS", block_runs)
    failed = _fill_after(monkeypatch, 1_500_000)  # about 0.2 s of line-bimorph-5's 1500 blocks per second
    real_close = TraceWriter.close
    closed = {}

    def close(self, *a, **kw):  # after the loop's fade and the drain's last pass
        closed.setdefault("at", time.monotonic())
        return real_close(self, *a, **kw)

    monkeypatch.setattr(TraceWriter, "close", close)
    res = run(scenes.load("line-bimorph-5", ["timing.duration=3"]), out_dir=tmp_path, realtime=realtime, plot=False)
    s = res.summary
    held = TraceReader(tmp_path / "trace")
    assert held.closed and held.layout["write_error"] == "no space left on device writing blocks.bin"
    assert 0.1 < held.n_blocks * held.block / held.fs < 0.4
    line = f"no space left on device writing {tmp_path / 'trace' / 'blocks.bin'}: the trace holds the first "
    assert len(s["faults"]) == 1 and line in s["faults"][0] and " of 3 s " in s["faults"][0]
    assert s["faults"][0].endswith("outputs faded to 0 V")
    assert s["stop"]["by"] == "fault" and s["stop"]["fade"] == "linear"
    # promptly: the loop sees the failure within a slice of blocks (50 ms of wall time) and fades
    # in one block, not after its 3 s; a run paced to the wall clock then ran on that much too
    assert closed["at"] - failed["at"] < 0.5 and s["duration_s"] < 3
    if realtime:
        assert s["duration_s"] < held.n_blocks * held.block / held.fs + 0.2
    assert s["trace"]["blocks"] == held.n_blocks and s["trace"]["closed"]
    assert json.loads((tmp_path / "summary.json").read_text())["faults"] == s["faults"]
    assert not (tmp_path / "trace" / "trace.json.tmp").exists()


def test_the_command_line_says_it_in_one_line(tmp_path, monkeypatch, capsys):
    _fill_after(monkeypatch, 1_500_000)
    out = tmp_path / "r"
    rc = cli.main(["run", "line-bimorph-5", "--duration", "1", "--out", str(out), "--no-plot", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1, err
    assert len(err) == 1 and err[0].startswith("rtctl: fault: at ")
    assert f"no space left on device writing {out / 'trace' / 'blocks.bin'}: the trace holds the first " in err[0]
    assert " of 1 s " in err[0]


def test_a_summary_that_cannot_be_written_is_said_with_the_trace(tmp_path, monkeypatch):
    _fill_after(monkeypatch, 1_500_000)
    real = type(tmp_path).write_text

    def write_text(self, *a, **kw):
        if self.name == "summary.json":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(self, *a, **kw)

    monkeypatch.setattr(type(tmp_path), "write_text", write_text)
    with pytest.raises(OutputError, match=r"no space left on device writing .*summary.json: the run's summary is "
                                          r"not written; no space left on device writing .*blocks.bin: the trace"):
        run(scenes.load("line-bimorph-5", ["timing.duration=1"]), out_dir=tmp_path, plot=False)
    assert not (tmp_path / "summary.json").exists()


def test_a_trace_that_would_not_fit_is_refused_before_the_run(tmp_path, monkeypatch, capsys):
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(3_000_000, 0, 3_000_000))
    (tmp_path / "summary.json").write_text("{}")  # an earlier run's: a refused run leaves it
    rc = cli.main(["run", "line-bimorph-5", "--duration", "10", "--out", str(tmp_path), "--quiet", "--no-plot"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith(f"rtctl: error: --out {tmp_path}: this run's trace needs about ")
    assert " MB (10 s: " in err[0] and "but its filesystem has 3 MB free" in err[0]
    assert (tmp_path / "summary.json").read_text() == "{}" and not (tmp_path / "trace").exists()
    # one that fits runs
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 0, 10**9))
    assert run(scenes.load("line-bimorph-5", ["timing.duration=0.05"]), out_dir=tmp_path, plot=False).summary


class _Snaps:
    def __init__(self):
        self.status = np.zeros(4, dtype=np.int64)
        self.compute_us = np.zeros(4)
        self.done = 0


class _Device:
    """A device that runs its blocks itself (the audio backend's way): ``on_block`` per block
    until it asks to stop, then the fade's two blocks."""

    def __init__(self):
        self.snaps, self.delivered = _Snaps(), []

    def run(self, rig, n_blocks, on_block):
        for k in range(n_blocks):
            self.delivered.append(k)
            self.snaps.done = k + 1
            if on_block(k, k % 4):
                break
        for k in range(len(self.delivered), len(self.delivered) + 2):
            self.delivered.append(k)
            on_block(k, k % 4)
        return 0


class _Rig:
    block, fs = 4, 1000.0

    def __init__(self):
        self.device = _Device()

    def apply_schedule(self, k):
        pass

    def record(self, rec, status, compute_us, snaps, slot):
        rec["status"] = status
        rec["drive"][:] = 1.0


class _Bar:
    def update(self, done):
        pass

    def close(self):
        pass


def test_a_device_that_runs_its_own_blocks_is_stopped_too(tmp_path, monkeypatch):
    rig = _Rig()
    w = TraceWriter(tmp_path, {"drive": ("V", 1)}, fs=rig.fs, block=rig.block, channels=["a"], chunk=8)
    _fill_after(monkeypatch, 3 * 8 * w.dtype.itemsize + 3 * 16 + 5)  # the fourth chunk fails
    faults = []
    blocks, _, interrupted, trace_stopped = runmod._run_callback(rig, w, 1000, np.zeros(1000), faults, _Bar())
    assert trace_stopped and not interrupted and blocks == 33 and faults == []  # the writer's line comes from run()
    assert len(rig.device.delivered) == 35  # asked to stop at once: the fade's blocks, no more
    w.close(check=False)
    assert TraceReader(tmp_path).n_blocks == 24 and "holds the first 0.096 s of 1 s (24 blocks)" in w.failure(1.0)


def test_check_trace_reads_a_trace_cut_by_a_full_disk_as_honest(tmp_path, monkeypatch, capsys):
    """The invariant checker on a run a full disk ended: the trace stops where the write failed
    (mid-run, outputs still on), and the summary's one fault is that failure, which no record
    carries. Both read as violations before ("end": the outputs end at 100 V; "summary": a fault
    no record carries); now `end` is not checked and says why, and everything else still is."""
    from rtctl import safety
    from rtctl.check import check_trace
    from rtctl.check import main as check_main

    _fill_after(monkeypatch, 1_500_000)
    summary = run(scenes.load("line-bimorph-5", ["timing.duration=1"]), out_dir=tmp_path, plot=False).summary
    monkeypatch.undo()  # (the files are written: reading them needs no seam)
    rep = check_trace(tmp_path)
    assert rep["ok"] and rep["cut"] == "no space left on device writing blocks.bin", rep
    assert rep["blocks"] > 100 and np.any(TraceReader(tmp_path / "trace").signal("drive")[:, -1] != 0.0)
    assert check_main([str(tmp_path)]) == 0
    assert "end          not checked: the trace ends early (no space left on device" in capsys.readouterr().out
    # the summary is still checked against the records: a warning no record carries
    text = next(t for b, t in safety.STATUS_NAMES.items() if not b & (safety.FAULTS | safety.DEADLINE_MISSED
                                                                     | safety.TRACE_DROPPED))
    rep = check_trace(tmp_path, dict(summary, warnings=[text]))
    assert not rep["ok"] and rep["violations"]["summary"] == 1, rep
    # and a trace without a write failure must still end at 0 V and hold its run's blocks
    rep = check_trace(tmp_path, dict(summary, trace=None))
    assert not rep["ok"] and rep["violations"]["summary"] >= 1


def test_check_trace_of_no_trace_says_it_once(tmp_path):
    """An unreadable trace is named once (the reader's line was wrapped in a second copy of it)."""
    from rtctl.check import TraceUnreadable, check_trace

    with pytest.raises(TraceUnreadable) as e:
        check_trace(tmp_path / "nonexist")
    assert str(e.value).count("not a readable rtctl trace") == 1, str(e.value)


def test_the_command_line_names_no_plot_that_a_full_disk_kept_from_being_written(tmp_path, monkeypatch, capsys):
    from rtctl.engine import report

    def full(summary, reader, path, *a, **kw):
        path.write_bytes(b"\x89PNG")  # the part written before the disk filled
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(report, "plot", full)
    out = tmp_path / "r"
    rc = cli.main(["run", "line-bimorph-5", "--duration", "0.05", "--out", str(out), "--quiet"])
    stdout = capsys.readouterr().out.splitlines()
    assert rc == 0
    assert f"trace, summary.json in {out}" in stdout, stdout
    assert not (out / "plot.png").exists()
    assert "plot.png not written: no space left on device" in json.loads((out / "summary.json").read_text())["warnings"]
