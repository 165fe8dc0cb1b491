"""LockIn: known tones, beat pairs, least-squares reference, twin, long-run stability."""

import naive_dsp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rtctl.dsp import LockIn, OscillatorBank, beat_window, lockin_process, window_leakage
from rtctl.dsp import _kernels as K

FS = 48000.0
TINY_NORMAL = np.finfo(np.float64).tiny


def tones(n, freqs, amps, phases, n_channels=1, chan=None, ramp=32):
    """Signal made by the oscillator bank (same phase convention as the lock-in)."""
    chan = [0] * len(freqs) if chan is None else chan
    bank = OscillatorBank(n_channels, chan, FS, freqs, amps, phases, ramp=ramp)
    x = np.zeros((n_channels, n))
    bank.process(x)
    return x


def feed(lock, x, splits=()):
    cuts = sorted({0, x.shape[1], *splits})
    outs = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        outs.append(lock.process(np.ascontiguousarray(x[:, a:b])))
    return outs


def lstsq_fit(xw, freq, n_end):
    """Independent reference: least-squares fit of A cos(theta + phi) to the window ``xw`` that
    ends at sample ``n_end``, theta = 2 pi frac(inc n) computed exactly; returns A exp(i phi)."""
    n = np.arange(n_end - len(xw), n_end)
    theta = 2 * np.pi * np.array([naive_dsp.exact_cycles(freq, FS, int(m)) for m in n])
    design = np.stack([np.cos(theta), -np.sin(theta)], axis=1)  # A cos(t+p) = Ac cos t - As sin t
    (c, s), *_ = np.linalg.lstsq(design, xw, rcond=None)
    return c + 1j * s


@pytest.mark.parametrize("freq, amp, phase", [(250.0, 1.0, 0.0), (1000.0, 0.3, 2.0), (30.0, 5.0, -2.5)],
                         ids=["250Hz", "1kHz", "30Hz"])
def test_known_tone(freq, amp, phase):
    window = 4800  # whole periods of each frequency: no self-leakage from the mirror image
    lock = LockIn(1, [[freq]], FS, window)
    est = feed(lock, tones(2 * window, [freq], [amp], [phase]), splits=range(0, 9600, 32))[-1]
    # the bank's samples are exact to ~1e-14 and a window sum of 4800 products adds ~1e-13:
    # 1e-10 is far below the required 1e-6 and still catches any convention slip
    assert est[0, 0, 0] == pytest.approx(amp, rel=1e-10)
    assert np.angle(np.exp(1j * (est[0, 0, 1] - phase))) == pytest.approx(0.0, abs=1e-10)
    assert lock.phasor[0, 0] == pytest.approx(amp * np.exp(1j * phase), rel=1e-10)


@pytest.mark.parametrize("layout", ["one-channel", "two-channels"])
def test_beat_pair_tones_separated(layout):
    fc, fb, amp = 250.0, 10.0, 2.0
    window = beat_window(FS, fb)
    assert window == 4800
    if layout == "one-channel":
        x = tones(2 * window, [fc - fb / 2, fc + fb / 2], [amp / 2, amp / 2], [0.4, -1.1])
        lock = LockIn(1, [[fc - fb / 2, fc + fb / 2]], FS, window)
        est = feed(lock, x)[-1][0]
    else:  # each cell demodulated at both tones: the absent one must read ~0
        x = tones(2 * window, [fc - fb / 2, fc + fb / 2], [amp / 2, amp / 2], [0.4, -1.1], n_channels=2, chan=[0, 1])
        lock = LockIn(2, [[fc - fb / 2, fc + fb / 2]] * 2, FS, window)
        out = feed(lock, x)[-1]
        assert out[0, 1, 0] < 1e-12 and out[1, 0, 0] < 1e-12
        est = np.array([out[0, 0], out[1, 1]])
    np.testing.assert_allclose(est[:, 0], [amp / 2, amp / 2], rtol=1e-10)
    np.testing.assert_allclose(est[:, 1], [0.4, -1.1], atol=1e-10)


@pytest.mark.parametrize("window", [2400, 4000, 7200], ids=lambda w: f"W{w}")
def test_leakage_follows_the_documented_formula(window):
    """A lone 255 Hz tone read at 245 Hz leaks by |D_W(10 Hz)| (+ its 500 Hz mirror)."""
    lock = LockIn(1, [[245.0]], FS, window, hop=8)
    est = feed(lock, tones(2 * window, [255.0], [1.0], [0.0]))[-1]
    bound = window_leakage(10.0, window, FS) + window_leakage(500.0, window, FS)
    low = window_leakage(10.0, window, FS) - window_leakage(500.0, window, FS)
    assert low - 1e-12 <= est[0, 0, 0] <= bound + 1e-12
    assert window_leakage(10.0, 4800, FS) < 1e-15


def test_against_least_squares_with_noise():
    """With a whole number of periods of every tone in the window the cos / sin columns are
    orthogonal, so the lock-in estimate is the least-squares fit: equal to round-off, noise or not."""
    rng = np.random.default_rng(0)
    window, n = 4800, 7000
    x = tones(n, [245.0, 255.0, 1000.0], [0.5, 0.2, 1.0], [0.1, 2.0, -1.0]) + 0.3 * rng.standard_normal((1, n))
    lock = LockIn(1, [[245.0, 255.0]], FS, window, hop=8)
    n_end = n - n % 8
    est = feed(lock, x[:, :n_end])[-1]
    for j, f in enumerate([245.0, 255.0]):
        fit = lstsq_fit(x[0, n_end - window : n_end], f, n_end)
        assert est[0, j, 0] == pytest.approx(abs(fit), rel=1e-9)
        assert np.angle(np.exp(1j * (est[0, j, 1] - np.angle(fit)))) == pytest.approx(0.0, abs=1e-9)


def test_matches_naive_twin_with_frequency_change():
    rng = np.random.default_rng(1)
    n, window, hop, ramp = 3000, 400, 8, 32
    x = rng.standard_normal(n)
    sched = {800: 1500.0, 1608: 900.0}
    lock = LockIn(1, [[300.0]], FS, window, hop=hop, ramp=ramp)
    got = []
    for a in range(0, n, hop):
        if a in sched:
            lock.set_freq([[sched[a]]])
        lock.process(x[None, a : a + hop].copy())
        got.append(lock.phasor[0, 0])
    want = naive_dsp.lockin(x, 300.0, FS, window, hop, ramp, sched)
    # window sums of 400 unit-variance products: round-off ~1e-14 of the sum's scale
    np.testing.assert_allclose(np.array(got), want, rtol=0, atol=1e-12)


def test_window_per_row_matches_naive_twin_per_row():
    """A window per row: every slot equals the one-channel twin over its own row's window, through
    many ring wraps of each (50, 12 and 30 hops) and a frequency change on one row."""
    rng = np.random.default_rng(4)
    n, hop, ramp = 3200, 8, 32
    windows = [400, 96, 240]
    freqs = [[300.0, 1000.0], [2000.0, 0.0], [600.0, 50.0]]
    x = rng.standard_normal((3, n))
    sched = {800: 1500.0}  # row 2, slot 0
    lock = LockIn(3, freqs, FS, windows, hop=hop, ramp=ramp)
    assert lock.window == 400 and lock.windows.tolist() == windows
    got = []
    for a in range(0, n, hop):
        if a in sched:
            lock.set_freq([freqs[0], freqs[1], [sched[a], 50.0]])
        lock.process(np.ascontiguousarray(x[:, a:a + hop]))
        got.append(lock.phasor)
    got = np.array(got)
    for r, (w, row) in enumerate(zip(windows, freqs)):
        for k, f in enumerate(row):
            if f == 0.0:
                assert np.isnan(got[:, r, k]).all()
                continue
            want = naive_dsp.lockin(x[r], f, FS, w, hop, ramp, sched if (r, k) == (2, 0) else None)
            np.testing.assert_allclose(got[:, r, k], want, rtol=0, atol=1e-12, err_msg=f"row {r} slot {k}")
    amp = lock.amplitude
    np.testing.assert_allclose(amp[np.isfinite(amp)], np.abs(got[-1])[np.isfinite(amp)], rtol=1e-12)


def test_window_per_row_validation():
    with pytest.raises(ValueError, match=r"window\[1\] = 100 is not a multiple of hop = 32"):
        LockIn(2, [[250.0], [500.0]], FS, [96, 100], hop=32)
    with pytest.raises(ValueError, match=r"window has shape \(3,\): expected an int or \(2,\)"):
        LockIn(2, [[250.0], [500.0]], FS, [96, 96, 96])
    assert LockIn(2, [[250.0], [500.0]], FS, [96, 48]).hop == 24  # the largest <= 32 dividing both


def test_reads_bank_phase_across_a_frequency_ramp():
    """Bank and lock-in ramp frequency alike, so the tone's phase relative to the reference
    stays phi; a reference that stepped instead would be off by 2 pi df (R - 1) / (2 fs)."""
    phi = 0.7
    bank = OscillatorBank(1, [0], FS, 200.0, 1.0, phi, ramp=32)
    lock = LockIn(1, [[200.0]], FS, 4800, hop=32, ramp=32)
    x = np.zeros((1, 32))
    for b in range(600):
        if b == 100:
            bank.set(0, freq=300.0)
            lock.set_freq([[300.0]])
        x[:] = 0.0
        bank.process(x)
        est = lock.process(x)
    assert est[0, 0, 0] == pytest.approx(1.0, rel=1e-10)
    assert est[0, 0, 1] == pytest.approx(phi, abs=1e-10)


@given(splits=st.lists(st.integers(1, 1999), max_size=20), per_row=st.booleans())
@settings(max_examples=30, deadline=None)
def test_chunk_invariance(splits, per_row):
    """Sums are accumulated in time order and hops close on the sample clock: bitwise equal."""
    x = np.random.default_rng(2).standard_normal((2, 2000))

    def final(cuts):
        lock = LockIn(2, [[100.0, 2000.0], [0.0, 50.0]], FS, [480, 160] if per_row else 480, hop=16)
        out = feed(lock, x, cuts)[-1]
        return out, lock.acc.copy(), lock.ref.copy()

    for a, b in zip(final(()), final(splits)):
        assert np.array_equal(a, b, equal_nan=True)


def test_unused_slots_read_nan():
    lock = LockIn(2, [[100.0, np.nan], [0.0, 200.0]], FS, 96)
    out = lock.process(np.ones((2, 96)))
    assert np.isnan(out[0, 1]).all() and np.isnan(out[1, 0]).all()
    assert np.isfinite(out[0, 0]).all() and np.isfinite(out[1, 1]).all()
    lock.set_freq([[100.0, 300.0], [0.0, 200.0]])
    out = lock.process(np.ones((2, 96)))
    assert np.isfinite(out[0, 1]).all()


def test_long_run_does_not_drift():
    """10**7 samples: a burst of 1e10-sized noise, then a unit tone. The estimate at the end must
    equal a fresh least-squares fit on the last window.

    A plain add-new / subtract-old window sum keeps the round-off of every value that ever went
    through it: after this burst it reads the tone 5e-7 off (measured by disabling the fresh-sum
    replacement in ``_lockin_hop``); the kernel's periodic fresh sum forgets the burst once the
    ring wraps and stays at ~1e-14.
    """
    n, window, hop = 10**7, 4800, 32
    rng = np.random.default_rng(3)
    lock = LockIn(1, [[250.0]], FS, window, hop=hop)
    bank = OscillatorBank(1, [0], FS, 250.0, 1.0, 0.3)
    block = 1 << 16
    done = 0
    while done < n:
        m = min(block, n - done)
        buf = rng.standard_normal((1, m)) * (1e10 if done < 10**6 else 1e-3)
        bank.process(buf)
        est = lock.process(buf)
        done += m
    assert m >= window
    fit = lstsq_fit(buf[0, m - window :], 250.0, n)
    assert est[0, 0, 0] == pytest.approx(abs(fit), rel=1e-10)
    assert est[0, 0, 1] == pytest.approx(np.angle(fit), abs=1e-10)
    ring_sum = lock.ring[:, 0, 0].sum() + 1j * lock.ring[:, 1, 0].sum()
    s = lock.acc[K.S_R, 0] + 1j * lock.acc[K.S_I, 0]
    assert abs(s - ring_sum) <= 1e-12 * np.abs(lock.ring[:, :, 0]).sum()


def test_no_subnormal_state_after_silence():
    lock = LockIn(1, [[250.0, 1000.0]], FS, 480, hop=16)
    feed(lock, tones(960, [250.0], [1.0], [0.0]))
    feed(lock, np.full((1, 2000), 1e-310))  # subnormal input, then silence
    feed(lock, np.zeros((1, 2000)))
    for a in (lock.acc, lock.ring, lock.ref):
        assert not np.any((a != 0) & (np.abs(a) < TINY_NORMAL))
    assert np.all(lock.amplitude == 0.0)


def test_kernel_args_order():
    lock = LockIn(1, [[250.0]], FS, 96)
    twin = LockIn(1, [[250.0]], FS, 96)
    x = tones(96, [250.0], [1.0], [0.0])
    out = np.empty((1, 1, 2))
    lockin_process(*lock.args, x, out)
    assert np.array_equal(out, twin.process(x))


def test_beat_window_and_validation():
    assert beat_window(FS, 7.0) == 48000 and beat_window(FS, 10.0, periods=3) == 14400
    with pytest.raises(ValueError, match=r"window = 100 is not a multiple of hop = 32"):
        LockIn(1, [[250.0]], FS, 100, hop=32)
    with pytest.raises(ValueError, match=r"freq\[0, 1\] = 30000.0 Hz is out of range"):
        LockIn(1, [[250.0, 30000.0]], FS, 96)
    with pytest.raises(ValueError, match=r"beat = 0.0 Hz"):
        beat_window(FS, 0.0)
    assert LockIn(1, [[250.0]], FS, 100).hop == 25


# --- least squares over windows that are not whole periods ------------------------------------------

def lstsq_fit_tones(xw, freqs, n_end):
    """Independent reference: joint least-squares fit of ``sum_k A_k cos(theta_k + phi_k)`` to the
    window ``xw`` ending at sample ``n_end`` (numpy ``lstsq``); returns ``A_k exp(i phi_k)``."""
    n = np.arange(n_end - len(xw), n_end)
    cols = []
    for f in freqs:
        theta = 2 * np.pi * np.array([naive_dsp.exact_cycles(f, FS, int(m)) for m in n])
        cols += [np.cos(theta), -np.sin(theta)]
    c, *_ = np.linalg.lstsq(np.stack(cols, axis=1), xw, rcond=None)
    return c[0::2] + 1j * c[1::2]


def test_lsq_gram_is_the_references_gram_matrix():
    """The closed form against numpy's ``A^T A`` of the window's cosines and sines, turned to the
    window's end (``theta_l = -w_l p`` at ``p`` samples before the next one)."""
    from rtctl.dsp.lockin import lsq_gram

    for freqs, w in (([235.0, 265.0], 1600), ([80.0], 608), ([35.0, 45.0, 250.0], 1000)):
        p = np.arange(1, w + 1)
        a = np.stack([g(2 * np.pi * f / FS * p) for f in freqs for g in (np.cos, np.sin)], axis=1)
        np.testing.assert_allclose(lsq_gram(freqs, w, FS), a.T @ a, atol=1e-9 * w)
    assert np.allclose(lsq_gram([235.0, 265.0], 9600, FS), 4800 * np.eye(4), atol=1e-8)  # whole periods


@pytest.mark.parametrize("window", [1600, 1632, 2080, 1280])
def test_least_squares_reads_a_pure_pair_exactly(window):
    """235 + 265 Hz (whole periods of both: 9600 samples) over one beat period (1600) and windows
    that are whole periods of neither tone nor of the beat: each tone read exactly (the closed
    form), where the plain sums are off by the neighbour and the mirrors."""
    x = tones(4800 + 7, [235.0, 265.0], [3.3, 1.2], [0.4, -2.1])
    lock = LockIn(1, [[235.0, 265.0]], FS, window, hop=32, lstsq=True)
    plain = LockIn(1, [[235.0, 265.0]], FS, window, hop=32)
    n = (x.shape[1] // 32) * 32
    feed(lock, x[:, :n], splits=range(0, n, 100))
    feed(plain, x[:, :n])
    want = np.array([3.3 * np.exp(0.4j), 1.2 * np.exp(-2.1j)])
    np.testing.assert_allclose(lock.phasor[0], want, rtol=0, atol=1e-12 * 3.3)
    np.testing.assert_allclose(lock.amplitude[0], [3.3, 1.2], rtol=1e-12)
    np.testing.assert_allclose(lock.phase[0], [0.4, -2.1], atol=1e-12)
    assert np.abs(plain.phasor[0] - want).max() > 1e-3
    assert 1.0 <= lock.cond[0] <= 2.0 and np.isnan(plain.cond[0])


def test_least_squares_against_numpy_lstsq_with_noise():
    """Two tones, a third one (not in the fit) and noise: the joint fit of the same samples by
    numpy's ``lstsq``, per row, each row over its own window; a plain row beside it unchanged."""
    rng = np.random.default_rng(11)
    n = 32 * 230
    x0 = tones(n, [235.0, 265.0, 700.0], [2.0, 1.5, 0.3], [1.0, 0.2, 0.0])[0] + 0.05 * rng.standard_normal(n)
    x1 = tones(n, [35.0, 45.0], [1.0, 0.7], [0.3, 2.0])[0] + 0.05 * rng.standard_normal(n)
    x = np.stack([x0, x1, x1])
    freqs = [[235.0, 265.0], [35.0, 45.0], [35.0, 45.0]]
    lock = LockIn(3, freqs, FS, [1632, 4800, 4800], hop=32, lstsq=[True, True, False])
    feed(lock, x, splits=range(0, n, 160))
    for r, w in ((0, 1632), (1, 4800)):
        np.testing.assert_allclose(lock.phasor[r], lstsq_fit_tones(x[r, -w:], freqs[r], n), rtol=0, atol=1e-11)
    plain = 2.0 / 4800 * np.array([np.sum(x1[-4800:] * np.exp(-2j * np.pi * f * np.arange(n - 4800, n) / FS))
                                   for f in (35.0, 45.0)])
    np.testing.assert_allclose(lock.phasor[2], plain, rtol=1e-9)


def test_least_squares_single_tone_any_window():
    """One tone over 608 samples (80 Hz: 1.013 periods): the mirror removed too."""
    x = tones(3200, [80.0], [2.0], [0.7])
    lock = LockIn(1, [[80.0, 0.0]], FS, 608, hop=32, lstsq=True)
    feed(lock, x)
    assert lock.phasor[0, 0] == pytest.approx(2.0 * np.exp(0.7j), abs=1e-12)
    assert np.isnan(lock.phasor[0, 1])


def test_least_squares_refuses_an_ill_conditioned_row():
    with pytest.raises(ValueError, match=r"row 0: least squares over 1600 samples .* ill-conditioned \(condition"):
        LockIn(1, [[249.0, 251.0]], FS, 1600, lstsq=True)  # 2 Hz apart: a twelfth of their beat
    lock = LockIn(1, [[235.0, 265.0]], FS, 1600, lstsq=True)
    with pytest.raises(ValueError, match=r"set_freq: least-squares rows"):
        lock.set_freq([[240.0, 270.0]])


@pytest.mark.parametrize("splits", [(), (5, 37, 38, 200, 517, 1111, 1500, 2222, 2999)])
def test_edges_give_the_first_differences_window_sums(splits):
    """``lockin_process_edges``: ``J S + (E - E')`` is the window sum of the first difference
    ``x[n] - x[n-1]`` (``x[-1] = 0``) against the reference, summed here sample by sample in
    numpy over the window of the last closed hop, with per-row windows, hops that do not divide
    the blocks, and a signal that steps."""
    rng = np.random.default_rng(7)
    freqs = np.array([[50.0, 230.0], [1000.0, 0.0]])
    windows = [48 * 20, 48 * 12]
    lock = LockIn(2, freqs, FS, windows, hop=48)
    n = 3000
    x = rng.normal(size=(2, n)) + np.repeat(rng.normal(size=(2, n // 100)) * 5, 100, axis=1)
    edge = np.zeros_like(lock.ring)
    ed = np.zeros((2, lock.acc.shape[1]))
    out = np.zeros((2, 2, 2))
    dx = np.diff(x, axis=1, prepend=0.0)
    cuts = sorted({0, n, *splits})
    checked = 0
    for a, b in zip(cuts[:-1], cuts[1:]):
        K.lockin_process_edges(*lock.args, np.ascontiguousarray(x[:, a:b]), out, edge, ed)
        end = (b // 48) * 48
        for r in range(2):
            for k in range(2):
                s = 2 * r + k
                f = freqs[r, k]
                if f <= 0.0 or end < windows[r]:
                    continue
                m = np.arange(end - windows[r], end)
                theta = 2 * np.pi * np.array([naive_dsp.exact_cycles(f, FS, int(i)) for i in m])
                want_s = np.sum(x[r, m] * np.exp(-1j * theta))
                want_d = np.sum(dx[r, m] * np.exp(-1j * theta))
                S = lock.acc[K.S_R, s] + 1j * lock.acc[K.S_I, s]
                J = 1.0 - np.exp(-2j * np.pi * f / FS)
                got_d = J * S + (ed[0, s] + 1j * ed[1, s])
                assert S == pytest.approx(want_s, rel=1e-9, abs=1e-9 * np.abs(want_s))
                assert abs(got_d - want_d) <= 1e-9 * np.sum(np.abs(x[r, m]))
                checked += 1
    assert checked >= 3  # (every slot of a block at least)
