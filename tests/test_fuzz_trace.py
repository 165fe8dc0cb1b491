"""Fuzzing the trace reader (rtctl.trace.TraceReader): traces of random layout written by the
writer, then torn (cut at any byte), extended with junk, bytes flipped, files missing or swapped
for directories, and ``trace.json`` rewritten with hostile values, keys dropped and formats this
version does not write. The reader gives one clear error line naming the trace, or records that
are exactly the first records written (a torn trace loses only what was never complete), with
every signal readable. The hand-made traces are tests/corpus/trace."""

import json
import shutil

import numpy as np
from fuzzing import clean_or_clear, fuzz
from hypothesis import given
from hypothesis import strategies as st

from rtctl.errors import RtctlError
from rtctl.trace import TraceReader, TraceWriter

ERRORS = (RtctlError, OSError)


@st.composite
def traces(draw):
    """(writer arguments, records): a layout of 0-3 signals and the records to write."""
    n_sig = draw(st.integers(0, 3))
    signals = {}
    for i in range(n_sig):
        rows = draw(st.integers(0, 3))
        signals[f"s{i}"] = ("V", rows, 0) if draw(st.booleans()) else ("V", rows)
    block = draw(st.integers(1, 8))
    n = draw(st.integers(0, 12))
    return signals, block, n


def _write(path, signals, block, n, chunk=4):
    rng = np.random.default_rng(n)
    with TraceWriter(path, signals, fs=1000.0, block=block, channels=["a"], chunk=chunk) as w:
        for _ in range(n):
            r = w.next()
            r["status"] = 0
            for name in signals:
                r[name] = rng.standard_normal(r[name].shape)
        dtype = w.dtype
    return np.fromfile(path / "blocks.bin", dtype=dtype)


def _check_reader(path):
    r = clean_or_clear(TraceReader, path, errors=ERRORS, names=[str(path)])
    if isinstance(r, Exception):
        return r
    for name in r.dtype.names[3:]:
        a = r.signal(name)
        assert a.shape[1] == r.n_blocks * (1 if name in r.layout.get("per_block", []) else r.block)
        if a.shape[0]:
            assert np.array_equal(r.signal(name, 0), a[0], equal_nan=True)
    assert r.status.shape == (r.n_blocks,) and r.time().shape == (r.n_blocks * r.block,)
    return r


@fuzz(100)
@given(traces(), st.data())
def test_torn_and_extended_traces_keep_their_complete_records(tmp_path_factory, spec, data):
    path = tmp_path_factory.mktemp("trace") / "t"
    written = _write(path, *spec)
    raw = (path / "blocks.bin").read_bytes()
    op = data.draw(st.sampled_from(["tear", "extend", "flip", "clean"]))
    if op == "tear":
        raw = raw[: data.draw(st.integers(0, len(raw)))]
    elif op == "extend":
        raw += data.draw(st.binary(max_size=200))
    elif op == "flip" and raw:
        i = data.draw(st.integers(0, len(raw) - 1))
        raw = raw[:i] + bytes([raw[i] ^ 0xFF]) + raw[i + 1:]
    (path / "blocks.bin").write_bytes(raw)
    r = _check_reader(path)
    if op in ("tear", "extend", "clean") and not isinstance(r, Exception):
        k = r.n_blocks
        assert k <= len(written) or op == "extend"  # junk may look like more records, never fewer
        for name in written.dtype.names:  # what was written is read back exactly
            m = min(k, len(written))
            assert np.array_equal(np.asarray(r.records[name][:m]), written[name][:m], equal_nan=True)
        if op == "clean":
            assert k == len(written)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=10),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=10,
)
KEYS = ["format", "dtype", "units", "per_block", "fs", "block", "channels", "meta", "dropped_records"]


@fuzz(150)
@given(traces(), st.lists(st.tuples(st.sampled_from(KEYS + ["x"]), st.sampled_from(["set", "drop", "item"]),
                                    json_values), min_size=1, max_size=3))
def test_damaged_layouts_give_one_line(tmp_path_factory, spec, edits):
    path = tmp_path_factory.mktemp("trace") / "t"
    _write(path, *spec)
    layout = json.loads((path / "trace.json").read_text())
    for key, op, value in edits:
        if op == "drop":
            layout.pop(key, None)
        elif op == "item" and isinstance(layout.get(key), list) and layout[key]:
            layout[key][0] = value  # e.g. one dtype field replaced
        else:
            layout[key] = value
    (path / "trace.json").write_text(json.dumps(layout))
    _check_reader(path)


@fuzz(60)
@given(traces(), st.binary(max_size=200) | st.sampled_from([b"", b"{}", b"[]", b"null", b"NaN", b"\xff\xfe{"]))
def test_random_bytes_as_trace_json(tmp_path_factory, spec, raw):
    path = tmp_path_factory.mktemp("trace") / "t"
    _write(path, *spec)
    (path / "trace.json").write_bytes(raw)
    _check_reader(path)


@fuzz(20)
@given(traces(), st.sampled_from(["rtctl-trace-0", "rtctl-trace-999", "", None, 1, ["rtctl-trace-1"]]))
def test_a_format_this_version_does_not_write_is_refused(tmp_path_factory, spec, fmt):
    path = tmp_path_factory.mktemp("trace") / "t"
    _write(path, *spec)
    layout = json.loads((path / "trace.json").read_text())
    assert layout["format"] != fmt
    layout["format"] = fmt
    (path / "trace.json").write_text(json.dumps(layout))
    assert isinstance(_check_reader(path), RtctlError)


def test_missing_files_and_directories_in_their_place(tmp_path):
    _write(tmp_path / "t", {"drive": ("V", 2)}, 4, 3)
    for name in ("blocks.bin", "trace.json"):
        shutil.copytree(tmp_path / "t", tmp_path / name)
        (tmp_path / name / name).unlink()
        assert isinstance(_check_reader(tmp_path / name), OSError)
        (tmp_path / name / name).mkdir()
        assert isinstance(_check_reader(tmp_path / name), ERRORS)
