"""Signals in a scene: sources, envelopes and their algebra, compiled into oscillator partials.

A scene's ``[[stimulus.signals]]`` name signals (a sine, a chirp, an ADSR envelope, the product
of two others...) and ``[[stimulus.play]]`` puts them on channels. Everything here runs once,
at build time: each signal becomes a list of :class:`Partial` -- one cosine each, with a
piecewise-linear frequency track and a piecewise-linear amplitude track -- which the stimulus
turns into oscillator-bank tones and block-rate ramp schedules (:mod:`rtctl.stimulus`).

The discrete law a partial plays (the oscillator bank's, see :mod:`rtctl.dsp.envelope`), with
tracks ``F`` (Hz) and ``A`` over time in samples ``x``::

    y[m]     = A(m + 1) cos(phase[m])
    phase[m] = phase0 + 2 pi sum_{j < m} F(j + 1) / fs

so sample ``m`` carries the tracks' value at its end. Algebra on partials is exact on this law:
``cos a cos b = (cos(a - b) + cos(a + b)) / 2`` and frequency tracks add sample by sample. The
only approximations, each within :data:`TOL` of the peak and flagged, are a product of two
amplitude tracks that both slope on the same stretch (a parabola drawn as straight lines) and
exponential fades (straight lines under the curve).

Duration rules (``None``: lasts until the run ends): a source lasts its ``duration`` (0: the
whole run); an envelope lasts the sum of its stages (its last breakpoint); a sum as long as its
longest term; a product as long as its shortest factor; a sequence the sum of its items' and
gaps; a repetition ``count`` items and ``count - 1`` gaps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .errors import SceneError

#: Straight lines standing in for a curve stay within this fraction of the curve's peak.
TOL = 1e-4
#: A smooth stage (an envelope's, a fade in or out) is a raised cosine drawn in this many
#: straight pieces (fewer when it is shorter than that many samples): its corners are so small
#: that nothing shows above the tactile band at -80 dB (docs/stimulus.md, "Clicks").
PIECES = 32


def smooth_stage(x0: float, x1: float, v0: float, v1: float, grid: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Breakpoints of a raised cosine from ``(x0, v0)`` to ``(x1, v1)``, both ends included, the
    ones between on multiples of ``grid`` samples (the block: so the bank plays each piece as
    drawn) and at most :data:`PIECES` pieces."""
    n = int(max(1, min(PIECES, (x1 - x0) // grid)))
    inner = np.round(np.linspace(x0, x1, n + 1)[1:-1] / grid) * grid
    x = np.unique(np.concatenate([[x0], inner[(inner > x0) & (inner < x1)], [x1]]))
    u = (x - x0) / (x1 - x0) if x1 > x0 else np.ones_like(x)
    return x, v0 + (v1 - v0) * 0.5 * (1.0 - np.cos(np.pi * u))


def draw(x, v, curve: str, grid: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Stages between breakpoints ``(x, v)`` straight (``linear``) or as raised cosines (``smooth``)."""
    x, v = np.asarray(x, float), np.asarray(v, float)
    if curve == "linear" or x.size < 2:
        return x, v
    xs, vs = [x[:1]], [v[:1]]
    for i in range(x.size - 1):
        if x[i + 1] == x[i] or v[i + 1] == v[i]:
            xs.append(x[i + 1:i + 2])
            vs.append(v[i + 1:i + 2])
            continue
        a, b = smooth_stage(x[i], x[i + 1], v[i], v[i + 1], grid)
        xs.append(a[1:])
        vs.append(b[1:])
    return np.concatenate(xs), np.concatenate(vs)
KINDS_SOURCE = ("sine", "square", "saw", "chirp", "noise", "dc")
KINDS_ENVELOPE = ("asr", "adsr", "breakpoints", "fade")
KINDS_COMBINE = ("sum", "product", "sequence", "repeat")
KINDS = KINDS_SOURCE + KINDS_ENVELOPE + KINDS_COMBINE


@dataclass(frozen=True)
class Track:
    """Breakpoints ``(x, v)``: straight lines between, constant before the first and after the last."""

    x: np.ndarray  # samples (integer-valued floats), non-decreasing
    v: np.ndarray

    def at(self, q):
        return np.interp(q, self.x, self.v)

    def shifted(self, s: float) -> Track:
        return Track(self.x + s, self.v)


def const(v: float) -> Track:
    return Track(np.array([0.0]), np.array([float(v)]))


@dataclass(frozen=True)
class Partial:
    """One cosine: ``phase`` (rad) at sample 0, tracks, and the span ``[lo, hi)`` it sounds in
    (``hi`` None: to the end of the run)."""

    phase: float
    freq: Track
    amp: Track
    lo: float = 0.0
    hi: float | None = None
    dc: bool = False  # a level, not a tone: frequency 0 and phase 0 (envelopes, dc sources)
    approx: bool = False  # some stretch is drawn as straight lines under a curve (TOL)


def shift(p: Partial, s: float, fs: float) -> Partial:
    """``p`` delayed by ``s`` samples; the phase at the new sample 0 keeps the first frequency."""
    ph = p.phase if p.dc else p.phase - 2 * math.pi * p.freq.v[0] * s / fs
    return replace(p, phase=ph, freq=p.freq.shifted(s), amp=p.amp.shifted(s), lo=p.lo + s,
                   hi=None if p.hi is None else p.hi + s)


def _union(*xs) -> np.ndarray:
    return np.unique(np.concatenate(xs))


def add_tracks(a: Track, b: Track, sign: float = 1.0) -> Track:
    """``a + sign b``: exact (both are straight between the union of their breakpoints)."""
    x = _union(a.x, b.x)
    return Track(x, a.at(x) + sign * b.at(x))


def mul_tracks(a: Track, b: Track) -> tuple[Track, bool]:
    """``a b`` as straight lines: exact where one factor is flat on a stretch, else the stretch is
    cut until the parabola's distance from its chords, ``|sa sb| L**2 / 4``, is within TOL of the
    peak. Returns the track and whether any stretch was cut."""
    x = _union(a.x, b.x)
    peak = max(np.abs(a.v).max() * np.abs(b.v).max(), 1e-300)
    pts, approx = [x[:1]], False
    for x0, x1 in zip(x[:-1], x[1:]):
        L = x1 - x0
        sa = (a.at(x1) - a.at(x0)) / L
        sb = (b.at(x1) - b.at(x0)) / L
        k = 1
        if sa != 0.0 and sb != 0.0:
            k = max(1, math.ceil(math.sqrt(abs(sa * sb) * L * L / (4 * TOL * peak))))
            approx = True
        pts.append(np.round(np.linspace(x0, x1, k + 1)[1:]))
    xs = np.unique(np.concatenate(pts))
    return Track(xs, a.at(xs) * b.at(xs)), approx


def multiply(p: Partial, q: Partial, fs: float) -> list[Partial]:
    """The partials of ``p q`` (product-to-sum; a level just scales the other factor)."""
    if q.dc:
        p, q = q, p
    amp, approx = mul_tracks(p.amp, q.amp)
    lo = max(p.lo, q.lo)
    hi = p.hi if q.hi is None else q.hi if p.hi is None else min(p.hi, q.hi)
    approx |= p.approx or q.approx
    if p.dc:
        return [Partial(q.phase, q.freq, amp, lo, hi, q.dc, approx)]
    half = Track(amp.x, amp.v * 0.5)
    out = []
    for sign in (-1.0, 1.0):
        f = add_tracks(p.freq, q.freq, sign)
        ph = p.phase + sign * q.phase
        if f.v.max() <= 0.0:  # cos is even: the difference tone at a positive frequency
            f, ph = Track(f.x, -f.v), -ph
        elif f.v.min() < 0.0:
            raise ValueError("the difference of the factors' frequencies crosses 0 Hz")
        out.append(Partial(ph, f, half, lo, hi, False, approx))
    return out


# ----------------------------------------------------------------------------- compile a scene


class Signals:
    """The scene's named signals, each compiled on demand into partials (local time from 0).

    Parameters
    ----------
    items : sequence of mapping
        The validated ``stimulus.signals`` tables.
    fs : float
    where : str
        Prefix of error messages (the scene's source).
    """

    def __init__(self, items, fs: float, where: str, grid: int = 1):
        self.fs, self.where, self.grid = float(fs), where, int(grid)
        self.items = {}
        for i, s in enumerate(items):
            if s["name"] in self.items:
                raise self._fail(s["name"], "name", s["name"], "names must be unique")
            self.items[s["name"]] = (i, s)
        self._done: dict[str, tuple] = {}
        self._busy: list[str] = []

    def _fail(self, name, key, value, problem) -> SceneError:
        i = self.items[name][0] if name in self.items else "?"
        v = repr(value) if not isinstance(value, float) else f"{value:g}"
        return SceneError(f"{self.where}: stimulus.signals.{i}.{key} = {v}: {problem} (signal {name!r})")

    def samples(self, t: float) -> float:
        return float(round(t * self.fs))

    def get(self, name: str, at: float = 0.0) -> tuple[list[Partial], float | None]:
        """Partials (from local sample 0) and duration (samples; None: the whole run) of signal
        ``name`` when it starts at run sample ``at``: smooth stages put their pieces on the
        block grid of the run, so where a signal starts changes how they are cut."""
        key = (name, at % self.grid)
        if key in self._done:
            return self._done[key]
        if name not in self.items:
            raise SceneError(f"{self.where}: no signal named {name!r} in stimulus.signals "
                             f"(have {', '.join(self.items) or 'none'})")
        if name in self._busy:
            raise self._fail(name, "of", list(self.items[name][1]["of"]),
                             f"refers back to itself ({' -> '.join(self._busy + [name])})")
        self._busy.append(name)
        try:
            out = self._build(name, self.items[name][1], at)
        finally:
            self._busy.pop()
        self._done[key] = out
        return out

    # --- the kinds -----------------------------------------------------------------------------

    def _build(self, name, s, at):
        kind = s["type"]
        if kind in KINDS_SOURCE:
            return self._source(name, s)
        if kind in KINDS_ENVELOPE:
            track, d, approx = self._envelope(name, s, at)
            return [Partial(0.0, const(0.0), track, 0.0, d, True, approx)], d
        ops = list(s["of"])
        if not ops:
            raise self._fail(name, "of", ops, f"a {kind} needs the names of its signals")
        if kind in ("sum", "product"):
            parts = [self.get(o, at) for o in ops]
        if kind == "sum":
            d = None if any(p[1] is None for p in parts) else max(p[1] for p in parts)
            return [x for p in parts for x in p[0]], d
        if kind == "product":
            acc, d = parts[0]
            for ps, dd in parts[1:]:
                try:
                    acc = [r for a in acc for b in ps for r in multiply(a, b, self.fs)]
                except ValueError as e:
                    raise self._fail(name, "of", ops, str(e)) from None
                d = dd if d is None else d if dd is None else min(d, dd)
            return acc, d
        gap = self.samples(s["gap"])
        if kind == "repeat":
            if len(ops) != 1:
                raise self._fail(name, "of", ops, "a repeat names one signal")
            ops = ops * s["count"]
        out, t, end = [], 0.0, 0.0
        for j, o in enumerate(ops):
            ps, d = self.get(o, at + t)
            if d is None and j < len(ops) - 1:
                raise self._fail(name, "of", list(s["of"]), f"{o!r} lasts the whole run: only the last item "
                                 "of a sequence may")
            out += [shift(p, t, self.fs) for p in ps]
            if d is None:
                return out, None
            end = max(end, t + d)
            if d + gap < 0 and j < len(ops) - 1:
                # the next item would start before this one: the order written is not the order
                # played (an overlap up to this item's whole length still keeps it)
                raise self._fail(name, "gap", s["gap"], f"an overlap longer than {o!r} "
                                 f"({d / self.fs:g} s): the item after it would start before it")
            t = t + d + gap
        return out, end

    def _duration(self, name, s, need=False):
        d = s["duration"]
        if d == 0.0:
            if need:
                raise self._fail(name, "duration", d, f"a {s['type']} needs a duration (s)")
            return None
        return self.samples(d)

    def _source(self, name, s):
        kind, amp, f = s["type"], s["amp"], s["freq"]
        d = self._duration(name, s, need=kind == "chirp" and not s["freqs"])
        ph = math.radians(s["phase"])
        nyq = self.fs / 2
        if kind == "dc":
            return [Partial(0.0, const(0.0), const(amp), 0.0, d, True)], d
        if kind == "noise":
            lo, hi = s["band"]
            if not 0.0 < lo < hi < nyq:
                raise self._fail(name, "band", list(s["band"]), f"needs 0 < low < high < fs / 2 = {nyq:g} Hz")
            rng = np.random.default_rng(s["seed"])
            m = s["components"]
            fr, phs = rng.uniform(lo, hi, m), rng.uniform(0.0, 2 * math.pi, m)
            c = amp / math.sqrt(m)  # the multisine's RMS is a sine's of amplitude amp
            return [Partial(float(p), const(x), const(c), 0.0, d) for x, p in zip(fr, phs)], d
        if f <= 0.0 and not (kind == "chirp" and s["freqs"]):
            raise self._fail(name, "freq", f, f"a {kind} needs a frequency above 0 Hz")
        if kind == "chirp" and s["freqs"]:
            t, fr = list(s["times"]), list(s["freqs"])
            if len(t) != len(fr) or t[0] != 0.0 or any(b < a for a, b in zip(t, t[1:])):
                raise self._fail(name, "freqs", fr, f"needs one frequency per time ({len(t)}), times from 0 in order")
            if min(fr) <= 0.0 or max(fr) >= nyq:
                raise self._fail(name, "freqs", fr, f"must be in (0, fs / 2 = {nyq:g}) Hz")
            ft, f = Track(np.array([self.samples(q) for q in t]), np.array(fr, float)), fr[0]
        elif kind == "chirp":
            f1 = s["freq_end"]
            if not 0.0 < f1 < nyq:
                raise self._fail(name, "freq_end", f1, f"must be in (0, fs / 2 = {nyq:g}) Hz")
            ft = Track(np.array([0.0, d]), np.array([f, f1]))
        else:
            ft = const(f)
        if f >= nyq:
            raise self._fail(name, "freq", f, f"at or above fs / 2 = {nyq:g} Hz")
        if kind in ("sine", "chirp"):
            return [Partial(ph, ft, const(amp), 0.0, d)], d
        # band-limited square / saw: their sine series, harmonics below fs / 2 only
        top = ft.v.max()
        out = []
        for k in range(1, s["harmonics"] + 1):
            if k * top >= nyq:
                break
            if kind == "square":
                if k % 2 == 0:
                    continue
                c = 4.0 / (math.pi * k)
                extra = 0.0
            else:
                c = 2.0 / (math.pi * k)
                extra = 0.0 if k % 2 else math.pi  # (-1)^(k+1) sin(k x)
            out.append(Partial(k * ph - math.pi / 2 + extra, Track(ft.x, k * ft.v), const(amp * c), 0.0, d))
        return out, d

    def _envelope(self, name, s, at):
        kind, amp = s["type"], s["amp"]
        smp = self.samples
        if kind == "asr":
            a, st, r = s["attack"], s["sustain"], s["release"]
            t = [0.0, a, a + st, a + st + r]
            v = [0.0, 1.0, 1.0, 0.0]
        elif kind == "adsr":
            a, dcy, st, r, lev = s["attack"], s["decay"], s["sustain"], s["release"], s["level"]
            t = [0.0, a, a + dcy, a + dcy + st, a + dcy + st + r]
            v = [0.0, 1.0, lev, lev, 0.0]
        elif kind == "breakpoints":
            t, v = list(s["times"]), list(s["levels"])
            if len(t) != len(v) or len(t) < 2:
                raise self._fail(name, "levels", v, f"needs as many levels as times ({len(t)}), at least 2")
            if t[0] != 0.0 or any(b < a for a, b in zip(t, t[1:])):
                raise self._fail(name, "times", t, "must start at 0 s and never decrease")
        else:  # fade: exponential, from 1 to 0 (out) or 0 to 1 (in) over duration, time constant tau
            d = self._duration(name, s, need=True)
            tau = smp(s["tau"])
            if tau <= 0.0:
                raise self._fail(name, "tau", s["tau"], "must be at least one sample")
            den = 1.0 - math.exp(-d / tau)
            # chord error of a convex curve: L**2 / 8 max |f''| <= TOL, max |f''| = 1 / (tau**2 den)
            n = max(1, math.ceil(d / math.sqrt(8 * TOL * tau * tau * den)))
            x = np.unique(np.round(np.linspace(0.0, d, n + 1)))
            y = (np.exp(-x / tau) - math.exp(-d / tau)) / den
            if s["direction"] == "in":  # the charging curve: fast first, settling at 1
                y = 1.0 - y
            return Track(x, amp * y), d, True
        x, v = draw([smp(q) + at for q in t], amp * np.asarray(v, float), s["curve"], self.grid)
        x = x - at
        return Track(x, v), float(x[-1]), False


@dataclass(frozen=True)
class Voice:
    """A partial placed on a channel, as the oscillator bank plays it: ``x`` breakpoints
    (samples, the union of both tracks', from the first change on), ``freq`` and ``amp`` at
    them; before ``x[0]`` the tone is at ``freq[0]`` and ``amp[0]`` (0)."""

    channel: int
    phase: float
    x: np.ndarray
    freq: np.ndarray
    amp: np.ndarray
    approx: bool
    signal: str


def place(p: Partial, channel: int, gain: Track | None, n_run: float, ramp: float, max_ramp: int,
          signal: str, grid: int = 1) -> Voice | None:
    """The partial ``p`` (already at its start time) on ``channel``, times ``gain``, gated to its
    span: a span that starts or ends at a level other than 0 fades in or out over ``ramp``
    samples (half the span at most) along a smooth stage. None when it never sounds within
    the run."""
    amp, approx = (p.amp, p.approx) if gain is None else mul_tracks(p.amp, gain)
    approx = approx or p.approx
    lo = p.lo
    hi = n_run if p.hi is None else min(p.hi, n_run)
    if hi <= lo:
        return None
    inner = amp.x[(amp.x > lo) & (amp.x < hi)]
    x = np.concatenate([[lo], inner, [hi]])
    v = amp.at(x)
    r = min(ramp, (hi - lo) / 2)
    r = float(np.floor(r))
    if v[0] != 0.0 and r > 0:  # fade in: a smooth stage from 0 to where the signal is r samples in
        keep = x > lo + r
        fx, fv = smooth_stage(lo, lo + r, 0.0, float(amp.at(lo + r)), grid)
        x, v = np.concatenate([fx, x[keep]]), np.concatenate([fv, v[keep]])
    if v[-1] != 0.0 and hi < n_run and r > 0:
        keep = x < hi - r
        fx, fv = smooth_stage(hi - r, hi, float(amp.at(hi - r)), 0.0, grid)
        x, v = np.concatenate([x[keep], fx]), np.concatenate([v[keep], fv])
    x, idx = np.unique(x, return_index=True)  # a span shorter than 2 ramps: one peak
    v = v[idx]
    if not np.any(v):
        return None
    # the frequency track from sample 0 (it sets the phase at the onset), then cut ramps longer
    # than the bank's longest (exact for straight lines)
    ux = _union(x, p.freq.x[(p.freq.x >= 0.0) & (p.freq.x < n_run)])
    gaps = np.diff(ux)
    if gaps.size and gaps.max() > max_ramp:
        ux = _union(ux, *[np.arange(a, b, max_ramp) for a, b in zip(ux[:-1], ux[1:]) if b - a > max_ramp])
    return Voice(channel, p.phase, ux, p.freq.at(ux), np.interp(ux, x, v), approx, signal)
