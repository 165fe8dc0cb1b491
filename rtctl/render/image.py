"""Loading and validating images for rendering: one clear line for every bad input.

Accepted: 8-bit grayscale or 8-bit colour (BGR, as OpenCV reads it) images with both sides
between :data:`MIN_SIDE` and :data:`MAX_SIDE` pixels and at most :data:`MAX_PIXELS` pixels.
Everything else raises :class:`ImageError` naming the file, what is wrong and how to fix it.
"""

from __future__ import annotations

import os
import stat
import warnings

import cv2
import numpy as np

from rtctl.errors import RtctlError

__all__ = ["ImageError", "load_image", "check_image", "to_gray", "MIN_SIDE", "MAX_SIDE", "MAX_PIXELS"]

#: Smallest side accepted, px: the 5x5 Gaussian and the 3x3 Sobel/closing kernels need an interior.
MIN_SIDE = 8
#: Largest side, px (OpenCV's own decoder limit is 2**30 pixels in total).
MAX_SIDE = 16384
#: Largest image, pixels: 64 Mpx is 64 MB per 8-bit plane and ~1.5 GB for all the maps a beat
#: renderer keeps (labels, summed-area tables); larger images should be downscaled first.
MAX_PIXELS = 1 << 26

#: What a path that is not a regular file is, in the words of ``ls -l``'s type letters.
_KINDS = {stat.S_IFIFO: "a FIFO (named pipe)", stat.S_IFCHR: "a character device", stat.S_IFBLK: "a block device",
          stat.S_IFSOCK: "a socket"}


class ImageError(RtctlError, ValueError):
    """An image cannot be rendered: the message names the file, the cause and the fix."""


def load_image(path) -> np.ndarray:
    """Read an image file as 8-bit gray ``(H, W)`` or 8-bit BGR ``(H, W, 3)``.

    Parameters
    ----------
    path : str or os.PathLike
        A format both Pillow (which reads the header) and OpenCV (which decodes) know: PNG,
        JPEG, BMP, TIFF, GIF, WebP, PPM/PGM, ...

    Returns
    -------
    ndarray, uint8, shape (H, W) or (H, W, 3)

    Raises
    ------
    ImageError
        Missing file, empty file, not an image, 16-bit, with an alpha channel, too small or too
        large.

    Examples
    --------
    >>> from matplotlib import cbook
    >>> load_image(cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)).shape
    (600, 512, 3)
    """
    p = os.fspath(path)
    if not os.path.exists(p):
        raise ImageError(f"{p}: no such file; give the path of an image file")
    if os.path.isdir(p):
        raise ImageError(f"{p}: is a directory, not an image file")
    mode = os.stat(p).st_mode
    if not stat.S_ISREG(mode):  # a FIFO or a device would block a read or report 0 bytes
        raise ImageError(f"{p}: is {_KINDS.get(stat.S_IFMT(mode), 'not a regular file')}, not an image file; "
                         "give a regular image file")
    size = os.path.getsize(p)
    if size == 0:
        raise ImageError(f"{p}: file is empty (0 bytes); give an image file")
    fmt, mode = _check_header(p)
    if fmt == "JPEG":
        _check_jpeg_end(p)
    if mode == "CMYK":  # OpenCV reads its four planes as if the fourth were alpha
        raise ImageError(f"{p}: CMYK colour (print separations); save it as RGB or grayscale")
    if mode in ("LA", "La"):  # OpenCV hands gray + alpha over as four planes: it would pass for RGBA
        raise ImageError(f"{p}: gray with an alpha channel (LA); flatten it onto a background and save it as "
                         "8-bit gray without alpha (e.g. PIL.Image.open(f).convert('L'))")
    # IMREAD_UNCHANGED keeps 16-bit depth and the alpha channel so we can refuse them plainly
    # instead of letting OpenCV silently convert them.
    try:
        img = cv2.imread(p, cv2.IMREAD_UNCHANGED)
    except cv2.error as e:  # e.g. an allocation the header asked for failed
        why = str(e).strip().splitlines()[-1].split("error: ", 1)[-1]
        raise ImageError(f"{p}: OpenCV cannot decode it ({why}); give a PNG, JPEG, BMP or TIFF file") from None
    if img is None:
        raise ImageError(f"{p}: not an image OpenCV can read; give a PNG, JPEG, BMP or TIFF file")
    return check_image(img, name=p)


def _check_header(p: str) -> tuple[str | None, str | None]:
    """Refuse huge images from the header alone, before decoding allocates the pixels; return
    the format and mode Pillow found. A file whose header Pillow cannot read is refused too:
    OpenCV reads some formats Pillow does not (Radiance HDR, PAM, PFM), and would allocate
    whatever size their header claims before finding the pixels missing."""
    try:
        from PIL import Image  # matplotlib depends on Pillow; it reads sizes without decoding
    except ImportError:  # pragma: no cover - then the decoded array is checked instead
        return None, None
    try:
        # a damaged header makes Pillow warn (e.g. "Tag data larger than file"): a warning would
        # print lines of its own; the decoder below decides whether the file is readable
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(p) as im:
                w, h, fmt, mode = *im.size, im.format, im.mode
    except Image.DecompressionBombError:  # over twice Pillow's own limit, far above ours
        raise ImageError(f"{p}: its header declares over {2 * Image.MAX_IMAGE_PIXELS >> 20} Mpx, too large "
                         f"(limit {MAX_SIDE} px a side and {MAX_PIXELS >> 20} Mpx); downscale it first") from None
    except Exception:
        raise ImageError(f"{p}: not an image rtctl can read (no known image header); give a PNG, JPEG, BMP "
                         "or TIFF file") from None
    _check_size(h, w, p)
    return fmt, mode


def _check_jpeg_end(p: str) -> None:
    """A JPEG cut short decodes without error in OpenCV, its missing rows flat gray: refuse it.
    The image ends with an EOI marker (FF D9) after its last start-of-scan (FF DA); marker bytes
    cannot occur inside the scan data (an FF there is stuffed as FF 00)."""
    with open(p, "rb") as f:
        data = f.read()
    if data.rfind(b"\xff\xd9") < data.rfind(b"\xff\xda"):
        raise ImageError(f"{p}: truncated JPEG (its data ends before the end-of-image marker); give the "
                         "whole file")


def _check_size(h: int, w: int, name: str) -> None:
    if h < MIN_SIDE or w < MIN_SIDE:
        raise ImageError(f"{name}: {w}x{h} px is too small; images need at least {MIN_SIDE} px on each side")
    if h > MAX_SIDE or w > MAX_SIDE or h * w > MAX_PIXELS:
        raise ImageError(f"{name}: {w}x{h} px is too large (limit {MAX_SIDE} px a side and {MAX_PIXELS >> 20} Mpx); "
                         "downscale it first")


def check_image(img, name: str = "image") -> np.ndarray:
    """Validate an image array and return it C-contiguous.

    Parameters
    ----------
    img : ndarray, uint8, shape (H, W), (H, W, 1) or (H, W, 3)
        Gray or BGR. ``bool`` arrays are taken as black (False) / white (True).
    name : str
        How messages refer to the image.

    Returns
    -------
    ndarray, uint8, shape (H, W) or (H, W, 3)
    """
    img = np.asarray(img)
    if img.dtype == np.bool_:
        img = img.astype(np.uint8) * 255
    if img.size == 0:
        raise ImageError(f"{name}: image is empty (shape {img.shape}); give a non-empty image")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.shape[2] == 4:
        raise ImageError(f"{name}: has an alpha channel (RGBA); flatten it onto a background "
                         "(e.g. cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)) and save it without alpha")
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise ImageError(f"{name}: shape {img.shape} is not a gray (H, W) or colour (H, W, 3) image")
    if img.dtype != np.uint8:
        bits = 8 * img.dtype.itemsize
        kind = {"f": "float ", "i": "signed "}.get(img.dtype.kind, "")
        raise ImageError(f"{name}: {bits}-bit {kind}pixels; rendering needs "
                         "8-bit images: convert it (e.g. cv2.convertScaleAbs(img, alpha=255 / img.max()))")
    _check_size(img.shape[0], img.shape[1], name)
    return np.ascontiguousarray(img)


def to_gray(img) -> np.ndarray:
    """8-bit gray ``(H, W)`` from a validated gray or BGR image (ITU-R 601 luma, as OpenCV)."""
    img = check_image(img)
    if img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return img
