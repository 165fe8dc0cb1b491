"""Closed-loop amplitude control: kernels and a thin wrapper; knows no scene (as ``rtctl.dsp``).

:class:`AmplitudeController` sets each controlled tone's drive amplitude once per block from the
self-sensing observer's estimate of that tone's tip amplitude: a feedforward from the model, then
ratio corrections each time the estimate is fresh, the wait designed at build time from the
observer's window and the I/O latency (:func:`design`). Saturation never winds up; a non-finite estimate freezes the
drive. See docs/control.md.
"""

from ._kernels import amplitude_control
from .amplitude import AmplitudeController, design

__all__ = ["AmplitudeController", "amplitude_control", "design"]
