"""Paths of the HIA over the image, sampled at the render rate, and their hand-over to the loop.

A :class:`Path` holds HIA centres ``x, y`` (px, x right, y down) at times ``t = t0 + k / rate``.
Build one from a raster scan (:func:`raster`), from way-points with times (:func:`through`) or
from a recorded mouse CSV (:func:`from_csv`). :class:`PathPlayer` turns it into parameter
changes for the fixed-rate loop: before block ``k`` (starting at ``k block / fs``) the loop asks
for the render update in force at that time; when it is new, the renderer fills the pending
per-pin parameter array, which the oscillators ramp across the next block.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rtctl.errors import SceneError

__all__ = ["Path", "raster", "through", "from_csv", "PathPlayer"]


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
    n = int(math.floor((tt[-1] - tt[0]) * rate + 1e-9)) + 1
    t = tt[0] + np.arange(n) / rate
    return Path(t, np.interp(t, tt, pts[:, 0]), np.interp(t, tt, pts[:, 1]), rate)


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
    if not (speed > 0.0 and math.isfinite(speed)):
        raise SceneError(f"raster speed = {speed!r} px/s must be > 0")
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
    n = int(math.floor(t_end * rate + 1e-9)) + 1
    t = np.arange(n) / rate
    d = np.minimum(t * speed, s[-1])
    return Path(t, np.interp(d, s, vx), np.interp(d, s, vy), rate)


def from_csv(file, rate=1000.0) -> Path:
    """A recorded mouse path: CSV with columns ``t, x, y`` (s, px, px), resampled at ``rate``.

    A first line of column names is allowed (``t``/``time``, ``x``, ``y`` in any order); rows
    with a time not after the previous row's (duplicate mouse events) are dropped.
    """
    try:
        with open(file, encoding="utf-8") as fh:
            lines = [ln.strip() for ln in fh if ln.strip() and not ln.lstrip().startswith("#")]
    except OSError as e:
        raise SceneError(f"{file}: cannot read the mouse path ({e.strerror}); give a CSV of t,x,y") from None
    if not lines:
        raise SceneError(f"{file}: empty mouse path; give a CSV of t,x,y rows")
    cols = (0, 1, 2)
    head = [h.strip().lower() for h in lines[0].split(",")]
    try:
        float(head[0])
    except ValueError:
        names = {"t": "t", "time": "t", "t_s": "t", "x": "x", "y": "y"}
        idx = {names.get(h): k for k, h in enumerate(head) if h in names}
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
