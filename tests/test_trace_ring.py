"""The trace ring: its compiled copy equals Rig.record (the trace's reference) bitwise for every
bundled scene; a full ring drops and counts, and the trace says which blocks are placeholders; a
run that is not real time waits for the writer instead and loses nothing."""

import threading

import numpy as np
import pytest

from rtctl import safety
from rtctl import scene as scenes
from rtctl.engine import loop as loopmod
from rtctl.engine import ring as ringmod
from rtctl.engine.rig import build
from rtctl.engine.ring import DROPPED, READ, WRITE, Drain, TraceRing
from rtctl.engine.run import run
from rtctl.trace import TraceReader, TraceWriter


def _dtype(rig, extra=None):
    import tempfile

    signals = rig.trace_signals()
    if extra:
        signals[extra] = ("us", 1, 0)
    with tempfile.TemporaryDirectory() as d:
        w = TraceWriter(d, signals, rig.fs, rig.block, rig.channel_names)
        w.close()
    return w.dtype


@pytest.mark.parametrize("name,over", [(n, []) for n in scenes.bundled()]
                         + [("line-bimorph-5", ["control.observe=true"])])
def test_the_compiled_copy_is_rig_record_bitwise(name, over):
    sc = scenes.load(name, over)
    rig = build(sc)
    dt = _dtype(rig, loopmod.LATE_FIELD)
    sources = loopmod.trace_sources(rig, dt)
    assert sources is not None, "a traced signal has no source in loop.trace_sources"
    ring = TraceRing(dt, sources, 8, loopmod.LATE_FIELD)
    ref = np.zeros(1, dtype=dt)
    for k in range(12):
        rig.apply_schedule(k)
        status = rig.advance()
        rig.record(ref[0], status, 12.5 + k)
        ref[0]["block"] = k
        ref[0][loopmod.LATE_FIELD] = 3.25 * k
        assert ring.push(k, status, 12.5 + k, 3.25 * k)
        got = ring.records[k % 8]
        assert got.tobytes() == ref[0].tobytes(), [f for f in dt.names
                                                   if not np.array_equal(got[f], ref[0][f], equal_nan=True)]
        ring.heads[READ] = ring.heads[WRITE]  # consumed


def _tiny(tmp_path, slots=4):
    w = TraceWriter(tmp_path, {"drive": ("V", 2)}, fs=1000.0, block=3, channels=["a", "b"])
    src = np.zeros((2, 3))
    return w, src, TraceRing(w.dtype, [("drive", src, 1.0)], slots)


class _Bar:
    def __init__(self):
        self.done = 0

    def update(self, done):
        self.done = done


def test_a_full_ring_drops_counts_and_leaves_placeholders(tmp_path):
    w, src, ring = _tiny(tmp_path)
    pushed = []
    for k in range(10):  # nobody drains: 4 fit, 6 are dropped
        src[:] = k
        pushed.append(ring.push(k, 0))
    assert pushed == [True] * 4 + [False] * 6 and ring.dropped == 6 and ring.heads[DROPPED] == 6
    bar = _Bar()
    d = Drain(ring, w, bar, poll_s=0.001)
    d.start()
    while ring.heads[READ] < 4:
        pass
    for k in (10, 11):  # room again
        src[:] = k
        assert ring.push(k, safety.LIMIT_VOLTAGE)
    d.stop(14)  # the loop ran 14 blocks: 12 and 13 were dropped at the end
    w.close()
    assert d.error is None and bar.done == 14
    r = TraceReader(tmp_path)
    assert r.n_blocks == 14 and r.dropped == 8
    np.testing.assert_array_equal(r.records["block"], np.arange(14))
    gap = np.isin(np.arange(14), [4, 5, 6, 7, 8, 9, 12, 13])
    np.testing.assert_array_equal(r.status == safety.TRACE_DROPPED, gap)
    drive = r.records["drive"]
    assert np.isnan(drive[gap]).all()
    np.testing.assert_array_equal(drive[~gap][:, 0, 0], [0, 1, 2, 3, 10, 11])


def test_the_drain_hands_back_each_piece_as_soon_as_it_is_written(tmp_path, monkeypatch):
    """A producer waiting for room goes on while the rest of a pass is written: with pieces of
    two records, the slots of each piece are free before the next piece is appended."""
    w, src, ring = _tiny(tmp_path, slots=8)
    monkeypatch.setattr(ringmod, "PIECE_BYTES", 2 * ring.records.dtype.itemsize)
    for k in range(7):
        src[:] = k
        assert ring.push(k, 0)
    seen = []

    class Noting:
        def __getattr__(self, name):
            return getattr(w, name)

        def append(self, recs):
            seen.append((int(ring.heads[READ]), len(recs)))
            w.append(recs)

    d = Drain(ring, Noting(), _Bar(), poll_s=0.001)
    d.start()
    d.stop(7)
    w.close()
    assert d.error is None
    assert seen == [(0, 2), (2, 2), (4, 2), (6, 1)]
    np.testing.assert_array_equal(TraceReader(tmp_path).records["drive"][:, 0, 0], np.arange(7))


def test_an_old_trace_without_the_count_reads_as_none_dropped(tmp_path):
    import json

    w, _, _ = _tiny(tmp_path)
    w.next()["drive"][:] = 1.0
    w.close()
    layout = json.loads((tmp_path / "trace.json").read_text())
    del layout["dropped_records"]
    (tmp_path / "trace.json").write_text(json.dumps(layout))
    assert TraceReader(tmp_path).dropped == 0


class _SlowWriter:
    """A TraceWriter whose appends take ``delay`` seconds (a slow disk), noting their threads."""

    def __init__(self, real, delay):
        self._real, self.delay, self.threads = real, delay, set()

    def __getattr__(self, name):
        return getattr(self._real, name)

    def append(self, recs):
        self.threads.add(threading.get_ident())
        threading.Event().wait(self.delay)
        self._real.append(recs)


def test_a_run_that_is_not_real_time_waits_for_a_slow_writer_and_loses_nothing(tmp_path, monkeypatch):
    made = {}
    real_init = loopmod.Loop.__init__

    def init(self, rig, writer, *a, **kw):
        made["w"] = _SlowWriter(writer, 0.01)
        real_init(self, rig, made["w"], *a, **kw)

    monkeypatch.setattr(loopmod.Loop, "__init__", init)
    monkeypatch.setattr(ringmod, "slots_for", lambda *a: 4)  # a ring far smaller than the run
    res = run(scenes.load("line-bimorph-5", ["timing.duration=0.1"]), out_dir=tmp_path, plot=False)
    r = TraceReader(tmp_path / "trace")
    assert res.summary["trace_dropped"] == 0 and r.dropped == 0
    assert r.n_blocks >= 150 and not np.any(r.status & safety.TRACE_DROPPED)
    np.testing.assert_array_equal(r.records["block"], np.arange(r.n_blocks))
    assert threading.get_ident() not in made["w"].threads


def test_a_signal_the_ring_does_not_know_is_recorded_from_python_the_same(tmp_path, monkeypatch):
    sc = scenes.load("line-bimorph-5", ["timing.duration=0.1", "control.observe=true"])
    run(sc, out_dir=tmp_path / "a", plot=False, report=False)
    monkeypatch.setattr(loopmod, "trace_sources", lambda rig, dtype: None)
    run(sc, out_dir=tmp_path / "b", plot=False, report=False)
    a, b = TraceReader(tmp_path / "a" / "trace"), TraceReader(tmp_path / "b" / "trace")
    assert a.n_blocks == b.n_blocks
    for f in a.dtype.names:
        if f != "compute_us":
            np.testing.assert_array_equal(a.records[f], b.records[f], err_msg=f)
