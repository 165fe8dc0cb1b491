"""Run traces: one fixed-size record per block, appended in checksummed chunks.

A trace is a directory of three files:

* ``trace.json``: the layout (``format``, the record dtype, signal names, units, channel names,
  fs, block, ``meta``), rewritten only whole (a new file renamed over the old one), so a killed
  process never leaves half of it;
* ``blocks.bin``: the records back to back, one per block (a reader maps it);
* ``chunks.bin``: one 16-byte entry per append, written after the records it covers: the first
  record's index (uint64), the record count (uint32) and the CRC-32 of their bytes (uint32).

The writer appends a chunk when its buffer is full, when :data:`FLUSH_S` has passed since the
last append (so a killed process loses at most that much, whatever the block size), on
:meth:`TraceWriter.flush` and on close; each append goes to the operating system at once (no
user-space buffer), where it survives the process. The reader keeps the records of the chunks
whose checksums hold, in order, and ignores the rest: a torn tail (records or an entry the
process was killed while writing) or anything after a chunk that fails its checksum. It says
what it recovered (:meth:`TraceReader.recovery`).

A write that fails (a full disk, a quota, an I/O error) ends the trace there: the writer raises
:class:`TraceWriteError` and writes nothing more; :meth:`TraceWriter.close` then cuts the files
back to their last whole chunk and closes the trace with ``write_error`` saying why it ends
early. A full disk would leave no room for that last ``trace.json``, so the writer holds a
reserve (a file of zeros it deletes on close, :data:`RESERVE`) for it and for the run's other
small files.

A paced run hands whole records over from its loop thread (:mod:`rtctl.engine.ring`) and they are
appended as they are (:meth:`TraceWriter.append`); a record the loop had to drop (its ring full)
is written as a placeholder (:meth:`TraceWriter.gap`: NaN data, status ``TRACE_DROPPED``), and
``dropped_records`` counts them.

>>> import tempfile
>>> d = tempfile.mkdtemp()
>>> w = TraceWriter(d, {"drive": ("V", 2)}, fs=1000.0, block=4, channels=["a", "b"])
>>> r = w.next(); r["drive"][:] = 1.5; r["status"] = 0
>>> w.close()
>>> TraceReader(d).signal("drive").shape
(2, 4)
"""

from __future__ import annotations

import errno
import json
import os
import time
import zlib
from pathlib import Path

import numpy as np

from .errors import OutputError, TraceError

HEADER_FIELDS = [("block", "<i8"), ("status", "<i4"), ("compute_us", "<f4")]
#: The format this writer writes, and every format the reader reads (1: no checksums).
FORMAT = "rtctl-trace-2"
FORMATS = ("rtctl-trace-1", FORMAT)
#: A chunk index entry.
CHUNK = np.dtype([("first", "<u8"), ("n", "<u4"), ("crc", "<u4")])
#: Longest time records wait in the writer's buffer before an append, s.
FLUSH_S = 0.02
#: The reserve's file in a trace directory while a writer has it open.
RESERVE = "reserve.bin"
#: Bytes the reserve holds beyond room for ``trace.json`` (a caller adds its own files' needs).
RESERVE_BYTES = 64 << 10


class TraceWriteError(OutputError):
    """The trace's files cannot be written (disk full, quota, I/O error): names the cause, the
    file and how much of the trace was written."""


class TraceMissing(TraceError, FileNotFoundError):
    """No readable ``trace.json`` (a FileNotFoundError, as the reader raised before formats had versions)."""


def _write_all(fd: int, data) -> None:
    view = memoryview(data).cast("B")
    while view:
        view = view[os.write(fd, view):]


def _replace_json(path: Path, doc: dict) -> None:
    """Write ``doc`` to ``path`` whole: a temporary file renamed over it (removed if it cannot
    be written whole: a full disk must not leave a half or empty one behind)."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(json.dumps(doc, indent=1))
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)
        raise


def record_fields(signals: dict, block: int) -> tuple[list, list]:
    """The record fields of a trace of ``signals`` (as :class:`TraceWriter` takes them; numpy's
    list form) and the names of its per-block signals. ``np.dtype(fields).itemsize`` is the bytes
    the trace grows by per block."""
    fields = list(HEADER_FIELDS)
    per_block = []
    for name, spec in signals.items():
        rows = spec[1]
        if len(spec) > 2 and spec[2] == 0:
            fields.append((name, "<f4", (rows,)))
            per_block.append(name)
        else:
            fields.append((name, "<f4", (rows, block)))
    return fields, per_block


def why_failed(e: OSError) -> str:
    """An OSError's cause in words, lower case ("no space left on device")."""
    text = e.strerror or (errno.errorcode.get(e.errno) if e.errno else None) or str(e) or type(e).__name__
    return text[:1].lower() + text[1:]


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
        Most records buffered before an append.
    meta : dict, optional
        Stored as ``meta`` in ``trace.json`` (what made the trace: scene, versions, ...).
    flush_s : float
        Longest time a record waits in the buffer (checked when a record is added).
    reserve : int
        Bytes held in :data:`RESERVE` beyond room for the closing ``trace.json``, freed on close
        for the caller's own files (a run's summary and plot).

    Once a write fails, :attr:`error` holds the OSError and every later write raises
    :class:`TraceWriteError` again; nothing more is written before :meth:`close`.
    """

    def __init__(self, path, signals: dict, fs: float, block: int, channels, chunk: int = 64,
                 meta: dict | None = None, flush_s: float = FLUSH_S, reserve: int = RESERVE_BYTES):
        self.path = Path(path)
        self.path.mkdir(parents=True, exist_ok=True)
        fields, per_block = record_fields(signals, block)
        self.dtype = np.dtype(fields)
        self._buf = np.zeros(chunk, dtype=self.dtype)
        self._n = 0
        self.blocks = 0
        self.dropped = 0
        self.flush_s = float(flush_s)
        self._last = time.monotonic()
        self._gap = None
        #: the OSError that ended the trace early (None: every write went through)
        self.error = None
        self._error_file = None
        self._entries = 0  # entries in chunks.bin
        self._layout = {
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
        for name in ("blocks.bin", "chunks.bin", RESERVE):  # an earlier trace's files: gone before the new layout
            (self.path / name).unlink(missing_ok=True)
        try:
            _replace_json(self.path / "trace.json", self._layout)
            # room for the closing trace.json (a little longer than this one) and the caller's files
            self._reserve(len(json.dumps(self._layout, indent=1)) + 4096 + int(reserve))
        except OSError as e:
            (self.path / RESERVE).unlink(missing_ok=True)
            raise TraceWriteError(f"{why_failed(e)} writing {self.path}: the trace cannot be started") from None
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0)
        self._data = os.open(self.path / "blocks.bin", flags, 0o644)
        self._index = os.open(self.path / "chunks.bin", flags, 0o644)
        self._entry = np.zeros(1, dtype=CHUNK)
        self._written = 0  # records in blocks.bin

    def _reserve(self, n: int) -> None:
        """Hold ``n`` bytes of the filesystem in :data:`RESERVE`: written out, not a sparse file,
        so the space is taken now and is there to free when the disk is full."""
        fd = os.open(self.path / RESERVE, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0), 0o644)
        try:
            _write_all(fd, bytes(n))
            os.fsync(fd)
        finally:
            os.close(fd)

    @property
    def closed(self) -> bool:
        return self._data < 0

    @property
    def written(self) -> int:
        """Records in the file's whole chunks (what a reader gets)."""
        return self._written

    def failure(self, of_s: float | None = None) -> str:
        """One line on why the trace ended early or was not closed: the cause, the file, what it
        holds (of ``of_s`` seconds, when given); '' when every write went through."""
        secs = self._written * self._layout["block"] / self._layout["fs"]
        of = f" of {of_s:.4g} s" if of_s is not None else ""
        holds = f"the trace holds the first {secs:.3f} s{of} ({self._written} blocks)"
        line = f"{why_failed(self.error)} writing {self.path / self._error_file}: {holds}" if self.error else ""
        if self.closing_error is not None:
            unclosed = (f"{why_failed(self.closing_error)} writing {self.path / 'trace.json'}: the trace is not "
                        f"closed; readers recover its {self._written} blocks ({secs:.3f} s) as from a killed process")
            line = f"{line}; {unclosed}" if line else unclosed
        return line

    def _failed(self) -> TraceWriteError:
        return TraceWriteError(self.failure())

    def next(self) -> np.void:
        """The next record to fill (a view into the chunk buffer); appends the buffer first when
        it is full or its oldest record has waited ``flush_s``."""
        if self._n == len(self._buf) or (self._n and time.monotonic() - self._last >= self.flush_s):
            self.flush()
        rec = self._buf[self._n]
        rec["block"] = self.blocks
        self._n += 1
        self.blocks += 1
        return rec

    def append(self, records: np.ndarray) -> None:
        """Append whole records (of :attr:`dtype`, their ``block`` fields already set) after
        the buffered ones, as one chunk."""
        self.flush()
        self._chunk(records)
        self.blocks += len(records)

    def gap(self, n: int) -> None:
        """Append ``n`` placeholder records for blocks that have no record (dropped): NaN data,
        status ``TRACE_DROPPED``; counted in ``trace.json`` as ``dropped_records``."""
        if n <= 0:
            return
        if self._gap is None:
            from .safety import TRACE_DROPPED

            self._gap = np.zeros(256, dtype=self.dtype)
            for name in self.dtype.names[2:]:
                self._gap[name] = np.nan
            self._gap["status"] = TRACE_DROPPED
        self.flush()
        done = 0
        while done < n:
            m = min(n - done, len(self._gap))
            g = self._gap[:m]
            g["block"] = np.arange(self.blocks, self.blocks + m)
            self._chunk(g)
            self.blocks += m
            done += m
        self.dropped += n

    def flush(self) -> None:
        """Append the buffered records to the file (one chunk)."""
        if self._n:
            self._chunk(self._buf[: self._n])
            self._n = 0

    def started(self, monotonic_ns: int) -> None:
        """Note when the run's clock started (CLOCK_MONOTONIC, ns; paced runs): block ``k`` was
        due ``k`` periods after it. Recorded in ``trace.json`` as ``clock_start_ns``."""
        self._layout["clock_start_ns"] = int(monotonic_ns)
        if self.error is not None:  # recorded on close, if at all
            return
        try:
            _replace_json(self.path / "trace.json", self._layout)
        except OSError as e:
            self.error, self._error_file = e, "trace.json"
            raise self._failed() from None

    def _chunk(self, records: np.ndarray) -> None:
        if self.error is not None:  # nothing after a failed write: the file ends at its last whole chunk
            raise self._failed()
        records = np.ascontiguousarray(records)
        e = self._entry
        e["first"] = self._written
        e["n"] = len(records)
        e["crc"] = zlib.crc32(memoryview(records).cast("B"))
        name = "blocks.bin"
        try:
            _write_all(self._data, records)
            name = "chunks.bin"
            _write_all(self._index, e)  # after the records: an entry never covers bytes not yet written
        except OSError as err:
            self.error, self._error_file = err, name
            raise self._failed() from None
        self._written += len(records)
        self._entries += 1
        self._last = time.monotonic()

    def close(self, check: bool = True) -> None:
        """Append what is buffered, fsync, free the reserve and write the closing ``trace.json``.

        After a failed write (or one failing here) the files are cut back to their whole chunks
        and ``trace.json`` says why the trace ends early (``write_error``); then, with ``check``,
        :class:`TraceWriteError` is raised (:meth:`failure`'s line); without, the caller reads
        :attr:`error`. A ``trace.json`` that cannot be written even then is said in that line.
        """
        if self._data < 0:
            return
        try:
            if self.error is None:
                try:
                    self.flush()
                    self._error_file = "blocks.bin"
                    os.fsync(self._data)
                    self._error_file = "chunks.bin"
                    os.fsync(self._index)
                except TraceWriteError:
                    pass
                except OSError as e:
                    self.error = e
            if self.error is not None:
                self._cut()
        finally:
            os.close(self._data)
            os.close(self._index)
            self._data = self._index = -1
            (self.path / RESERVE).unlink(missing_ok=True)
        self._layout["dropped_records"] = self.dropped
        self._layout["closed"] = True
        if self.error is not None:  # why the records end early; the index says how many there are
            self._layout["write_error"] = f"{why_failed(self.error)} writing {self._error_file}"
        try:
            _replace_json(self.path / "trace.json", self._layout)
        except OSError as e:
            self.closing_error = e
        if check and (self.error is not None or self.closing_error is not None):
            raise TraceWriteError(self.failure())

    #: the OSError that kept the closing ``trace.json`` from being written (None: it was)
    closing_error = None

    def _cut(self) -> None:
        """Cut both files back to the whole chunks written (a failed write may have left part of
        one): what a reader keeps anyway, without the torn bytes taking room."""
        sizes = ((self._data, self._written * self.dtype.itemsize), (self._index, self._entries * CHUNK.itemsize))
        for fd, size in sizes:
            try:
                os.ftruncate(fd, size)
                os.fsync(fd)
            except OSError:  # the reader ignores a torn tail: cutting it is tidiness
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class TraceReader:
    """Read a trace written by :class:`TraceWriter`: the records of its checksummed chunks, in
    order, up to the first that is missing, torn or fails its checksum.

    Parameters
    ----------
    path : str or Path
        The trace directory.
    verify : bool
        Check every chunk's CRC-32 (reads the whole file once); without it only the chunk
        index's record counts bound what is kept.

    Raises :class:`TraceError` (one line) for a directory that is no trace or of a format this
    version does not read.
    """

    def __init__(self, path, verify: bool = True):
        self.path = Path(path)
        try:
            self.layout = json.loads((self.path / "trace.json").read_text())
        except (OSError, ValueError) as e:
            raise TraceMissing(f"{self.path}: not a readable rtctl trace ({e})") from None
        self.format = self.layout.get("format") if isinstance(self.layout, dict) else None
        if isinstance(self.layout, dict) and self.format not in FORMATS:
            raise TraceError(f"{self.path}: trace format {_short(self.format)} is unknown to rtctl "
                             f"(it reads {', '.join(FORMATS)}); read it with the rtctl that wrote it")
        self.dtype = _check_layout(self.layout, self.path)
        try:
            size = (self.path / "blocks.bin").stat().st_size
        except OSError as e:
            raise TraceMissing(f"{self.path}: not a readable rtctl trace (blocks.bin: {e.strerror})") from None
        self.fs = float(self.layout["fs"])
        self.block = int(self.layout["block"])
        self.channels = self.layout["channels"]
        self.units = self.layout["units"]
        self.size = size
        whole = size // self.dtype.itemsize
        #: whether the writer closed the trace (else its process ended first)
        self.closed = bool(self.layout.get("closed", False))
        #: record index of a chunk that failed its checksum (None: none did)
        self.bad_chunk = None
        self.checksummed = self.format != "rtctl-trace-1"
        self.n_blocks = self._check(whole, verify) if self.checksummed else whole
        #: bytes of blocks.bin beyond the records kept (a torn tail, or records after a bad chunk)
        self.torn_bytes = size - self.n_blocks * self.dtype.itemsize
        self.records = self._map(self.n_blocks)
        #: placeholder records (status ``TRACE_DROPPED``) in place of records the loop dropped
        self.dropped = int(self.layout.get("dropped_records", 0)) if self.closed else self._count_dropped()

    def _map(self, n: int):
        if n:
            return np.memmap(self.path / "blocks.bin", dtype=self.dtype, mode="r", shape=(n,))
        return np.zeros(0, dtype=self.dtype)

    def _check(self, whole: int, verify: bool) -> int:
        """Records covered by the valid prefix of the chunk index."""
        p = self.path / "chunks.bin"
        raw = p.read_bytes() if p.exists() else b""
        entries = np.frombuffer(raw[: len(raw) // CHUNK.itemsize * CHUNK.itemsize], dtype=CHUNK)
        data = self._map(whole)
        #: records the index lists in order, read or not: more than the file holds when it was cut
        #: after its writer closed it (a copy cut short)
        self.indexed = 0
        for e in entries:
            if int(e["first"]) != self.indexed:
                break
            self.indexed += int(e["n"])
        n = 0
        for e in entries:
            first, count = int(e["first"]), int(e["n"])
            if first != n or n + count > whole:
                break
            if verify and zlib.crc32(memoryview(np.ascontiguousarray(data[n:n + count])).cast("B")) != int(e["crc"]):
                self.bad_chunk = n
                break
            n += count
        return n

    def _count_dropped(self) -> int:
        from .safety import TRACE_DROPPED

        return int(np.count_nonzero(np.asarray(self.records["status"]) & TRACE_DROPPED)) if self.n_blocks else 0

    def recovery(self) -> str:
        """One line: how many blocks were read, and what was left out and why."""
        secs = self.n_blocks * self.block / self.fs
        head = f"{self.n_blocks} blocks ({secs:.3f} s)"
        if self.bad_chunk is not None:
            return (f"{head} recovered; the chunk from record {self.bad_chunk} fails its checksum: it and the "
                    f"{self.torn_bytes} bytes after it are left out")
        if not self.checksummed:
            return f"{head} (format {self.format}: no checksums)"
        ended = self.layout.get("write_error")
        if self.closed and not self.torn_bytes and isinstance(ended, str):
            return f"{head}, closed by its writer early ({ended}), every chunk's checksum holds"
        if self.closed and not self.torn_bytes:
            return f"{head}, closed by its writer, every chunk's checksum holds"
        torn = f"; a torn tail of {self.torn_bytes} bytes ignored" if self.torn_bytes else ""
        if self.closed and getattr(self, "indexed", 0) > self.n_blocks:
            # the writer closed it whole: blocks.bin lost its end afterwards, and the blocks lost are known
            return (f"{head} recovered of the {self.indexed} its writer closed it with: blocks.bin was cut "
                    f"short after it was written (a copy or a disk that lost its end), "
                    f"{self.indexed - self.n_blocks} blocks lost{torn}")
        return f"{head} recovered (the writing process ended before closing it){torn}"

    @property
    def meta(self) -> dict:
        return self.layout.get("meta", {})

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
    if layout.get("format") not in FORMATS:
        raise bad(f"format {_short(layout.get('format'))}: this rtctl reads {', '.join(FORMATS)}")
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
