"""Beat rendering (seed 004): beat frequency from blobs, carrier from edge blobs, amplitude from
the gray variance.

Preprocessing (once per image):

* binary image (Otsu, or a fixed threshold) -> label the black blobs (8-connected) -> a blob is
  *valid* when its area is at least ``min_blob_area`` (12.6 mm^2, the mean receptive field of a
  Meissner corpuscle: smaller blobs cannot be resolved by the finger);
* Sobel gradient magnitude of the gray image -> binarize (Otsu) -> label the white edge blobs
  (valid when at least ``min_edge_area``, default 0: all);
* summed-area tables of gray and gray^2 (variance of any rectangle in O(1));
* the normalising counts. Valid blobs (``normalize="field"``, the default): the most valid
  blobs that can stimulate the finger in one unit, its area over the 12.6 mm^2 receptive field,
  ``n_max = floor(unit area / min_blob_area)``. The packing: receptive fields tile the skin under
  the unit without gaps or overlap (density 1), one blob per field; this is the most blobs of
  at least that area that fit in the unit's area at all (real blobs need gaps, so the count an
  image reaches is lower). A unit holding more (blobs straddling its edge count) clips to 1.
  With it, a texture gives the same beat frequency in any image. ``normalize="image"`` instead
  takes the largest count found in any unit-sized window of this image (sampled on a grid of a
  quarter unit): every image then reaches the top of the band at its densest place, one blob or
  forty. Edge blobs have no size bound (``min_edge_area`` 0) and no physiological maximum: their
  count is normalised by the image's largest in either mode (seed 004: "the number of maximum
  valid edge blobs in the HIA").

Per unit (the whole HIA by default, or blocks of cells) in each update (Eqs. 1-3)::

    f_b = alpha (f_bb (f_h - f_l) + f_l),        f_bb = n_valid / n_valid_max   (0.3 - 40 Hz)
    f_c = alpha (f_eb (f_ph - f_pl) + f_pl),     f_eb = n_edge / n_edge_max     (40 - 400 Hz)
    A_c = 1 - 1 / (1 + amp_scale var)

and each pair of neighbouring cells (columns 2k, 2k + 1) is driven at ``f_c -+ f_b / 2``, so the
film between them vibrates at the carrier ``f_c`` under a beat envelope ``f_b`` (seed 004: 100 +
110 Hz gives a 10 Hz beat on a 105 Hz carrier).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from rtctl.errors import SceneError
from rtctl.render import _kernels as _k
from rtctl.render.hia import Renderer
from rtctl.render.image import to_gray

__all__ = ["BeatRenderer", "blob_labels", "edge_image", "beat_frequency", "carrier_frequency",
           "carrier_amplitude", "MEISSNER_FIELD_M2", "NORMALIZE"]

#: Mean receptive field of a Meissner corpuscle, m^2 (seed 004: 12.6 mm^2).
MEISSNER_FIELD_M2 = 12.6e-6
#: How valid-blob counts are normalised: by the physiological maximum per unit, or by the image's.
NORMALIZE = ("field", "image")


def beat_frequency(f_bb, alpha=1.0, f_l=0.3, f_h=40.0):
    """Seed 004 Eq. (1): ``alpha (f_bb (f_h - f_l) + f_l)``, Hz, ``f_bb`` in [0, 1]."""
    return alpha * (np.asarray(f_bb) * (f_h - f_l) + f_l)


def carrier_frequency(f_eb, alpha=1.0, f_pl=40.0, f_ph=400.0):
    """Seed 004 Eq. (2): ``alpha (f_eb (f_ph - f_pl) + f_pl)``, Hz, ``f_eb`` in [0, 1]."""
    return alpha * (np.asarray(f_eb) * (f_ph - f_pl) + f_pl)


def carrier_amplitude(var, amp_scale):
    """Seed 004 Eq. (3): ``1 - 1 / (1 + amp_scale var)``, var in gray levels^2."""
    return 1.0 - 1.0 / (1.0 + amp_scale * np.asarray(var, dtype=float))


def blob_labels(mask, px_size, min_area):
    """Label the nonzero blobs of ``mask`` (8-connected) and flag those of at least ``min_area``.

    Parameters
    ----------
    mask : ndarray, uint8, shape (H, W)
        Nonzero pixels belong to blobs.
    px_size : float
        Side of one pixel, m.
    min_area : float
        Smallest valid blob area, m^2 (``area_px * px_size**2 >= min_area``, with a relative
        tolerance of 1e-9 so that a blob exactly at the limit is valid despite rounding).

    Returns
    -------
    labels : ndarray, int32, shape (H, W)
        0 background, 1..n-1 blobs.
    valid : ndarray, uint8, shape (n,)
        1 for valid blobs; ``valid[0] = 0``.
    areas : ndarray, int64, shape (n,)
        Blob areas, px.
    """
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8, ltype=cv2.CV_32S)
    areas = stats[:, cv2.CC_STAT_AREA].astype(np.int64)
    valid = (areas * px_size ** 2 >= min_area * (1.0 - 1e-9)).astype(np.uint8)
    valid[0] = 0
    return labels, valid, areas


def edge_image(gray, sobel_scale=0.25) -> np.ndarray:
    """Sobel gradient magnitude of ``gray`` times ``sobel_scale``, saturated to uint8."""
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.convertScaleAbs(cv2.magnitude(gx, gy), alpha=sobel_scale)


def _binarize(img, threshold, inverse):
    mode = cv2.THRESH_BINARY_INV if inverse else cv2.THRESH_BINARY
    if threshold is None:
        _, m = cv2.threshold(img, 0, 1, mode | cv2.THRESH_OTSU)
    else:
        # black is gray < threshold (as ROI scanning), i.e. not (gray > threshold - 1)
        _, m = cv2.threshold(img, threshold - 1, 1, mode)
    return m


class BeatRenderer(Renderer):
    """Beat, carrier and amplitude per unit of cells, cell pairs at ``f_c -+ f_b / 2`` (seed 004).

    Parameters
    ----------
    grid : (int, int)
        Cells (rows, cols); seed 004's PVDF array is 6x8.
    hia : int
        HIA side (of the longer grid side), px.
    px_size : float, optional
        Side of one image pixel on the display, m. Default ``pitch / cell``: the image is felt
        at the display's scale.
    pitch : float
        Cell pitch, m (seed 004: 1.5 mm); only sets the default ``px_size``.
    min_blob_area : float
        Smallest valid binary blob, m^2 (seed 004: 12.6 mm^2).
    min_edge_area : float
        Smallest valid edge blob, m^2 (default 0: every edge blob counts).
    beat_band, carrier_band : (float, float)
        ``(f_l, f_h)`` = (0.3, 40) Hz (Merkel and Meissner) and ``(f_pl, f_ph)`` = (40, 400) Hz
        (Pacinian).
    alpha : float
        Scale factor of Eqs. (1) and (2).
    amp_scale : float
        ``a`` of Eq. (3), per gray level^2; the default 1/1024 gives ``A_c = 1/2`` at a gray
        standard deviation of 32 levels (the seed gives no value).
    threshold : int, optional
        Gray level below which a pixel is black; default Otsu's threshold of the image.
    unit : (int, int), optional
        Cells per unit sharing one (f_b, f_c, A_c); default the whole HIA (seed 004). Must
        divide the grid; its column count must be even unless it spans all columns (pairs may
        not straddle units).
    normalize : str
        ``"field"`` (default): valid blobs over the physiological maximum, the unit's area over
        ``min_blob_area`` (see module); ``"image"``: over the image's own densest unit window.
        Edge blobs: over the image's densest window either way.
    max_count : (int, int), optional
        Normalising counts (valid blobs, edge blobs), overriding ``normalize``.
    sobel_scale : float
        Gradient scale of the edge image (see :func:`edge_image`).

    Examples
    --------
    >>> img = np.full((96, 96), 255, np.uint8)
    >>> img[20:40, 10:30] = 0; img[60:80, 60:80] = 0       # two 20 x 20 px black squares
    >>> r = BeatRenderer(grid=(2, 2), hia=96, px_size=0.25e-3).prepare(img)
    >>> int(r.areas[1]), r.max_count        # 400 px = 25 mm^2 each; 576 mm^2 / 12.6 mm^2 = 45.7
    (400, (45, 2))
    >>> out = r.empty(); r.update(48, 48, out)
    0
    >>> out[0, 1:4].round(3)                # freq, beat, carrier of cell (0, 0): f_b = 0.3 + 2/45 39.7
    array([398.968,   2.064, 400.   ])
    >>> r = BeatRenderer(grid=(2, 2), hia=96, px_size=0.25e-3, normalize="image").prepare(img)
    >>> r.update(48, 48, out), r.max_count, float(out[0, 2])  # the image's own densest window: 2
    (0, (2, 2), 40.0)
    """

    method = "beat"
    fields = ("freq_hz", "beat_hz", "carrier_hz", "amplitude")

    def __init__(self, grid=(6, 8), hia=96, px_size=None, pitch=1.5e-3, min_blob_area=MEISSNER_FIELD_M2,
                 min_edge_area=0.0, beat_band=(0.3, 40.0), carrier_band=(40.0, 400.0), alpha=1.0,
                 amp_scale=1.0 / 1024.0, threshold=None, unit=None, max_count=None, sobel_scale=0.25,
                 normalize="field"):
        super().__init__(grid, hia)
        R, C = self.grid
        if px_size is None:
            if not pitch > 0.0:
                raise SceneError(f"pitch = {pitch!r} m must be > 0")
            px_size = pitch / self.cell
        if not (px_size > 0.0 and np.isfinite(px_size)):
            raise SceneError(f"px_size = {px_size!r} m must be > 0 (beat rendering needs the pixel size: --mm-per-px)")
        for name, v in (("min_blob_area", min_blob_area), ("min_edge_area", min_edge_area)):
            if not v >= 0.0:
                raise SceneError(f"{name} = {v!r} m^2 must be >= 0")
        for name, (lo, hi) in (("beat_band", beat_band), ("carrier_band", carrier_band)):
            if not 0.0 <= lo <= hi:
                raise SceneError(f"{name} = ({lo}, {hi}) Hz needs 0 <= low <= high")
        if not alpha > 0.0 or not amp_scale >= 0.0:
            raise SceneError(f"alpha = {alpha!r} must be > 0 and amp_scale = {amp_scale!r} >= 0")
        if threshold is not None and not 1 <= int(threshold) <= 255:
            raise SceneError(f"threshold = {threshold!r} gray levels is outside [1, 255]")
        ur, uc = (R, C) if unit is None else (int(unit[0]), int(unit[1]))
        if ur < 1 or uc < 1 or R % ur or C % uc:
            raise SceneError(f"unit = {unit!r} cells must divide the grid {R}x{C}")
        if uc % 2 and uc != C:
            raise SceneError(f"unit = {unit!r}: an odd number of columns would split a cell pair; "
                             "use an even column count or the full width")
        if normalize not in NORMALIZE:
            raise SceneError(f"normalize = {normalize!r}: use one of {', '.join(NORMALIZE)}")
        if normalize == "field" and max_count is None and not min_blob_area > 0.0:
            raise SceneError("min_blob_area = 0 m^2 leaves no physiological maximum of blobs per unit; "
                             "use normalize='image' or give max_count")
        self.normalize = normalize
        self.unit = (ur, uc)
        self.px_size = float(px_size)
        self.min_blob_area = float(min_blob_area)
        self.min_edge_area = float(min_edge_area)
        self.threshold = None if threshold is None else int(threshold)
        self.sobel_scale = float(sobel_scale)
        self._max_count_given = None if max_count is None else (int(max_count[0]), int(max_count[1]))
        self.params = np.array([alpha, beat_band[0], beat_band[1], carrier_band[0], carrier_band[1], amp_scale,
                                0.0, 0.0])
        self.tick = np.zeros(1, dtype=np.int64)

    def _prepare(self, image):
        gray = to_gray(image)
        self.gray = gray
        self.binary = _binarize(gray, self.threshold, inverse=True)  # 1 = black
        self.labels, self.valid, self.areas = blob_labels(self.binary, self.px_size, self.min_blob_area)
        self.edges = edge_image(gray, self.sobel_scale)
        self.edge_mask = _binarize(self.edges, None, inverse=False)  # 1 = edge
        self.edge_labels, self.edge_valid, self.edge_areas = blob_labels(self.edge_mask, self.px_size,
                                                                         self.min_edge_area)
        # per-pixel validity maps: what an update scans (no per-pixel lookup of the flags)
        self.vlab = np.where(self.valid[self.labels] != 0, self.labels, 0).astype(np.int32)
        self.edge_vlab = np.where(self.edge_valid[self.edge_labels] != 0, self.edge_labels, 0).astype(np.int32)
        self.S_gray, self.S_gray2 = cv2.integral2(gray, sdepth=cv2.CV_64F, sqdepth=cv2.CV_64F)
        self.stamp_b = _k.stamp_array(self.valid.size)
        self.stamp_e = _k.stamp_array(self.edge_valid.size)
        self.tick[0] = 0
        if self._max_count_given is None:
            h, w = self.unit[0] * self.cell, self.unit[1] * self.cell
            sr, sc = max(1, h // 4), max(1, w // 4)
            if self.normalize == "field":
                nb = self.field_max_count()
            else:
                nb = _k.max_window_count(self.vlab, _k.stamp_array(self.valid.size), h, w, sr, sc)
            ne = _k.max_window_count(self.edge_vlab, _k.stamp_array(self.edge_valid.size), h, w, sr, sc)
            self.max_count = (int(nb), int(ne))
        else:
            self.max_count = self._max_count_given
        self.params[6] = 1.0 / self.max_count[0] if self.max_count[0] > 0 else 0.0
        self.params[7] = 1.0 / self.max_count[1] if self.max_count[1] > 0 else 0.0

    def field_max_count(self) -> int:
        """The most valid blobs one unit can hold: its area on the display over ``min_blob_area``
        (receptive fields tiling it, one blob each; see the module), at least 1."""
        area = self.unit[0] * self.cell * self.unit[1] * self.cell * self.px_size ** 2
        return max(1, int(math.floor(area / self.min_blob_area * (1.0 + 1e-12))))

    def _update(self, r0, c0, out):
        R, C = self.grid
        return _k.beat_update(self.S_gray, self.S_gray2, self.vlab, self.edge_vlab, self.stamp_b, self.stamp_e,
                              self.tick, r0, c0, R, C, self.cell,
                              self.unit[0], self.unit[1], self.params, out)

    def images(self):
        valid_px = self.valid[self.labels] != 0
        blobs = np.full(self.gray.shape + (3,), 255, np.uint8)
        blobs[self.binary != 0] = (160, 160, 160)  # dropped blobs light gray
        blobs[valid_px] = (0, 0, 0)                # valid blobs black
        return {"binary": np.where(self.binary != 0, 0, 255).astype(np.uint8), "edges": self.edges,
                "edge_blobs": (self.edge_mask * 255).astype(np.uint8), "blobs": blobs}
