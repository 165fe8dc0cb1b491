"""Traces survive interruption: complete records are readable, partial ones ignored."""

import numpy as np

from rtctl.trace import TraceReader, TraceWriter


def write(path, n_blocks, chunk=4, close=True):
    w = TraceWriter(path, {"drive": ("V", 2), "target_um": ("um", 2, 0)}, fs=100.0, block=3,
                    channels=["a", "b"], chunk=chunk)
    for k in range(n_blocks):
        r = w.next()
        r["drive"][:] = np.arange(6).reshape(2, 3) + 10 * k
        r["target_um"][:] = [k, -k]
        r["status"] = k % 2
    if close:
        w.close()
    return w


def test_round_trip(tmp_path):
    write(tmp_path, 10)
    r = TraceReader(tmp_path)
    assert r.n_blocks == 10
    d = r.signal("drive")
    assert d.shape == (2, 30)
    np.testing.assert_array_equal(d[0, :6], [0, 1, 2, 10, 11, 12])
    np.testing.assert_array_equal(r.signal("target_um")[1], -np.arange(10))
    np.testing.assert_array_equal(r.status, np.arange(10) % 2)
    assert r.units == {"drive": "V", "target_um": "um"} and r.channels == ["a", "b"]
    assert r.time()[-1] == 29 / 100.0


def test_flushed_chunks_are_readable_without_close_and_partial_records_ignored(tmp_path):
    w = write(tmp_path, 9, chunk=4, close=False)  # 8 blocks flushed, 1 buffered
    assert TraceReader(tmp_path).n_blocks == 8
    with open(tmp_path / "blocks.bin", "ab") as f:  # a torn write of a killed process
        f.write(b"\x00" * 7)
    r = TraceReader(tmp_path)
    assert r.n_blocks == 8
    np.testing.assert_array_equal(r.signal("drive")[0, -3:], [70, 71, 72])
    w._f.close()


def test_single_row_read_equals_the_full_read(tmp_path):
    write(tmp_path, 10)
    r = TraceReader(tmp_path)
    np.testing.assert_array_equal(r.signal("drive", 1), r.signal("drive")[1])


def test_plot_envelope_keeps_every_bucket_extreme():
    from rtctl.engine.report import _envelope

    rng = np.random.default_rng(0)
    x = rng.normal(size=1_000_003)
    t = np.arange(x.size) / 48000.0
    tt, xx = _envelope(t, x, points=2000)
    assert xx.size <= 2000 and tt.size == xx.size
    k = x.size // 1000
    m = (x.size // k) * k
    np.testing.assert_array_equal(xx[0::2], x[:m].reshape(-1, k).min(axis=1))
    np.testing.assert_array_equal(xx[1::2], x[:m].reshape(-1, k).max(axis=1))
