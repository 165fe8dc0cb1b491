"""Bad images give one clear error (through the CLI's ``main``); the CLI's outputs; doctests."""

import doctest
import importlib
import json
import subprocess
import sys

import cv2
import numpy as np
import pytest
from matplotlib import cbook

from rtctl.errors import RtctlError
from rtctl.render import image as image_mod
from rtctl.render.cli import main
from rtctl.render.image import ImageError, check_image, load_image

HOPPER = cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)
RGBA_PNG = cbook.get_sample_data("Minduka_Present_Blue_Pack.png", asfileobj=False)  # shipped, 4 channels


def _png(path, arr):
    assert cv2.imwrite(str(path), arr)
    return str(path)


def _bad_files(tmp):
    (tmp / "empty.png").write_bytes(b"")
    (tmp / "notes.png").write_text("this is not an image\n")
    (tmp / "trunc.png").write_bytes(open(HOPPER, "rb").read()[:40])  # a JPEG cut after its header
    return {
        "missing": (str(tmp / "nope.png"), ["no such file"]),
        "directory": (str(tmp), ["is a directory"]),
        "empty": (str(tmp / "empty.png"), ["empty", "0 bytes"]),
        "not-an-image": (str(tmp / "notes.png"), ["not an image"]),
        "truncated": (str(tmp / "trunc.png"), ["not an image"]),
        "1x1": (_png(tmp / "one.png", np.zeros((1, 1), np.uint8)), ["1x1 px is too small", "at least 8"]),
        "16-bit": (_png(tmp / "deep.png", np.full((20, 20), 40000, np.uint16)), ["16-bit", "8-bit"]),
        "rgba": (RGBA_PNG, ["alpha channel", "RGBA"]),
        "huge": (_png(tmp / "long.png", np.zeros((8, 16385), np.uint8)), ["16385x8 px is too large", "downscale"]),
    }


CASES = ["missing", "directory", "empty", "not-an-image", "truncated", "1x1", "16-bit", "rgba", "huge"]


@pytest.mark.parametrize("case", CASES)
def test_bad_image_raises_one_line_through_main(tmp_path, case):
    path, words = _bad_files(tmp_path)[case]
    with pytest.raises(ImageError) as e:
        main([path, "--method", "roi", "--json"])
    msg = str(e.value)
    assert isinstance(e.value, RtctlError) and isinstance(e.value, ValueError)
    assert "\n" not in msg and path in msg
    for w in words:
        assert w in msg, (w, msg)


def test_too_many_pixels_from_the_header(tmp_path, monkeypatch):
    # the pixel-count limit applies before decoding (read from the header): lower it to test
    monkeypatch.setattr(image_mod, "MAX_PIXELS", 512 * 512)
    with pytest.raises(ImageError, match="512x600 px is too large"):
        main([HOPPER, "--method", "frequency"])


def test_wrapper_prints_one_line_and_exits_2(tmp_path):
    p = subprocess.run([sys.executable, "-m", "rtctl.render.cli", str(tmp_path / "nope.png")],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    assert p.stderr.strip().splitlines() == [f"rtctl: error: {tmp_path / 'nope.png'}: no such file; "
                                             "give the path of an image file"]


@pytest.mark.parametrize("arr, words", [
    (np.zeros((0, 10), np.uint8), ["empty"]),
    (np.zeros((10, 10), np.float32), ["32-bit float", "8-bit"]),
    (np.zeros((10, 10, 2), np.uint8), ["(10, 10, 2)"]),
    (np.zeros((10, 10, 4), np.uint8), ["alpha channel"]),
], ids=["empty", "float", "two-channel", "rgba"])
def test_bad_arrays(arr, words):
    with pytest.raises(ImageError) as e:
        check_image(arr)
    for w in words:
        assert w in str(e.value)


def test_good_images_load_as_8_bit():
    img = load_image(HOPPER)
    assert img.shape == (600, 512, 3) and img.dtype == np.uint8
    assert check_image(np.ones((8, 8), bool)).max() == 255  # bool: True is white


@pytest.mark.parametrize("method, fields", [
    ("roi", {"up"}), ("canny", {"up"}), ("frequency", {"freq_hz"}),
    ("beat", {"freq_hz", "beat_hz", "carrier_hz", "amplitude"}),
])
def test_cli_json_and_images(tmp_path, capsys, method, fields):
    assert main([HOPPER, "--method", method, "--at", "250,300", "--json", "--out", str(tmp_path)]) == 0
    d = json.loads(capsys.readouterr().out)
    R, C = d["grid"]
    assert len(d["pins"]) == R * C
    assert [(p["row"], p["col"]) for p in d["pins"]] == [(i, j) for i in range(R) for j in range(C)]
    assert all(set(p) == {"row", "col"} | fields for p in d["pins"])
    names = {f.rsplit("/", 1)[-1] for f in d["files"]}
    assert "hia.png" in names and ("tactile.png" in names or "binary.png" in names)
    if method == "beat":
        assert {"edges.png", "blobs.png"} <= names and d["mm_per_px"] == pytest.approx(0.125)
    for f in d["files"]:
        assert cv2.imread(f) is not None
    hia = cv2.imread(str(tmp_path / "hia.png"))
    assert hia.shape == (600, 512, 3)


def test_cli_options(capsys):
    assert main([HOPPER, "--method", "beat", "--grid", "2x4", "--hia", "40", "--mm-per-px", "0.5", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["grid"] == [2, 4] and d["cell_px"] == 10 and d["mm_per_px"] == 0.5
    assert d["at"] == [255.5, 299.5]  # default: image centre
    from rtctl.errors import SceneError

    with pytest.raises(SceneError, match="--mm-per-px applies to --method beat only"):
        main([HOPPER, "--method", "roi", "--mm-per-px", "0.1"])
    with pytest.raises(SceneError, match="smaller than the grid"):
        main([HOPPER, "--method", "roi", "--hia", "3"])


MODULES = ["rtctl.render.image", "rtctl.render.hia", "rtctl.render.factory", "rtctl.render.roi",
           "rtctl.render.frequency", "rtctl.render.beat", "rtctl.render.path", "rtctl.render.braille",
           "rtctl.render.shapes"]


@pytest.mark.parametrize("name", MODULES)
def test_examples(name):
    res = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert res.failed == 0 and res.attempted > 0
