"""DSP kernels for the real-time loop: oscillators, beat pairs, pulse trains, ramps, lock-in.

Each streaming object is a small wrapper (validation, arrays, ``process``/``reset``) around a
numba kernel that the loop can also call from its own ``@njit`` block step as
``kernel(*obj.args, out)``. Imports only numpy and numba.
"""

from rtctl.dsp._kernels import fade_process, lockin_process, osc_bank_process, pulse_process, ramp_process
from rtctl.dsp.envelope import Fade, Ramp
from rtctl.dsp.lockin import LockIn, beat_window, window_leakage
from rtctl.dsp.oscillator import OscillatorBank, beat_tones
from rtctl.dsp.pulse import PulseTrain

__all__ = [
    "OscillatorBank",
    "beat_tones",
    "PulseTrain",
    "Ramp",
    "Fade",
    "LockIn",
    "beat_window",
    "window_leakage",
    "osc_bank_process",
    "pulse_process",
    "ramp_process",
    "fade_process",
    "lockin_process",
]
