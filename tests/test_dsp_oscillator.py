"""OscillatorBank and beat pairs: twin, chunk invariance, exact phase, continuity, beat envelope."""

from fractions import Fraction

import naive_dsp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit
from scipy.signal import hilbert

from rtctl.dsp import OscillatorBank, beat_tones, osc_bank_process
from rtctl.dsp import _kernels as K

FS = 48000.0
TINY_NORMAL = np.finfo(np.float64).tiny


def run(bank, n, splits=(), schedule=None):
    """Process ``n`` samples in calls split at ``splits`` (and at every scheduled change)."""
    schedule = schedule or {}
    cuts = sorted({0, n, *splits, *schedule})
    blocks = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        for i, f, amp, r in schedule.get(a, ()):
            bank.set(i, freq=f, amp=amp, ramp=r)
        out = np.zeros((bank.n_channels, b - a))
        bank.process(out)
        blocks.append(out)
    return np.concatenate(blocks, axis=1)


def subnormals(*arrays):
    return sum(int(np.count_nonzero((a != 0) & (np.abs(a) < TINY_NORMAL))) for a in arrays)


# ---- against the naive twin ------------------------------------------------------------------
CASES = {
    "one-tone-steady": dict(chan=[0], freq=[1234.5], amp=[0.7], phase=[0.3], sched={}),
    "shared-rows": dict(chan=[0, 0, 1, 2], freq=[100.0, 3000.0, 23999.0, 0.0], amp=[1.0, 0.25, 0.5, 0.1],
                        phase=[0, 1, 2, 3], sched={}),
    "ramps-across-calls": dict(
        chan=[0, 1, 1],
        freq=[250.0, 40.0, 1000.0],
        amp=[1.0, 0.5, 0.2],
        phase=[0.0, -1.0, 2.5],
        sched={
            100: [(0, 260.0, None, None), (1, None, 0.0, 77)],
            130: [(0, 5000.0, 2.0, 300)],  # new ramp starts mid-ramp
            700: [(2, 0.0, 1.0, 1), (1, 23000.0, 0.3, None)],
            1500: [(0, 250.0, 0.0, 1000)],  # spans several calls and an anchor
        },
    ),
}


@pytest.mark.parametrize("case", CASES.values(), ids=CASES.keys())
def test_matches_naive_twin(case):
    n = 3000
    bank = OscillatorBank(3, case["chan"], FS, case["freq"], case["amp"], case["phase"], ramp=64)
    got = run(bank, n, splits=range(0, n, 97), schedule=case["sched"])
    want, phase = naive_dsp.osc_bank(3, case["chan"], FS, case["freq"], case["amp"], case["phase"], 64, n,
                                     case["sched"])
    # Error budget: <= 256 complex rotations between exact anchors at ~2 ulp each (~1e-13),
    # the float-rounded ramp step DINC (R^2 * 1e-17 cycles) and np.cos' own rounding: 1e-12
    # of the summed amplitudes is a 10x margin.
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * 3)
    np.testing.assert_allclose(np.angle(np.exp(1j * (bank.phase - phase))), 0.0, atol=1e-12)


@given(
    splits=st.lists(st.integers(1, 2047), max_size=25),
    change_at=st.lists(st.integers(0, 2047), max_size=6),
    data=st.data(),
)
@settings(max_examples=40, deadline=None)
def test_chunk_invariance(splits, change_at, data):
    """Any split of the same calls gives bitwise identical samples, ramps spanning calls included.

    Bitwise because anchors sit on the global sample clock, ramps start at scheduled call
    boundaries, and the per-sample arithmetic of a tone does not depend on the call.
    """
    n = 2048
    sched = {}
    for j in change_at:
        i = data.draw(st.integers(0, 2), label="tone")
        f = data.draw(st.floats(0.0, FS / 2), label="freq")
        a = data.draw(st.floats(0.0, 2.0), label="amp")
        r = data.draw(st.integers(1, 600), label="ramp")
        sched.setdefault(j, []).append((i, f, a, r))
    make = lambda: OscillatorBank(2, [0, 1, 1], FS, [440.0, 30.0, 7000.0], [1.0, 0.5, 0.25], [0.0, 1.0, 2.0])  # noqa: E731
    one = run(make(), n, schedule=sched)
    many = run(make(), n, splits=splits, schedule=sched)
    assert np.array_equal(one, many)


# ---- exact phase over an hour ----------------------------------------------------------------
def test_frequency_by_phase_derivative_after_one_hour():
    """Run 172.8 M samples through the kernel; phase and frequency from the output stay exact.

    Tone 0 is cos(theta), tone 1 is cos(theta - pi/2) = sin(theta), so theta = atan2(y1, y0)
    comes from the samples alone. The exact theta of sample n is 2 pi frac(inc n) (inc is the
    float64 f / fs, a dyadic rational: computed with Python integers).
    """
    f = 1234.56789
    n_hour = int(3600 * FS)
    block = 1 << 20
    bank = OscillatorBank(2, [0, 1], FS, f, 1.0, [0.0, -np.pi / 2])
    out = np.empty((2, block))
    done = 0
    while done < n_hour:
        m = min(block, n_hour - done)
        buf = out[:, :m] if m == block else np.zeros((2, m))
        buf[:] = 0.0
        bank.process(buf)
        done += m
    tail = np.zeros((2, 48000))
    bank.process(tail)
    theta = np.unwrap(np.arctan2(tail[1], tail[0]))
    f_inst = np.diff(theta) * FS / (2 * np.pi)
    assert np.max(np.abs(f_inst / f - 1)) < 1e-9
    want = 2 * np.pi * naive_dsp.exact_cycles(f, FS, n_hour)
    err = np.angle(np.exp(1j * (theta[0] - want)))
    # a relative frequency error e over the hour would show as 2 pi f T e rad here
    assert abs(err) / (2 * np.pi * f * 3600) < 1e-15
    assert abs(err) < 1e-11


def test_phase_exact_across_the_sample_count_fold():
    """Steady segments re-base at K >= 2**30 samples: jump K there and compare with exact phase."""
    f = 987.654321
    bank = OscillatorBank(1, [0], FS, f, 1.0)
    k0 = (1 << 30) - 1000
    bank.state[K.K] = k0
    bank.state[K.CLOCK] = k0 - k0 % K.ANCHOR  # re-anchor from the jumped count on the next anchor
    bank.state[K.ZR], bank.state[K.ZI] = (np.cos(2 * np.pi * naive_dsp.exact_cycles(f, FS, k0)),
                                          np.sin(2 * np.pi * naive_dsp.exact_cycles(f, FS, k0)))
    out = np.zeros((1, 3000))
    bank.process(out)
    assert bank.state[K.K, 0] < 3000  # the fold happened
    n = k0 + np.arange(3000)
    want = np.cos(2 * np.pi * np.array([naive_dsp.exact_cycles(f, FS, int(m)) for m in n]))
    np.testing.assert_allclose(out[0], want, atol=1e-12)


def test_cis_without_libm_is_accurate():
    """The kernels' own cos / sin (octant + Taylor) against long-double numpy on exactly reduced
    arguments, including tiny negative ones (the ramp step D): within 4e-16 absolute."""
    rng = np.random.default_rng(0)
    c = np.concatenate([rng.uniform(-3, 3, 20000), rng.uniform(-1e-4, 1e-4, 2000), np.arange(-16, 17) / 16,
                        [1 / 16 + 1e-17, -(1e-300)]])
    got = np.array([K._cis(x) for x in c])
    r = np.array([float(Fraction(x) - round(Fraction(x))) for x in c])
    rl = np.longdouble(r) * np.longdouble("6.283185307179586476925286766559")
    assert np.max(np.abs(got[:, 0] - np.cos(rl))) < 4e-16
    assert np.max(np.abs(got[:, 1] - np.sin(rl))) < 4e-16
    small = (np.abs(c) < 1e-4) & (c != 0)  # relative accuracy where D lives
    assert np.max(np.abs(got[small, 1] / np.sin(rl[small]) - 1)) < 4e-16


# ---- no discontinuity at parameter changes ---------------------------------------------------
@pytest.mark.parametrize("ramp", [1, 32, 500], ids=lambda r: f"ramp{r}")
def test_no_jump_at_changes(ramp):
    """Sample steps stay within what the ramp allows; phase and envelope are continuous.

    For y = a cos(theta): |y[n+1] - y[n]| <= |a[n+1] - a[n]| + max(a) |theta[n+1] - theta[n]|,
    with |da| <= |a1 - a0| / R and dtheta <= 2 pi max(inc) (the increment never leaves
    [inc0, inc1]). Phase: the second difference of theta is the increment step, <= 2 pi |inc1 -
    inc0| / R; a phase jump of even 1e-6 rad would break it.
    """
    f0, f1, a0, a1 = 300.0, 2000.0, 0.2, 1.0
    bank = OscillatorBank(2, [0, 1], FS, f0, a0, [0.0, -np.pi / 2], ramp=ramp)
    sched = {500: [(0, f1, a1, None), (1, f1, a1, None)], 1500: [(0, f0, 0.0, None), (1, f0, 0.0, None)]}
    y = run(bank, 2500, splits=range(0, 2500, 32), schedule=sched)
    step_bound = abs(a1 - a0) / ramp + a1 * 2 * np.pi * f1 / FS + 1e-12
    assert np.max(np.abs(np.diff(y[0]))) <= step_bound
    env = np.hypot(y[0], y[1])
    assert np.max(np.abs(np.diff(env))) <= max(abs(a1 - a0), a1) / ramp + 1e-12
    theta = np.unwrap(np.arctan2(y[1], y[0])[:1500])  # before the fade to 0 (no phase there)
    d2 = np.diff(theta, 2)
    assert np.max(np.abs(d2)) <= 2 * np.pi * (f1 - f0) / FS / ramp + 1e-11
    assert np.diff(theta)[-1] == pytest.approx(2 * np.pi * f1 / FS, rel=1e-12)
    assert env[-1] == 0.0


def test_amplitude_ramp_is_linear_and_exact_at_end():
    bank = OscillatorBank(2, [0, 1], FS, 1000.0, 0.5, [0.0, -np.pi / 2], ramp=100)
    bank.set_all(amp=1.5)
    y = run(bank, 300, splits=[37, 61, 200])
    env = np.hypot(y[0], y[1])
    np.testing.assert_allclose(env[:100], 0.5 + np.arange(1, 101) / 100, atol=1e-13)
    assert bank.amp[0] == 1.5 and np.allclose(env[100:], 1.5, atol=1e-13)


def test_accessors_follow_the_ramp():
    bank = OscillatorBank(1, [0], FS, 100.0, 1.0, 0.5, ramp=10)
    bank.set(0, freq=200.0, amp=0.0)
    bank.process(np.zeros((1, 5)))
    assert bank.freq[0] == pytest.approx(150.0, rel=1e-12)
    assert bank.amp[0] == pytest.approx(0.5, rel=1e-12)
    assert bank.target_freq[0] == 200.0 and bank.target_amp[0] == 0.0
    bank.process(np.zeros((1, 5)))
    assert bank.freq[0] == pytest.approx(200.0, rel=1e-12) and bank.amp[0] == 0.0
    # phase of the next sample: 0.5 rad + the exact sum of the increments
    incs = [100.0 / FS + (100.0 / FS) * (k + 1) / 10 for k in range(10)]
    assert np.angle(np.exp(1j * (bank.phase[0] - 0.5 - 2 * np.pi * sum(incs)))) == pytest.approx(0.0, abs=1e-13)


def test_reset_restarts_identically():
    bank = OscillatorBank(2, [0, 1], FS, [100.0, 200.0], 1.0)
    first = run(bank, 1000, schedule={300: [(0, 900.0, 0.1, None)]})
    bank.reset()
    assert np.array_equal(run(bank, 1000, schedule={300: [(0, 900.0, 0.1, None)]}), first)


# ---- beat pairs ------------------------------------------------------------------------------
@pytest.mark.parametrize("split", [False, True], ids=["one-channel", "neighbour-cells"])
def test_beat_pair_envelope_and_carrier(split):
    fc, fb, amp = 250.0, 8.0, 1.2
    bank = OscillatorBank.beat_pairs(2, [[0, 1]] if split else [0], FS, fc, fb, amp)
    out = np.zeros((2, int(FS)))
    bank.process(out)
    y = out.sum(axis=0)  # what a finger between two cells feels is the superposition
    analytic = hilbert(y)
    env = np.abs(analytic)[2000:-2000]  # hilbert is periodic: trim its edge effects
    assert env.max() == pytest.approx(amp, rel=1e-3)
    # envelope amp |cos(pi fb t)|: nulls every 1 / fb
    nulls = 1 + np.flatnonzero((env[1:-1] < env[:-2]) & (env[1:-1] <= env[2:]) & (env[1:-1] < 0.05 * amp))
    assert len(nulls) >= 6
    assert np.diff(nulls) == pytest.approx(FS / fb, abs=2)
    assert np.max(np.abs(y)) == pytest.approx(amp, rel=1e-3)
    # carrier by the phase of the analytic signal, away from the envelope nulls
    phase = np.unwrap(np.angle(analytic))
    keep = (np.abs(analytic) > 0.5 * amp)[1:]
    f_inst = np.diff(phase)[keep][2000:-2000] * FS / (2 * np.pi)
    assert np.median(f_inst) == pytest.approx(fc, rel=1e-3)
    if split:  # one tone per cell: 246 Hz on row 0, 254 Hz on row 1 (1 Hz bins, no leakage)
        s0, s1 = (np.abs(np.fft.rfft(row)) / (FS / 2) for row in out)
        assert s0[246] == pytest.approx(amp / 2) and s0[254] < 1e-9
        assert s1[254] == pytest.approx(amp / 2) and s1[246] < 1e-9


def test_beat_tones_split_amplitude():
    f, a = beat_tones(300.0, 20.0, 1.0)
    assert list(f) == [290.0, 310.0] and list(a) == [0.5, 0.5]
    with pytest.raises(ValueError, match="carrier"):
        beat_tones(5.0, 20.0, 1.0)


def test_set_beat_retargets_without_jumps():
    bank = OscillatorBank.beat_pairs(1, [0], FS, 250.0, 10.0, 1.0, ramp=32)
    bank.set_beat((0, 1), carrier=400.0)
    assert list(bank.target_freq) == [395.0, 405.0] and list(bank.target_amp) == [0.5, 0.5]
    bank.set_beat((0, 1), beat=30.0, amp=2.0)
    assert list(bank.target_freq) == [385.0, 415.0] and list(bank.target_amp) == [1.0, 1.0]
    y = run(bank, 200, splits=[10, 20])[0]
    # each tone moves at most 2 pi 415 / fs rad per sample and its amplitude by 0.5 / 32
    assert np.max(np.abs(np.diff(y))) <= 2 * (1.0 * 2 * np.pi * 415 / FS + 0.5 / 32)


# ---- the loop's interface --------------------------------------------------------------------
@njit
def _block_step(state, pending, chan, out, new_amp):
    out[:] = 0.0
    pending[K.P_AMP, 0] = new_amp
    pending[K.P_FLAG, 0] = 1.0
    osc_bank_process(state, pending, chan, out)


def test_kernel_callable_from_an_njit_block_step():
    bank = OscillatorBank(1, [0], FS, 1000.0, 0.0, ramp=32)
    twin = OscillatorBank(1, [0], FS, 1000.0, 0.0, ramp=32)
    out = np.zeros((1, 32))
    _block_step(*bank.args, out, 1.0)
    twin.set(0, amp=1.0)
    want = np.zeros((1, 32))
    twin.process(want)
    assert np.array_equal(out, want) and bank.amp[0] == 1.0


# ---- subnormals and validation ---------------------------------------------------------------
def test_no_subnormal_state_after_silence():
    bank = OscillatorBank(2, [0, 1], FS, [100.0, 1000.0], [1.0, 1e-300], ramp=1000)
    bank.set_all(amp=[0.0, 1e-310])  # ramp to silence; a subnormal target is flushed
    run(bank, 5000, splits=[1234])
    assert subnormals(bank.state) == 0
    assert np.all(bank.amp == 0.0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(freq=30000.0), r"freq = 30000.0 Hz is out of range: allowed 0.0 <= freq <= fs / 2 = 24000.0 Hz"),
        (dict(amp=-1.0), r"amp = -1.0 is out of range"),
        (dict(tone_channel=[0, 3]), r"tone_channel\[1\] = 3 is out of range"),
        (dict(ramp=0), r"ramp = 0 is out of range"),
        (dict(fs=-1.0), r"fs = -1.0 Hz"),
        (dict(freq=[1.0, 2.0, 3.0]), r"freq has shape \(3,\)"),
    ],
    ids=["freq-above-nyquist", "negative-amp", "channel-out-of-range", "zero-ramp", "negative-fs", "freq-shape"],
)
def test_constructor_validation(kwargs, match):
    args = dict(n_channels=2, tone_channel=[0, 1], fs=FS, freq=100.0, amp=1.0) | kwargs
    with pytest.raises(ValueError, match=match):
        OscillatorBank(**args)


def test_process_and_set_validation():
    bank = OscillatorBank(2, [0, 1], FS, 100.0, 1.0)
    with pytest.raises(ValueError, match="rows: expected 2"):
        bank.process(np.zeros((3, 8)))
    with pytest.raises(ValueError, match="C-contiguous"):
        bank.process(np.zeros((8, 2)).T)
    with pytest.raises(ValueError, match="float64"):
        bank.process(np.zeros((2, 8), dtype=np.float32))
    with pytest.raises(ValueError, match=r"i = 2 is out of range"):
        bank.set(2, freq=1.0)
    with pytest.raises(ValueError, match=r"freq = -5.0 Hz"):
        bank.set(0, freq=-5.0)
    assert bank.pending[K.P_FLAG].sum() == 0  # a rejected change leaves nothing pending


@pytest.mark.parametrize("idx, f, amp, r, says", [
    ([0, 4], [10.0, 10.0], [1.0, 1.0], [1, 1], "i = 4 is out of range"),
    ([1, 1], [10.0, 10.0], [1.0, 1.0], [1, 1], "more than once"),
    ([0], [FS], [1.0], [1], r"freq\[0\] = 48000.0 Hz is out of range"),
    ([0], [10.0], [-1.0], [1], r"amp\[0\] = -1.0 is out of range"),
    ([0], [10.0], [1.0], [0], "ramp must be"),
    ([0], [10.0], [1.0], [K.MAX_RAMP + 1], "ramp must be"),
    ([0.0], [10.0], [1.0], [1], "integer"),
])
def test_check_many_refuses_what_set_refuses(idx, f, amp, r, says):
    bank = OscillatorBank(2, np.array([0, 1, 1, 0]), FS, np.full(4, 50.0), np.ones(4), np.zeros(4))
    with pytest.raises(ValueError, match=says):
        bank.check_many(np.array(idx), np.array(f), np.array(amp), np.array(r))
    idx, f, amp, r = bank.check_many(np.array([3, 1]), [60.0, 70.0], [0.5, 0.0], np.array([1, 5]))
    assert idx.dtype == np.int64 and r.dtype == np.float64 and list(r) == [1.0, 5.0]
