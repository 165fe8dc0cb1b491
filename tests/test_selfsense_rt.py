"""Real-time observer: kernel vs naive twin, and the accuracy targets (docs/selfsense.md) on the FE plant."""

import math

import numpy as np
import pytest
from naive_selfsense import observer_block, rebuild, steps_K

from rtctl.plant import Amplifier, BimorphPlant, CurrentSense, SimGroup
from rtctl.plant.beam import BeamSpec, Layer, build_beam
from rtctl.plant.materials import BUILTIN
from rtctl.selfsense.frontend import FrontEnd
from rtctl.selfsense.rt import Observer, ObserverRows, tone_window, tone_windows
from rtctl.selfsense.sweep import finger_loads, run_case
from rtctl.selfsense.tmm import TMMBeam, _load_stiffness

PZT = BUILTIN["PZT-5A"]
FS, BLOCK = 48000.0, 32


def fe_model():
    spec = BeamSpec(15e-3, 1.5e-3, (Layer(PZT, 0.3e-3), Layer(PZT, 0.3e-3)), "parallel",
                    (0.5, 0.5), 0.01)
    return build_beam(spec)


def _feed(obs, H, drive, sensed):
    """Run ``obs`` over the samples block by block; its matrices ``H`` and estimates as complex,
    and its segments per channel."""
    for b in range(drive.shape[1] // BLOCK):
        sl = slice(b * BLOCK, (b + 1) * BLOCK)
        assert obs.process(np.ascontiguousarray(drive[:, sl]), np.ascontiguousarray(sensed[:, sl])) == 0
    return H[..., 0] + 1j * H[..., 1], obs.est[..., 0] + 1j * obs.est[..., 1], obs.n_seg


def test_kernel_matches_naive_twin():
    rng = np.random.default_rng(5)
    freqs = np.array([[245.0, 255.0], [1000.0, 0.0], [120.0, 40.0]])
    obs = Observer(TMMBeam.from_fe(fe_model()), freqs, FS, BLOCK)
    H = rng.standard_normal(obs.H.shape)
    H[1, 1] = 0.0                                  # the unused slot
    obs.H[:] = H
    W = obs.window
    assert W == tone_window(freqs, FS, BLOCK) and W % BLOCK == 0
    n = np.arange(W)
    drive = np.stack([np.cos(2 * np.pi * f[0] * n / FS + 0.3) + rng.standard_normal(W) for f in freqs])
    sensed = rng.standard_normal((3 * obs.n_seg, W)) * 1e-6
    for b in range(W // BLOCK):
        sl = slice(b * BLOCK, (b + 1) * BLOCK)
        assert obs.process(np.ascontiguousarray(drive[:, sl]), np.ascontiguousarray(sensed[:, sl])) == 0
    Hc = H[..., 0] + 1j * H[..., 1]
    want = observer_block(Hc, drive, sensed, freqs, FS, obs.n_seg, K=steps_K(obs))
    got = obs.est[..., 0] + 1j * obs.est[..., 1]
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12 * np.abs(want).max())
    wave = rebuild(want[:, :, 0], freqs, FS, W - BLOCK, BLOCK)
    np.testing.assert_allclose(obs.wave, wave, rtol=1e-9, atol=1e-9 * np.abs(wave).max())


@pytest.mark.parametrize("rows", [1, 3])
def test_leading_rows_only(rows):
    """``rows``: the block step computes the leading estimate rows alone, each as the naive twin
    does (the rest of ``H`` is there, and ignored); a row not kept is refused by name."""
    from rtctl.errors import ModelError
    from rtctl.selfsense.observer import EST_NAMES

    rng = np.random.default_rng(7)
    freqs = np.array([[245.0, 255.0], [1000.0, 0.0]])
    obs = Observer(TMMBeam.from_fe(fe_model()), freqs, FS, BLOCK, rows=rows)
    assert obs.est.shape == (2, 2, rows, 2) and obs.H.shape[2] == len(EST_NAMES)
    H = rng.standard_normal(obs.H.shape)
    H[1, 1] = 0.0
    obs.H[:] = H
    W = obs.window
    n = np.arange(W)
    drive = np.stack([np.cos(2 * np.pi * f[0] * n / FS + 0.3) + rng.standard_normal(W) for f in freqs])
    sensed = rng.standard_normal((2 * obs.n_seg, W)) * 1e-6
    _, got, _ = _feed(obs, H, drive, sensed)
    want = observer_block(H[..., 0] + 1j * H[..., 1], drive, sensed, freqs, FS, obs.n_seg, K=steps_K(obs))
    np.testing.assert_allclose(got, want[:, :, :rows], rtol=1e-9, atol=1e-12 * np.abs(want).max())
    np.testing.assert_allclose(obs.wave, rebuild(want[:, :, 0], freqs, FS, W - BLOCK, BLOCK), rtol=1e-9,
                               atol=1e-9 * np.abs(want[:, :, 0]).max())
    assert np.array_equal(obs.phasors(EST_NAMES[rows - 1]), got[:, :, rows - 1])
    with pytest.raises(ModelError, match=rf"computes only tip_m.*rows={rows}\); build it with rows > {rows} "
                                         rf"to read {EST_NAMES[rows]}"):
        obs.phasors(EST_NAMES[rows])
    for bad in (0, len(EST_NAMES) + 1, 1.0, True):
        with pytest.raises(ModelError, match="rows must be an integer in 1 ... 9"):
            Observer(TMMBeam.from_fe(fe_model()), freqs, FS, BLOCK, rows=bad)


def test_window_per_channel_matches_naive_twin_per_channel():
    """Each channel over whole periods of its own tones only: its estimates and rebuilt wave are
    those of direct sums over its own last window (not the longest one's), through ring wraps."""
    rng = np.random.default_rng(6)
    freqs = np.array([[245.0, 255.0], [1000.0, 0.0], [120.0, 40.0], [250.0, 0.0]])
    windows = tone_windows(freqs, FS, BLOCK)
    # the smallest multiple of the block holding whole periods of the row's tones, by hand:
    # 245 and 255 Hz repeat every 9600 samples, 1 kHz every 48, 40 Hz every 1200, 250 Hz every 192
    assert windows.tolist() == [9600, 96, 2400, 192]
    obs = Observer(TMMBeam.from_fe(fe_model()), freqs, FS, BLOCK, window=windows)
    assert obs.window == 9600 and np.array_equal(obs.windows, windows)
    H = rng.standard_normal(obs.H.shape)
    H[1, 1] = H[3, 1] = 0.0                        # the unused slots
    obs.H[:] = H
    n_total = 9600 + 2400 + 5 * BLOCK              # not a multiple of any window but the last two
    n = np.arange(n_total)
    drive = np.stack([np.cos(2 * np.pi * f[0] * n / FS + 0.3) + rng.standard_normal(n_total) for f in freqs])
    sensed = rng.standard_normal((4 * obs.n_seg, n_total)) * 1e-6
    Hc, got, m = _feed(obs, H, drive, sensed)
    for c, w in enumerate(windows):
        rows = slice(c * m, (c + 1) * m)
        want = observer_block(Hc[c:c + 1], drive[c:c + 1, -w:], sensed[rows, -w:], freqs[c:c + 1], FS, m,
                              start=n_total - w, K=steps_K(obs)[c:c + 1], before=drive[c:c + 1, -w - 1])
        np.testing.assert_allclose(got[c:c + 1], want, rtol=1e-9, atol=1e-12 * np.abs(want).max())
        wave = rebuild(want[:, :, 0], freqs[c:c + 1], FS, n_total - BLOCK, BLOCK)
        np.testing.assert_allclose(obs.wave[c:c + 1], wave, rtol=1e-9, atol=1e-9 * np.abs(wave).max())
        for k, f in enumerate(freqs[c]):  # the drive's own phasor (amplitude, phase) per slot
            if f > 0:
                u = 2.0 / w * np.sum(drive[c, -w:] * np.exp(-2j * np.pi * f * np.arange(n_total - w, n_total) / FS))
                assert obs.u_out[c, k, 0] == pytest.approx(abs(u), rel=1e-9)
                assert obs.u_out[c, k, 1] == pytest.approx(np.angle(u), abs=1e-9)
        if w < obs.window:  # and the longest window would have given something else
            other = observer_block(Hc[c:c + 1], drive[c:c + 1, -obs.window:], sensed[rows, -obs.window:],
                                   freqs[c:c + 1], FS, m, start=n_total - obs.window, K=steps_K(obs)[c:c + 1],
                                   before=drive[c:c + 1, -obs.window - 1])
            assert np.abs(other - want).max() > 1e-3 * np.abs(want).max()
    # a channel's view: the observer's own arrays, indexed within the view
    view = ObserverRows(obs, 2, 4)
    assert view.n_channels == 2 and view.first == 2 and view.window == 2400
    assert np.shares_memory(view.est, obs.est) and np.array_equal(view.est, obs.est[2:4])
    assert view.est.flags.c_contiguous and view.u_out.flags.c_contiguous
    assert np.shares_memory(view.u_out, obs.u_out) and view.u_acc is obs.lock_u.acc
    assert np.array_equal(view.scale, 2.0 / windows[2:4])


def test_window_must_be_whole_hops():
    from rtctl.errors import ModelError

    with pytest.raises(ModelError, match=r"window\[1\] = 100 must be a multiple of hop = 32"):
        Observer(TMMBeam.from_fe(fe_model()), [[250.0], [500.0]], FS, BLOCK, window=[192, 100])
    with pytest.raises(ModelError, match=r"window\[1\] = 100 must be a multiple of hop = 8"):
        Observer(TMMBeam.from_fe(fe_model()), [[250.0], [500.0]], FS, BLOCK, window=[192, 100], hop=8)
    with pytest.raises(ModelError, match=r"hop = 12 must divide block = 32"):
        Observer(TMMBeam.from_fe(fe_model()), [[250.0]], FS, BLOCK, window=192, hop=12)


def test_nonfinite_reading_is_flagged():
    obs = Observer(TMMBeam.from_fe(fe_model()), [[250.0]], FS, BLOCK)
    drive = np.zeros((1, BLOCK))
    sensed = np.full((2, BLOCK), np.nan)
    assert obs.process(drive, sensed) != 0


CASES = [([10.0], 20.0), ([250.0], 20.0), ([1000.0], 20.0), ([245.0, 255.0], 10.0),
         ([995.0, 1005.0], 10.0)]


@pytest.mark.slow
@pytest.mark.parametrize("load", ["50g", "2g", "none"])
@pytest.mark.parametrize("freqs,volts", CASES, ids=["10Hz", "250Hz", "1kHz", "beat250", "beat1k"])
def test_observer_on_fe_plant_60db(freqs, volts, load):
    """Targets at 60 dB SNR: amplitude within 1 %, phase within 1 degree, tip force within
    5 % (none: 5 % of k_beam x). The truth plant keeps every mode up to 5 fs (8: the images of
    the DAC staircase at 1-4 fs sit beside modes 5-8, see test_image_model_*), and starts in
    its steady state. Measured worst: amplitude 0.07 %, phase 0.02 deg, force 0.5 %
    at 50 g, 1.7 % at 2 g (250 Hz, a 4 ms window: noise), 0.14 % without contact. On the
    loop's 4-mode plant the force is off by 4.5 % (50 g) and 14-19 % (2 g): docs/selfsense.md."""
    r = run_case(fe_model(), finger_loads()[load], freqs, [volts] * len(freqs), snr_db=60.0)
    assert r["n_modes"] == 8
    assert r["amp_err_pct"] < 1.0
    assert r["phase_err_deg"] < 1.0
    assert r["cond"] < 10
    assert r["force_err_pct"] < 5.0


@pytest.mark.parametrize("load", ["50g", "none"])
@pytest.mark.parametrize("f", [10.0, 1000.0])
def test_image_model_matches_a_converged_plant(f, load):
    """The observer removes the images of the DAC staircase (k fs +- f, about -13 % of each
    reading) as the continuum predicts them. The exact sampled response of the FE plant
    (its ZOH discretization at z = exp(j w dt)) minus its own k = 0 line is the plant's image
    sum. Measured, relative to the weaker segment's motional current: 8 modes 1.5e-4 - 4.4e-4,
    12 modes about the same; the loop's 4 modes 3.9e-3 - 1.3e-2, mostly from the images at 48
    and 96 kHz, beside modes 5 and 6 (69, 103 kHz) that it keeps only as static flexibility.
    A 2 g finger's force is ~12 % of k_beam x, so 0.6 % of the motional current is 15 % of it."""
    fe = fe_model()
    ld = finger_loads()[load]
    front = FrontEnd(FS, 20e3, 20e3, 2)
    beam = TMMBeam.from_fe(fe)
    w = 2 * math.pi * f
    img = front.images(f, lambda om: beam.solve(om, _load_stiffness(ld, om))["current"])
    P = (1 - np.exp(-1j * w / FS)) / (1j * w / FS)                     # zero-order hold
    miss = {}
    for n_modes in (4, 8):
        plant = BimorphPlant(fe, Amplifier(20e3), CurrentSense(100.0, 20e3, 2), ld, n_modes=n_modes)
        sensed = SimGroup(plant, FS, 1).sysd.frequency_response([f])[0, 4:6, 0]
        cont = plant.frequency_response([f])[0]              # continuous, per commanded volt
        line0 = front.aa(f) * P * cont[4:6]
        motional = front.aa(f) * P * (cont[4:6] - 1j * w * fe.Cp * cont[3])
        miss[n_modes] = np.abs(sensed - line0 - img).max() / np.abs(motional).min()
    assert miss[8] < 1e-3
    assert miss[4] > 3e-3


def test_short_windows_by_hand():
    """On the block grid unless that is more than twice the shortest window without leakage (or
    twice a shortest window of 50 ms or more): whole periods on the sample grid (fs / f's reduced
    numerator, least common multiple over a channel's tones), or one period of the closest spacing
    by least squares; a window of whole periods holding fewer than 4 of the lowest tone made the
    multiple of itself that does, if that is at most 4 ms; the hop the largest divisor of the
    block dividing them all."""
    from rtctl.selfsense.rt import short_windows

    w, lsq, hop = short_windows([[2.0], [10.0], [40.0], [120.0], [250.0]], FS, BLOCK)
    # 48000 / 40 = 1200 and 48000 / 120 = 400: the block grid's 2400 and 800 are twice that, kept
    assert w.tolist() == [24000, 4800, 2400, 800, 192] and not lsq.any() and hop == 32
    w, _, hop = short_windows([[40.0], [120.0]], FS, BLOCK, shorten=1)
    assert w.tolist() == [1200, 400] and hop == 16
    pairs = [[80.0, 0.0], [235.0, 265.0], [245.0, 255.0], [240.0, 270.0], [35.0, 45.0], [1000.0, 0.0]]
    w, lsq, hop = short_windows(pairs, FS, BLOCK)
    # 80 Hz: 600 against 2400; 235 + 265: one 30 Hz beat (1600) against 9600; 245 + 255: one 10 Hz
    # beat (4800, 100 ms: at least LONG_WINDOW_S) against 9600, taken at twice; 240 + 270 Hz:
    # whole periods of both are one beat (1600); 35 + 45: 4800 against 9600, taken; 1 kHz: 48
    # against 96, kept (twice, and 1 ms), then 2 periods made 4 (192 samples, 4 ms)
    assert w.tolist() == [600, 1600, 4800, 1600, 4800, 192]
    assert lsq.tolist() == [False, True, True, False, True, False] and hop == 8
    w, lsq, _ = short_windows(pairs, FS, BLOCK, long_s=0.2)  # twice is never enough
    assert w.tolist() == [600, 1600, 9600, 1600, 9600, 192]
    assert lsq.tolist() == [False, True, False, False, False, False]
    w, lsq, _ = short_windows(pairs, FS, BLOCK, shorten=1)
    assert w.tolist() == [600, 1600, 4800, 1600, 4800, 192]
    assert lsq.tolist() == [False, True, True, False, True, False]
    w, _, _ = short_windows(pairs, FS, BLOCK, shorten=1, ring_s=0.0)  # never longer: 1 period
    assert w.tolist() == [600, 1600, 4800, 1600, 4800, 48]
    # 500 Hz: 4 periods would be 8 ms, kept at 1 (96); 1500 Hz: 1 period (32) made 4 (128); 2 kHz:
    # already 4 (96); 1 kHz asked for 3 periods: the multiple of its 96 that holds them (192)
    w, _, hop = short_windows([[500.0], [1500.0], [2000.0]], FS, BLOCK)
    assert w.tolist() == [96, 128, 96] and hop == 32
    assert short_windows([[1000.0]], FS, BLOCK, min_periods=3)[0].tolist() == [192]
    assert short_windows([[500.0]], FS, BLOCK, ring_s=0.008)[0].tolist() == [384]
    # a tone whose one period (601 samples) would need a hop of 1: one period rounded up to the
    # block by least squares instead (608 samples, 1.013 periods)
    w, lsq, hop = short_windows([[48000.0 / 601, 0.0], [80.0, 0.0]], FS, BLOCK)
    assert w.tolist() == [608, 600] and lsq.tolist() == [True, False] and hop == 8
    # too close for a window of one beat on the block grid to be well conditioned: whole periods
    w, lsq, _ = short_windows([[249.0, 251.0]], FS, BLOCK, max_cond=1.0, shorten=1)
    assert w.tolist() == [48000] and not lsq.any()  # 1 / gcd(249, 251 Hz) = 1 s


def test_least_squares_channels_match_numpy_lstsq():
    """Channels read by least squares over one beat period and a single tone over 600 samples
    with a hop of 8: each estimate is ``H`` applied to the joint least-squares phasors (numpy
    ``lstsq``) of the drive and of each current over the channel's own last window."""
    rng = np.random.default_rng(8)
    freqs = np.array([[235.0, 265.0], [80.0, 0.0]])
    windows, lsq = np.array([1600, 600]), np.array([True, False])
    obs = Observer(TMMBeam.from_fe(fe_model()), freqs, FS, BLOCK, window=windows, hop=8, lstsq=lsq)
    H = rng.standard_normal(obs.H.shape)
    H[1, 1] = 0.0
    obs.H[:] = H
    n_total = 1600 + 20 * BLOCK
    n = np.arange(n_total)
    drive = np.stack([sum(np.cos(2 * np.pi * f * n / FS + p) for f, p in zip(row, (0.3, 1.9)) if f > 0)
                      for row in freqs]) + 0.1 * rng.standard_normal((2, n_total))
    sensed = rng.standard_normal((2 * obs.n_seg, n_total)) * 1e-6
    Hc, got, m = _feed(obs, H, drive, sensed)
    for c, w in enumerate(windows):
        f = freqs[c][freqs[c] > 0]
        t = np.arange(n_total - w, n_total)
        a = np.stack([g(2 * np.pi * fk * t / FS) for fk in f for g in (np.cos, lambda x: -np.sin(x))], axis=1)

        def fit(x, a=a, w=w):
            coef, *_ = np.linalg.lstsq(a, x[-w:], rcond=None)
            return coef[0::2] + 1j * coef[1::2]

        ph = np.stack([fit(drive[c])] + [fit(sensed[c * m + j]) for j in range(m)], axis=-1)  # (n_f, 1 + m)
        want = np.einsum("kej,kj->ke", Hc[c, :f.size], ph)
        # less a drive step's term: the first difference's phasors over a steady tone's, less the drive's
        d = fit(np.diff(drive[c, -w - 1:])) / (1.0 - np.exp(-2j * np.pi * f / FS))
        want -= steps_K(obs)[c, :f.size] * (d - ph[:, 0])[:, None]
        np.testing.assert_allclose(got[c, :f.size], want, rtol=1e-9, atol=1e-9 * np.abs(want).max())
        np.testing.assert_allclose(obs.u_out[c, :f.size, 0], np.abs(ph[:, 0]), rtol=1e-9)


def _tone_window_one_by_one(freqs, fs, hop, max_seconds=1.0):
    """tone_window as a plain loop over the candidate windows (the reference)."""
    f = np.asarray(freqs, dtype=float).ravel()
    f = f[np.isfinite(f) & (f > 0)]
    m_max = max(1, int(max_seconds * fs) // hop)
    for m in range(1, m_max + 1):
        cyc = f * (m * hop) / fs
        if np.all(np.abs(cyc - np.round(cyc)) < 1e-9):
            return m * hop
    return m_max * hop


def test_tone_window_is_the_first_candidate_of_whole_periods():
    """Against the candidates tried one by one: tones with short, long and no whole-period
    windows (the last give up at max_seconds), beat pairs, unused slots, several hops."""
    rng = np.random.default_rng(7)
    rows = [[250.0], [245.0, 255.0], [2.0, 0.0], [80.0], [601.0], [123.456], [0.0], [np.nan, 40.0],
            [1000.0, 1500.0, 1200.0], [47.9]]
    rows += [[round(x, k)] for x, k in zip(rng.uniform(20.0, 900.0, 40), rng.integers(0, 4, 40))]
    for row in rows:
        for fs, hop, sec in ((48000.0, 32, 1.0), (48000.0, 8, 1.0), (44100.0, 64, 2.0), (48000.0, 32, 0.01)):
            assert tone_window(row, fs, hop, sec) == _tone_window_one_by_one(row, fs, hop, sec), (row, hop)


def test_a_grid_window_that_leaks_is_never_the_default():
    """At block 1024 no multiple of the block within 1 s holds whole periods of 2 Hz (24 000
    samples is 23.4 blocks): the observer's default window and the closed loop's short windows
    are then whole periods with a finer hop, and a 2 Hz drive reads its amplitude exactly (the
    grid's 47 104 samples, 1.96 periods, read it 0.3 % off here; the closed loop's 2 Hz tip
    estimate, through the observer's matrices, read 11 % high)."""
    from rtctl.selfsense.rt import block_window, holds_whole_periods, short_windows

    block, f, amp = 1024, 2.0, 3.0
    leaky = tone_window([f], FS, block)
    assert not holds_whole_periods([f], leaky, FS)  # the case this guards against exists
    assert block_window([f], FS, block) == (24000, 64)
    w, lsq, hop = short_windows([[2.0], [10.0], [40.0]], FS, block)
    assert w.tolist() == [24000, 4800, 1200] and not lsq.any() and hop == 16
    assert block_window([f], FS, 32) == (24000, 32)  # on the grid when it holds whole periods

    obs = Observer(TMMBeam.from_fe(fe_model()), [[f]], FS, block)
    assert (obs.window, obs.hop) == (24000, 64)
    n = np.arange(3 * obs.window + block)
    drive = amp * np.cos(2 * np.pi * f * n / FS + 0.4)
    sensed = np.zeros((obs.n_seg, block))
    for b in range(len(n) // block):
        obs.process(np.ascontiguousarray(drive[None, b * block:(b + 1) * block]), sensed)
    assert obs.lock_u.amplitude[0, 0] == pytest.approx(amp, rel=1e-9)
    grid = Observer(TMMBeam.from_fe(fe_model()), [[f]], FS, block, window=leaky)
    for b in range(len(n) // block):
        grid.process(np.ascontiguousarray(drive[None, b * block:(b + 1) * block]), sensed)
    assert abs(grid.lock_u.amplitude[0, 0] / amp - 1.0) > 1e-3  # what the default avoids
