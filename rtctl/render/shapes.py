"""Simple shapes for binary pin displays (seed 002, Fig. 16; seed 001's plane figures).

Curved and slanted shapes are drawn by OpenCV on a canvas of ``k x k`` px per pin (subpixel
vertices) and each pin is up when more than half of its pixels are covered: the ROI rule of
seed 001 (:mod:`rtctl.render.roi`) applied to a drawing. Shapes made of whole pins (square,
frame, cross, lines) are set directly.
"""

from __future__ import annotations

import cv2
import numpy as np

from rtctl.errors import SceneError

__all__ = ["shape", "SHAPES"]

SHAPES = ("square", "frame", "cross", "hline", "vline", "disc", "ring", "triangle", "diagonal")
_K = 32           # canvas px per pin
_SHIFT = 4        # fractional bits of OpenCV's drawing coordinates


def _covered(canvas, R, C):
    # mean coverage of each pin's k x k px, > 1/2 = up (area averaging: INTER_AREA)
    cover = cv2.resize(canvas.astype(np.float32), (C, R), interpolation=cv2.INTER_AREA)
    return cover > 0.5


def _pt(x, y):
    return (int(round(x * _K * (1 << _SHIFT))), int(round(y * _K * (1 << _SHIFT))))


def shape(name: str, grid=(8, 8)) -> np.ndarray:
    """A shape filling the pin grid; bool ``(rows, cols)``, True = pin up.

    Parameters
    ----------
    name : str
        ``square`` (all pins), ``frame`` (border pins), ``cross`` (middle row(s) and
        column(s)), ``hline`` / ``vline`` (middle row(s) / column(s)), ``disc`` and ``ring``
        (inscribed circle, filled / one pin wide), ``triangle`` (apex at the top centre, base
        on the bottom edge), ``diagonal`` (top-left to bottom-right, one pin wide).
    grid : (int, int)
        Pins (rows, cols).

    Examples
    --------
    >>> shape("disc", (4, 4)).astype(int)
    array([[0, 1, 1, 0],
           [1, 1, 1, 1],
           [1, 1, 1, 1],
           [0, 1, 1, 0]])
    """
    R, C = (int(v) for v in grid)
    if R < 1 or C < 1:
        raise SceneError(f"grid {grid!r} must have at least one row and column")
    out = np.zeros((R, C), dtype=bool)
    mr = slice((R - 1) // 2, R // 2 + 1)  # one middle row (odd R) or two (even R)
    mc = slice((C - 1) // 2, C // 2 + 1)
    if name == "square":
        out[:] = True
    elif name == "frame":
        out[[0, -1], :] = True
        out[:, [0, -1]] = True
    elif name == "cross":
        out[mr, :] = True
        out[:, mc] = True
    elif name == "hline":
        out[mr, :] = True
    elif name == "vline":
        out[:, mc] = True
    elif name in ("disc", "ring", "triangle", "diagonal"):
        canvas = np.zeros((R * _K, C * _K), np.uint8)
        if name in ("disc", "ring"):
            rad = min(R, C) / 2.0
            centre = _pt(C / 2.0, R / 2.0)
            if name == "disc":
                cv2.circle(canvas, centre, _pt(rad, 0)[0], 1, -1, cv2.LINE_8, _SHIFT)
            else:
                cv2.circle(canvas, centre, _pt(rad - 0.5, 0)[0], 1, _K, cv2.LINE_8, _SHIFT)
        elif name == "triangle":
            pts = np.array([_pt(C / 2.0, 0.0), _pt(0.0, R), _pt(C, R)], np.int32)
            cv2.fillPoly(canvas, [pts], 1, cv2.LINE_8, _SHIFT)
        else:
            cv2.line(canvas, _pt(0, 0), _pt(C, R), 1, _K, cv2.LINE_8, _SHIFT)
        out = _covered(canvas, R, C)
    else:
        raise SceneError(f"shape {name!r} is unknown; use one of {', '.join(SHAPES)}")
    return out
