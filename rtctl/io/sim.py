"""The ``sim`` backend: simulated plants behind the same block contract as hardware.

``write(drive)`` hands one block of drive voltages to the simulated groups, which advance and
produce the sensed currents of that block; ``read(sensed)`` returns them at the start of the
*next* block. That is one block of I/O latency, as on an audio interface, so a controller tested
here meets the same delay it meets on hardware. The true plant states (tip displacement and
friends) of the block just written are available in ``truth`` for the trace and the report: a
simulation knows the truth, hardware does not.
"""

from __future__ import annotations

import numpy as np

from ..safety import OVERTEMP, PLANT_NONFINITE, SENSOR_SATURATED

# simulated-group status bits -> rig status bits
_ADC_SATURATED, _NONFINITE, _OVERTEMP = 1, 2, 4


class SimDevice:
    """Simulated groups, each driving a contiguous range of channels and sensed rows.

    Parameters
    ----------
    groups : list of (group, slice, slice)
        A simulated group, its rows in ``drive``/``truth`` and its rows in ``sensed``. Any
        plant's group works that follows the simulated-group contract: ``group.kernel(*group.args,
        drive, sensed, truth) -> status`` over preallocated arrays, ``reset()``, and ``probe``
        (group-level signals the kernel writes, ``(n_probe, >= block)``). Status bits: 1 a
        sensor saturated, 2 a state is non-finite, 4 an actuator is over temperature.
    drive : ndarray, shape (n_channels, block)
        The rig's output buffer (read by :meth:`write`).
    sensed : ndarray, shape (n_sensed, block)
        The rig's input buffer (filled by :meth:`read`).
    n_truth : int
        Truth signals per channel.
    """

    def __init__(self, groups, drive: np.ndarray, sensed: np.ndarray, n_truth: int):
        self.groups = groups
        self.sensed = sensed
        self._next = np.zeros_like(sensed)
        self.truth = np.zeros((drive.shape[0], n_truth, drive.shape[1]))
        # Kernel arguments fixed once, with views into the buffers: nothing is allocated or
        # checked per block (a group's process() would check shapes every call).
        self._calls = [(g.kernel, (*g.args, drive[ch], self._next[sr], self.truth[ch]))
                       for g, ch, sr in groups]

    def read(self) -> int:
        """Fill ``sensed`` with the currents of the previous block (one block of latency)."""
        np.copyto(self.sensed, self._next)
        return 0

    def write(self) -> int:
        """Advance every simulated group by the block now in ``drive`` (volts)."""
        status = 0
        for kernel, args in self._calls:
            s = kernel(*args)
            if s & _ADC_SATURATED:
                status |= SENSOR_SATURATED
            if s & _NONFINITE:
                status |= PLANT_NONFINITE
            if s & _OVERTEMP:
                status |= OVERTEMP
        return status

    def compile(self) -> None:
        """Run the kernel once on the real buffers (compiles or loads it), then reset."""
        self.write()
        self.reset()

    def reset(self) -> None:
        self._next[:] = 0.0
        self.sensed[:] = 0.0
        self.truth[:] = 0.0
        for g, _, _ in self.groups:
            g.reset()
