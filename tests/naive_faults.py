"""Plain-Python twins of the fault injector's kernels (:mod:`rtctl.io.faults`), written from
docs/faults.md: per block, the readings the faulty device delivers and what its plant receives."""

from __future__ import annotations

import math

import numpy as np

SENSED_ORDER = (("latency_spike",), ("sensed_zero", "sensed_frozen", "electrode_open"),
                ("sensed_nan", "sensed_inf", "adc_saturated"), ("block_dropped", "xrun_burst", "device_stopped"))
PERMANENT = ("electrode_open", "device_stopped", "finger_slam", "finger_lift")


def active(f, k):
    end = math.inf if f.blocks == 0 or f.kind in PERMANENT else f.start + f.blocks
    return f.start <= k < end


def rows(row, n):
    return range(n) if row < 0 else [row % n]


class Device:
    """The faulty device, one block at a time: ``sensed(k, true)`` and ``drive(k, x, vmax)``."""

    def __init__(self, faults, n_sensed, full_scale):
        self.faults, self.full = list(faults), np.asarray(full_scale, dtype=float)
        self.true = {}                      # block -> the readings before any fault
        self.last = np.zeros(n_sensed)      # the last value delivered, per row

    def sensed(self, k, true):
        self.true[k] = true.copy()
        x, flags = true.copy(), set()
        for kinds in SENSED_ORDER:
            for f in self.faults:
                if f.kind not in kinds or not active(f, k):
                    continue
                if kinds is SENSED_ORDER[3]:
                    x[:] = 0.0
                    flags.add("lost" if f.kind == "device_stopped" else "xrun")
                    continue
                for r in rows(f.row, x.shape[0]):
                    if f.kind == "latency_spike":
                        n = int(f.value) or 1
                        x[r] = self.true[k - n][r] if k - n >= 0 else 0.0
                    elif f.kind in ("sensed_zero", "electrode_open"):
                        x[r] = 0.0
                    elif f.kind == "sensed_frozen":
                        x[r] = self.last[r]
                    elif f.kind == "sensed_nan":
                        x[r] = np.nan
                    elif f.kind == "sensed_inf":
                        x[r] = np.inf
                    else:
                        x[r] = self.full[r]
                        flags.add("saturated")
        self.last = x[:, -1].copy()
        return x, flags

    def drive(self, k, x, vmax):
        y = x.copy()
        for f in self.faults:
            if not active(f, k):
                continue
            if f.kind in ("block_dropped", "xrun_burst", "device_stopped"):
                y[:] = 0.0
            elif f.kind == "amp_clipped":
                for c in rows(f.row, y.shape[0]):
                    lim = (f.value or 0.5) * vmax[c]
                    y[c] = np.clip(y[c], -lim, lim)
        return y
