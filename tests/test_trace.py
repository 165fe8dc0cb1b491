"""Traces survive interruption: checksummed chunks are readable, a torn tail is ignored and said,
an unknown format is refused in one line; exports read back with numpy, csv and scipy."""

import csv
import json
import math
import os
import time
import zlib

import numpy as np
import pytest

from rtctl.trace import CHUNK, TraceError, TraceReader, TraceWriter


def write(path, n_blocks, chunk=4, close=True, flush_s=math.inf):
    w = TraceWriter(path, {"drive": ("V", 2), "target_um": ("um", 2, 0)}, fs=100.0, block=3,
                    channels=["a", "b"], chunk=chunk, flush_s=flush_s)
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
    os.close(w._data), os.close(w._index)  # a killed process's descriptors: closed by the kernel


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


def test_a_torn_tail_is_ignored_and_said(tmp_path):
    w = write(tmp_path, 9, chunk=4, close=False)  # two chunks on disk, one record buffered
    rec = np.zeros(3, dtype=w.dtype)
    with open(tmp_path / "blocks.bin", "ab") as f:  # records whose chunk entry never made it
        f.write(rec.tobytes())
    with open(tmp_path / "chunks.bin", "ab") as f:  # and half an entry
        f.write(b"\x01" * 9)
    r = TraceReader(tmp_path)
    assert r.n_blocks == 8 and not r.closed and r.bad_chunk is None
    assert r.torn_bytes == 3 * w.dtype.itemsize
    assert "8 blocks" in r.recovery() and f"torn tail of {3 * w.dtype.itemsize} bytes" in r.recovery()
    os.close(w._data), os.close(w._index)


def test_a_closed_trace_cut_short_afterwards_says_so_and_what_was_lost(tmp_path):
    w = write(tmp_path, 12, chunk=4)  # closed whole: three chunks of four
    size = w.dtype.itemsize
    os.truncate(tmp_path / "blocks.bin", 6 * size + 5)  # a copy that stopped inside the second chunk
    r = TraceReader(tmp_path)
    assert r.closed and r.n_blocks == 4 and r.torn_bytes == 2 * size + 5
    line = r.recovery()
    assert "process ended before closing" not in line, line  # it did close: the file lost its end later
    assert "recovered of the 12 its writer closed it with" in line and "8 blocks lost" in line, line


def test_a_chunk_failing_its_checksum_ends_what_is_read(tmp_path):
    w = write(tmp_path, 12, chunk=4)
    size = w.dtype.itemsize
    with open(tmp_path / "blocks.bin", "r+b") as f:  # one flipped bit in the second chunk
        f.seek(5 * size + 20)
        b = f.read(1)
        f.seek(5 * size + 20)
        f.write(bytes([b[0] ^ 0x10]))
    r = TraceReader(tmp_path)
    assert r.n_blocks == 4 and r.bad_chunk == 4 and r.torn_bytes == 8 * size
    assert "fails its checksum" in r.recovery()
    assert TraceReader(tmp_path, verify=False).n_blocks == 12  # the counts alone cannot see it
    assert zlib.crc32(b"123456789") == 0xCBF43926  # the check value of CRC-32 (ISO-HDLC)


def test_records_wait_at_most_flush_s_before_they_reach_the_file(tmp_path):
    w = TraceWriter(tmp_path, {"drive": ("V", 1)}, fs=100.0, block=2, channels=["a"], chunk=1000, flush_s=0.02)
    w.next()
    w.next()
    assert TraceReader(tmp_path).n_blocks == 0  # in the buffer: neither full nor old
    time.sleep(0.03)
    w.next()  # the buffer's oldest record waited longer than flush_s: appended first
    assert TraceReader(tmp_path).n_blocks == 2
    w.close()
    r = TraceReader(tmp_path)
    assert r.n_blocks == 3 and r.closed and r.torn_bytes == 0
    np.testing.assert_array_equal(np.fromfile(tmp_path / "chunks.bin", dtype=CHUNK)["n"], [2, 1])


def test_dropped_placeholders_are_chunked_and_counted(tmp_path):
    w = TraceWriter(tmp_path, {"drive": ("V", 1)}, fs=100.0, block=2, channels=["a"])
    w.next()
    w.gap(300)
    w.next()
    w.close()
    r = TraceReader(tmp_path)
    assert r.n_blocks == 302 and r.dropped == 300
    np.testing.assert_array_equal(r.records["block"], np.arange(302))
    assert np.isnan(r.signal("drive")[0, 2:602]).all()


def test_unknown_format_is_refused_in_one_line(tmp_path, capsys):
    from rtctl.cli import main

    write(tmp_path, 2)
    layout = json.loads((tmp_path / "trace.json").read_text())
    layout["format"] = "rtctl-trace-9"
    (tmp_path / "trace.json").write_text(json.dumps(layout))
    with pytest.raises(TraceError, match="trace format 'rtctl-trace-9' is unknown"):
        TraceReader(tmp_path)
    assert main(["trace", "info", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "rtctl-trace-9" in err and "Traceback" not in err


def test_a_format_1_trace_is_read_without_checksums(tmp_path):
    write(tmp_path, 5)
    layout = json.loads((tmp_path / "trace.json").read_text())
    layout["format"] = "rtctl-trace-1"
    del layout["closed"]
    (tmp_path / "trace.json").write_text(json.dumps(layout))
    (tmp_path / "chunks.bin").unlink()
    r = TraceReader(tmp_path)
    assert r.n_blocks == 5 and "no checksums" in r.recovery()


def test_exports_read_back_with_numpy_csv_and_scipy(tmp_path):
    from scipy.io import wavfile

    from rtctl.trace_export import export

    d = tmp_path / "trace"
    w = TraceWriter(d, {"drive": ("V", 2), "target_um": ("um", 2, 0)}, fs=1000.0, block=4, channels=["a", "b"],
                    meta={"scene": {"io": {"volts_per_fs": 100.0, "outputs": [3, 1]}}})
    rng = np.random.default_rng(1)
    for k in range(7):
        r = w.next()
        r["drive"][:] = rng.uniform(-150, 150, size=(2, 4))
        r["target_um"][:] = [k, 2 * k]
    w.close()
    tr = TraceReader(d)
    drive = tr.signal("drive")
    export(tr, "npz", tmp_path / "t.npz")
    z = np.load(tmp_path / "t.npz")
    np.testing.assert_array_equal(z["drive"], drive)
    assert list(z["channels"]) == ["a", "b"] and float(z["fs"]) == 1000.0
    export(tr, "csv", tmp_path / "t.csv")
    with open(tmp_path / "t.csv", newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0][:5] == ["t_s", "block", "status", "drive:a (V)", "drive:b (V)"]
    table = np.array(rows[1:], dtype=float)
    np.testing.assert_array_equal(table[:, 3:5].T.astype(np.float32), drive.astype(np.float32))  # %.9g: float32 exact
    np.testing.assert_array_equal(table[:, 6], np.repeat(2 * np.arange(7), 4))
    export(tr, "wav", tmp_path / "t.wav")
    rate, frames = wavfile.read(tmp_path / "t.wav")
    assert rate == 1000 and frames.dtype == np.float32 and frames.shape == (28, 4)
    np.testing.assert_array_equal(frames[:, 3], np.clip(drive[0] / 100.0, -1, 1).astype(np.float32))
    np.testing.assert_array_equal(frames[:, 1], np.clip(drive[1] / 100.0, -1, 1).astype(np.float32))
    assert not frames[:, [0, 2]].any()


@pytest.mark.parametrize("argv", [["trace", "info"], ["trace", "export"], ["replay"]])
def test_a_missing_trace_is_one_line(tmp_path, capsys, argv):
    from rtctl.cli import main

    assert main([*argv, str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no such trace" in err and "Traceback" not in err


def test_a_directory_without_a_trace_is_still_a_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a readable rtctl trace"):
        TraceReader(tmp_path)


def test_info_reads_a_run_directory_and_says_what_made_it(tmp_path, capsys):
    from rtctl.cli import main

    w = TraceWriter(tmp_path / "trace", {"drive": ("V", 1)}, fs=100.0, block=2, channels=["a"],
                    meta={"scene_name": "x", "seed": 7, "backend": "sim", "rtctl": {"version": "9"}})
    w.next()
    w.close()
    assert main(["trace", "info", str(tmp_path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["blocks"] == 1 and d["closed"] and d["made_by"]["seed"] == 7 and d["format"] == "rtctl-trace-2"
