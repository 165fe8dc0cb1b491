"""Plain-Python twins of the root-level kernels (safety limiter)."""

import math

import numpy as np


def limit_block(x, state, params, fade, counts):
    """Per-sample reference of rtctl.safety.limit_block, written from its docstring."""
    status = 0
    vmax, dvmax, heat, rth, alpha, tamb, tmax = (params[:, i] for i in range(7))
    for c in range(x.shape[0]):
        for i in range(x.shape[1]):
            v = x[c, i]
            if not math.isfinite(v):
                v, status = 0.0, status | 4
            if fade[1] > 0:
                k = fade[0] + i + 1
                v = state[c, 2] * max(0.0, 1.0 - k / fade[1])
            if abs(v) > vmax[c]:
                v, status = math.copysign(vmax[c], v), status | 1
                counts[c, 0] += 1
            if abs(v - state[c, 0]) > dvmax[c]:
                v, status = state[c, 0] + math.copysign(dvmax[c], v - state[c, 0]), status | 2
                counts[c, 1] += 1
            p = heat[c] * abs(v * (v - state[c, 0]))
            state[c, 1] += alpha[c] * (tamb[c] + rth[c] * p - state[c, 1])
            state[c, 0] = v
            x[c, i] = v
        if state[c, 1] > tmax[c]:
            status |= 8
    if fade[1] > 0:
        fade[0] += x.shape[1]
    return status
