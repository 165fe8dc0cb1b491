"""Output paths checked before anything runs.

A run, a calibration or a rendering writes its files at the end; a directory that cannot be
written (``/proc/x``, ``/sys/x``, an existing regular file, a read-only mount) would otherwise
be found only then, after the rig was built and the run made. :func:`writable_dir` and
:func:`writable_file` create what is missing and prove it writable by creating and removing a
file there, and raise :class:`~rtctl.errors.OutputError` (one line, exit 2) when it is not.
Permission bits alone are not enough: root passes ``os.access`` on ``/proc`` and ``/sys``.
"""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path

from .errors import OutputError

__all__ = ["writable_dir", "writable_file", "kind_of"]

_KINDS = {stat.S_IFREG: "a regular file", stat.S_IFDIR: "a directory", stat.S_IFIFO: "a FIFO (named pipe)",
          stat.S_IFCHR: "a character device", stat.S_IFBLK: "a block device", stat.S_IFSOCK: "a socket",
          stat.S_IFLNK: "a symbolic link"}


def kind_of(path) -> str:
    """What ``path`` is ("a regular file", "a FIFO (named pipe)", ...), following links."""
    return _KINDS.get(stat.S_IFMT(os.stat(path).st_mode), "not a regular file")


def writable_dir(path, what: str = "--out", subdirs=(), files=()) -> Path:
    """Create directory ``path`` (parents too) and prove a file can be written in it.

    ``subdirs`` and ``files`` are names the caller will write inside (``trace``, ``summary.json``):
    one of them that exists as the other kind is refused too. Returns ``Path(path)``.
    """
    fix = f"give {what} a directory you can write to"
    p = _nonempty(path, what, fix)
    if p.exists() and not p.is_dir():
        raise OutputError(f"{what} {p}: is {kind_of(p)}, not a directory; {fix}")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{what} {p}: cannot create the directory ({_why(e)}); {fix}") from None
    _probe(p, what, fix)
    for name, want_dir in [(n, True) for n in subdirs] + [(n, False) for n in files]:
        q = p / name
        if q.exists() and q.is_dir() != want_dir:
            raise OutputError(f"{what} {p}: {name} there is {kind_of(q)}, where this writes "
                              f"{'a directory' if want_dir else 'a file'}; remove it or {fix}")
    return p


def writable_file(path, what: str = "--out") -> Path:
    """Prove ``path`` can be written as a file (its directory created, a probe written there);
    an existing ``path`` must be a regular file (it is replaced). Returns ``Path(path)``."""
    fix = f"give {what} a file path you can write to"
    p = _nonempty(path, what, fix)
    if p.exists() and not p.is_file():
        raise OutputError(f"{what} {p}: is {kind_of(p)}, not a regular file; {fix}")
    parent = p.parent
    if parent.exists() and not parent.is_dir():
        raise OutputError(f"{what} {p}: {parent} is {kind_of(parent)}, not a directory; {fix}")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{what} {p}: cannot create its directory {parent} ({_why(e)}); {fix}") from None
    _probe(parent, what, fix, shown=p)
    return p


def _nonempty(path, what: str, fix: str) -> Path:
    # Path("") is ".": an empty value would quietly write into the working directory
    if isinstance(path, str) and not path.strip():
        raise OutputError(f"{what} is empty; {fix}")
    return Path(path)


def _probe(d: Path, what: str, fix: str, shown: Path | None = None) -> None:
    try:
        fd, name = tempfile.mkstemp(prefix=".rtctl-probe-", dir=d)
    except OSError as e:
        raise OutputError(f"{what} {shown or d}: cannot write in {d} ({_why(e)}); {fix}") from None
    os.close(fd)
    os.unlink(name)


def _why(e: OSError) -> str:
    return e.strerror or type(e).__name__
