"""Frequency rendering (seed 003): tactile image vs a scipy.ndimage twin, Eq. (1) vs the numpy
twin and a closed form, and the seed's bump patterns (Table 1) against the 33 px HIA."""

import cv2
import numpy as np
import pytest
from matplotlib import cbook
from naive_render import naive_frequency
from scipy import ndimage

from rtctl.errors import SceneError
from rtctl.render.frequency import FrequencyRenderer, tactile_image
from rtctl.render.image import load_image, to_gray

HOPPER = cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)
TABLE1_GAPS = [124, 62, 41, 30, 24, 21, 18, 15, 13, 12]  # seed 003, Table 1, px


def scipy_tactile(gray):
    """Seed 003's pipeline written with numpy and scipy.ndimage (no OpenCV)."""
    g = gray.astype(float)
    s = np.rint((g - g.min()) * 255.0 / (g.max() - g.min()))
    m = np.rint(s * s / 255.0)
    # closing = erosion of the dilation; 'nearest' borders make max/min ignore the outside, as OpenCV
    c = ndimage.grey_erosion(ndimage.grey_dilation(m, size=(3, 3), mode="nearest"), size=(3, 3), mode="nearest")
    gx = ndimage.sobel(c, axis=1, mode="mirror")  # OpenCV's default border is reflect-101 = 'mirror'
    gy = ndimage.sobel(c, axis=0, mode="mirror")
    return np.clip(np.rint(np.hypot(gx, gy) / 4.0), 0, 255)


@pytest.mark.parametrize("source", ["photo", "noise"])
def test_tactile_image_matches_scipy(source):
    if source == "photo":
        gray = to_gray(load_image(HOPPER))
    else:
        gray = np.random.default_rng(0).integers(60, 180, (120, 90)).astype(np.uint8)
    t = tactile_image(gray).astype(float)
    ref = scipy_tactile(gray)
    diff = np.abs(t - ref)
    assert diff.max() <= 1.0            # float32 vs float64 rounding at .5 steps
    assert (diff == 0).mean() > 0.99


def test_histogram_stretch_reaches_full_range():
    gray = np.random.default_rng(3).integers(90, 140, (40, 40)).astype(np.uint8)
    from rtctl.render.frequency import self_multiply, stretch

    s = stretch(gray)
    assert s.min() == 0 and s.max() == 255
    np.testing.assert_array_equal(self_multiply(np.array([[0, 128, 255]], np.uint8)), [[0, 64, 255]])


def test_step_edge_closed_form():
    # black | white step between columns 49 and 50: the tactile image is 255 on columns 49 and 50
    # only, so the pin whose 11 columns hold both gets f_pmax * 2 / 11 (Eq. 1), the others 0
    img = np.zeros((99, 99), np.uint8)
    img[:, 50:] = 255
    r = FrequencyRenderer(f_pmax=140.0).prepare(img)
    out = r.empty()
    r.update(49, 49, out)
    f = out[:, 1].reshape(3, 3)
    np.testing.assert_allclose(f[:, 1], 140.0 * 2 / 11, rtol=1e-12)
    assert not f[:, [0, 2]].any()


def test_pins_match_naive_twin_on_a_photo():
    img = load_image(HOPPER)
    r = FrequencyRenderer(grid=(3, 3), hia=33, f_pmax=120.0).prepare(img)
    out = r.empty()
    rng = np.random.default_rng(5)
    for x, y in zip(rng.uniform(-20, 530, 300), rng.uniform(-20, 620, 300)):
        r.update(x, y, out)
        r0, c0 = r.origin(x, y)
        ref = naive_frequency(r.tactile, r0, c0, 3, 3, 11, 120.0)
        np.testing.assert_allclose(out[:, 1], ref, rtol=1e-12, atol=1e-12)
        assert out[:, 1].max() <= 120.0


def bumps(gap):
    """Seed 003 Fig. 8-style sample: small white bumps (5 px discs) on a square lattice of pitch
    ``gap`` px, in an image a whole number of periods wide (>= 330 px, the seed's image size)."""
    n = -(-330 // gap)
    img = np.zeros((n * gap, n * gap), np.uint8)
    for cy in range(gap // 2, n * gap, gap):
        for cx in range(gap // 2, n * gap, gap):
            cv2.circle(img, (cx, cy), 2, 255, -1)
    return img


@pytest.mark.parametrize("gap", TABLE1_GAPS)
def test_bump_pattern_period_is_the_gap(gap):
    img = bumps(gap)
    r = FrequencyRenderer().prepare(img)  # the seed's 33 x 33 px HIA over 3x3 pins
    W = img.shape[1]
    xs = np.arange(20, W - 20 - gap)       # HIA and its shifted copy clear of the borders
    y = gap // 2 + gap                     # through a row of bumps
    a = r.render_path(xs, np.full(xs.size, y))
    b = r.render_path(xs + gap, np.full(xs.size, y))
    np.testing.assert_array_equal(a, b)    # exactly periodic with the gap (by construction)
    centre = a[:, 4, 1]
    assert centre.max() - centre.min() > 5.0  # and the pin does feel the bumps go by


@pytest.mark.parametrize("gap", TABLE1_GAPS)
def test_silent_hia_positions_exist_only_when_the_gap_exceeds_the_hia(gap):
    # seed 003, 4.1: recognition drops once the gap falls below the 33 px HIA. When gap <= 33 every
    # 33 x 33 HIA holds a bump centre (a lattice point), so some pin always vibrates; when the gap
    # is at least twice the HIA there are places where all nine pins are still.
    img = bumps(gap)
    r = FrequencyRenderer().prepare(img)
    c = np.arange(gap, 2 * gap) + 0.0      # one period of centres, clear of the borders
    X, Y = np.meshgrid(c, c)
    f = r.render_path(X.ravel(), Y.ravel())[:, :, 1]
    silent = np.all(f == 0.0, axis=1)
    if gap <= 33:
        assert not silent.any()
    elif gap >= 62:
        assert silent.any()


def test_f_pmax_must_stay_below_150_hz():
    with pytest.raises(SceneError, match=r"f_pmax = 150.0 Hz is outside \(0, 150\) Hz"):
        FrequencyRenderer(f_pmax=150.0)
