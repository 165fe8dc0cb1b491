"""The paced loop's thread runs blocks and nothing else: it makes no write system call during a
run (the trace goes out from the drain thread), and a slow disk (a writer that sleeps) costs it
no deadline: the loop keeps finishing blocks while the writer sleeps. The same for the serial
backend behind the pty emulator (the DAQ backend runs the same loop).

Robust on a noisy machine: the tests count what the loop thread did while the writer slept and
compare the misses with what an inline writer would have cost (every sleep of 100 ms is about
19 block periods), not wall-clock thresholds."""

import os
import select
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from rtctl import scene as scenes
from rtctl.engine import chunk
from rtctl.engine import loop as loopmod
from rtctl.engine.rig import Rig
from rtctl.engine.ring import WRITE
from rtctl.engine.run import run
from rtctl.trace import TraceReader

IO = Path("/proc/thread-self/io")


def _writes_so_far() -> int:
    """Write-type system calls this thread has made (Linux task I/O accounting)."""
    for line in IO.read_text().splitlines():
        if line.startswith("syscw:"):
            return int(line.split()[1])
    raise RuntimeError("no syscw in /proc/thread-self/io")


class _SlowWriter:
    """The run's TraceWriter, each append sleeping ``delay`` s first (a slow disk); per append
    the thread and the loop's published-record count before and after the sleep."""

    def __init__(self, real, delay):
        self._real, self.delay = real, delay
        self.ring = None
        self.calls = []  # (thread, published before, published after)

    def __getattr__(self, name):
        return getattr(self._real, name)

    def append(self, recs):
        before = int(self.ring.heads[WRITE])
        threading.Event().wait(self.delay)
        self.calls.append((threading.get_ident(), before, int(self.ring.heads[WRITE])))
        self._real.append(recs)


@pytest.fixture
def slow_writer(monkeypatch):
    made = {}
    real_init = loopmod.Loop.__init__

    def init(self, rig, writer, *a, **kw):
        made["w"] = _SlowWriter(writer, 0.1)
        real_init(self, rig, made["w"], *a, **kw)
        made["w"].ring = self.ring

    monkeypatch.setattr(loopmod.Loop, "__init__", init)
    return made


def _check_never_waited(w, summary, n_blocks):
    loop_thread = threading.get_ident()
    assert w.calls and all(t != loop_thread for t, _, _ in w.calls), "the trace was written from the loop thread"
    total = max(after for _, _, after in w.calls)
    during_run = [(b, a) for _, b, a in w.calls if a < total]
    assert len(during_run) >= 3
    # while the writer slept (100 ms, about 19 periods) the loop went on finishing blocks
    assert all(a > b for b, a in during_run), during_run
    # an inline writer would have missed about 19 deadlines per sleep
    assert summary["deadline_misses"] < len(during_run), summary
    assert summary["trace_dropped"] == 0 and summary["duration_s"] > 0


@pytest.mark.skipif(not IO.exists(), reason="no per-thread I/O accounting (/proc/thread-self/io)")
@pytest.mark.parametrize("blocks_from", ["compiled runs", "python"])
def test_the_paced_loop_thread_makes_no_write_during_a_run(tmp_path, monkeypatch, blocks_from):
    """Both ways the loop runs blocks: runs of blocks in one compiled call (the simulated rig),
    one call per block from Python (``RTCTL_BLOCK_RUNS=0``; backends whose I/O is Python's)."""
    seen = {"n": 0}
    n_blocks = 300  # block 32 at 48 kHz for 0.2 s
    if blocks_from == "python":
        monkeypatch.setenv("RTCTL_BLOCK_RUNS", "0")
        real = Rig.advance

        def advance(self):
            seen["n"] += 1
            if seen["n"] == 1:
                seen["first"] = _writes_so_far()
            st = real(self)
            if seen["n"] == n_blocks:
                seen["last"] = _writes_so_far()
            return st

        monkeypatch.setattr(Rig, "advance", advance)
    else:
        real_runs = chunk.BlockRuns.__call__

        def runs(self, k, *a):
            if k == 0:
                seen["first"] = _writes_so_far()
            got = real_runs(self, k, *a)
            seen["n"] = max(seen["n"], got[0])
            if got[0] >= n_blocks and "last" not in seen:
                seen["last"] = _writes_so_far()
            return got

        monkeypatch.setattr(chunk.BlockRuns, "__call__", runs)
    res = run(scenes.load("line-bimorph-5", ["timing.duration=0.2"]), out_dir=tmp_path, realtime=True, plot=False)
    r = TraceReader(tmp_path / "trace")
    assert r.n_blocks > n_blocks  # the run and its fade
    if blocks_from == "python":
        assert r.n_blocks == seen["n"]
    assert res.summary["trace_dropped"] == 0
    assert seen["last"] == seen["first"], "the loop thread made write system calls during the run"


def test_a_slow_disk_costs_the_paced_loop_no_deadline(tmp_path, slow_writer):
    # a generous period (block 256: 5.3 ms) keeps the machine's own hiccups out of the count
    sc = scenes.load("line-bimorph-5", ["timing.duration=1.5", "timing.block=256"])
    res = run(sc, out_dir=tmp_path, realtime=True, plot=False, report=False)
    _check_never_waited(slow_writer["w"], res.summary, 282)
    r = TraceReader(tmp_path / "trace")
    assert r.dropped == 0
    np.testing.assert_array_equal(r.records["block"], np.arange(r.n_blocks))


@pytest.fixture
def dot_port():
    p = subprocess.Popen([sys.executable, "-m", "rtctl.emulate.serial", "dot-4x4"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        if not select.select([p.stdout], [], [], 120)[0]:
            pytest.fail("the serial emulator printed no port within 120 s")
        port = p.stdout.readline().strip()
        if not port.startswith("/dev/"):
            pytest.fail(f"the serial emulator did not start: {port!r}")
        yield port
    finally:
        p.terminate()
        p.communicate(timeout=10)


@pytest.mark.hil
def test_a_slow_disk_costs_the_serial_loop_no_deadline(tmp_path, slow_writer, dot_port):
    sc = scenes.load("dot-4x4", ["io.backend=serial", f"io.port={dot_port}", "timing.duration=1.5",
                                 "timing.block=256"])
    res = run(sc, out_dir=tmp_path, plot=False, report=False)  # serial: paced by the device, always
    _check_never_waited(slow_writer["w"], res.summary, 282)
    assert not res.summary["faults"] and res.summary["io"]["frames_acked"] > 0
    assert os.path.getsize(tmp_path / "trace" / "blocks.bin") > 0
