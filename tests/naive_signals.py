"""Naive numpy evaluations of signal expressions, written from the law in docs/stimulus.md (sample
``m`` carries the envelope's value at ``m + 1``; the phase advances by ``2 pi f(m + 1) / fs``),
not from the compiler: direct products of cosines, cumulative phases, per-sample loops."""

import math

import numpy as np

FS = 48000.0


def cosine(n, freq, phase0=0.0, start=0, fs=FS):
    """``cos(phase[m])`` with ``phase[start] = phase0`` and ``freq(x)`` (Hz at sample position x);
    before ``start`` the phase runs back at the first frequency."""
    m = np.arange(n, dtype=float)
    inc = 2 * math.pi * np.asarray(freq(m + 1.0), float) * np.ones(n) / fs
    ph = np.concatenate([[0.0], np.cumsum(inc[:-1])])
    return np.cos(phase0 + ph - ph[start])


def const(v):
    return lambda x: np.full(np.shape(x), float(v))


def line(x0, x1, f0, f1):
    """A frequency or level going straight from ``f0`` at sample ``x0`` to ``f1`` at ``x1``."""
    return lambda x: np.interp(x, [x0, x1], [f0, f1])


def raised_cosine(x0, x1, v0, v1, pieces=32, grid=1):
    """Breakpoints of a raised-cosine stage drawn in straight pieces, the inner ones on multiples
    of ``grid`` (documented law)."""
    n = int(max(1, min(pieces, (x1 - x0) // grid)))
    xs = [float(x0)]
    for j in range(1, n):
        x = round((x0 + (x1 - x0) * j / n) / grid) * grid
        if xs[-1] < x < x1:
            xs.append(float(x))
    xs.append(float(x1))
    vs = [v0 + (v1 - v0) * 0.5 * (1 - math.cos(math.pi * (x - x0) / (x1 - x0))) for x in xs]
    return xs, vs


def stages(points, curve="smooth", grid=1):
    """Breakpoints of ``[(x, v), ...]`` joined by raised cosines (or straight lines)."""
    xs, vs = [points[0][0]], [points[0][1]]
    for (x0, v0), (x1, v1) in zip(points, points[1:]):
        if curve == "linear" or v0 == v1 or x0 == x1:
            xs.append(x1)
            vs.append(v1)
            continue
        a, b = raised_cosine(x0, x1, v0, v1, grid=grid)
        xs += a[1:]
        vs += b[1:]
    return np.array(xs, float), np.array(vs, float)


def level(n, xs, vs):
    """Envelope per sample: its value at the end of the sample."""
    return np.interp(np.arange(n) + 1.0, xs, vs)


def block_events(n, block, xs, vs, v_init=0.0):
    """What a bank tone plays when, at the start of block ``floor(x_i / block)``, it is told to
    ramp to ``v_{i+1}`` over ``x_{i+1} - x_i`` samples, each ramp from the value of the sample
    before it; of two told at one block start the later holds, and a target equal to the one
    in force changes nothing: one sample at a time."""
    events = {}
    for i in range(len(xs) - 1):
        r = int(xs[i + 1] - xs[i])
        if r > 0:
            events[int(xs[i] // block) * block] = [(vs[i + 1], r)]
    out = np.empty(n)
    cur, target, step, left = v_init, v_init, 0.0, 0
    for m in range(n):
        for v, r in events.get(m, ()):
            if v != target:
                target, step, left = v, (v - cur) / r, r
        if left > 0:
            left -= 1
            cur = target if left == 0 else cur + step
        out[m] = cur
    return out
