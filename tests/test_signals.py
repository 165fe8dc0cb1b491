"""Signals in a scene against naive numpy evaluations of the same expressions (tests/naive_signals.py),
sample for sample to 1e-9 of full scale; clicks against a spectrogram."""

import math

import numpy as np
import pytest
from naive_signals import FS, block_events, const, cosine, level, line, stages
from scipy import signal as sps

from rtctl import scene
from rtctl.errors import SceneError
from rtctl.signals import TOL
from rtctl.stimulus import Stimulus

BASE = scene.resolve("line-bimorph-5").read_text().split("[stimulus]")[0] + "[stimulus]\nkind = \"tones\"\n"


def render(stim, block=1, duration=0.1, overrides=()):
    """The oscillator bank's output for a scene's stimulus, block by block as the loop runs it."""
    s = scene.loads(BASE + stim, [f"timing.block={block}", f"timing.duration={duration}", *overrides])
    st = Stimulus(s, {"lateral": 0}, 5, FS, block)
    n = int(round(duration * FS))
    nb = -(-n // block)
    st.reset()
    out = np.zeros((5, nb * block))
    for k in range(nb):
        st.apply(k)
        blk = np.zeros((5, block))
        st.bank.process(blk)
        out[:, k * block:(k + 1) * block] = blk
    return out[:, :n], st


def close(got, want, full):
    err = np.abs(got - want).max() / full
    assert err <= 1e-9, f"max error {err:.3g} of full scale"


BURST = """
signals = [
  {name = "car", type = "sine", freq = 250.0, amp = 20.0, phase = 30.0},
  {name = "env", type = "asr", attack = 0.01, sustain = 0.02, release = 0.01, curve = "CURVE"},
  {name = "burst", type = "product", of = ["car", "env"]},
]
play = [{signal = "burst", channel = 2, start = START}]
"""


def burst(block, curve, start):
    return render(BURST.replace("CURVE", curve).replace("START", str(start)), block=block)[0]


def burst_points(s0):
    return [(s0, 0.0), (s0 + 480, 20.0), (s0 + 1440, 20.0), (s0 + 1920, 0.0)]


@pytest.mark.parametrize("curve", ["smooth", "linear"])
def test_sine_times_asr_is_the_naive_product_at_block_1(curve):
    out = burst(1, curve, 0.004)
    n = out.shape[1]
    xs, vs = stages(burst_points(192), curve)
    want = level(n, xs, vs) * cosine(n, const(250.0), math.radians(30.0), start=192)
    close(out[2], want, 20.0)
    assert not out[[0, 1, 3, 4]].any()


def test_block_aligned_times_play_the_same_at_block_32():
    """Every breakpoint on a block boundary (192, 672, 1632, 2112 samples): block size changes nothing."""
    np.testing.assert_allclose(burst(32, "linear", 0.004), burst(1, "linear", 0.004), rtol=0, atol=20.0 * 1e-9)


def test_unaligned_changes_are_handed_over_at_their_block_with_ramps_as_written():
    """Start 0.0051 s (244.8 samples -> 245): at block 64 each change starts at the beginning of its
    block, its ramp as long as written (naive per-sample event model), and the result stays within
    a block's worth of slope of the ideal signal."""
    out = burst(64, "smooth", 0.0051)
    n = out.shape[1]
    xs, vs = stages(burst_points(245), grid=64)
    carrier = cosine(n, const(250.0), math.radians(30.0), start=245)
    close(out[2], block_events(n, 64, xs, vs) * carrier, 20.0)
    ideal = level(n, xs, vs) * carrier
    slope = np.abs(np.diff(vs) / np.diff(xs)).max()
    assert np.abs(out[2] - ideal).max() <= slope * 64


def test_amplitude_modulation_is_the_product_of_the_cosines():
    stim = """
signals = [
  {name = "car", type = "sine", freq = 250.0, amp = 10.0},
  {name = "dc", type = "dc", amp = 0.5},
  {name = "mod", type = "sine", freq = 10.0, amp = 0.5},
  {name = "lift", type = "sum", of = ["dc", "mod"]},
  {name = "am", type = "product", of = ["car", "lift"]},
]
play = [{signal = "am", channel = 0}]
"""
    out, st = render(stim, duration=0.2)
    n = out.shape[1]
    assert st.bank.n_tones == 3  # 250 Hz, and 240 + 260 Hz
    fade = level(n, *stages([(0, 0.0), (960, 1.0)]))  # stimulus.ramp = 20 ms: it starts at full level
    m = np.arange(n)
    want = fade * 10.0 * np.cos(2 * np.pi * 250.0 * m / FS) * (0.5 + 0.5 * np.cos(2 * np.pi * 10.0 * m / FS))
    close(out[0], want, 10.0)


@pytest.mark.parametrize("seed", range(4))
def test_random_products_of_sums_are_the_products_of_the_cosines(seed):
    """(a1 + a2) x b x c with random frequencies, amplitudes and phases: the product-to-sum
    expansion (up to 12 tones) against the direct product of the factors, evaluated naively."""
    rng = np.random.default_rng(seed)
    f = rng.uniform(20.0, 400.0, 4)
    a = rng.uniform(0.2, 3.0, 4)
    ph = rng.uniform(-180.0, 180.0, 4)
    items = ",\n".join(f'  {{name = "s{i}", type = "sine", freq = {f[i]:.17g}, amp = {a[i]:.17g}, '
                       f'phase = {ph[i]:.17g}}}' for i in range(4))
    stim = f"""
signals = [
{items},
  {{name = "sum", type = "sum", of = ["s0", "s1"]}},
  {{name = "p", type = "product", of = ["sum", "s2", "s3"]}},
]
play = [{{signal = "p", channel = 1}}]
"""
    out, _ = render(stim, duration=0.1)
    n = out.shape[1]
    m = np.arange(n)
    cos = [a[i] * np.cos(2 * np.pi * f[i] * m / FS + math.radians(ph[i])) for i in range(4)]
    fade = level(n, *stages([(0, 0.0), (960, 1.0)]))
    want = fade * (cos[0] + cos[1]) * cos[2] * cos[3]
    close(out[1], want, (a[0] + a[1]) * a[2] * a[3])


def test_chirp_sweeps_its_frequency_in_a_straight_line():
    stim = """
signals = [{name = "up", type = "chirp", freq = 100.0, freq_end = 400.0, duration = 0.05, amp = 5.0}]
play = [{signal = "up", channel = 1, start = 0.01}]
"""
    out, _ = render(stim)
    n = out.shape[1]
    want = cosine(n, line(480, 2880, 100.0, 400.0), 0.0, start=480)
    env = level(n, *stages([(480, 0.0), (1440, 5.0), (1920, 5.0), (2880, 0.0)]))
    close(out[1], env * want, 5.0)


def test_sequence_and_repeat_place_items_one_after_another():
    stim = """
ramp = 0.005
signals = [
  {name = "a", type = "sine", freq = 200.0, duration = 0.03},
  {name = "b", type = "sine", freq = 300.0, duration = 0.03, phase = 90.0},
  {name = "ab", type = "sequence", of = ["a", "b"], gap = 0.01},
  {name = "twice", type = "repeat", of = ["ab"], count = 2, gap = 0.02},
]
play = [{signal = "twice", channel = 3}]
"""
    out, _ = render(stim, duration=0.2)
    n = out.shape[1]
    want = np.zeros(n)
    for t0, f, ph in ((0.0, 200.0, 0.0), (0.04, 300.0, 90.0), (0.09, 200.0, 0.0), (0.13, 300.0, 90.0)):
        s0 = round(t0 * FS)
        env = level(n, *stages([(s0, 0.0), (s0 + 240, 1.0), (s0 + 1200, 1.0), (s0 + 1440, 0.0)]))
        want += env * cosine(n, const(f), math.radians(ph), start=s0)
    close(out[3], want, 1.0)


@pytest.mark.parametrize("kind", ["square", "saw"])
def test_square_and_saw_are_their_band_limited_sine_series(kind):
    stim = f"""
ramp = 0.001
signals = [{{name = "w", type = "{kind}", freq = 50.0, amp = 2.0, harmonics = 7}}]
play = [{{signal = "w", channel = 0}}]
"""
    out, st = render(stim)
    n = out.shape[1]
    m = np.arange(n)
    ks = (1, 3, 5, 7) if kind == "square" else range(1, 8)
    want = sum((4 / (math.pi * k) if kind == "square" else (-1) ** (k + 1) * 2 / (math.pi * k))
               * np.sin(2 * np.pi * k * 50.0 * m / FS) for k in ks)
    fade = level(n, *stages([(0, 0.0), (48, 1.0)]))
    close(out[0], 2.0 * fade * want, 2.0)
    assert st.bank.n_tones == len(ks)


def test_envelopes_alone_play_as_levels():
    stim = """
signals = [
  {name = "e1", type = "adsr", attack = 0.01, decay = 0.005, level = 0.5, sustain = 0.02, release = 0.01, amp = 3.0},
  {name = "e2", type = "breakpoints", times = [0, 0.02, 0.03, 0.06], levels = [0, 1, 0.25, 0], curve = "linear"},
]
play = [{signal = "e1", channel = 0}, {signal = "e2", channel = 1, start = 0.01}]
"""
    out, _ = render(stim)
    n = out.shape[1]
    e1 = level(n, *stages([(0, 0.0), (480, 3.0), (720, 1.5), (1680, 1.5), (2160, 0.0)]))
    e2 = level(n, [480, 1440, 1920, 3360], [0.0, 1.0, 0.25, 0.0])
    close(out[0], e1, 3.0)
    close(out[1], e2, 1.0)


@pytest.mark.parametrize("direction", ["out", "in"])
def test_exponential_fade_stays_within_tol_of_the_exponential(direction):
    """Drawn as straight lines under the curve: within TOL of the peak, and not exact."""
    stim = f"""
signals = [{{name = "f", type = "fade", duration = 0.08, tau = 0.02, amp = 4.0, direction = "{direction}"}}]
play = [{{signal = "f", channel = 0}}]
"""
    out, _ = render(stim)
    d, tau = 0.08 * FS, 0.02 * FS
    x = np.arange(int(d)) + 1.0  # inside the fade (sample m carries x = m + 1)
    y = (np.exp(-x / tau) - math.exp(-d / tau)) / (1 - math.exp(-d / tau))
    want = 4.0 * (y if direction == "out" else 1.0 - y)
    # on its own it starts (out) or ends (in) at full level: stimulus.ramp (960 samples) fades that
    part = slice(960, int(d)) if direction == "out" else slice(0, int(d) - 960)
    err = np.abs(out[0, : int(d)] - want)[part]
    assert err.max() <= 4.0 * TOL * (1 + 1e-9)
    assert err.max() > 4.0 * TOL / 100  # straight lines, not the curve itself


def test_noise_is_a_multisine_with_a_sines_rms_in_its_band():
    stim = """
signals = [{name = "n", type = "noise", band = [100.0, 300.0], components = 64, amp = 2.0, seed = 7}]
play = [{signal = "n", channel = 4}]
"""
    out, _ = render(stim, duration=2.0)
    y = out[4, 4800:]
    assert abs(np.sqrt(np.mean(y**2)) - 2.0 / math.sqrt(2)) < 0.05 * 2.0 / math.sqrt(2)
    f, p = sps.welch(y, FS, window="blackmanharris", nperseg=8192, detrend=False)
    inside = (f >= 70.0) & (f <= 330.0)  # the band and the window's main lobe (4 bins of 5.9 Hz)
    assert p[~inside].sum() < 1e-6 * p[inside].sum()


def _broadband_db(y, cut=2000.0):
    """Worst spectrogram frame's energy above ``cut`` against the strongest frame's total, dB."""
    f, _, S = sps.spectrogram(y, FS, window="blackmanharris", nperseg=1024, noverlap=768, mode="psd")
    return 10 * np.log10(S[f > cut].sum(axis=0).max() / S.sum(axis=0).max())


CHANGES = """
ramp = RAMP
signals = [
  {name = "a", type = "sine", freq = 250.0, amp = 50.0, duration = 0.2},
  {name = "b", type = "sine", freq = 300.0, amp = 50.0, duration = 0.2},
  {name = "env", type = "adsr", attack = 0.03, decay = 0.03, level = 0.3, sustain = 0.05, release = 0.03},
  {name = "c", type = "sine", freq = 200.0, amp = 80.0},
  {name = "burst", type = "product", of = ["c", "env"]},
  {name = "all", type = "sequence", of = ["a", "b", "burst"], gap = -0.02},
]
play = [{signal = "all", channel = 0, start = 0.05}]
"""


def test_no_click_at_any_change_at_block_32():
    """Switch-on, a cross-fade between two frequencies, an ADSR burst, switch-off: nothing above
    2 kHz (the tactile band with an octave to spare) reaches -80 dB in any frame; the same
    changes with 0.1 ms fades do (the test can fail)."""
    smooth, _ = render(CHANGES.replace("RAMP", "0.02"), block=32, duration=0.8)
    hard, _ = render(CHANGES.replace("RAMP", "0.0001"), block=32, duration=0.8)
    assert _broadband_db(smooth[0]) < -80.0
    assert _broadband_db(hard[0]) > -60.0


@pytest.mark.parametrize("stim, words", [
    ('signals = [{name = "a", type = "sine", freq = 100.0}]\nplay = [{signal = "b"}]', "no such stimulus.signals"),
    ('signals = [{name = "a", type = "sum", of = ["b"]}, {name = "b", type = "sum", of = ["a"]}]\n'
     'play = [{signal = "a"}]', "refers back to itself"),
    ('signals = [{name = "a", type = "chirp", freq = 100.0, freq_end = 200.0}]\nplay = [{signal = "a"}]',
     "needs a duration"),
    ('signals = [{name = "a", type = "chirp", freq = 100.0, freq_end = 300.0, duration = 0.05}, '
     '{name = "b", type = "sine", freq = 200.0}, {name = "p", type = "product", of = ["a", "b"]}]\n'
     'play = [{signal = "p"}]', "crosses 0 Hz"),
    ('signals = [{name = "a", type = "sine", freq = 30000.0}]\nplay = [{signal = "a"}]', "fs / 2"),
    ('signals = [{name = "a", type = "sine", freq = 100.0}]\nplay = [{signal = "a", unit = "um"}]', "open loop"),
    ('signals = [{name = "a", type = "sine", freq = 100.0}]\nplay = [{signal = "a", channel = 5}]', "0..4"),
    ('signals = [{name = "a", type = "sine", freq = 100.0}, {name = "a", type = "dc"}]\nplay = [{signal = "a"}]',
     "unique"),
    ('signals = [{name = "a", type = "sine", freq = 100.0}, {name = "s", type = "sequence", of = ["a", "a"]}]\n'
     'play = [{signal = "s"}]', "whole run"),
])
def test_bad_signals_are_refused_in_one_line(stim, words):
    with pytest.raises(SceneError) as e:
        render(stim, duration=0.05)
    msg = str(e.value)
    assert words in msg and "\n" not in msg


OVERLAP = """
ramp = 0.005
signals = [
  {name = "a", type = "sine", freq = 200.0, duration = 0.03},
  {name = "b", type = "sine", freq = 300.0, duration = 0.03},
  {name = "ab", type = "sequence", of = ["a", "b"], gap = GAP},
  {name = "aaa", type = "repeat", of = ["a"], count = 3, gap = GAP},
]
play = [{signal = "PLAY", channel = 3}]
"""


@pytest.mark.parametrize("play, index", [("ab", 2), ("aaa", 3)])
def test_an_overlap_longer_than_the_item_before_is_refused(play, index):
    """gap = -0.05 s after a 0.03 s item would start the next 0.02 s before it: refused, naming the
    signal, the gap and the item, not clamped to the sequence's start; gap = -0.03 s still plays."""
    with pytest.raises(SceneError) as e:
        render(OVERLAP.replace("GAP", "-0.05").replace("PLAY", play), duration=0.1)
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.endswith(f"stimulus.signals.{index}.gap = -0.05: an overlap longer than 'a' (0.03 s): the item "
                        f"after it would start before it (signal {play!r})"), msg
    # gap = -duration, the longest overlap there is, plays: the next item starts with the one before
    out, _ = render(OVERLAP.replace("GAP", "-0.03").replace("PLAY", "ab"), duration=0.1)
    n = out.shape[1]
    env = level(n, *stages([(0, 0.0), (240, 1.0), (1200, 1.0), (1440, 0.0)]))
    close(out[3], env * (cosine(n, const(200.0), 0.0) + cosine(n, const(300.0), 0.0)), 2.0)


def test_tone_scenes_build_the_bank_they_always_did():
    """A scene without stimulus.play: the same tones, phases and schedule as before signals."""
    s = scene.load("line-bimorph-5")
    st = Stimulus(s, {"lateral": 0}, 5, FS, 32)
    assert st.bank.n_tones == 5 and not st._sig_schedule and not st.closed_voices
    np.testing.assert_array_equal(st.bank.phase, np.zeros(5))
    assert st._schedule == {0: [(i, v, None) for i, v in enumerate((140.0, 140.0, 40.0, 30.0, 1.0))]}


def test_a_tone_ramp_in_seconds_is_the_same_at_every_block_size():
    """tones.N.ramp = 5 ms: 240 samples of straight ramp at block 1 and at block 32, not one block."""
    outs = []
    for block in (1, 32):
        s = scene.load("line-bimorph-5", ["stimulus.tones.4.ramp=0.005", f"timing.block={block}"])
        st = Stimulus(s, {"lateral": 0}, 5, FS, block)
        st.reset()
        out = np.zeros((5, 480))
        for k in range(480 // block):
            st.apply(k)
            blk = np.zeros((5, block))
            st.bank.process(blk)
            out[:, k * block:(k + 1) * block] = blk
        outs.append(out[4])
    m = np.arange(480)
    want = np.minimum((m + 1) / 240, 1.0) * np.cos(2 * np.pi * 250.0 * m / FS)
    close(outs[0], want, 1.0)
    close(outs[1], want, 1.0)
