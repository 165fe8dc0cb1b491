"""Plain per-sample twins of the ``rtctl.dsp`` kernels (as stumpy's ``tests/naive.py``).

Written for obviousness, not speed: phases are accumulated sample by sample as exact rationals
(``fractions.Fraction``) and turned into samples with ``np.cos``; window sums are recomputed
from scratch. A schedule of changes is a dict ``{sample index: [change, ...]}``; changes at
index ``j`` are applied just before sample ``j`` (i.e. at the start of a call beginning there).
"""

from collections import deque
from fractions import Fraction

import numpy as np

PULSE_UNIT = 2**40


class _Tone:
    """One oscillator: exact phase (cycles), the ramp law of the docs, amplitude in float.

    A change restarts the ramp of each parameter whose target changed, from its current value
    (the last applied increment, the amplitude of the last sample); the other one carries on.
    """

    def __init__(self, fs, freq, amp, phase_rad, ramp):
        self.fs = fs
        self.phase = Fraction(phase_rad / (2 * np.pi)) % 1
        self.inc = Fraction(freq / fs)  # the float64 quotient, held exactly
        self.amp = float(amp)
        self.ramp = ramp
        self.target_freq = freq
        self.target_amp = amp
        self.f_left = self.a_left = 0

    def change(self, freq=None, amp=None, ramp=None):
        r = self.ramp if ramp is None else ramp
        if freq is not None and freq / self.fs != self.target_freq / self.fs:
            self.target_freq = freq
            self.inc0, self.inc1 = self.inc, Fraction(freq / self.fs)
            self.f_r, self.f_k, self.f_left = r, 0, r
        if amp is not None and amp != self.target_amp:
            self.target_amp = amp
            self.a0, self.a1 = self.amp, float(amp)
            self.a_r, self.a_k, self.a_left = r, 0, r

    def step(self):
        """Return this sample's value and advance the phase by one sample."""
        if self.f_left > 0:
            self.f_k += 1
            self.f_left -= 1
            self.inc = self.inc1 if self.f_left == 0 else self.inc0 + (self.inc1 - self.inc0) * self.f_k / self.f_r
        if self.a_left > 0:
            self.a_k += 1
            self.a_left -= 1
            self.amp = self.a1 if self.a_left == 0 else self.a0 + (self.a1 - self.a0) * self.a_k / self.a_r
        y = self.amp * np.cos(2 * np.pi * float(self.phase))
        self.phase = (self.phase + self.inc) % 1
        return y

    @property
    def phase_rad(self):
        return 2 * np.pi * float(self.phase)


def osc_bank(n_channels, chan, fs, freq, amp, phase, ramp, n, schedule=None):
    """Twin of ``OscillatorBank``: ``out`` shape (n_channels, n) and the tones' final phases (rad).

    ``schedule[j]`` is a list of ``(i, freq, amp, ramp)`` (``None`` keeps).
    """
    nt = len(chan)
    freq, amp, phase = (np.broadcast_to(np.asarray(v, float), (nt,)) for v in (freq, amp, phase))
    tones = [_Tone(fs, freq[i], amp[i], phase[i], ramp) for i in range(nt)]
    schedule = schedule or {}
    out = np.zeros((n_channels, n))
    for j in range(n):
        for i, f, a, r in schedule.get(j, ()):
            tones[i].change(f, a, r)
        for i, tone in enumerate(tones):
            out[chan[i], j] += tone.step()
    return out, np.array([t.phase_rad for t in tones])


def exact_cycles(freq, fs, n):
    """``frac(inc * n)`` for the float64 increment ``inc = freq / fs``, exactly (inc is dyadic)."""
    return float((Fraction(freq / fs) * n) % 1)


def pulse_train(fs, freq, duty, high, low, phase, n, schedule=None):
    """Twin of ``PulseTrain`` for one channel: exact rational cycle position.

    The frequency and duty are the documented grid values ``round(x * 2**40) / 2**40``.
    ``schedule[j]`` is a dict with any of ``freq, duty, high, low``.
    """
    grid = lambda x: Fraction(int(np.floor(x * PULSE_UNIT + 0.5)), PULSE_UNIT)  # noqa: E731
    pos = Fraction(int(np.floor(phase * PULSE_UNIT)), PULSE_UNIT)
    p = dict(freq=freq, duty=duty, high=high, low=low)
    out = np.zeros(n)
    for j in range(n):
        p.update((schedule or {}).get(j, {}))
        inc, d = grid(p["freq"] / fs), grid(p["duty"])
        out[j] = p["high"] if pos < d else p["low"]
        pos = (pos + inc) % 1
    return out


def lockin(x, freq, fs, window, hop, ramp=1, schedule=None):
    """Twin of ``LockIn`` for one channel and one frequency, window sums recomputed directly.

    Returns the estimates ``A exp(i phi)`` after each completed hop, shape (n // hop,), where
    ``x ~ A cos(theta + phi)`` and ``theta`` is a reference tone (phase 0 at sample 0, the
    oscillator ramp law on changes). ``schedule[j]`` is a new frequency.
    """
    ref = _Tone(fs, freq, 1.0, 0.0, ramp)
    prods = deque([0j] * window, maxlen=window)
    est = []
    for j, v in enumerate(x):
        if j in (schedule or {}):
            ref.change(schedule[j], None)
        theta = 2 * np.pi * float(ref.phase)
        ref.step()
        prods.append(v * np.exp(-1j * theta))
        if (j + 1) % hop == 0:
            est.append(2.0 / window * np.sum(np.array(prods)))
    return np.array(est)


def ramp(values0, n, ramp_len, schedule=None):
    """Twin of ``Ramp`` for one parameter: ``v[k] = v0 + (v1 - v0)(k + 1)/R``, last = target."""
    v = float(values0)
    out = np.zeros(n)
    seg = None
    for j in range(n):
        if j in (schedule or {}):
            target, r = schedule[j]
            seg = (v, target, r or ramp_len, 0)
        if seg is not None:
            v0, v1, r, k = seg
            v = v1 if k + 1 == r else v0 + (v1 - v0) / r * (k + 1)
            seg = None if k + 1 == r else (v0, v1, r, k + 1)
        out[j] = v
    return out


def fade_gain(g0, g1, length, n):
    """Gains of ``n`` samples of a raised-cosine fade from ``g0`` to ``g1`` over ``length``."""
    k = np.arange(1, n + 1)
    g = g1 + (g0 - g1) * 0.5 * (1 + np.cos(np.pi * np.minimum(k, length) / length))
    g[k >= length] = g1
    return g
