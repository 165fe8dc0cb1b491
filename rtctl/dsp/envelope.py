"""Linear parameter ramps and raised-cosine fades.

The ramp law is the one the oscillator bank uses for amplitude and instantaneous frequency
(``_kernels.ramp_step`` / ``ramp_value``): a change to ``v1`` over ``R`` samples gives
``v[k] = v0 + (v1 - v0) (k + 1) / R`` for ``k = 0 .. R - 1``, so the first sample already moves
and the last one is exactly ``v1``.
"""

import numpy as np

from rtctl.dsp import _kernels as _k
from rtctl.dsp.oscillator import _check_block, _check_int, _vector

__all__ = ["Ramp", "Fade"]


class Ramp:
    """``n_params`` values, each moving linearly to its latest target over ``ramp`` samples.

    Parameters
    ----------
    n_params : int
        Number of parameters (rows of the output).
    value : float or array_like, shape (n_params,)
        Initial values.
    ramp : int
        Default ramp length, samples, ``>= 1``.

    Notes
    -----
    For the loop: ``ramp_process(*ramp.args, out)`` with ``ramp.args == (state, pending)``.

    Examples
    --------
    >>> gain = Ramp(1, value=0.0, ramp=4)
    >>> gain.set(0, 1.0)
    >>> out = np.empty((1, 6))
    >>> gain.process(out)
    >>> out[0]
    array([0.25, 0.5 , 0.75, 1.  , 1.  , 1.  ])
    """

    def __init__(self, n_params, value=0.0, ramp=32):
        self.n_params = _check_int("n_params", n_params, 1)
        self.ramp = _check_int("ramp", ramp, 1)
        self._value0 = _vector("value", value, self.n_params)
        if not np.isfinite(self._value0).all():
            raise ValueError("value must be finite")
        self.state = np.zeros((_k.N_RAMP, self.n_params))
        self.pending = np.zeros((_k.N_RPEND, self.n_params))
        self.reset()

    @property
    def args(self):
        """Arrays in kernel order: ``ramp_process(*ramp.args, out)``."""
        return (self.state, self.pending)

    def process(self, out):
        """Write the next ``out.shape[1]`` values of each parameter into ``out``, shape (n_params, n)."""
        _check_block("out", out, self.n_params)
        _k.ramp_process(self.state, self.pending, out)

    def reset(self):
        """Back to the initial values; no ramp in progress or pending."""
        self.state[:] = 0.0
        self.state[_k.R_VAL] = self._value0
        self.state[_k.R_TARGET] = self._value0
        self.pending[_k.RP_TARGET] = self._value0
        self.pending[_k.RP_RAMP] = self.ramp
        self.pending[_k.RP_FLAG] = 0.0

    def set(self, i, target, ramp=None):
        """Ramp parameter ``i`` to ``target`` from the start of the next call."""
        i = _check_int("i", i, 0, self.n_params - 1)
        self.pending[_k.RP_TARGET, i] = self._target(target, 1)[0]
        self.pending[_k.RP_RAMP, i] = self.ramp if ramp is None else _check_int("ramp", ramp, 1)
        self.pending[_k.RP_FLAG, i] = 1.0

    def set_all(self, target, ramp=None):
        """Ramp every parameter to ``target`` (scalar or shape (n_params,))."""
        self.pending[_k.RP_TARGET] = self._target(target, self.n_params)
        self.pending[_k.RP_RAMP] = self.ramp if ramp is None else _check_int("ramp", ramp, 1)
        self.pending[_k.RP_FLAG] = 1.0

    @property
    def value(self):
        """ndarray, shape (n_params,): value of the last sample written."""
        return self.state[_k.R_VAL].copy()

    @staticmethod
    def _target(target, n):
        t = _vector("target", target, n)
        if not np.isfinite(t).all():
            raise ValueError(f"target = {target} must be finite")
        return t


class Fade:
    """Raised-cosine gain applied in place to every channel of a block (e.g. fade all to zero).

    Parameters
    ----------
    length : int
        Default fade length, samples, ``>= 1``.
    gain : float
        Initial (idle) gain; 1 passes blocks through untouched.

    Notes
    -----
    Sample ``k = 1 .. N`` of a fade from ``g0`` (the gain of the last sample) to ``g1`` gets
    ``g1 + (g0 - g1) (1 + cos(pi k / N)) / 2``: zero slope at both ends, exactly ``g1`` on the
    last sample, held afterwards. A fade to 0 writes exact zeros (NaN inputs included), which is
    what the safety code wants once the outputs are down. For the loop:
    ``fade_start(fade.state, gain, length)`` then ``fade_process(*fade.args, out)`` each block,
    with ``fade.args == (state,)`` (both in :mod:`rtctl.dsp._kernels`).

    Examples
    --------
    >>> fade = Fade(4)
    >>> fade.fade_out()
    >>> out = np.ones((2, 6))
    >>> fade.process(out)
    >>> np.round(out[0], 4)
    array([0.8536, 0.5   , 0.1464, 0.    , 0.    , 0.    ])
    """

    def __init__(self, length, gain=1.0):
        self.length = _check_int("length", length, 1)
        self._gain0 = self._gain(gain)
        self.state = np.zeros(_k.N_FADE)
        self.reset()

    @property
    def args(self):
        """Arrays in kernel order: ``fade_process(*fade.args, out)``."""
        return (self.state,)

    def process(self, out):
        """Multiply ``out``, shape (n_channels, n), float64, in place by the gain of each sample."""
        if not isinstance(out, np.ndarray) or out.ndim != 2:
            raise ValueError(f"out must be a float64 array of shape (n_channels, n), got {type(out).__name__}")
        _check_block("out", out, out.shape[0])
        _k.fade_process(self.state, out)

    def reset(self):
        """Idle at the initial gain."""
        self.state[:] = 0.0
        self.state[_k.FD_GAIN] = self._gain0

    def fade_to(self, gain, length=None):
        """Start a fade from the current gain to ``gain`` over ``length`` samples (next call on)."""
        g1 = self._gain(gain)
        n = self.length if length is None else _check_int("length", length, 1)
        _k.fade_start(self.state, g1, float(n))

    def fade_out(self, length=None):
        """Fade to 0 (then hold exact zeros)."""
        self.fade_to(0.0, length)

    def fade_in(self, length=None):
        """Fade to 1 (then pass blocks through)."""
        self.fade_to(1.0, length)

    @property
    def gain(self):
        """float: gain of the last sample."""
        return float(self.state[_k.FD_GAIN])

    @property
    def active(self):
        """bool: a fade is in progress."""
        return bool(self.state[_k.FD_N] > 0.0)

    @staticmethod
    def _gain(gain):
        return float(_vector("gain", gain, 1, 0.0, np.inf)[0])
