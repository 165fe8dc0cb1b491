"""Fuzzing the image loader (rtctl.render.image.load_image, behind ``rtctl render`` and
``stimulus.image``): small valid files of every format OpenCV and Pillow share, then cut short,
bytes flipped, header fields overwritten with lying sizes, junk spliced in. Each file loads as an
8-bit gray or BGR image within the size limits, or is one :class:`ImageError` line naming it.
The hand-made cases (decompression bombs, huge headers, odd bit depths) are tests/corpus/image."""

import io
import struct

import cv2
import numpy as np
from fuzzing import clean_or_clear, fuzz, run_cli
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image

from rtctl.render.image import MAX_PIXELS, MAX_SIDE, MIN_SIDE, ImageError, load_image


def _seeds():
    rng = np.random.default_rng(0)
    gray = rng.integers(0, 256, (24, 32), dtype=np.uint8)
    bgr = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    out = {}
    for ext in (".png", ".jpg", ".bmp", ".tiff", ".ppm"):
        g = ".pgm" if ext == ".ppm" else ext  # PPM is colour; its gray sibling is PGM
        out["gray" + g] = cv2.imencode(g, gray)[1].tobytes()
        out["bgr" + ext] = cv2.imencode(ext, bgr)[1].tobytes()
    out["deep.png"] = cv2.imencode(".png", gray.astype(np.uint16) * 257)[1].tobytes()
    for mode, fmt in (("P", "GIF"), ("1", "PNG"), ("LA", "PNG"), ("F", "TIFF"), ("CMYK", "JPEG")):
        b = io.BytesIO()
        Image.fromarray(gray).convert(mode).save(b, format=fmt)
        out[f"{mode}.{fmt.lower()}"] = b.getvalue()
    return out


SEEDS = _seeds()


@st.composite
def damaged(draw):
    name = draw(st.sampled_from(sorted(SEEDS)))
    data = bytearray(SEEDS[name])
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, len(data)))
        op = draw(st.sampled_from(["cut", "flip", "lie", "lie", "junk"]))
        if op == "cut":
            data = data[:i]
        elif op == "flip" and i < len(data):
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "lie":  # a width, height or length field: early bytes hold the headers
            i = draw(st.integers(0, min(len(data), 64)))
            size = draw(st.sampled_from([0, 1, 7, 8, 255, 16384, 16385, 65535, 2**31 - 1, 2**32 - 1])
                        | st.integers(0, 2**32 - 1))
            data[i:i + 4] = struct.pack(draw(st.sampled_from([">I", "<I"])), size)
        elif op == "junk":
            data[i:i] = draw(st.binary(max_size=16))
    return name, bytes(data)


@fuzz(200)
@given(damaged())
def test_damaged_images_load_as_8_bit_or_give_one_line(tmp_path_factory, case):
    name, data = case
    path = tmp_path_factory.mktemp("img") / name
    path.write_bytes(data)
    img = clean_or_clear(load_image, path, errors=ImageError, names=[str(path)])
    if not isinstance(img, ImageError):
        assert img.dtype == np.uint8 and (img.ndim == 2 or img.shape[2] == 3), (img.dtype, img.shape)
        h, w = img.shape[:2]
        assert MIN_SIDE <= h <= MAX_SIDE and MIN_SIDE <= w <= MAX_SIDE and h * w <= MAX_PIXELS


@fuzz(40)
@given(st.binary(max_size=300), st.sampled_from([".png", ".jpg", ".bmp", ".tiff", ".gif", ""]))
def test_random_bytes_are_not_an_image(tmp_path_factory, data, ext):
    path = tmp_path_factory.mktemp("img") / f"random{ext}"
    path.write_bytes(data)
    clean_or_clear(load_image, path, errors=ImageError, names=[str(path)])


@fuzz(15)
@given(damaged())
def test_damaged_images_through_rtctl_render_exit_0_or_2(tmp_path_factory, case):
    name, data = case
    path = tmp_path_factory.mktemp("img") / name
    path.write_bytes(data)
    status, _, _ = run_cli(["render", str(path), "--method", "roi", "--json"])
    assert status in (0, 2)
