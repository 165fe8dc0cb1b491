"""Run traces: one fixed-size record per block, appended in chunks.

A trace is a directory with ``trace.json`` (the layout: record dtype, signal names, units,
channel names, fs, block, and ``dropped_records``) and ``blocks.bin`` (records back to back, one
per block). The writer keeps a preallocated chunk of records and appends it to the file when
full, on :meth:`TraceWriter.flush` and on close, so Ctrl-C or an exception keeps every finished
block readable; the reader maps the file and ignores a trailing partial record, so even a killed
process leaves a readable trace. A paced run hands whole records over from its loop thread
(:mod:`rtctl.engine.ring`) and they are appended as they are (:meth:`TraceWriter.append`); a
record the loop had to drop (its ring full) is written as a placeholder (:meth:`TraceWriter.gap`:
NaN data, status ``TRACE_DROPPED``), and ``dropped_records`` counts them.

>>> import tempfile
>>> d = tempfile.mkdtemp()
>>> w = TraceWriter(d, {"drive": ("V", 2)}, fs=1000.0, block=4, channels=["a", "b"])
>>> r = w.next(); r["drive"][:] = 1.5; r["status"] = 0
>>> w.close()
>>> TraceReader(d).signal("drive").shape
(2, 4)
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .errors import TraceError

HEADER_FIELDS = [("block", "<i8"), ("status", "<i4"), ("compute_us", "<f4")]
#: ``trace.json``'s ``format``: the layout and record format this module writes and reads.
FORMAT = "rtctl-trace-1"


class TraceWriter:
    """Append per-block records.

    Parameters
    ----------
    path : str or Path
        Directory to create (or reuse: an existing trace there is replaced).
    signals : dict
        ``name -> (unit, rows)`` for per-sample signals stored as float32 ``(rows, block)``, or
        ``name -> (unit, rows, 0)`` for one float32 value per row and block.
    fs, block : float, int
        Sample rate and block length.
    channels : list of str
        Channel names, for readers.
    chunk : int
        Records buffered before an append.
    """

    def __init__(self, path, signals: dict, fs: float, block: int, channels, chunk: int = 64,
                 meta: dict | None = None):
        self.path = Path(path)
        self.path.mkdir(parents=True, exist_ok=True)
        fields = list(HEADER_FIELDS)
        per_block = []
        for name, spec in signals.items():
            rows = spec[1]
            if len(spec) > 2 and spec[2] == 0:
                fields.append((name, "<f4", (rows,)))
                per_block.append(name)
            else:
                fields.append((name, "<f4", (rows, block)))
        self.dtype = np.dtype(fields)
        self._buf = np.zeros(chunk, dtype=self.dtype)
        self._n = 0
        self.blocks = 0
        self.dropped = 0
        self._gap = None
        self._layout = layout = {
            "format": FORMAT,
            "dtype": [list(f) if len(f) == 2 else [f[0], f[1], list(f[2])] for f in fields],
            "units": {name: spec[0] for name, spec in signals.items()},
            "per_block": per_block,
            "fs": fs,
            "block": block,
            "channels": list(channels),
            "meta": meta or {},
            "dropped_records": 0,
        }
        (self.path / "trace.json").write_text(json.dumps(layout, indent=1))
        self._f = open(self.path / "blocks.bin", "wb")

    def next(self) -> np.void:
        """The next record to fill (a view into the chunk buffer); flushes a full chunk first."""
        if self._n == len(self._buf):
            self.flush()
        rec = self._buf[self._n]
        rec["block"] = self.blocks
        self._n += 1
        self.blocks += 1
        return rec

    def append(self, records: np.ndarray) -> None:
        """Append whole records (of :attr:`dtype`, their ``block`` fields already set) after
        the buffered ones."""
        self.flush()
        self._f.write(memoryview(records).cast("B"))
        self.blocks += len(records)

    def gap(self, n: int) -> None:
        """Append ``n`` placeholder records for blocks that have no record (dropped): NaN data,
        status ``TRACE_DROPPED``; counted in ``trace.json`` as ``dropped_records``."""
        if n <= 0:
            return
        if self._gap is None:
            from .safety import TRACE_DROPPED

            self._gap = np.zeros(1, dtype=self.dtype)
            for name in self.dtype.names[2:]:
                self._gap[name] = np.nan
            self._gap["status"] = TRACE_DROPPED
        self.flush()
        for _ in range(n):
            self._gap["block"] = self.blocks
            self._f.write(memoryview(self._gap).cast("B"))
            self.blocks += 1
        self.dropped += n

    def flush(self) -> None:
        """Append the buffered records to the file."""
        if self._n:
            self._f.write(memoryview(self._buf[: self._n]).cast("B"))
            self._f.flush()
            self._n = 0

    def close(self) -> None:
        if not self._f.closed:
            self.flush()
            os.fsync(self._f.fileno())
            self._f.close()
            if self.dropped:
                self._layout["dropped_records"] = self.dropped
                (self.path / "trace.json").write_text(json.dumps(self._layout, indent=1))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class TraceReader:
    """Read a trace written by :class:`TraceWriter` (complete records only)."""

    def __init__(self, path):
        self.path = Path(path)
        try:
            self.layout = json.loads((self.path / "trace.json").read_text())
        except (OSError, ValueError) as e:
            raise FileNotFoundError(f"{self.path}: not a readable rtctl trace ({e})") from None
        self.dtype = _check_layout(self.layout, self.path)
        try:
            size = (self.path / "blocks.bin").stat().st_size
        except OSError as e:
            raise FileNotFoundError(f"{self.path}: not a readable rtctl trace (blocks.bin: {e.strerror})") from None
        self.n_blocks = size // self.dtype.itemsize
        if self.n_blocks:
            self.records = np.memmap(self.path / "blocks.bin", dtype=self.dtype, mode="r", shape=(self.n_blocks,))
        else:
            self.records = np.zeros(0, dtype=self.dtype)
        self.fs = float(self.layout["fs"])
        self.block = int(self.layout["block"])
        self.channels = self.layout["channels"]
        self.units = self.layout["units"]
        #: placeholder records (status ``TRACE_DROPPED``) in place of records the loop dropped
        self.dropped = int(self.layout.get("dropped_records", 0))

    def signal(self, name: str, row: int | None = None) -> np.ndarray:
        """A per-sample signal as float64 ``(rows, n_blocks * block)``, or a per-block one as
        ``(rows, n_blocks)``; with ``row``, only that row, 1-D (reads just that row from disk,
        so long many-channel traces need not fit in memory twice)."""
        rec = self.records[name]
        if row is not None:
            return np.asarray(rec[:, row], dtype=float).reshape(-1)
        a = np.asarray(rec, dtype=float)
        if name in self.layout.get("per_block", ()):
            return a.T.copy()
        # explicit sizes: a signal of no rows (pin displays sense nothing) has nothing to infer -1 from
        return a.transpose(1, 0, 2).reshape(a.shape[1], a.shape[0] * a.shape[2])

    @property
    def status(self) -> np.ndarray:
        return np.asarray(self.records["status"])

    @property
    def compute_us(self) -> np.ndarray:
        return np.asarray(self.records["compute_us"], dtype=float)

    def time(self) -> np.ndarray:
        """Sample times, s."""
        return np.arange(self.n_blocks * self.block) / self.fs


def _check_layout(layout, path: Path) -> np.dtype:
    """The record dtype of a ``trace.json`` layout, after checking every field the reader uses;
    anything else (another format, a damaged or hand-edited file) is one :class:`TraceError`."""

    def bad(what: str) -> TraceError:
        return TraceError(f"{path}: not a readable rtctl trace: trace.json {what}")

    if not isinstance(layout, dict):
        raise bad(f"is a JSON {type(layout).__name__}, not an object")
    if layout.get("format") != FORMAT:
        raise bad(f"format {_short(layout.get('format'))}: this rtctl reads {FORMAT!r}")
    fs, block = layout.get("fs"), layout.get("block")
    if isinstance(fs, bool) or not isinstance(fs, (int, float)) or not (0 < fs < float("inf")):
        raise bad(f"fs = {_short(fs)}: not a positive sample rate")
    if isinstance(block, bool) or not isinstance(block, int) or block < 1:
        raise bad(f"block = {_short(block)}: not a positive integer")
    per_block = layout.setdefault("per_block", [])  # absent: no per-block signals
    for key, kind in (("channels", list), ("units", dict), ("per_block", list), ("dtype", list)):
        if not isinstance(layout.get(key), kind):
            raise bad(f"{key}: missing or not a JSON {'array' if kind is list else 'object'}")
    dropped = layout.get("dropped_records", 0)
    if isinstance(dropped, bool) or not isinstance(dropped, int) or dropped < 0:
        raise bad(f"dropped_records = {_short(dropped)}: not a count")
    try:
        fields = [tuple(f) if len(f) == 2 else (f[0], f[1], tuple(f[2])) for f in layout["dtype"]]
        dtype = np.dtype(fields)
    except (TypeError, ValueError, IndexError, KeyError) as e:
        raise bad(f"dtype is not a record type ({_short(str(e), 80)})") from None
    names = dtype.names or ()
    if [(n, dtype[n].str) for n in names[:3]] != [(n, np.dtype(t).str) for n, t in HEADER_FIELDS]:
        raise bad(f"dtype does not start with the record header {[n for n, _ in HEADER_FIELDS]}")
    for n in names[3:]:
        sub = dtype[n]
        want = 1 if n in per_block else 2
        if sub.base.kind != "f" or len(sub.shape) != want or (want == 2 and sub.shape[1] != block):
            raise bad(f"field {_short(n)}: {sub.str} {sub.shape} is not a float signal of "
                      f"{'(rows,)' if want == 1 else f'(rows, {block})'}")
    return dtype


def _short(v, n: int = 40) -> str:
    """``v`` for a one-line message: repr (escapes newlines), at most ``n`` characters."""
    s = " ".join(repr(v).split())
    return s if len(s) <= n else s[: n - 3] + "..."
