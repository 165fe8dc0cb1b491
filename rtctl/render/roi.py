"""ROI scanning for binary pins (seed 001): a section is up when more than half of it is black.

Two sources of "black":

* ``roi``: the image itself, thresholded (gray < ``threshold`` is black), for binary images of
  filled figures.
* ``canny``: edges. Gray -> Gaussian blur -> Canny -> invert (edges black on white, as the
  seed's simulator expects) -> thicken the lines. The seed thickens with Hough lines; we dilate
  the edge map instead: a probabilistic Hough transform redraws only the straight segments it
  finds, so curved edges (the seed's flower and fingertip) come out broken or dropped, while a
  dilation thickens every edge pixel by the same amount, curved or straight, and has a single
  parameter (the line width in pixels).
"""

from __future__ import annotations

import cv2
import numpy as np

from rtctl.errors import SceneError
from rtctl.render import _kernels as _k
from rtctl.render.hia import Renderer
from rtctl.render.image import to_gray

__all__ = ["RoiRenderer", "black_mask", "canny_lines"]


def black_mask(gray, threshold=128) -> np.ndarray:
    """0/1 mask of the black pixels, ``gray < threshold``; uint8, shape (H, W)."""
    return (np.asarray(gray) < threshold).astype(np.uint8)


def canny_lines(gray, low=50.0, high=150.0, blur_px=5, line_px=3) -> np.ndarray:
    """Edges as black lines on white (seed 001, Fig. 7d); uint8 0/255, shape (H, W).

    Parameters
    ----------
    gray : ndarray, uint8, shape (H, W)
    low, high : float
        Canny hysteresis thresholds (gradient magnitude, gray levels per pixel).
    blur_px : int
        Gaussian kernel side (odd, px; sigma from OpenCV's rule ``0.3 ((k - 1) / 2 - 1) + 0.8``);
        1 skips the blur.
    line_px : int
        Width of the thickened lines, px (a ``line_px`` disc dilation of the 1 px Canny edges);
        1 keeps them thin.
    """
    g = gray if blur_px <= 1 else cv2.GaussianBlur(gray, (blur_px, blur_px), 0)
    edges = cv2.Canny(g, low, high)
    if line_px > 1:
        edges = cv2.dilate(edges, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (line_px, line_px)))
    return cv2.bitwise_not(edges)


class RoiRenderer(Renderer):
    """Binary pins from ROI scanning (seed 001): ``up`` where a section is more than 50 % black.

    Parameters
    ----------
    grid : (int, int)
        Pins (rows, cols); the seed's Dot display is 4x4, the SMA display 8x8.
    hia : int
        ROI side, px (``hia // max(grid)`` px per section).
    edges : bool
        False: scan the thresholded image (``roi``); True: scan thickened Canny edges (``canny``).
    threshold : int
        Gray level below which a pixel is black (``roi``), 1-255.
    canny_low, canny_high : float
        Canny thresholds (``canny``).
    blur_px : int
        Gaussian blur kernel side before Canny, odd.
    line_px : int
        Thickened line width, px.

    Examples
    --------
    >>> img = np.full((64, 64), 255, np.uint8); img[:, :32] = 0      # left half black
    >>> r = RoiRenderer(grid=(4, 4), hia=32).prepare(img)
    >>> out = r.empty(); r.update(32, 32, out)                     # ROI straddles the border
    0
    >>> out[:, 0].reshape(4, 4).astype(int)
    array([[1, 1, 0, 0],
           [1, 1, 0, 0],
           [1, 1, 0, 0],
           [1, 1, 0, 0]])
    """

    fields = ("up",)

    def __init__(self, grid=(4, 4), hia=32, edges=False, threshold=128, canny_low=50.0, canny_high=150.0,
                 blur_px=5, line_px=3):
        super().__init__(grid, hia)
        self.method = "canny" if edges else "roi"
        self.edges = bool(edges)
        if not 1 <= int(threshold) <= 255:
            raise SceneError(f"threshold = {threshold!r} gray levels is outside [1, 255]")
        if not 0 <= canny_low <= canny_high:
            raise SceneError(f"canny thresholds ({canny_low}, {canny_high}) need 0 <= low <= high")
        if int(blur_px) < 1 or int(blur_px) % 2 == 0:
            raise SceneError(f"blur_px = {blur_px!r} must be an odd number of pixels >= 1")
        if int(line_px) < 1:
            raise SceneError(f"line_px = {line_px!r} must be >= 1 px")
        self.threshold = int(threshold)
        self.canny = (float(canny_low), float(canny_high))
        self.blur_px = int(blur_px)
        self.line_px = int(line_px)

    def _prepare(self, image):
        gray = to_gray(image)
        if self.edges:
            self.tactile = canny_lines(gray, *self.canny, blur_px=self.blur_px, line_px=self.line_px)
            mask = (self.tactile == 0).astype(np.uint8)
        else:
            mask = black_mask(gray, self.threshold)
            self.tactile = np.where(mask, 0, 255).astype(np.uint8)
        self.black = mask
        self.S_black = cv2.integral(mask, sdepth=cv2.CV_64F)

    def _update(self, r0, c0, out):
        R, C = self.grid
        return _k.roi_update(self.S_black, r0, c0, R, C, self.cell, out)

    def images(self):
        return {"tactile": self.tactile}
