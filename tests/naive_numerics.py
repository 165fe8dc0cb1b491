"""A toy nonlinear plant behind the simulated-group contract, with a naive loop twin.

Mass on a linear suspension pushing a stiff one-sided spring (an end stop at ``gap``)::

    m x'' = g u - k x - c x' - k_s max(x - gap, 0)

Group kernel: trapezoidal rule per substep on the piecewise-linear force; the active set (on
or off the stop at the end of the substep) is guessed from the start and corrected once.
``truth`` rows: x (m), x' (m/s), stop force (N, >= 0), u (V) -- state before each sample.
"""

import numpy as np
from numba import njit

M, K, C, G, KS, GAP = 1e-3, 1e3, 0.05, 1e-2, 1e7, 5e-5


def rhs(t, y, u):
    x, v = y
    f = KS * max(x - GAP, 0.0)
    return np.array([v, (G * u - K * x - C * v - f) / M])


def outputs(y, u):
    return np.array([y[0], y[1], KS * max(y[0] - GAP, 0.0), u])


@njit(cache=True)
def _trap(x, v, u, h, on):
    # x' = v, v' = (G u - K x - C v - ks (x - gap)) / M with ks = KS if on else 0: linear.
    ks = KS if on else 0.0
    kk = K + ks
    f0 = (G * u - kk * x - C * v + ks * GAP) / M
    # Trapezoid: x1 = x + h/2 (v + v1); v1 = v + h/2 (f0 + f1), f1 = (G u - kk x1 - C v1 + ks gap)/M
    a = h / 2.0
    # substitute x1 -> linear equation in v1
    rhs_ = v + a * f0 + a * (G * u - kk * (x + a * v) + ks * GAP) / M
    den = 1.0 + a * (kk * a + C) / M
    v1 = rhs_ / den
    x1 = x + a * (v + v1)
    return x1, v1


@njit(cache=True)
def toy_process(params, state, drive, sensed, truth):
    substeps = int(params[0])
    fs = params[1]
    h = 1.0 / (fs * substeps)
    nc, n = drive.shape
    status = 0
    for ch in range(nc):
        x, v = state[ch, 0], state[ch, 1]
        for t in range(n):
            u = drive[ch, t]
            truth[ch, 0, t] = x
            truth[ch, 1, t] = v
            truth[ch, 2, t] = KS * (x - GAP) if x > GAP else 0.0
            truth[ch, 3, t] = u
            for _ in range(substeps):
                on = x > GAP
                x1, v1 = _trap(x, v, u, h, on)
                if (x1 > GAP) != on:
                    x1, v1 = _trap(x, v, u, h, not on)
                x, v = x1, v1
        state[ch, 0], state[ch, 1] = x, v
        if not (np.isfinite(x) and np.isfinite(v)):
            status |= 2
    return status


class ToyGroup:
    """The simulated-group contract around :func:`toy_process`."""

    n_sensed = 0
    sensed_labels = ()
    probe_names = ()
    capacitance = 0.0

    def __init__(self, fs, n_channels=1, substeps=4, max_block=64):
        self.n_channels = n_channels
        self.kernel = toy_process
        self.probe = np.zeros((0, max_block))
        self.args = (np.array([substeps, fs], dtype=np.float64), np.zeros((n_channels, 2)))

    def reset(self):
        self.args[1][:] = 0.0

    def process(self, drive, sensed, truth):
        return self.kernel(*self.args, drive, sensed, truth)


def naive_toy(fs, substeps, drive):
    """Loop twin: the same trapezoid/active-set scheme in plain Python, one channel."""
    h = 1.0 / (fs * substeps)
    x = v = 0.0
    out = np.empty((4, drive.size))
    for t, u in enumerate(drive):
        out[:, t] = outputs((x, v), u)
        for _ in range(substeps):
            def trap(on, x=x, v=v, u=u):
                ks = KS if on else 0.0
                A = np.array([[0.0, 1.0], [-(K + ks) / M, -C / M]])
                b = np.array([0.0, (G * u + ks * GAP) / M])
                I = np.eye(2)
                return np.linalg.solve(I - h / 2 * A, (I + h / 2 * A) @ np.array([x, v]) + h * b)
            on = x > GAP
            y1 = trap(on)
            if (y1[0] > GAP) != on:
                y1 = trap(not on)
            x, v = y1
    return out
