"""Rendered stimuli in the loop: image, Braille and shape scenes drive the channels the renderer
says, through pulse trains (levels, pin frequencies) or the oscillator bank (beat)."""

import cv2
import numpy as np
import pytest
from test_rig import drive_of

from rtctl import scene
from rtctl.engine.rig import build
from rtctl.needs import needs
from rtctl.render.braille import braille_frames
from rtctl.render.factory import make_renderer

GROUP = """
[scene]
name = "stim"
[timing]
duration = 0.5
[[actuator]]
name = "pins"
type = "bimorph"
grid = [4, 4]
max_voltage = 50.0
[actuator.beam]
length = 15.0e-3
width = 1.5e-3
layers = [{material = "PZT-5A", thickness = 0.3e-3}, {material = "PZT-5A", thickness = 0.3e-3}]
"""


def test_braille_pages_are_held_levels_and_cycle_every_frame_s():
    s = scene.loads(GROUP + '[stimulus]\nkind = "braille"\ntext = "abcd"\nframe_s = 0.01\nvoltage = 20.0\n')
    n = needs(s)
    assert "render.braille" in n.needed and "render" in n.left_out  # no OpenCV for Braille
    rig = build(s)
    frames = braille_frames("abcd", (4, 4), 8).reshape(-1, 16)
    assert frames.shape[0] == 2
    blocks = int(round(0.01 * 48000 / 32))  # 15 blocks per page
    d = drive_of(rig, 3 * blocks)
    for page, k in ((0, blocks - 1), (1, 2 * blocks - 1), (0, 3 * blocks - 1)):
        col = d[:, k * 32 + 31]
        np.testing.assert_array_equal(col, np.where(frames[page], 20.0, 0.0))


def _image(tmp_path):
    img = np.full((64, 64), 255, np.uint8)
    img[:, :32] = 0  # left half black
    p = tmp_path / "half.png"
    cv2.imwrite(str(p), img)
    return p, img


def test_roi_image_at_a_fixed_hia_raises_the_pins_over_black(tmp_path):
    p, img = _image(tmp_path)
    s = scene.loads(GROUP + f'[stimulus]\nkind = "image"\nmethod = "roi"\nimage = "{p}"\npath = "fixed"\n'
                    'at = [32.0, 32.0]\nhia = 32\n')
    d = drive_of(build(s), 4)
    up = d[:, -1].reshape(4, 4) > 0
    assert up[:, :2].all() and not up[:, 2:].any()
    # the renderer alone, asked directly, agrees
    r = make_renderer("roi", grid=(4, 4), hia=32).prepare(img)
    out = r.empty()
    r.update(32.0, 32.0, out)
    np.testing.assert_array_equal(up.ravel(), out[:, 0] > 0.5)


def test_beat_image_sets_oscillator_frequencies_and_amplitudes_from_the_renderer(tmp_path):
    rng = np.random.default_rng(3)
    img = (rng.random((200, 200)) > 0.5).astype(np.uint8) * 255
    img = cv2.GaussianBlur(img, (9, 9), 3)
    p = tmp_path / "noise.png"
    cv2.imwrite(str(p), img)
    s = scene.loads(GROUP.replace("[4, 4]", "[2, 4]") +
                    f'[stimulus]\nkind = "image"\nmethod = "beat"\nimage = "{p}"\npath = "fixed"\n'
                    'at = [100.0, 100.0]\nhia = 48\nvoltage = 30.0\n')
    assert "dsp.oscillator" in needs(s).needed
    rig = build(s)
    drive_of(rig, 3)
    r = make_renderer("beat", grid=(2, 4), hia=48).prepare(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE))
    out = r.empty()
    r.update(100.0, 100.0, out)
    np.testing.assert_allclose(rig.bank.freq, out[:, 1], rtol=1e-6)
    np.testing.assert_allclose(rig.bank.amp, 30.0 * out[:, 4], rtol=1e-9, atol=1e-12)


def test_image_scene_without_an_image_is_refused_in_one_line():
    from rtctl.errors import SceneError

    s = scene.loads(GROUP + '[stimulus]\nkind = "image"\nmethod = "roi"\n')
    with pytest.raises(SceneError, match="stimulus.image is empty"):
        build(s)
