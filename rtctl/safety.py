"""The final limiter: the last stage of every block, which no controller bug can bypass.

Per channel and sample, in this order:

1. a non-finite request (NaN/Inf from any upstream bug) becomes 0 V and raises ``NONFINITE``;
2. during a shutdown the request is ignored and replaced by a linear fade of the last output to
   zero (so a fault brings every output to 0 V within the fade length, one block by default);
3. the voltage is clipped to +-``max_voltage`` (``LIMIT_VOLTAGE``);
4. the change per sample is clipped to ``min(slew, current / C) / fs`` (``LIMIT_SLEW``): a piezo is a
   capacitor, so the drive current is ``C dV/dt`` and limiting the slope limits the current;
5. a lumped thermal model integrates the dielectric loss: for a sine of amplitude V at angular
   frequency w the loss is ``tan(delta) w C V^2 / 2``, which is exactly the cycle mean of
   ``(pi/2) tan(delta) C |v dv/dt|``, the instantaneous form used here (approximate for several
   tones). ``T' = (T_amb + R_th P - T) / tau_th``; above ``temperature`` it raises ``OVERTEMP``.

Coil actuators (electromagnetic, solenoid, Dot, SMA wires) are resistive, not capacitive: a
channel built with ``capacitance = 0`` and a ``resistance`` R instead has its current bounded by
a voltage bound ``|v| <= current * R`` (the steady-state coil current V/R never exceeds the limit;
the inductance only delays it), only the slew bound on the slope, and Joule heating ``v^2 / R``
in the thermal model.

The motional part of the current is not included in 4: for the demo bimorph it adds 6-10 % to the
capacitive current below 100 Hz, 14 % at 500 Hz and up to a third near the first resonance, so
``current`` should be set with that margin.
"""

from __future__ import annotations

import math

import numpy as np

from ._numba import kernel

LIMIT_VOLTAGE = 1
LIMIT_SLEW = 2
NONFINITE = 4
OVERTEMP = 8
SENSOR_SATURATED = 16
PLANT_NONFINITE = 32
DEADLINE_MISSED = 64
DEVICE_LOST = 128
IO_XRUN = 256
ESTIMATE_NONFINITE = 512

#: Status bits that end a run (outputs fade to zero first).
FAULTS = NONFINITE | OVERTEMP | PLANT_NONFINITE | DEVICE_LOST

STATUS_NAMES = {
    LIMIT_VOLTAGE: "voltage limited",
    LIMIT_SLEW: "slew/current limited",
    NONFINITE: "non-finite drive request (NaN/Inf) replaced by 0 V",
    OVERTEMP: "actuator over temperature",
    SENSOR_SATURATED: "current sensor saturated",
    PLANT_NONFINITE: "simulated plant state became non-finite",
    DEADLINE_MISSED: "block deadline missed",
    DEVICE_LOST: "I/O device lost (unplugged, stalled or not answering)",
    IO_XRUN: "audio under/overflow (xrun)",
    ESTIMATE_NONFINITE: "self-sensing estimate non-finite (a sensed reading was NaN/Inf)",
}

# limiter state rows
_V, _T, _FADE_FROM = 0, 1, 2
# limiter parameter rows
_VMAX, _DVMAX, _HEAT, _RTH, _ALPHA, _TAMB, _TMAX, _JOULE = range(8)


@kernel
def limit_block(x, state, params, fade, counts):
    """Limit ``x`` (n_channels, n) in place; return the OR of status bits raised.

    ``state`` (3, n_channels): last output V, temperature degC, fade start V.
    ``params`` (8, n_channels): see the row constants (``_ALPHA`` holds 1 / (fs tau_th),
    ``_JOULE`` 1 / R for a coil, 0 for a piezo).
    ``fade`` int64 (2,): samples done and length of a shutdown fade (length 0 = running).
    ``counts`` int64 (2, n_channels): samples voltage-limited and slew-limited so far.

    Per channel, passes over the contiguous row: (1) NaN/Inf -> 0 or the fade, voltage clip;
    (2) the largest step, which needs no recursion; only if it exceeds the slew bound does
    (3) the sequential slew clamp run. Requests that respect the slew bound, the normal case,
    thus cost no dependency chain. The heat of the block is integrated once per block: the
    thermal time constant (seconds) is far longer than a block (under a millisecond).
    """
    n_ch, n = x.shape
    fading = fade[1] > 0
    status = 0
    for c in range(n_ch):
        row = x[c]
        vmax = params[_VMAX, c]
        dvmax = params[_DVMAX, c]
        v0 = state[_V, c]
        if fading:  # the request is ignored: fade from the last output to zero
            f0 = state[_FADE_FROM, c]
            for i in range(n):
                k = fade[0] + i + 1
                row[i] = f0 * (1.0 - k / fade[1]) if k < fade[1] else 0.0
        else:
            # v * 0 is 0 for finite v and NaN for NaN/Inf: one vectorizable probe instead of a
            # branch per sample (a per-sample isfinite stops LLVM vectorizing the loop).
            probe = 0.0
            for i in range(n):
                probe += row[i] * 0.0
            if probe != 0.0:
                status |= NONFINITE
                for i in range(n):
                    if not math.isfinite(row[i]):
                        row[i] = 0.0
        n_v = 0
        for i in range(n):
            v = row[i]
            n_v += (v > vmax) | (v < -vmax)
            row[i] = min(max(v, -vmax), vmax)
        if n_v:
            counts[0, c] += n_v
            status |= LIMIT_VOLTAGE
        step = abs(row[0] - v0)
        for i in range(1, n):
            step = max(step, abs(row[i] - row[i - 1]))
        if step > dvmax:
            n_s = 0
            prev = v0
            for i in range(n):
                v = row[i]
                lo = prev - dvmax
                hi = prev + dvmax
                n_s += (v > hi) | (v < lo)
                prev = min(max(v, lo), hi)
                row[i] = prev
            if n_s:
                counts[1, c] += n_s
                status |= LIMIT_SLEW
        heat = abs(row[0] * (row[0] - v0))
        joule = row[0] * row[0]
        for i in range(1, n):
            heat += abs(row[i] * (row[i] - row[i - 1]))
            joule += row[i] * row[i]
        power = (params[_HEAT, c] * heat + params[_JOULE, c] * joule) / n
        a = -math.expm1(-n * params[_ALPHA, c])
        t = state[_T, c]
        t += a * (params[_TAMB, c] + params[_RTH, c] * power - t)
        state[_T, c] = t
        state[_V, c] = row[n - 1]
        if t > params[_TMAX, c]:
            status |= OVERTEMP
    if fading:
        fade[0] += n
    return status


class Limiter:
    """Per-channel limits and state of the final limiter.

    Parameters
    ----------
    fs : float
        Sample rate, Hz.
    max_voltage, slew, current, capacitance, temperature, ambient, loss_tangent,
    thermal_resistance, thermal_tau : array_like, shape (n_channels,)
        V, V/s, A, F, degC, degC, -, K/W, s (broadcast from scalars).

    Examples
    --------
    >>> lim = Limiter(48000.0, max_voltage=[10.0], slew=[1e9], current=[1.0], capacitance=[1e-9],
    ...               temperature=[80.0], ambient=[25.0], loss_tangent=[0.02],
    ...               thermal_resistance=[100.0], thermal_tau=[10.0])
    >>> x = np.array([[5.0, 50.0, np.nan]])
    >>> status = lim.process(x)
    >>> x.tolist(), bool(status & LIMIT_VOLTAGE), bool(status & NONFINITE)
    ([[5.0, 10.0, 0.0]], True, True)
    """

    def __init__(self, fs, *, max_voltage, slew, current, capacitance, temperature, ambient,
                 loss_tangent, thermal_resistance, thermal_tau, resistance=0.0):
        vmax = np.atleast_1d(np.asarray(max_voltage, dtype=float))
        n = vmax.size
        b = lambda a: np.broadcast_to(np.asarray(a, dtype=float), (n,))  # noqa: E731
        cap, res = b(capacitance), b(resistance)
        if not (np.all(np.isfinite(vmax)) and np.all(vmax > 0)):
            raise ValueError(f"max_voltage must be finite and > 0, got {vmax}")
        coil = cap == 0.0
        if not np.all((cap > 0) | (coil & (res > 0))):
            raise ValueError(f"each channel needs capacitance > 0 F (piezo) or capacitance 0 and "
                             f"resistance > 0 ohm (coil), got C = {cap}, R = {res}")
        # The current limit is a slope limit on a capacitor: |dV/dt| <= I_max / C; on a coil it
        # is a voltage bound |V| <= I_max R.
        with np.errstate(divide="ignore"):
            slope = np.where(coil, b(slew), np.minimum(b(slew), b(current) / np.where(coil, 1.0, cap)))
            vmax = np.where(coil, np.minimum(vmax, b(current) * np.where(coil, res, 1.0)), vmax)
        self.fs = float(fs)
        self.params = np.empty((8, n))
        self.params[_VMAX] = vmax
        self.params[_JOULE] = np.where(coil, 1.0 / np.where(coil, res, 1.0), 0.0)
        self.params[_DVMAX] = slope / self.fs
        self.params[_HEAT] = 0.5 * np.pi * b(loss_tangent) * cap * self.fs
        self.params[_RTH] = b(thermal_resistance)
        self.params[_ALPHA] = 1.0 / (self.fs * b(thermal_tau))
        self.params[_TAMB] = b(ambient)
        self.params[_TMAX] = b(temperature)
        self.state = np.zeros((3, n))
        self.fade = np.zeros(2, dtype=np.int64)
        self.counts = np.zeros((2, n), dtype=np.int64)
        self.reset()

    @property
    def args(self):
        """Arrays in :func:`limit_block` order, after ``x``."""
        return (self.state, self.params, self.fade, self.counts)

    def process(self, x: np.ndarray) -> int:
        """Limit ``x`` (n_channels, n) in place; return the status bits."""
        return limit_block(x, *self.args)

    def shutdown(self, n_samples: int) -> int:
        """Fade every output linearly from its last value to 0 V; return the fade length.

        The fade lasts ``n_samples``, or longer where the slew bound needs it: a linear fade
        from ``v`` over ``N`` samples steps ``v / N`` per sample, so ``N >= |v| / dV_max``
        keeps the slew clamp from stopping it short of zero (one sample more, so rounding never
        makes the fade's step exceed the bound).
        """
        need = np.floor(np.max(np.abs(self.state[_V]) / self.params[_DVMAX], initial=0.0)) + 1
        self.state[_FADE_FROM] = self.state[_V]
        self.fade[0] = 0
        self.fade[1] = max(int(n_samples), int(need), 1)
        return int(self.fade[1])

    @property
    def done(self) -> bool:
        """A shutdown fade has run its length and every output is at 0 V."""
        return bool(self.fade[1] > 0 and self.fade[0] >= self.fade[1] and not np.any(self.state[_V]))

    def commands_only(self) -> None:
        """The outputs are pin commands to a controller whose firmware pulses the coils (Dot: a
        3 ms pulse per change) and guards them (SMA: its thermal cutoff), not coil voltages: no
        Joule heating from a held level. The voltage bound stays."""
        self.params[_JOULE] = 0.0

    @property
    def temperature(self) -> np.ndarray:
        return self.state[_T]

    @property
    def last(self) -> np.ndarray:
        return self.state[_V]

    def reset(self) -> None:
        self.state[:] = 0.0
        self.state[_T] = self.params[_TAMB]
        self.fade[:] = 0
        self.counts[:] = 0


def describe(status: int) -> list[str]:
    """Human names of the bits set in ``status``."""
    return [name for bit, name in STATUS_NAMES.items() if status & bit]
