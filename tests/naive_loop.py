"""Plain-Python twins of the root-level kernels (safety limiter)."""

import math

import numpy as np


def limit_block(x, state, params, fade, counts):
    """Per-sample reference of rtctl.safety.limit_block, written from its docstring: clip, then
    a slew clamp on every sample (no fast path), heat integrated once per block."""
    status = 0
    vmax, dvmax, heat, rth, inv_fs_tau, tamb, tmax, joule = params
    n = x.shape[1]
    for c in range(x.shape[0]):
        v0 = prev = state[0, c]
        energy = 0.0
        sq = 0.0
        for i in range(n):
            v = x[c, i]
            if fade[1] > 0:  # a shutdown ignores the request, NaN or not
                k = fade[0] + i + 1
                v = state[2, c] * max(0.0, 1.0 - k / fade[1])
            elif not math.isfinite(v):
                v, status = 0.0, status | 4
            if abs(v) > vmax[c]:
                v, status = math.copysign(vmax[c], v), status | 1
                counts[0, c] += 1
            if abs(v - prev) > dvmax[c]:
                v, status = prev + math.copysign(dvmax[c], v - prev), status | 2
                counts[1, c] += 1
            energy += abs(v * (v - prev))
            sq += v * v
            prev = x[c, i] = v
        a = 1.0 - math.exp(-n * inv_fs_tau[c])
        state[1, c] += a * (tamb[c] + rth[c] * (heat[c] * energy + joule[c] * sq) / n - state[1, c])
        state[0, c] = prev
        if state[1, c] > tmax[c]:
            status |= 8
    if fade[1] > 0:
        fade[0] += n
    return status
