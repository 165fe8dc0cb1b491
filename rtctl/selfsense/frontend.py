"""What the ADC reads of a segment current: amplifier lag, DAC staircase, AA filter, aliasing.

The drive ``u[n]`` leaves a DAC as a staircase; the amplifier (first order) drives the piezo; each
segment current passes a Butterworth anti-alias filter and is sampled on the DAC's clock. For a
drive tone with phasor ``D`` at ``w`` the staircase has lines at ``w + k ws`` (all integers
``k``) with phasors ``D P(w + k ws)``, ``P(W) = (1 - exp(-j W dt)) / (j W dt)``; sampling folds
every line back onto ``w``. So the sensed phasor of segment ``j`` is exactly::

    S_j = sum_k H_aa(W_k) A(W_k) P(W_k) Y_j(W_k) D,     W_k = w + k ws

with ``Y_j`` the segment's current per actuator volt (``G(-W) = conj G(W)`` for ``k < 0``). This
is the identity behind the exact zero-order-hold discretization (docs/physics.md 3.7). The
``k = 0`` term holds the mechanics the observer wants; the images ``k != 0`` (about -13 % of
the reading for the bundled scene, nearly all capacitive) are predicted from the model and
removed. Truncated at ``|k| <= n_images``; the tail falls like ``k^-3`` (about 1e-6 of the
reading at 40 images with a second-order filter).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.signal

from rtctl.errors import ModelError

__all__ = ["FrontEnd"]


@dataclass(frozen=True)
class FrontEnd:
    """Sampled drive and sense chain of one channel.

    Parameters
    ----------
    fs : float
        Sample rate of the DAC and the ADC, Hz.
    amp_bandwidth_hz : float
        First-order amplifier bandwidth, Hz.
    aa_cutoff_hz : float
        Butterworth anti-alias cutoff, Hz.
    aa_order : int
        Its order.
    n_images : int
        Images folded on each side.

    Examples
    --------
    >>> fe = FrontEnd(48000.0, 20e3, 20e3, 2)
    >>> round(abs(fe.voltage(250.0)), 6)   # actuator volt per drive volt at 250 Hz
    0.999877
    """

    fs: float
    amp_bandwidth_hz: float = 20e3
    aa_cutoff_hz: float = 20e3
    aa_order: int = 2
    n_images: int = 40

    def __post_init__(self):
        for name in ("fs", "amp_bandwidth_hz", "aa_cutoff_hz"):
            v = float(getattr(self, name))
            if not (v > 0.0 and math.isfinite(v)):
                raise ModelError(f"FrontEnd.{name} must be > 0 Hz, got {v!r}")
            object.__setattr__(self, name, v)
        if int(self.aa_order) != self.aa_order or not 1 <= self.aa_order <= 8:
            raise ModelError(f"FrontEnd.aa_order must be 1..8, got {self.aa_order!r}")
        object.__setattr__(self, "_ba", scipy.signal.butter(int(self.aa_order),
                                                           2 * math.pi * self.aa_cutoff_hz,
                                                           analog=True))

    @classmethod
    def from_sense(cls, fs, amplifier, sense, n_images=40) -> FrontEnd:
        """From a plant's :class:`Amplifier` and :class:`CurrentSense` (their settings only)."""
        return cls(fs, amplifier.bandwidth_hz, sense.aa_cutoff_hz, sense.aa_order, n_images)

    def _line(self, omega):
        """``H_aa A P`` and ``A P`` at angular frequencies ``omega`` (any sign, != 0)."""
        w = np.atleast_1d(np.asarray(omega, dtype=float))
        dt = 1.0 / self.fs
        p = (1.0 - np.exp(-1j * w * dt)) / (1j * w * dt)
        a = 1.0 / (1.0 + 1j * w / (2 * math.pi * self.amp_bandwidth_hz))
        _, h = scipy.signal.freqs(*self._ba, worN=np.abs(w))
        h = np.where(w < 0, np.conj(h), h)
        return h * a * p, a * p

    def voltage(self, f_hz):
        """Fundamental of the actuator voltage per drive volt, ``A(w) P(w)`` (complex)."""
        return complex(self._line(2 * math.pi * float(f_hz))[1][0])

    def aa(self, f_hz):
        """Anti-alias filter response at ``f_hz`` (complex)."""
        return complex(self._line(2 * math.pi * float(f_hz))[0][0] / self._line(2 * math.pi * float(f_hz))[1][0])

    def images(self, f_hz, current_per_volt):
        """Sum of the folded images in the sensed current per drive volt.

        Parameters
        ----------
        f_hz : float
            Tone frequency, 0 < f < fs / 2.
        current_per_volt : callable
            ``omega (rad/s, > 0) -> ndarray (n_seg,)`` complex: segment currents per actuator
            volt (e.g. from :meth:`TMMBeam.solve`).

        Returns
        -------
        ndarray, shape (n_seg,), complex
            A per drive volt, to subtract from the sensed phasor.
        """
        om = self._image_lines(f_hz)
        g, _ = self._line(om)
        total = 0.0
        for gi, oi in zip(g, om):
            y = np.asarray(current_per_volt(abs(oi)))
            total = total + gi * (np.conj(y) if oi < 0 else y)
        return total

    def _image_lines(self, f_hz):
        """The images' angular frequencies ``w + k ws``, ``0 < |k| <= n_images`` (signed)."""
        w = 2 * math.pi * float(f_hz)
        ws = 2 * math.pi * self.fs
        k = np.concatenate((np.arange(-self.n_images, 0), np.arange(1, self.n_images + 1)))
        return w + k * ws

    def image_omegas(self, f_hz) -> np.ndarray:
        """The angular frequencies (rad/s, > 0) at which :meth:`images` asks ``current_per_volt``
        for the currents of tone ``f_hz``, in its order: solve them all at once beforehand (e.g.
        :meth:`~rtctl.selfsense.tmm.TMMBeam.currents`) and hand :meth:`images` a look-up."""
        return np.abs(self._image_lines(f_hz))
