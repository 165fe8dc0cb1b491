"""Ramp and Fade: twins, chunk invariance, exact end values, silence."""

import naive_dsp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rtctl.dsp import Fade, Ramp, fade_process, ramp_process

TINY_NORMAL = np.finfo(np.float64).tiny


def run_ramp(ramp, n, splits=(), schedule=None):
    schedule = schedule or {}
    cuts = sorted({0, n, *splits, *schedule})
    blocks = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        if a in schedule:
            ramp.set(0, *schedule[a])
        out = np.empty((ramp.n_params, b - a))
        ramp.process(out)
        blocks.append(out)
    return np.concatenate(blocks, axis=1)


def run_fade(fade, x, splits=(), schedule=None):
    schedule = schedule or {}
    cuts = sorted({0, x.shape[1], *splits, *schedule})
    blocks = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        if a in schedule:
            fade.fade_to(*schedule[a])
        blk = x[:, a:b].copy()
        fade.process(blk)
        blocks.append(blk)
    return np.concatenate(blocks, axis=1)


SCHED = {10: (1.0, None), 20: (-2.0, 100), 400: (0.5, 1), 600: (3.0, 250)}


def test_ramp_matches_naive_twin():
    got = run_ramp(Ramp(1, 0.25, ramp=32), 1000, splits=range(0, 1000, 45), schedule=SCHED)[0]
    want = naive_dsp.ramp(0.25, 1000, 32, SCHED)
    # same formula v0 + step (k + 1) in both; only the float rounding of step differs: 1e-15
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-14)
    assert got[20 + 99] == -2.0 and got[600 + 249] == 3.0  # ramps land exactly


@given(splits=st.lists(st.integers(1, 999), max_size=25))
@settings(max_examples=40, deadline=None)
def test_ramp_chunk_invariance(splits):
    one = run_ramp(Ramp(1, 0.25), 1000, schedule=SCHED)
    many = run_ramp(Ramp(1, 0.25), 1000, splits=splits, schedule=SCHED)
    assert np.array_equal(one, many)


def test_ramp_vectorized_and_kernel_args():
    r = Ramp(3, [0.0, 1.0, 2.0], ramp=4)
    r.set_all([4.0, 1.0, -2.0])
    out = np.empty((3, 5))
    ramp_process(*r.args, out)
    np.testing.assert_array_equal(out, [[1, 2, 3, 4, 4], [1, 1, 1, 1, 1], [1, 0, -1, -2, -2]])
    assert list(r.value) == [4.0, 1.0, -2.0]


def test_fade_out_shape_and_silence():
    n = 64
    fade = Fade(n)
    x = np.ones((3, 200))
    x[1, 150] = np.nan
    fade.fade_out()
    y = run_fade(fade, x, splits=[17, 40])
    g = naive_dsp.fade_gain(1.0, 0.0, n, 200)
    np.testing.assert_allclose(y[0], g, rtol=0, atol=1e-15)
    # raised cosine: the steepest step is pi / (2 N) and the ends are flat (slope ~ 1/N^2)
    assert np.max(np.abs(np.diff(y[0]))) <= np.pi / (2 * n) + 1e-15
    assert 1.0 - y[0, 0] < (np.pi / n) ** 2
    assert np.all(y[:, n - 1 :] == 0.0)  # exact zeros, NaN input included
    assert fade.gain == 0.0 and not fade.active


@given(splits=st.lists(st.integers(1, 299), max_size=20))
@settings(max_examples=30, deadline=None)
def test_fade_chunk_invariance(splits):
    x = np.random.default_rng(5).standard_normal((2, 300))
    sched = {0: (0.0, 50), 120: (1.0, 100), 170: (0.3, 7)}  # the fade-in is interrupted
    assert np.array_equal(run_fade(Fade(10), x, schedule=sched), run_fade(Fade(10), x, splits, sched))


def test_fade_interrupted_continues_from_current_gain():
    fade = Fade(100, gain=0.0)
    fade.fade_in()
    x = np.ones((1, 50))
    fade.process(x)
    g_mid = fade.gain
    assert 0.4 < g_mid < 0.6
    fade.fade_out(20)
    y = np.ones((1, 30))
    fade_process(*fade.args, y)
    np.testing.assert_allclose(y[0], naive_dsp.fade_gain(g_mid, 0.0, 20, 30), atol=1e-15)
    assert abs(y[0, 0] - g_mid) < np.pi / 40 * g_mid  # no step at the interruption


def test_no_subnormals_after_ramp_to_silence():
    r = Ramp(1, 1e-300, ramp=8)
    r.set(0, 1e-310)
    run_ramp(r, 20)
    assert not np.any((r.state != 0) & (np.abs(r.state) < TINY_NORMAL))
    assert r.value[0] == 0.0


@pytest.mark.parametrize(
    "make, match",
    [(lambda: Ramp(0), "n_params = 0"), (lambda: Ramp(1, ramp=0), "ramp = 0"), (lambda: Fade(0), "length = 0"),
     (lambda: Fade(8, gain=-1.0), "gain = -1.0")],
    ids=["no-params", "zero-ramp", "zero-fade", "negative-gain"],
)
def test_validation(make, match):
    with pytest.raises(ValueError, match=match):
        make()
