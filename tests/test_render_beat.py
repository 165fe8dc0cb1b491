"""Beat rendering (seed 004): blob validity at exactly 12.6 mm^2, counts and variances known by
construction, the numpy twin, cell pairs that really beat at f_b (scipy Hilbert envelope)."""

import cv2
import numpy as np
import pytest
from matplotlib import cbook
from naive_render import naive_beat, naive_max_window_count
from scipy.signal import hilbert

from rtctl.errors import SceneError
from rtctl.render import _kernels as _k
from rtctl.render.beat import BeatRenderer, blob_labels, carrier_amplitude
from rtctl.render.image import load_image

HOPPER = cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)


@pytest.mark.parametrize("px_mm, n_px, valid", [
    (0.1, 1260, True),   # 1260 px * 0.01 mm^2 = 12.6 mm^2 exactly: kept
    (0.1, 1259, False),
    (0.5, 51, True),     # 12.75 mm^2
    (0.5, 50, False),    # 12.5 mm^2
], ids=["0.1mm-at-limit", "0.1mm-below", "0.5mm-above", "0.5mm-below"])
def test_blob_exactly_at_the_meissner_limit(px_mm, n_px, valid):
    mask = np.zeros((60, 60), np.uint8)
    mask.reshape(-1)[np.arange(n_px) // 50 * 60 + np.arange(n_px) % 50] = 1  # rows of 50 px: one blob
    labels, v, areas = blob_labels(mask, px_mm * 1e-3, 12.6e-6)
    assert areas.tolist()[1:] == [n_px]
    assert bool(v[1]) is valid and v[0] == 0


def squares(n, side=10, size=(96, 96), spacing=24):
    img = np.full(size, 255, np.uint8)
    for k in range(n):
        r, c = 4 + (k // 4) * spacing, 4 + (k % 4) * spacing
        img[r:r + side, c:c + side] = 0
    return img


def test_counts_give_beat_and_carrier_by_eq_1_and_2():
    # px 0.4 mm: a 10 x 10 px square is 16 mm^2 (valid), a 5 x 5 one 4 mm^2 (dropped)
    img = squares(5)
    img[80:85, 80:85] = 0
    r = BeatRenderer(grid=(2, 2), hia=96, px_size=0.4e-3, max_count=(8, 20)).prepare(img)
    assert (r.valid.sum(), r.valid.size - 1) == (5, 6)
    out = r.empty()
    r.update(48, 48, out)                   # the HIA is the whole image
    fb = 0.3 + 5 / 8 * (40 - 0.3)
    # edge blobs: each square's outline is one ring of Sobel edge pixels, and so is the small one
    assert r.edge_valid.sum() == 6
    fc = 40 + 6 / 20 * (400 - 40)
    np.testing.assert_allclose(out[:, 2], fb, rtol=1e-12)
    np.testing.assert_allclose(out[:, 3], fc, rtol=1e-12)
    np.testing.assert_allclose(out[:, 1], [fc - fb / 2, fc + fb / 2] * 2, rtol=1e-12)


def test_variance_gives_amplitude_by_eq_3():
    img = np.zeros((40, 40), np.uint8)
    img[:, 20:] = 200                       # half 0, half 200: variance 100^2 exactly
    r = BeatRenderer(grid=(1, 2), hia=40, px_size=1e-3, amp_scale=1e-4).prepare(img)
    out = r.empty()
    r.update(20, 20, out)
    np.testing.assert_allclose(out[:, 4], 1 - 1 / (1 + 1e-4 * 100.0 ** 2), rtol=1e-12)  # = 0.5
    np.testing.assert_allclose(carrier_amplitude(1e4, 1e-4), 0.5)
    img[:] = 77
    r.prepare(img).update(20, 20, out)
    assert np.all(out[:, 4] == 0.0)         # flat: no carrier amplitude


def test_seed_004_pair_beats_at_fb_on_the_carrier():
    # seed 004, 4.2: 100 Hz + 110 Hz on neighbouring cells -> 10 Hz beat on a 105 Hz carrier. Pin the
    # bands so that f_b = 10 Hz, f_c = 105 Hz whatever the image, and check the pair's drive
    # frequencies and, from their summed waveform, the envelope's frequency (scipy Hilbert).
    img = load_image(HOPPER)
    r = BeatRenderer(grid=(6, 8), beat_band=(10.0, 10.0), carrier_band=(105.0, 105.0)).prepare(img)
    out = r.empty()
    r.update(256, 300, out)
    f = out[:, 1].reshape(6, 8)
    np.testing.assert_allclose(f[:, 0::2], 100.0)
    np.testing.assert_allclose(f[:, 1::2], 110.0)
    fs, T = 8000.0, 2.0
    t = np.arange(int(fs * T)) / fs
    s = np.sin(2 * np.pi * f[0, 0] * t) + np.sin(2 * np.pi * f[0, 1] * t)
    env = np.abs(hilbert(s))
    spec = np.abs(np.fft.rfft(env - env.mean()))
    assert np.fft.rfftfreq(t.size, 1 / fs)[np.argmax(spec)] == pytest.approx(out[0, 2], abs=1 / T)
    phase = np.unwrap(np.angle(hilbert(s)))
    assert np.median(np.diff(phase)) * fs / (2 * np.pi) == pytest.approx(out[0, 3], rel=1e-3)


@pytest.mark.parametrize("unit", [None, (1, 2), (3, 4), (6, 8)], ids=["hia", "pairs", "quadrants", "hia-explicit"])
def test_matches_naive_twin_on_a_photo(unit):
    img = load_image(HOPPER)
    r = BeatRenderer(grid=(6, 8), hia=96, unit=unit).prepare(img)
    out = r.empty()
    rng = np.random.default_rng(7)
    for x, y in list(zip(rng.uniform(-60, 570, 60), rng.uniform(-60, 660, 60))) + [(-300, -300)]:
        r.update(x, y, out)
        r0, c0 = r.origin(x, y)
        ref = naive_beat(r.gray, r.labels, r.valid, r.edge_labels, r.edge_valid, r0, c0, 6, 8, 12,
                         r.unit, r.params)
        np.testing.assert_allclose(out[:, 1:5], ref, rtol=1e-9, atol=1e-9)
        assert np.all(out[:, 0] == 1.0)


def test_max_count_matches_the_naive_scan():
    img = load_image(HOPPER)
    r = BeatRenderer(grid=(6, 8), hia=96, px_size=0.06e-3, normalize="image").prepare(img)
    h, w = r.shape
    assert r.max_count == (naive_max_window_count(r.labels, r.valid, h, w, h // 4, w // 4),
                           naive_max_window_count(r.edge_labels, r.edge_valid, h, w, h // 4, w // 4))
    assert r.max_count[0] >= 2 and r.max_count[1] >= 10  # a photograph has blobs and edges


def test_count_kernel_on_random_labels():
    rng = np.random.default_rng(11)
    mask = (rng.random((50, 70)) < 0.45).astype(np.uint8)
    labels, valid, _ = blob_labels(mask, 1e-3, 3e-6)           # blobs of >= 3 px valid
    vlab = np.where(valid[labels] != 0, labels, 0).astype(np.int32)
    stamp = _k.stamp_array(valid.size)
    for tick in range(200):
        a, c = rng.integers(-10, 60), rng.integers(-10, 80)
        b, d = a + rng.integers(0, 30), c + rng.integers(0, 30)
        a, b, c, d = (int(np.clip(v, 0, lim)) for v, lim in ((a, 50), (b, 50), (c, 70), (d, 70)))
        u = np.unique(labels[a:b, c:d])
        assert _k.count_blobs(vlab, stamp, tick, a, b, c, d) == int(valid[u].sum())


def test_bad_configurations():
    with pytest.raises(SceneError, match="must divide the grid"):
        BeatRenderer(grid=(6, 8), unit=(4, 2))
    with pytest.raises(SceneError, match="split a cell pair"):
        BeatRenderer(grid=(6, 9), unit=(6, 3))
    with pytest.raises(SceneError, match="px_size"):
        BeatRenderer(px_size=-1.0)
    r = BeatRenderer(grid=(1, 3), hia=30, px_size=1e-3)  # odd width: the last cell is unpaired
    r.prepare(cv2.resize(load_image(HOPPER), (64, 64)))
    out = r.empty()
    r.update(32, 32, out)
    assert out[2, 1] == out[2, 3] and out[0, 1] == out[0, 3] - out[0, 2] / 2


# --- normalisation: the physiological maximum (default) against the image's own -----------------

PX = 0.5e-3  # an 8 x 8 px square is 16 mm^2: one valid blob (>= 12.6 mm^2)
#: the unit (the whole 96 x 96 px HIA of a 2 x 2 grid) is 48 mm x 48 mm = 2304 mm^2; receptive
#: fields of 12.6 mm^2 tiling it (density 1): floor(2304 / 12.6) = floor(182.86) = 182 blobs at most
N_MAX = 182


def blob_grid(n, size=(192, 192), at=(20, 20), spacing=12, cols=8):
    """White image with ``n`` black 8 x 8 px squares on a grid from ``at`` (row, col)."""
    img = np.full(size, 255, np.uint8)
    for k in range(n):
        r, c = at[0] + (k // cols) * spacing, at[1] + (k % cols) * spacing
        img[r:r + 8, c:c + 8] = 0
    return img


def beat_at(img, x, y, **kw):
    r = BeatRenderer(grid=(2, 2), hia=96, px_size=PX, **kw).prepare(img)
    out = r.empty()
    r.update(x, y, out)
    return r, out[0, 2]


@pytest.mark.parametrize("n", [1, 40])
def test_the_physiological_maximum_gives_each_blob_count_its_own_beat(n):
    img = blob_grid(n)  # every blob (rows 20-75, columns 20-111) inside the HIA centred at (66, 48)
    r, fb = beat_at(img, 66, 48)
    assert int(r.valid.sum()) == n and r.max_count[0] == N_MAX
    assert fb == pytest.approx(0.3 + n / N_MAX * (40 - 0.3), rel=1e-12)  # Eq. (1) with f_bb = n / 182
    r, fb = beat_at(img, 66, 48, normalize="image")
    assert r.max_count[0] == n and fb == pytest.approx(40.0, rel=1e-12)  # the densest place: the band's top


def test_a_texture_beats_alike_in_any_image_only_under_the_physiological_maximum():
    one = blob_grid(1, size=(192, 400))
    both = one.copy()
    both[:, 200:] = blob_grid(40, size=(192, 200))  # forty more blobs, far from the first one's HIA
    for normalize, same in (("field", True), ("image", False)):
        _, fb1 = beat_at(one, 55, 55, normalize=normalize)
        _, fb2 = beat_at(both, 55, 55, normalize=normalize)
        assert bool(fb1 == pytest.approx(fb2, rel=1e-12)) is same, (normalize, fb1, fb2)


def test_the_maximum_follows_the_unit_and_the_pixel_size():
    img = blob_grid(1)
    # the seed's display: 6 x 8 cells at 1.5 mm, 12 px per cell: 9 x 12 mm = 108 mm^2, 8 blobs
    r = BeatRenderer(grid=(6, 8), hia=96).prepare(img)
    assert r.max_count[0] == 8 == int(np.floor(9 * 12 / 12.6))
    # units of 2 x 2 cells: 3 x 3 mm = 9 mm^2 hold no whole field; one blob is the most
    assert BeatRenderer(grid=(6, 8), hia=96, unit=(2, 2)).prepare(img).max_count[0] == 1
    assert BeatRenderer(grid=(2, 2), hia=96, px_size=PX, max_count=(5, 7)).prepare(img).max_count == (5, 7)
    with pytest.raises(SceneError, match="no physiological maximum"):
        BeatRenderer(min_blob_area=0.0)
    with pytest.raises(SceneError, match="normalize"):
        BeatRenderer(normalize="densest")
