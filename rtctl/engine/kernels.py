"""The engine's own stage kernels."""

from .._numba import kernel


@kernel
def clear(out):
    """Zero the drive block: the synthesis stages add into it."""
    out[:, :] = 0.0


@kernel
def snapshot(out, sensed, estimated, amp, temperature, s_out, s_sensed, s_est, s_amp, s_temp, slot):
    """Copy one block's outputs, readings, estimates and temperatures into ring slot ``slot``."""
    s_out[slot, :, :] = out
    s_sensed[slot, :, :] = sensed
    s_est[slot, :, :] = estimated
    s_amp[slot, :] = amp
    s_temp[slot, :] = temperature
