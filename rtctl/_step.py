"""The rig's block steps: one ``@njit`` call per block over preallocated arrays.

A step exists per combination of stages a scene can need, each importing only its own kernels,
so a scene never compiles a stage it leaves out (numba cannot cache a step composed at run time
from function arguments or closures; explicit variants can be cached).
"""

from ._numba import kernel
from .dsp import osc_bank_process, pulse_process
from .safety import limit_block


@kernel
def step_tones(osc_state, osc_pending, osc_chan, lim_state, lim_params, lim_fade, lim_counts, out):
    """Open loop with tones: synthesize into ``out`` (n_channels, block), then limit it."""
    out[:, :] = 0.0
    osc_bank_process(osc_state, osc_pending, osc_chan, out)
    return limit_block(out, lim_state, lim_params, lim_fade, lim_counts)


@kernel
def step_pulses(pulse_state, pulse_pending, lim_state, lim_params, lim_fade, lim_counts, out):
    """Open loop with square/pulse tones only (coil pins, SMA): pulse trains, then the limiter."""
    out[:, :] = 0.0
    pulse_process(pulse_state, pulse_pending, out)
    return limit_block(out, lim_state, lim_params, lim_fade, lim_counts)


@kernel
def step_tones_pulses(osc_state, osc_pending, osc_chan, pulse_state, pulse_pending, lim_state,
                      lim_params, lim_fade, lim_counts, out):
    """Sine tones and square/pulse tones together, then the limiter."""
    out[:, :] = 0.0
    osc_bank_process(osc_state, osc_pending, osc_chan, out)
    pulse_process(pulse_state, pulse_pending, out)
    return limit_block(out, lim_state, lim_params, lim_fade, lim_counts)


@kernel
def step_silent(lim_state, lim_params, lim_fade, lim_counts, out):
    """No stimulus: zeros through the limiter (which still fades whatever was playing)."""
    out[:, :] = 0.0
    return limit_block(out, lim_state, lim_params, lim_fade, lim_counts)
