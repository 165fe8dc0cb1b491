"""Plain-Python twins of the root-level kernels (safety limiter)."""

import math

from scipy.optimize import brentq


def _capped(row, v0, dv, h, sign):
    """``sign * row`` under a ceiling ``h`` that may fall from ``sign * v0`` at most ``dv`` per sample."""
    return [min(sign * v, max(h, sign * v0 - (i + 1) * dv)) for i, v in enumerate(row)]


def _measure(u, kind, scale, thr=None):
    if kind == 1:
        return sum(u) / len(u)
    if kind == 3:  # pin commands: the fraction of samples commanded on
        return sum(x > thr for x in u) / len(u)
    return scale * sum(max(x, 0.0) ** 2 for x in u) / len(u)


def _lower(row, v0, dv, vmax, sign, kind, scale, target, thr):
    """The highest ceiling whose measure stays <= target (scipy's brentq on the measure minus
    the target; a pin command's measure is a step: off, ceiling 0), applied to ``row``; returns
    the number of changed samples."""
    lo = -vmax if kind == 1 else 0.0
    hi = max([lo] + [sign * v for v in row])
    f = lambda h: _measure(_capped(row, v0, dv, h, sign), kind, scale, thr) - target  # noqa: E731
    if kind == 3 or f(lo) > 0:
        h = lo
    else:
        h = hi if f(hi) <= 0 else brentq(f, lo, hi, xtol=1e-15, rtol=1e-15)
    new = [sign * u for u in _capped(row, v0, dv, h, sign)]
    changed = sum(abs(a - b) > 1e-12 * vmax for a, b in zip(new, row))  # more than rounding
    row[:] = new
    return changed


def limit_block(x, state, params, fade, counts):
    """Per-sample reference of rtctl.safety.limit_block, written from its docstring: clip, then
    a slew clamp on every sample (no fast path), the running mean, heat integrated once per block."""
    status = 0
    vmax, dvmax, heat, rth, inv_fs_tau, tamb, tmax, joule, mkind, mbound, malpha, mscale, mcmd = params
    n = x.shape[1]
    hard = fade[1] > 0 and fade[2] == 0  # a fault's shutdown; fade[2] == 1: a requested stop's
    for c in range(x.shape[0]):
        v0 = prev = state[0, c]
        for i in range(n):
            v = x[c, i]
            k = fade[0] + i + 1
            if hard:  # a fault's shutdown ignores the request, NaN or not
                v = state[2, c] * max(0.0, 1.0 - k / fade[1])
            elif not math.isfinite(v):
                v, status = 0.0, status | 4
            if fade[1] > 0 and not hard:  # the request under a raised cosine, then 0
                v *= (1.0 + math.cos(math.pi * k / fade[1])) / 2.0 if k < fade[1] else 0.0
            if abs(v) > vmax[c]:
                v, status = math.copysign(vmax[c], v), status | 1
                counts[0, c] += 1
            if abs(v - prev) > dvmax[c]:
                v, status = prev + math.copysign(dvmax[c], v - prev), status | 2
                counts[1, c] += 1
            prev = x[c, i] = v
        row = list(x[c])
        a = 1.0 - math.exp(-n * malpha[c])
        kind, D = int(mkind[c]), mbound[c]
        if kind == 1:  # piezo DC offset: |m| <= D
            m = state[3, c]
            new = m + a * (sum(row) / n - m)
            if abs(new) > D and not hard:
                sign = 1.0 if new > 0 else -1.0
                g = sign * m
                ch = _lower(row, v0, dvmax[c], vmax[c], sign, 1, 1.0, g + (D - g) / a, None)
                counts[2, c] += ch
                status |= 1024 if ch else 0
                new = m + a * (sum(row) / n - m)
            state[3, c] = new
        elif kind in (2, 3):  # SMA duty, each polarity: mean (v / V_max)^2 (commands: time on) <= D
            for r, sign in ((0, 1.0), (1, -1.0)):
                g = state[3 + r, c]
                new = g + a * (_measure([sign * v for v in row], kind, mscale[c], mcmd[c]) - g)
                if new > D and not hard:
                    ch = _lower(row, v0, dvmax[c], vmax[c], sign, kind, mscale[c], g + (D - g) / a, mcmd[c])
                    counts[2, c] += ch
                    status |= 2048 if ch else 0
                    new = g + a * (_measure([sign * v for v in row], kind, mscale[c], mcmd[c]) - g)
                state[3 + r, c] = new
        x[c] = row
        energy = sq = 0.0
        prev = v0
        for v in row:
            energy += abs(v * (v - prev))
            sq += v * v
            prev = v
        a = 1.0 - math.exp(-n * inv_fs_tau[c])
        state[1, c] += a * (tamb[c] + rth[c] * (heat[c] * energy + joule[c] * sq) / n - state[1, c])
        state[0, c] = prev
        if state[1, c] > tmax[c]:
            status |= 8
    if fade[1] > 0:
        fade[0] += n
    return status
