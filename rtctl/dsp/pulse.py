"""Rectangular pulse trains and on/off levels for binary pins."""

import numpy as np

from rtctl.dsp import _kernels as _k
from rtctl.dsp._routed import Routed
from rtctl.dsp.oscillator import _check_block, _check_fs, _check_int, _vector

__all__ = ["PulseTrain"]


class PulseTrain(Routed):
    """Per channel a rectangular wave between a high and a low level, or a held level.

    Parameters
    ----------
    n_channels : int
        Rows of the blocks this adds into.
    fs : float
        Sample rate, Hz.
    freq : float or array_like, shape (n_channels,)
        Pulse frequency, Hz, ``0 <= freq <= fs / 2``; 0 holds the position in the cycle, so the
        output holds its current level.
    duty : float or array_like, shape (n_channels,)
        Fraction of each cycle at the high level, ``0 <= duty <= 1``.
    high, low : float or array_like, shape (n_channels,)
        The two output levels (e.g. volts, or 1 / 0 for a logic pin).
    phase : float or array_like, shape (n_channels,)
        Initial position in the cycle, in cycles ``[0, 1)``: the output is high while the
        position is below ``duty``, so the first cycle starts with its high part at phase 0.

    Notes
    -----
    The position in the cycle is an integer count of ``2**-40`` cycle advanced exactly (a DDS
    accumulator), so edges never drift; the frequency is ``freq`` rounded to ``fs * 2**-40``
    (4.4e-8 Hz at 48 kHz, a relative 4e-8 at 1 Hz), the duty to ``2**-40``. Changes written by
    :meth:`set` take effect at the start of the next :meth:`process` call, without a ramp (pins
    are binary): a frequency change keeps the current position within the cycle, so the wave is
    phase-continuous. :meth:`set_level` is the pure level mode for latching pins (output ``high``
    when on, ``low`` when off).

    Like the oscillator bank, the train *adds* into ``out``. For the loop:
    ``pulse_process(*train.args, out)`` with ``train.args == (state, pending)``.

    Examples
    --------
    >>> train = PulseTrain(1, fs=1000.0, freq=250.0, duty=0.5)
    >>> out = np.zeros((1, 8))
    >>> train.process(out)
    >>> out[0]
    array([1., 1., 0., 0., 1., 1., 0., 0.])
    """


    def __init__(self, n_channels, fs, freq=0.0, duty=0.5, high=1.0, low=0.0, phase=0.0):
        self.n_channels = _check_int("n_channels", n_channels, 1)
        self.fs = _check_fs(fs)
        self._init = (
            self._freq(freq),
            _vector("duty", duty, self.n_channels, 0.0, 1.0),
            _vector("high", high, self.n_channels, -np.inf, np.inf),
            _vector("low", low, self.n_channels, -np.inf, np.inf),
            _vector("phase", phase, self.n_channels, 0.0, np.nextafter(1.0, 0.0), "cycles"),
        )
        for name, v in zip(("high", "low"), self._init[2:4]):
            if not np.isfinite(v).all():
                raise ValueError(f"{name} must be finite")
        self.state = np.zeros((_k.N_PULSE, self.n_channels))
        self.pending = np.zeros((_k.N_QPEND, self.n_channels))
        self.reset()

    @property
    def args(self):
        """Arrays in kernel order: ``pulse_process(*train.args, out)``."""
        return (self.state, self.pending)

    def process(self, out):
        """Add the next ``out.shape[1]`` samples into ``out``, shape (n_channels, n), float64."""
        _check_block("out", out, self.n_channels)
        _k.pulse_process(self.state, self.pending, out)

    def reset(self):
        """Back to the constructor's parameters and phase; no pending change."""
        freq, duty, high, low, phase = self._init
        self.pending[_k.Q_FREQ] = freq
        self.pending[_k.Q_DUTY] = duty
        self.pending[_k.Q_HIGH] = high
        self.pending[_k.Q_LOW] = low
        self.pending[_k.Q_FLAG] = 1.0
        self.state[:] = 0.0
        self.state[_k.POS] = np.floor(phase * _k.PULSE_UNIT)
        self.state[_k.PFS] = self.fs
        _k.pulse_process(self.state, self.pending, np.zeros((self.n_channels, 0)))

    def set(self, c, freq=None, duty=None, high=None, low=None):
        """Change channel ``c`` from the start of the next call; ``None`` keeps a parameter."""
        c = _check_int("c", c, 0, self.n_channels - 1)
        values = self._checked(freq, duty, high, low, 1)
        for row, v in zip((_k.Q_FREQ, _k.Q_DUTY, _k.Q_HIGH, _k.Q_LOW), values):
            if v is not None:
                self._write(row, c, v[0])
        self._write(_k.Q_FLAG, c, 1.0)

    def set_all(self, freq=None, duty=None, high=None, low=None):
        """Vectorized :meth:`set`: scalars or shape (n_channels,); ``None`` keeps."""
        values = self._checked(freq, duty, high, low, self.n_channels)
        for row, v in zip((_k.Q_FREQ, _k.Q_DUTY, _k.Q_HIGH, _k.Q_LOW), values):
            if v is not None:
                self._write(row, slice(None), v)
        self._write(_k.Q_FLAG, slice(None), 1.0)

    def set_range(self, channels: slice, freq=None, duty=None, high=None, low=None):
        """:meth:`set` for the contiguous channels ``channels`` (scalars or their shape)."""
        c0, c1, step = channels.indices(self.n_channels)
        if step != 1 or c1 <= c0:
            raise ValueError(f"channels must be a non-empty contiguous slice, got {channels!r}")
        values = self._checked(freq, duty, high, low, c1 - c0)
        for row, v in zip((_k.Q_FREQ, _k.Q_DUTY, _k.Q_HIGH, _k.Q_LOW), values):
            if v is not None:
                self._write(row, slice(c0, c1), v)
        self._write(_k.Q_FLAG, slice(c0, c1), 1.0)

    def set_level(self, c, on):
        """Level mode for a latching pin: hold ``high`` (on) or ``low`` (off) from the next call."""
        self.set(c, freq=0.0, duty=1.0 if on else 0.0)

    @property
    def position(self):
        """ndarray, shape (n_channels,): position in the cycle of the next sample, cycles [0, 1)."""
        return self.state[_k.POS] / _k.PULSE_UNIT

    @property
    def freq(self):
        """ndarray, shape (n_channels,): frequency in use (after rounding to the DDS grid), Hz."""
        return self.state[_k.PINC] / _k.PULSE_UNIT * self.fs

    @property
    def duty(self):
        """ndarray, shape (n_channels,): duty cycle in use."""
        return self.state[_k.PDUTY] / _k.PULSE_UNIT

    def _freq(self, freq, n=None):
        n = self.n_channels if n is None else n
        return _vector("freq", freq, n, 0.0, self.fs / 2, "Hz", hi_label=f"fs / 2 = {self.fs / 2}")

    def _checked(self, freq, duty, high, low, n):
        out = [
            None if freq is None else self._freq(freq, n),
            None if duty is None else _vector("duty", duty, n, 0.0, 1.0),
            None if high is None else _vector("high", high, n, -np.inf, np.inf),
            None if low is None else _vector("low", low, n, -np.inf, np.inf),
        ]
        for name, v in zip(("high", "low"), out[2:]):
            if v is not None and not np.isfinite(v).all():
                raise ValueError(f"{name} = {v} must be finite")
        return out
