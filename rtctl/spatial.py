"""The spatializer: a virtual source moving over an actuator grid gives each channel a gain.

Channel ``c`` of an ``R x C`` group sits at column ``c % C``, row ``c // C``; positions are in
channel pitches (``x`` along a row, ``y`` down a column), or in metres when the spatial table
gives the grid's ``pitch``. A source at ``p`` with radius ``r`` gives a channel at distance ``d``
the gain ``law(u)``, ``u = max(0, 1 - d / r)``:

* ``linear``: ``u`` (amplitude panning: halfway between two channels one pitch apart with
  ``r = 1``, each gets 0.5 -- the phantom sensation between them);
* ``smoothstep``: ``u**2 (3 - 2 u)`` (flat near the source and at the edge);
* ``log``: the level in dB falls in a straight line, from 0 dB at the source to -60 dB at
  ``r``, shifted to reach exactly 0 there: ``(10**(-3 (1 - u)) - 10**-3) / (1 - 10**-3)``;
* ``table``: the scene's gains at ``d / r = 0, 1 / (n - 1), ..., 1``, straight lines between.

The path is way-points ``(t, x, y)`` joined by straight lines, held before the first and after
the last. Gains are taken every ``1 / rate`` s and at every way-point, straight lines between
(the oscillator bank ramps each channel's amplitude along them). A 1 x N or N x 1 grid is a
line like any other: nothing is normalized by the grid's extent.
"""

from __future__ import annotations

import math

import numpy as np

from .signals import Track

LAWS = ("linear", "smoothstep", "log", "table")


def rolloff(law: str, d, radius: float, table=()) -> np.ndarray:
    """Gain at distance ``d`` (same unit as ``radius``) under ``law``."""
    d = np.asarray(d, float)
    u = np.clip(1.0 - d / radius, 0.0, 1.0)
    if law == "linear":
        return u
    if law == "smoothstep":
        return u * u * (3.0 - 2.0 * u)
    if law == "log":
        g = (10.0 ** (-3.0 * (1.0 - u)) - 1e-3) / (1.0 - 1e-3)
        return np.where(u > 0.0, g, 0.0)
    if law == "table":
        tab = np.asarray(table, float)
        return np.interp(d / radius, np.linspace(0.0, 1.0, tab.size), tab, right=0.0)
    raise ValueError(f"unknown roll-off law {law!r} (have {', '.join(LAWS)})")


def positions(grid, pitch=(0.0, 0.0)) -> np.ndarray:
    """Channel positions, shape (R C, 2): ``(x, y)`` in pitches, or metres for a non-zero pitch."""
    R, C = grid
    rows, cols = np.divmod(np.arange(R * C), C)
    px, py = (1.0, 1.0) if not any(pitch) else pitch
    return np.stack([cols * px, rows * py], axis=1).astype(float)


def source_at(t, times, xs, ys) -> np.ndarray:
    """Source position at times ``t`` (s), shape (len(t), 2)."""
    t = np.atleast_1d(np.asarray(t, float))
    return np.stack([np.interp(t, times, xs), np.interp(t, times, ys)], axis=1)


def gains(sp, grid, fs: float, n_run: float) -> tuple[np.ndarray, list[Track]]:
    """Per channel of ``grid``, its gain track (samples) under the validated spatial table ``sp``.

    Returns the sample positions the gains are taken at and one :class:`Track` per channel.
    """
    times = np.asarray(sp["times"], float)
    step = 1.0 / sp["rate"]
    t_end = n_run / fs
    t = np.unique(np.concatenate([np.arange(0.0, t_end, step), times[times < t_end], [t_end]]))
    x = np.unique(np.round(t * fs))
    src = source_at(x / fs, times, sp["x"], sp["y"])
    pos = positions(grid, tuple(sp["pitch"]))
    d = np.hypot(pos[:, None, 0] - src[None, :, 0], pos[:, None, 1] - src[None, :, 1])
    g = rolloff(sp["rolloff"], d, sp["radius"], sp["table"])
    return x, [Track(x, g[c]) for c in range(pos.shape[0])]


def check(sp, where: str) -> str | None:
    """What is wrong with a spatial table, or None."""
    n = len(sp["times"])
    if n < 1 or len(sp["x"]) != n or len(sp["y"]) != n:
        return f"{where}.times: times, x and y need the same number of way-points (>= 1)"
    if any(b < a for a, b in zip(sp["times"], sp["times"][1:])):
        return f"{where}.times = {list(sp['times'])}: way-points must be in time order"
    if sp["rolloff"] == "table" and len(sp["table"]) < 2:
        return f"{where}.table = {list(sp['table'])}: a table roll-off needs at least 2 gains (d / r = 0 ... 1)"
    if sp["rolloff"] != "table" and len(sp["table"]):
        return f"{where}.table: only for rolloff = 'table'"
    if any(sp["pitch"]) and not all(sp["pitch"]):
        return f"{where}.pitch = {list(sp['pitch'])}: give both pitches (m), or [0, 0] for positions in pitches"
    if any(math.isinf(v) for v in (*sp["x"], *sp["y"])):
        return f"{where}: way-points must be finite"
    return None
