"""Frequency rendering (seed 003): tactile image, then pin frequency from the mean gray.

Tactile image (seed 003, Fig. 2): gray -> histogram stretch to 0-255 -> multiply by itself
(renormalised, ``s * s / 255``, so black stays 0 and white 255 while the mid-tones darken and
boundaries sharpen) -> closing (dilate, then erode: removes the noise the product exposes and
restores the boundaries) -> Sobel gradient magnitude. Gray in the tactile image stands for the
change of surface height: 0 flat, 255 steep.

Pins (Eq. 1): ``f_p = f_pmax g / 255`` with ``g`` the mean tactile gray of the pin's
``cell x cell`` pixels (11 x 11 of a 33 x 33 HIA on the seed's 3x3 array) and ``f_pmax < 150 Hz``
(below 150 Hz a higher frequency at the same stroke feels stronger). The pins are driven with
pulse trains at ``f_p`` (fixed stroke; ``f_p = 0`` leaves a pin at rest).
"""

from __future__ import annotations

import cv2
import numpy as np

from rtctl.errors import SceneError
from rtctl.render import _kernels as _k
from rtctl.render.hia import Renderer
from rtctl.render.image import to_gray

__all__ = ["FrequencyRenderer", "tactile_image", "stretch", "self_multiply"]


def stretch(gray) -> np.ndarray:
    """Histogram stretch: linear map of ``[min, max]`` onto ``[0, 255]``; a flat image gives 0."""
    return cv2.normalize(gray, None, 0, 255, cv2.NORM_MINMAX, dtype=cv2.CV_8U)


def self_multiply(img) -> np.ndarray:
    """``round(img * img / 255)``, uint8: the image multiplied by itself, renormalised to 0-255."""
    return cv2.multiply(img, img, scale=1.0 / 255.0)


def tactile_image(gray, close_px=3, sobel_scale=0.25) -> np.ndarray:
    """The seed-003 tactile image of an 8-bit gray image; uint8, shape (H, W).

    Parameters
    ----------
    gray : ndarray, uint8, shape (H, W)
    close_px : int
        Side of the square closing element, px (1 skips the closing).
    sobel_scale : float
        Gradient magnitude (3x3 Sobel, gray levels) times this, saturated to 255. The default
        1/4 undoes the Sobel kernel's gain of 4, so a black-white step gives 255 and the gray is
        the height change per pixel.

    Examples
    --------
    >>> g = np.zeros((16, 16), np.uint8); g[:, 8:] = 200       # one vertical step
    >>> tactile_image(g)[8, 6:10]
    array([  0, 255, 255,   0], dtype=uint8)
    """
    m = self_multiply(stretch(gray))
    if close_px > 1:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_RECT, (close_px, close_px)))
    gx = cv2.Sobel(m, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(m, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.convertScaleAbs(cv2.magnitude(gx, gy), alpha=sobel_scale)


class FrequencyRenderer(Renderer):
    """Pin frequencies from the tactile image (seed 003): ``f_p = f_pmax * g / 255``.

    Parameters
    ----------
    grid : (int, int)
        Pins (rows, cols); seed 003: 3x3.
    hia : int
        HIA side, px; seed 003: 33 (11 px per pin).
    f_pmax : float
        Frequency of a pin whose pixels are all 255, Hz, ``0 < f_pmax < 150``.
    close_px : int
        Closing element side, px.
    sobel_scale : float
        See :func:`tactile_image`.

    Examples
    --------
    >>> img = np.zeros((99, 99), np.uint8); img[:, 50:] = 255   # a vertical edge at x = 49.5
    >>> r = FrequencyRenderer(f_pmax=140.0).prepare(img)
    >>> out = r.empty(); r.update(49, 49, out)
    0
    >>> out[:, 1].reshape(3, 3).round(1)                          # 2 of 11 columns are edge
    array([[ 0. , 25.5,  0. ],
           [ 0. , 25.5,  0. ],
           [ 0. , 25.5,  0. ]])
    """

    method = "frequency"
    fields = ("freq_hz",)

    def __init__(self, grid=(3, 3), hia=33, f_pmax=140.0, close_px=3, sobel_scale=0.25):
        super().__init__(grid, hia)
        if not 0.0 < f_pmax < 150.0:
            raise SceneError(f"f_pmax = {f_pmax!r} Hz is outside (0, 150) Hz (seed 003: f_pmax < 150 Hz)")
        if int(close_px) < 1:
            raise SceneError(f"close_px = {close_px!r} must be >= 1 px")
        if not sobel_scale > 0.0:
            raise SceneError(f"sobel_scale = {sobel_scale!r} must be > 0")
        self.f_pmax = float(f_pmax)
        self.close_px = int(close_px)
        self.sobel_scale = float(sobel_scale)

    def _prepare(self, image):
        self.tactile = tactile_image(to_gray(image), self.close_px, self.sobel_scale)
        self.S_tactile = cv2.integral(self.tactile, sdepth=cv2.CV_64F)

    def _update(self, r0, c0, out):
        R, C = self.grid
        return _k.frequency_update(self.S_tactile, r0, c0, R, C, self.cell, self.f_pmax, out)

    def images(self):
        return {"tactile": self.tactile}
