"""Paths of the HIA over the image, sampled at the render rate, and their hand-over to the loop.

A :class:`Path` holds HIA centres ``x, y`` (px, x right, y down) at times ``t = t0 + k / rate``.
Build one from a raster scan (:func:`raster`), from way-points with times (:func:`through`) or
at a constant speed (:func:`at_speed`), from a recorded mouse CSV (:func:`from_csv`), or from the
one-word form ``rtctl render --path`` takes (:func:`parse_path`). :class:`PathPlayer` turns it into parameter
changes for the fixed-rate loop: before block ``k`` (starting at ``k block / fs``) the loop asks
for the render update in force at that time; when it is new, the renderer fills the pending
per-pin parameter array, which the oscillators ramp across the next block.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from rtctl.errors import SceneError

__all__ = ["Path", "raster", "through", "at_speed", "from_csv", "parse_path", "PathPlayer", "MAX_UPDATES"]

#: Most render updates one path may take: 1000 s at 1 kHz. The arrays are allocated whole (and
#: ``rtctl render`` keeps every update's pin parameters), so a slow raster or a far-off last time
#: would otherwise ask for gigabytes before anything is rendered.
MAX_UPDATES = 1_000_000


@dataclass(frozen=True)
class Path:
    """HIA centres sampled at ``rate``.

    Attributes
    ----------
    t : ndarray, shape (n,)
        Times, s, ``t[0] + arange(n) / rate``.
    x, y : ndarray, shape (n,)
        HIA centre, px.
    rate : float
        Render rate, Hz.
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    rate: float

    def __len__(self):
        return self.t.size


def _rate(rate):
    if not (rate > 0.0 and math.isfinite(rate)):
        raise SceneError(f"render rate = {rate!r} Hz must be > 0")
    return float(rate)


def _updates(seconds: float, rate: float) -> int:
    """Updates of a path ``seconds`` long at ``rate``, refused above :data:`MAX_UPDATES` (counted
    before anything is allocated)."""
    n = math.floor(seconds * rate + 1e-9) + 1
    if n > MAX_UPDATES:
        raise SceneError(f"the path takes {n:.4g} render updates ({seconds:.4g} s at {rate:g} Hz), more than the "
                         f"{MAX_UPDATES} allowed; lower the render rate or shorten the path (or raise its speed)")
    return int(n)


def through(points, times, rate=1000.0) -> Path:
    """Piecewise-linear path through way-points, sampled at ``rate``.

    Parameters
    ----------
    points : array_like, shape (m, 2)
        ``(x, y)`` way-points, px.
    times : array_like, shape (m,)
        Their times, s, strictly increasing.
    rate : float
        Render rate, Hz.

    Examples
    --------
    >>> p = through([(0, 0), (10, 0)], [0.0, 0.01], rate=1000.0)
    >>> p.x
    array([ 0.,  1.,  2.,  3.,  4.,  5.,  6.,  7.,  8.,  9., 10.])
    """
    rate = _rate(rate)
    pts = np.asarray(points, dtype=float)
    tt = np.asarray(times, dtype=float).ravel()
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] != tt.size or tt.size < 1:
        raise SceneError(f"path points {pts.shape} and times {tt.shape} must be (m, 2) and (m,), m >= 1")
    if not (np.isfinite(pts).all() and np.isfinite(tt).all()):
        raise SceneError("path points and times must be finite")
    if np.any(np.diff(tt) <= 0.0):
        raise SceneError("path times must be strictly increasing")
    n = _updates(tt[-1] - tt[0], rate)
    t = tt[0] + np.arange(n) / rate
    return Path(t, np.interp(t, tt, pts[:, 0]), np.interp(t, tt, pts[:, 1]), rate)


def _speed(speed, what="path speed"):
    if not (speed > 0.0 and math.isfinite(speed)):
        raise SceneError(f"{what} = {speed!r} px/s must be > 0")
    return float(speed)


def at_speed(points, speed, rate=1000.0) -> Path:
    """Piecewise-linear path through way-points at a constant ``speed`` (px/s), from t = 0.

    Examples
    --------
    >>> p = at_speed([(0, 0), (3, 4), (3, 0)], speed=1000.0, rate=1000.0)   # 5 px, then 4 px
    >>> float(p.t[-1]), p.x[:6].round(12).tolist(), p.y[5:].round(12).tolist()
    (0.009, [0.0, 0.6, 1.2, 1.8, 2.4, 3.0], [4.0, 3.0, 2.0, 1.0, 0.0])
    """
    speed = _speed(speed)
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 2:
        raise SceneError(f"way-points {pts.shape} must be (m, 2) with m >= 2")
    if not np.isfinite(pts).all():
        raise SceneError("way-points must be finite")
    seg = np.hypot(np.diff(pts[:, 0]), np.diff(pts[:, 1]))
    keep = np.concatenate([[True], seg > 0.0])  # a repeated point adds no time
    pts, s = pts[keep], np.concatenate([[0.0], np.cumsum(seg[seg > 0.0])])
    if pts.shape[0] < 2:
        raise SceneError("way-points must not all be the same point")
    return through(pts, s / speed, rate)


def raster(width, height, speed, rate=1000.0, step=33.0) -> Path:
    """Serpentine raster scan of a ``width x height`` px image at constant ``speed``.

    Lines run left to right, then right to left, at ``y = step / 2, 3 step / 2, ...``; the HIA
    moves down by ``step`` between lines (at the same speed). Use ``step`` = the HIA height to
    cover the image once.

    Parameters
    ----------
    width, height : int
        Image size, px.
    speed : float
        HIA speed, px/s.
    rate : float
        Render rate, Hz.
    step : float
        Distance between lines, px.

    Examples
    --------
    >>> p = raster(100, 66, speed=1000.0, step=33.0)
    >>> len(p), float(p.y[0]), float(p.y[-1])            # 99 + 33 + 99 px at 1 px/ms
    (232, 16.5, 49.5)
    """
    rate = _rate(rate)
    _speed(speed, "raster speed")
    if not step > 0.0:
        raise SceneError(f"raster step = {step!r} px must be > 0")
    ys = np.arange(step / 2.0, max(height, step / 2.0 + 1e-9), step)
    xs = np.array([0.0, width - 1.0])
    vx, vy = [], []
    for i, y in enumerate(ys):
        a, b = (xs if i % 2 == 0 else xs[::-1])
        vx += [a, b]
        vy += [y, y]
    vx, vy = np.array(vx), np.array(vy)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(vx), np.diff(vy)))])
    t_end = s[-1] / speed
    n = _updates(t_end, rate)
    t = np.arange(n) / rate
    d = np.minimum(t * speed, s[-1])
    return Path(t, np.interp(d, s, vx), np.interp(d, s, vy), rate)


def from_csv(file, rate=1000.0, speed=None) -> Path:
    """A recorded mouse path: CSV with columns ``t, x, y`` (s, px, px), resampled at ``rate``.

    A first line of column names is allowed (``t``/``time``, ``x``, ``y`` in any order); rows
    with a time not after the previous row's (duplicate mouse events) are dropped. With
    ``speed`` (px/s), a file whose header names only ``x`` and ``y`` holds way-points, travelled
    at that speed (:func:`at_speed`).
    """
    try:
        with open(file, encoding="utf-8") as fh:
            lines = [ln.strip() for ln in fh if ln.strip() and not ln.lstrip().startswith("#")]
    except OSError as e:
        raise SceneError(f"{file}: cannot read the mouse path ({e.strerror}); give a CSV of t,x,y") from None
    except UnicodeDecodeError as e:
        raise SceneError(f"{file}: not UTF-8 text (a byte {e.object[e.start]:#04x}); give a CSV of t,x,y "
                         "rows") from None
    if not lines:
        raise SceneError(f"{file}: empty mouse path; give a CSV of t,x,y rows")
    cols = (0, 1, 2)
    head = [h.strip().lower() for h in lines[0].split(",")]
    try:
        float(head[0])
    except ValueError:
        names = {"t": "t", "time": "t", "t_s": "t", "x": "x", "y": "y"}
        idx = {names.get(h): k for k, h in enumerate(head) if h in names}
        if set(idx) == {"x", "y"} and speed is not None:
            try:
                rows = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
                return at_speed(rows[:, [idx["x"], idx["y"]]], speed, rate)
            except (ValueError, IndexError):
                raise SceneError(f"{file}: way-point rows must be numbers x,y") from None
        if set(idx) != {"t", "x", "y"}:
            raise SceneError(f"{file}: header {lines[0]!r} must name columns t, x and y") from None
        cols = (idx["t"], idx["x"], idx["y"])
        lines = lines[1:]
    try:
        rows = np.array([[float(v) for v in ln.split(",")] for ln in lines])
        data = rows[:, cols]
    except (ValueError, IndexError):
        raise SceneError(f"{file}: rows must be numbers t,x,y") from None
    t = data[:, 0]
    data = data[t > np.maximum.accumulate(np.concatenate([[-np.inf], t[:-1]]))]
    if data.shape[0] < 2:
        raise SceneError(f"{file}: a mouse path needs at least two rows at different times")
    return through(data[:, 1:], data[:, 0], rate)


def parse_path(spec: str, width: int, height: int, *, speed: float = 200.0, rate: float = 1000.0,
               step: float = 33.0) -> Path:
    """The HIA path ``spec`` names, over a ``width x height`` px image.

    ``spec`` is one of:

    * ``raster``: a serpentine scan of the image at ``speed`` px/s, lines ``step`` px apart
      (:func:`raster`);
    * way-points ``X,Y;X,Y;...`` (px, at least two) travelled at ``speed`` (:func:`at_speed`), or
      ``X,Y@T;X,Y@T;...`` with their times in s (:func:`through`; every point timed, or none);
    * a CSV file: ``t,x,y`` rows (a mouse recording, :func:`from_csv`), or way-points under a
      header ``x,y`` (no time column) travelled at ``speed``.

    Examples
    --------
    >>> len(parse_path("raster", 100, 66, speed=1000.0))
    232
    >>> parse_path("0,10;4,10", 100, 66, speed=1000.0).x.tolist()
    [0.0, 1.0, 2.0, 3.0, 4.0]
    >>> parse_path("0,10@0;0,14@0.002", 100, 66).y.tolist()
    [10.0, 12.0, 14.0]
    """
    text = spec.strip()
    if not text:
        raise SceneError("--path is empty; give 'raster', way-points X,Y;X,Y, or a CSV file")
    if text.lower() == "raster":
        return raster(width, height, speed, rate, step)
    if ";" in text or _is_point(text):
        return _inline(text, speed, rate)
    if not os.path.isfile(text):
        what = "no such file" if not os.path.exists(text) else "not a regular file"
        raise SceneError(f"--path {text!r}: {what}; give 'raster', way-points X,Y;X,Y (travelled at --speed) or "
                         "X,Y@T;X,Y@T (times in s), or a CSV file (t,x,y rows, or x,y way-points)")
    return from_csv(text, rate, speed=speed)


def _is_point(text: str) -> bool:
    """``text`` looks like one way-point (``X,Y`` or ``X,Y@T``), not a file name."""
    head = text.split("@")[0].split(",")
    try:
        return len(head) == 2 and all(math.isfinite(float(v)) for v in head)
    except ValueError:
        return False


def _inline(text: str, speed, rate) -> Path:
    pts, times = [], []
    for k, item in enumerate(p for p in text.split(";") if p.strip()):
        xy, _, t = item.partition("@")
        try:
            x, y = (float(v) for v in xy.split(","))
            times.append(float(t) if t.strip() else None)
        except ValueError:
            raise SceneError(f"--path way-point {k + 1} {item.strip()!r} must be X,Y or X,Y@T (px, px, s)") from None
        pts.append((x, y))
    timed = [t is not None for t in times]
    if any(timed) and not all(timed):
        raise SceneError("--path: give a time (X,Y@T) for every way-point or for none (then they are "
                         "travelled at --speed)")
    if len(pts) < 2:
        raise SceneError("--path needs at least two way-points (X,Y;X,Y), 'raster' or a CSV file")
    return through(pts, times, rate) if all(timed) else at_speed(pts, speed, rate)


class PathPlayer:
    """Hands the render updates of a path to a fixed-rate block loop.

    Parameters
    ----------
    renderer : Renderer
        Prepared renderer (see :mod:`rtctl.render.hia`).
    path : Path
    fs : float
        Loop sample rate, Hz.
    block : int
        Samples per block.

    Notes
    -----
    Block ``k`` starts at ``k block / fs`` after the path's start and uses update
    ``min(floor(k block rate / fs), n - 1)``: the latest one issued by then, held after the path
    ends. At 48 kHz, 32-sample blocks (1.5 kHz) and a 1 kHz render rate every second or third
    block brings a new update.

    Examples
    --------
    >>> from rtctl.render.factory import make_renderer
    >>> r = make_renderer("roi", grid=(4, 4), hia=32).prepare(np.zeros((64, 64), np.uint8))
    >>> player = PathPlayer(r, through([(0, 32), (63, 32)], [0.0, 0.063]), fs=48000.0, block=32)
    >>> pending = r.empty()
    >>> [player.step(k, pending) for k in range(4)]
    [True, False, True, True]
    """

    def __init__(self, renderer, path: Path, fs: float, block: int):
        self.renderer = renderer
        self.path = path
        self.fs = float(fs)
        self.block = int(block)
        self.index = -1

    def index_at(self, k: int) -> int:
        """Path update in force at the start of block ``k``."""
        i = int(math.floor(k * self.block * self.path.rate / self.fs + 1e-9))
        return min(i, len(self.path) - 1)

    def schedule(self, n_blocks: int) -> np.ndarray:
        """:meth:`index_at` for blocks ``0 .. n_blocks - 1``; int64, shape (n_blocks,)."""
        k = np.arange(int(n_blocks))
        return np.minimum(np.floor(k * self.block * self.path.rate / self.fs + 1e-9).astype(np.int64),
                          len(self.path) - 1)

    def step(self, k: int, pending) -> bool:
        """Before block ``k``: when a new update applies, render it into ``pending`` and return True."""
        i = self.index_at(k)
        if i == self.index:
            return False
        self.index = i
        self.renderer.update(self.path.x[i], self.path.y[i], pending)
        return True
