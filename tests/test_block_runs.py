"""Runs of blocks in one compiled call (rtctl/engine/chunk.py) against the loop that calls every
block from Python (``RTCTL_BLOCK_RUNS=0``, the path of backends whose I/O is Python's): the same
trace bitwise (timing fields aside), the same summary, for every bundled scene, a rendered
stimulus (schedule work in every block), finger events, a fault that ends the run inside a run of
blocks, and a paced run; and the runs are long (few calls from Python)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from matplotlib import cbook

from rtctl import safety, scene
from rtctl.engine import chunk
from rtctl.engine.rig import build
from rtctl.engine.run import run
from rtctl.trace import TraceReader

TIMING = ("compute_us", "wake_late_us")
PHOTO = cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)
#: Summary keys that are timings or say how the run was made, not what it did.
PACING = {"deadline_misses", "late_wakeups", "overruns", "miss_bursts", "status", "warnings"}
VARYING = {"realtime_factor", "cpu_realtime_factor", "build_s", "block_time_us", "wake_late_us", "realtime"}

CASES = {name: (name, ["timing.duration=0.2"]) for name in scene.bundled() if name != "line-bimorph-5-closed"}
CASES.update({
    "events": ("line-bimorph-5-closed", ["timing.duration=0.3", "events.0.at=0.08", "events.1.at=0.15",
                                         "events.2.at=0.22"]),
    "image-beat": ("line-bimorph-5", ["timing.duration=0.2", "stimulus.kind=image", "stimulus.method=beat",
                                      f"stimulus.image={PHOTO}", "stimulus.voltage=100.0"]),
    # the limiter's over-temperature bit, raised inside the block function at 0.109 s
    "fault": ("line-bimorph-5", ["timing.duration=0.3", "actuator.0.limits.temperature=25.0005",
                                 "actuator.0.limits.thermal_tau=1"]),
    # an injected fault: the device's I/O is Python's, so blocks are called one by one
    "injected": ("line-bimorph-5", ["timing.duration=0.3",
                                    'io.faults.inject=[{kind="device_stopped", at=0.137}]']),
})


def _run(sc, rig, out, monkeypatch, python_blocks: bool, calls=None, **kw):
    monkeypatch.setenv("RTCTL_BLOCK_RUNS", "0" if python_blocks else "1")
    if calls is not None:
        real = chunk.BlockRuns.__call__

        def counted(self, *a):
            calls.append(a[:2])
            return real(self, *a)

        monkeypatch.setattr(chunk.BlockRuns, "__call__", counted)
    res = run(sc, out, plot=False, rig=rig, **kw)
    monkeypatch.undo()
    return res


def _same(a_dir, b_dir, paced=False):
    a, b = TraceReader(a_dir / "trace"), TraceReader(b_dir / "trace")
    ra, rb = a.records, b.records
    assert len(ra) == len(rb) > 0
    for f in ra.dtype.names:
        if f == "status" and paced:  # which blocks missed their deadline is the machine's
            keep = ~np.uint32(safety.DEADLINE_MISSED)
            assert np.array_equal(ra[f] & keep, rb[f] & keep), "status differs"
        elif f not in TIMING:
            assert ra[f].tobytes() == rb[f].tobytes(), f"trace field {f} differs"
    sa, sb = (json.loads((d / "summary.json").read_text()) for d in (a_dir, b_dir))
    for k in sa:
        if k not in VARYING and not (paced and k in PACING):
            assert sa[k] == sb[k], f"summary {k}: {sa[k]!r} != {sb[k]!r}"
    return ra


@pytest.mark.parametrize("case", list(CASES))
def test_runs_of_blocks_give_the_per_block_loop_bitwise(case, tmp_path, monkeypatch):
    name, over = CASES[case]
    sc = scene.load(name, over)
    rig = build(sc)
    calls = []
    _run(sc, rig, tmp_path / "python", monkeypatch, True)
    _run(sc, rig, tmp_path / "runs", monkeypatch, False, calls)
    _same(tmp_path / "python", tmp_path / "runs")
    if case == "injected":
        assert not calls, "a device with Python I/O ran in compiled runs"
        return
    assert calls, "the compiled runs were not used"
    n_run = int(np.ceil(sc.timing.duration * sc.timing.fs / sc.timing.block))
    if case == "image-beat":  # schedule work in every block: a call per block
        assert len(calls) >= n_run
    elif case in ("line-bimorph-5", "events"):  # a few schedule changes: a few calls
        assert len(calls) < n_run / 20, len(calls)


def test_a_fault_inside_a_run_ends_it_at_its_block(tmp_path, monkeypatch):
    """The run of blocks stops at the faulting block, as the per-block loop does: same blocks,
    same one-line message."""
    sc = scene.load(*CASES["fault"])
    rig = build(sc)
    a = _run(sc, rig, tmp_path / "python", monkeypatch, True)
    b = _run(sc, rig, tmp_path / "runs", monkeypatch, False)
    fa, fb = a.summary["faults"], b.summary["faults"]
    assert fa and fa == fb
    assert "over temperature" in fa[0] and "at 0.10" in fa[0], fa
    assert a.summary["stop"]["by"] == b.summary["stop"]["by"] == "fault"
    _same(tmp_path / "python", tmp_path / "runs")


def test_paced_runs_of_blocks_keep_the_data_and_the_clock(tmp_path, monkeypatch):
    """Paced: the waits happen inside the compiled run; data bitwise as the per-block loop's,
    every block woken on its own deadline (lateness recorded per block, none negative)."""
    sc = scene.load("line-bimorph-5", ["timing.duration=0.15"])
    rig = build(sc)
    _run(sc, rig, tmp_path / "python", monkeypatch, True, realtime=True)
    calls = []
    _run(sc, rig, tmp_path / "runs", monkeypatch, False, calls, realtime=True)
    rec = _same(tmp_path / "python", tmp_path / "runs", paced=True)
    late = rec["wake_late_us"]
    assert np.all(np.isfinite(late)) and late.min() >= 0.0
    # the 50 ms slice: a 0.15 s paced run returns to Python a few times, not once per block
    assert 3 <= len(calls) < len(rec) / 10, len(calls)
