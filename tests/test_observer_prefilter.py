"""The observer's low-pass of drive and currents (``Observer(prefilter=...)``): the kernel's biquad
against scipy.signal.lfilter, the whole block step against the naive twin over filtered samples,
steady estimates unchanged by it, and a ring above the tone rejected by the filter's own response."""

import math

import numpy as np
import pytest
import scipy.signal
from naive_selfsense import observer_block, steps_K

from rtctl.errors import ModelError
from rtctl.plant.materials import BUILTIN
from rtctl.selfsense import _kernels
from rtctl.selfsense.rt import PREFILTER_DECAY, Observer, prefilter_cutoffs
from rtctl.selfsense.tmm import TMMBeam, laminate_of

PZT = BUILTIN["PZT-5A"]
FS, BLOCK = 48000.0, 32


def beam():
    return TMMBeam(laminate_of(1.5e-3, [(PZT, 0.3e-3), (PZT, 0.3e-3)], "parallel"), 15e-3, (0.5, 0.5), 0.01)


def _run(obs, drive, sensed):
    for b in range(drive.shape[1] // BLOCK):
        sl = slice(b * BLOCK, (b + 1) * BLOCK)
        status = obs.process(np.ascontiguousarray(drive[:, sl]), np.ascontiguousarray(sensed[:, sl]))
    return status


def test_biquad_is_lfilter_across_blocks_and_forgets_a_bad_reading():
    rng = np.random.default_rng(1)
    b, a = scipy.signal.butter(2, 240.0, fs=FS)
    pf = np.array([[1.0, 0, 0, 0, 0], [b[0], b[1], b[2], a[1], a[2]], [b[0], b[1], b[2], a[1], a[2]]])
    z = np.zeros((3, 2))
    n_blocks = 40
    x = rng.standard_normal((3, n_blocks * BLOCK))
    bad = 17 * BLOCK + 5
    x[2, bad] = np.nan
    y = np.zeros((3, n_blocks * BLOCK))
    buf = np.zeros((3, BLOCK))
    for k in range(n_blocks):
        sl = slice(k * BLOCK, (k + 1) * BLOCK)
        _kernels._prefilter(pf, z, np.ascontiguousarray(x[:, sl]), buf, 0)
        y[:, sl] = buf
    assert np.array_equal(y[0], x[0])                              # (1, 0, 0, 0, 0): copied
    np.testing.assert_allclose(y[1], scipy.signal.lfilter(b, a, x[1]), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(y[2, :bad], scipy.signal.lfilter(b, a, x[2, :bad]), rtol=1e-12, atol=1e-13)
    assert np.isnan(y[2, bad])                                     # the bad reading goes through once
    np.testing.assert_allclose(y[2, bad + 1:], scipy.signal.lfilter(b, a, x[2, bad + 1:]), rtol=1e-12, atol=1e-13)


def test_block_step_is_the_naive_twin_over_lfiltered_samples():
    """Random matrices in use: the estimates are the naive window sums of the lfiltered drive and
    currents through them, and the drive's reading is the filtered drive's over ``G``."""
    rng = np.random.default_rng(2)
    freqs = np.array([[80.0, 0.0], [240.0, 270.0], [120.0, 0.0]])
    fc = [240.0, 0.0, 500.0]
    obs = Observer(beam(), freqs, FS, BLOCK, window=[1200, 1600, 800], hop=8, prefilter=fc)
    H = rng.standard_normal(obs.H.shape)
    H[obs.freqs <= 0] = 0.0
    obs.H[:] = H
    n_ch, n_seg, W = 3, obs.n_seg, 1600
    n_total = 4 * W
    n = np.arange(n_total)
    drive = np.stack([sum(np.cos(2 * np.pi * f * n / FS + k) for k, f in enumerate(row) if f > 0) for row in freqs])
    drive += 0.1 * rng.standard_normal(drive.shape)
    sensed = 1e-6 * rng.standard_normal((n_ch * n_seg, n_total))
    assert _run(obs, drive, sensed) == 0
    fd, fsn = drive.copy(), sensed.copy()
    for c, f in enumerate(fc):
        if f > 0:
            b, a = scipy.signal.butter(2, f, fs=FS)
            fd[c] = scipy.signal.lfilter(b, a, drive[c])
            fsn[c * n_seg:(c + 1) * n_seg] = scipy.signal.lfilter(b, a, sensed[c * n_seg:(c + 1) * n_seg], axis=1)
    Hc = H[..., 0] + 1j * H[..., 1]
    got = obs.est[..., 0] + 1j * obs.est[..., 1]
    for c, w in enumerate(obs.windows):
        sl = slice(n_total - w, n_total)
        want = observer_block(Hc[c:c + 1], fd[c:c + 1, sl], fsn[c * n_seg:(c + 1) * n_seg, sl], freqs[c:c + 1],
                              FS, n_seg, start=n_total - w, K=steps_K(obs)[c:c + 1],
                              before=fd[c:c + 1, n_total - w - 1])
        np.testing.assert_allclose(got[c], want[0], rtol=1e-8, atol=1e-10 * np.abs(want).max())
    # the drive's reading, by least squares over the filtered drive, over the response at the tone
    c, w = 0, int(obs.windows[0])
    t = np.arange(n_total - w, n_total)
    A = np.column_stack([np.cos(2 * np.pi * 80.0 * t / FS), np.sin(2 * np.pi * 80.0 * t / FS)])
    cr, ci = np.linalg.lstsq(A, fd[c, t], rcond=None)[0]
    u = (cr - 1j * ci) / obs.prefilter_gain[0, 0]
    assert obs.u_out[0, 0, 0] == pytest.approx(abs(u), rel=1e-9)
    assert math.remainder(obs.u_out[0, 0, 1] - np.angle(u), 2 * np.pi) == pytest.approx(0.0, abs=1e-9)


def _steady(freq, fc, extra=0.0, extra_hz=742.0, extra_phase=0.0):
    """A filtered or unfiltered observer's tip phasor from steady sines (plus a sine of the
    currents only at ``extra_hz``, relative amplitude ``extra``, phase ``extra_phase``)."""
    obs = Observer(beam(), [[freq]], FS, BLOCK, window=600, hop=8, prefilter=fc)
    n = np.arange(60 * BLOCK * 20)
    drive = 10.0 * np.cos(2 * np.pi * freq * n / FS + 0.3)[None]
    i0 = 1e-5 * np.stack([np.cos(2 * np.pi * freq * n / FS + 1.1), 0.7 * np.cos(2 * np.pi * freq * n / FS - 0.4)])
    r = np.cos(2 * np.pi * extra_hz * n / FS + extra_phase)
    _run(obs, drive, i0 + extra * 1e-5 * np.stack([r, -r]))
    return obs.phasors()[0, 0], obs


def test_steady_estimates_and_drive_are_those_without_the_filter():
    plain, p = _steady(80.0, 0.0)
    lp, q = _steady(80.0, 240.0)
    assert abs(plain) > 0
    assert lp == pytest.approx(plain, rel=1e-9)
    assert q.u_out[0, 0] == pytest.approx(p.u_out[0, 0], rel=1e-9)


def test_a_ring_above_the_tone_is_rejected_by_the_filters_own_response():
    """A 742 Hz sine in the currents leaks into the 80 Hz reading over a one-period window; low-
    passed, it leaks as the unfiltered observer's leak of that sine through the filter's response
    at 742 Hz, over its response at 80 Hz (scipy's freqz): 9 times less."""
    base, _ = _steady(80.0, 0.0)
    plain = _steady(80.0, 0.0, extra=0.3)[0] - base
    lp = _steady(80.0, 240.0, extra=0.3)[0] - base
    b, a = scipy.signal.butter(2, 240.0, fs=FS)
    g80, g742 = scipy.signal.freqz(b, a, worN=[80.0, 742.0], fs=FS)[1]
    through = _steady(80.0, 0.0, extra=0.3 * abs(g742), extra_phase=np.angle(g742))[0] - base
    assert abs(plain) > 1e-2 * abs(base)                           # the leak is there to reject
    assert lp == pytest.approx(through / g80, rel=1e-6)
    assert abs(lp) < 0.15 * abs(plain)


def test_memory_is_where_the_impulse_response_has_fallen_to_its_decay():
    obs = Observer(beam(), [[80.0], [250.0]], FS, BLOCK, prefilter=[240.0, 0.0])
    m = int(obs.prefilter_memory[0])
    assert obs.prefilter_memory[1] == 0
    b, a = scipy.signal.butter(2, 240.0, fs=FS)
    h = np.abs(scipy.signal.lfilter(b, a, np.r_[1.0, np.zeros(4 * m)]))
    assert h[m:].max() <= PREFILTER_DECAY * h.max() < h[m - 1]     # the first sample after it
    assert m == 120                                                # 2.5 ms, as docs/control.md says


def test_cutoffs_sit_under_the_lowest_mode_for_tones_far_below_it_and_bad_ones_are_refused():
    fc = 0.45 * 700.0
    assert prefilter_cutoffs([[80.0, 0.0], [40.0, 120.0], [0.0, 0.0], [10.0, 0.0]], FS, 700.0).tolist() == [
        fc, 0.0, 0.0, fc]                                          # 120 Hz: over a third of the cutoff
    assert prefilter_cutoffs([[10.0]], FS, 50e3).tolist() == [0.0]  # over 0.4 fs
    for bad in (-1.0, float("nan"), FS / 2, [240.0, 240.0]):
        with pytest.raises(ModelError, match="prefilter"):
            Observer(beam(), [[80.0]], FS, BLOCK, prefilter=bad)
