"""The haptic interaction area (HIA) and the renderer contract shared by every method.

A renderer maps an image to per-pin parameters in two steps:

1. ``prepare(image)`` once: all image-wide work (tactile image, edges, blob labels, summed-area
   tables). Cost grows with the image.
2. ``update(x, y, out)`` per render tick: the HIA centred at pixel ``(x, y)`` (x right, y down)
   fills ``out`` (shape ``(n_pins, N_FIELDS)``, columns :data:`FIELDS`) by a numba kernel whose
   work grows with the HIA only. It allocates nothing and returns a status int.

The HIA is a grid of ``R x C`` square cells of ``cell = hia // max(R, C)`` pixels, one per pin,
row-major (pin ``i * C + j`` is row ``i`` from the top, column ``j`` from the left); its top-left
pixel is ``(round(y) - h // 2, round(x) - w // 2)`` with ``h = R cell``, ``w = C cell``.
"""

from __future__ import annotations

import math

import numpy as np

from rtctl.errors import SceneError
from rtctl.render import _kernels as _k
from rtctl.render.image import check_image

__all__ = ["Renderer", "FIELDS", "N_FIELDS", "METHODS"]

FIELDS = _k.FIELDS
N_FIELDS = _k.N_FIELDS
METHODS = ("roi", "canny", "frequency", "beat")


def _grid(grid) -> tuple[int, int]:
    try:
        r, c = (int(v) for v in grid)
    except (TypeError, ValueError):
        raise SceneError(f"grid = {grid!r} is not two integers (rows, cols), e.g. (4, 4)") from None
    if not (1 <= r <= 64 and 1 <= c <= 64):
        raise SceneError(f"grid = {grid!r}: rows and cols must be in [1, 64]")
    return r, c


class Renderer:
    """Base class: HIA geometry, the output array and path rendering. Use a subclass.

    Parameters
    ----------
    grid : (int, int)
        Pins (rows, cols) of the display.
    hia : int
        HIA side in image pixels (of the longer side of the grid); each pin covers
        ``hia // max(grid)`` px square.

    Attributes
    ----------
    fields : tuple of str
        The columns of ``out`` this method defines (the others stay 0).
    cell : int
        Pixels per pin side.
    shape : (int, int)
        HIA height and width in pixels, ``(R cell, C cell)``.
    """

    method = ""
    fields: tuple[str, ...] = ()

    def __init__(self, grid, hia):
        self.grid = _grid(grid)
        try:
            hia = int(hia)
        except (TypeError, ValueError):
            raise SceneError(f"hia = {hia!r} is not an integer number of pixels") from None
        R, C = self.grid
        if hia < max(R, C):
            raise SceneError(f"hia = {hia} px is smaller than the grid {R}x{C}: each pin needs at least 1 px; "
                             f"use hia >= {max(R, C)}")
        self.hia = hia
        self.cell = hia // max(R, C)
        self.shape = (R * self.cell, C * self.cell)
        self.n_pins = R * C
        self.image_shape = None

    # -- to be provided by subclasses ------------------------------------------------------------
    def _prepare(self, image):  # pragma: no cover - abstract
        raise NotImplementedError

    def _update(self, r0, c0, out):  # pragma: no cover - abstract
        raise NotImplementedError

    # -- public ----------------------------------------------------------------------------------
    def prepare(self, image):
        """Do the image-wide work once; returns ``self``.

        Parameters
        ----------
        image : ndarray, uint8, shape (H, W) or (H, W, 3)
            Gray or BGR (see :func:`rtctl.render.image.check_image`).
        """
        image = check_image(image)
        self.image_shape = image.shape[:2]
        self._prepare(image)
        return self

    def empty(self, n=None) -> np.ndarray:
        """A zeroed output array: ``(n_pins, N_FIELDS)``, or ``(n, n_pins, N_FIELDS)``."""
        shape = (self.n_pins, N_FIELDS) if n is None else (int(n), self.n_pins, N_FIELDS)
        return np.zeros(shape)

    def origin(self, x, y) -> tuple[int, int]:
        """Top-left pixel ``(row, col)`` of the HIA centred at ``(x, y)``.

        Examples
        --------
        A 4 x 4 grid on a 32 px HIA is 32 x 32 px, so its corner is 16 px up and left of the
        centre (rounded half up):

        >>> Renderer((4, 4), 32).origin(100.5, 50.0)
        (34, 85)
        """
        h, w = self.shape
        return int(math.floor(y + 0.5)) - h // 2, int(math.floor(x + 0.5)) - w // 2

    def update(self, x, y, out) -> int:
        """Fill ``out`` with the pins' parameters for the HIA centred at pixel ``(x, y)``.

        Parameters
        ----------
        x, y : float
            HIA centre in pixels, x to the right, y down. May lie outside the image (outside
            pixels are background).
        out : ndarray, float64, shape (n_pins, N_FIELDS)
            Overwritten; columns :data:`FIELDS`.

        Returns
        -------
        int
            ``0`` ok, ``1`` the HIA lies wholly outside the image.
        """
        if self.image_shape is None:
            raise SceneError(f"{type(self).__name__}.update before prepare(image); call prepare first")
        r0, c0 = self.origin(x, y)
        return self._update(r0, c0, out)

    def render_path(self, x, y, out=None) -> np.ndarray:
        """Run :meth:`update` at each point of a path.

        Parameters
        ----------
        x, y : array_like, shape (n,)
            HIA centres, px (e.g. ``path.x, path.y`` of :mod:`rtctl.render.path`).
        out : ndarray, float64, shape (n, n_pins, N_FIELDS), optional

        Returns
        -------
        ndarray, shape (n, n_pins, N_FIELDS)
        """
        x = np.asarray(x, dtype=float).ravel()
        y = np.asarray(y, dtype=float).ravel()
        if x.shape != y.shape:
            raise SceneError(f"path x and y differ in length ({x.size} vs {y.size})")
        out = self.empty(x.size) if out is None else out
        for k in range(x.size):
            self.update(x[k], y[k], out[k])
        return out

    def pins(self, out) -> list[dict]:
        """The rows of ``out`` as ``[{"row", "col", <the method's fields>}]`` (JSON-ready)."""
        R, C = self.grid
        idx = [FIELDS.index(f) for f in self.fields]
        res = []
        for p in range(self.n_pins):
            d = {"row": p // C, "col": p % C}
            for f, k in zip(self.fields, idx):
                v = float(out[p, k])
                d[f] = bool(v) if f == "up" else round(v, 6)
            res.append(d)
        return res

    def hia_rects(self, x, y):
        """Per pin ``(row0, col0, row1, col1)`` pixel rectangles (unclipped), for drawing."""
        r0, c0 = self.origin(x, y)
        R, C = self.grid
        s = self.cell
        return [(r0 + i * s, c0 + j * s, r0 + (i + 1) * s, c0 + (j + 1) * s) for i in range(R) for j in range(C)]

    def images(self) -> dict:
        """Intermediate images of the last :meth:`prepare` (name -> uint8 array), for display."""
        return {}

