"""ROI scanning (seed 001): exact 50 % rule, the numpy twin, Canny lines on constructed and real images."""

import numpy as np
import pytest
from matplotlib import cbook
from naive_render import naive_roi

from rtctl.render.factory import make_renderer
from rtctl.render.image import load_image, to_gray
from rtctl.render.roi import RoiRenderer, canny_lines

HOPPER = cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)


def test_exactly_half_black_is_down_one_more_pixel_is_up():
    # 4x4 sections of 8x8 px: section (i, j) gets 32 black pixels (exactly 50 %); those on the
    # diagonal get one more (33 / 64 > 50 %)
    img = np.full((32, 32), 255, np.uint8)
    for i in range(4):
        for j in range(4):
            sec = np.full(64, 255, np.uint8)
            sec[np.random.default_rng(4 * i + j).permutation(64)[: 32 + (i == j)]] = 0
            img[8 * i:8 * i + 8, 8 * j:8 * j + 8] = sec.reshape(8, 8)
    assert (img == 0).sum() == 16 * 32 + 4
    r = RoiRenderer(grid=(4, 4), hia=32).prepare(img)
    out = r.empty()
    assert r.update(16, 16, out) == 0  # centre (16, 16): top-left (0, 0)
    np.testing.assert_array_equal(out[:, 0].reshape(4, 4), np.eye(4))
    assert not out[:, 1:].any()


def test_threshold_defines_black():
    img = np.full((16, 16), 127, np.uint8)
    out = np.zeros((1, 5))
    RoiRenderer(grid=(1, 1), hia=16, threshold=128).prepare(img).update(8, 8, out)
    assert out[0, 0] == 1.0  # 127 < 128: black
    RoiRenderer(grid=(1, 1), hia=16, threshold=127).prepare(img).update(8, 8, out)
    assert out[0, 0] == 0.0


@pytest.mark.parametrize("grid, hia", [((4, 4), 32), ((8, 8), 40), ((2, 3), 33)], ids=["dot4x4", "sma8x8", "2x3"])
def test_roi_matches_naive_twin_on_random_images(grid, hia):
    rng = np.random.default_rng(1)
    img = np.where(rng.random((70, 90)) < 0.5, 0, 255).astype(np.uint8)
    img[20:50, 30:60] = 0  # a solid region, so that whole sections are up
    r = RoiRenderer(grid=grid, hia=hia).prepare(img)
    out = r.empty()
    R, C = grid
    # centres everywhere, including HIAs hanging over the edges and wholly outside
    for x, y in list(zip(rng.uniform(-40, 130, 300), rng.uniform(-40, 110, 300))) + [(-500, 5), (35.49, 20.5)]:
        status = r.update(x, y, out)
        r0, c0 = r.origin(x, y)
        np.testing.assert_array_equal(out[:, 0], naive_roi(r.black, r0, c0, R, C, r.cell))
        outside = r0 >= 70 or c0 >= 90 or r0 + r.shape[0] <= 0 or c0 + r.shape[1] <= 0
        assert status == int(outside)


def test_origin_rounds_the_centre():
    r = RoiRenderer(grid=(4, 4), hia=33)  # cell 8 -> HIA 32 px
    assert r.shape == (32, 32) and r.origin(16, 16) == (0, 0)
    assert r.origin(16.49, 15.5) == (0, 0) and r.origin(16.5, 16.5) == (1, 1)


def test_canny_lines_on_a_square_follow_its_border():
    img = np.zeros((80, 80), np.uint8)
    img[20:60, 20:60] = 255
    lines = canny_lines(img, line_px=3)
    black = lines == 0
    yy, xx = np.mgrid[:80, :80]
    # distance (chessboard) of each pixel to the square's border, which runs between 19|20 and 59|60
    d = np.minimum.reduce([np.abs(yy - 19.5), np.abs(xx - 19.5), np.abs(yy - 59.5), np.abs(xx - 59.5)])
    inside = (yy >= 19) & (yy <= 60) & (xx >= 19) & (xx <= 60)
    d = np.where(inside, d, np.maximum(np.maximum(19.5 - yy, yy - 59.5), np.maximum(19.5 - xx, xx - 59.5)))
    assert black[d <= 0.5].mean() > 0.95  # the border itself is a line
    assert not black[d >= 3.5].any()      # 1 px edge + 1 px each side at most, nothing else
    # a 4x4 Dot ROI centred on the left border: the sections on the border are up, the others down
    r = RoiRenderer(grid=(4, 4), hia=16, edges=True, line_px=7).prepare(img)  # 4 px sections
    out = r.empty()
    r.update(20, 40, out)  # columns 12..27: sections [12,16) [16,20) [20,24) [24,28)
    up = out[:, 0].reshape(4, 4)
    np.testing.assert_array_equal(up, np.tile([0, 1, 1, 0], (4, 1)))
    assert r.method == "canny"


def test_canny_on_a_real_photograph_matches_the_twin():
    img = load_image(HOPPER)
    r = make_renderer("canny", grid=(4, 4), hia=32).prepare(img)
    frac = r.black.mean()
    assert 0.03 < frac < 0.5  # edges, not everything or nothing
    np.testing.assert_array_equal(r.black, (canny_lines(to_gray(img)) == 0).astype(np.uint8))
    out = r.empty()
    rng = np.random.default_rng(2)
    ups = 0
    for x, y in zip(rng.uniform(0, 511, 200), rng.uniform(0, 599, 200)):
        r.update(x, y, out)
        r0, c0 = r.origin(x, y)
        np.testing.assert_array_equal(out[:, 0], naive_roi(r.black, r0, c0, 4, 4, 8))
        ups += out[:, 0].sum()
    assert 0 < ups < 200 * 16
