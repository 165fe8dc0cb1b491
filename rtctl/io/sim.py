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

from .._numba import kernel
from ..errors import SceneError
from ..safety import OVERTEMP, PLANT_NONFINITE, SENSOR_SATURATED
from .base import Backend

# simulated-group status bits -> rig status bits
_ADC_SATURATED, _NONFINITE, _OVERTEMP = 1, 2, 4


@kernel
def group_status(s):
    """A simulated group's status bits as the rig's."""
    st = 0
    if s & _ADC_SATURATED:
        st |= SENSOR_SATURATED
    if s & _NONFINITE:
        st |= PLANT_NONFINITE
    if s & _OVERTEMP:
        st |= OVERTEMP
    return st


@kernel
def deliver(src, dst):
    """The currents of the previous block become this block's readings (one block of latency)."""
    dst[:, :] = src
    return 0


# --- scene actuator groups -> simulated groups (one builder per type) ---------------------------

def _bimorph(models, g, gi, fs, block):
    from ..plant.bimorph import BimorphPlant, SimGroup
    from ..plant.frontend import Amplifier, CurrentSense

    s = g.sense
    sense = CurrentSense(s.shunt, s.aa_cutoff, s.aa_order, s.bits, s.full_scale, s.noise,
                         seed=models.scene.io.seed + 7919 * gi)
    plant = BimorphPlant(models.beam(g), Amplifier(g.amplifier.bandwidth), sense, models.finger(g),
                         n_modes=g.beam.modes)
    return SimGroup(plant, fs, g.grid[0] * g.grid[1], max_block=max(block, 1))


def _sma(models, g, gi, fs, block):
    from ..plant.sma import SmaGroup

    p = g.sma
    group = SmaGroup(models.sma(g), fs, g.grid[0] * g.grid[1], max_block=max(block, 1), mech_fs=p.mech_fs,
                     crossbar=p.crossbar, rows=g.grid[0], slot=p.slot)
    group.f_ext[:] = p.push
    return group


def _pvdf(models, g, gi, fs, block):
    from ..plant.pvdf import PvdfGroup

    return PvdfGroup(models.pvdf(g), fs, max_block=max(block, 1))


def _em(models, g, gi, fs, block):
    from ..plant.em import EMGroup

    return EMGroup(models.em(g), fs, g.grid[0] * g.grid[1], max_block=max(block, 1))


def _dot(models, g, gi, fs, block):
    from ..plant.dot import DotGroup

    return DotGroup(models.dot(g), fs, g.grid[0] * g.grid[1], up=g.dot.up, max_block=max(block, 1))


def _solenoid(models, g, gi, fs, block):
    from ..plant.solenoid import SolenoidGroup

    p = g.solenoid
    return SolenoidGroup(models.solenoid(g), fs, g.grid[0] * g.grid[1], max_block=max(block, 1),
                         substeps=p.substeps, levels=p.levels)


#: actuator type -> builder(models, group, group index, fs, block)
BUILDERS = {"bimorph": _bimorph, "sma": _sma, "pvdf": _pvdf, "em": _em, "dot": _dot,
            "solenoid": _solenoid}


def build_group(models, g, gi: int, fs: float, block: int):
    """The simulated group of actuator group ``g`` (index ``gi`` in the scene), following the
    simulated-group contract of :class:`SimDevice`; ``models`` is the scene's
    :class:`rtctl.models.Models`."""
    try:
        builder = BUILDERS[g.type]
    except KeyError:
        raise SceneError(f"actuator.{g.name}: type {g.type!r} has no simulated plant yet") from None
    return builder(models, g, gi, fs, block)


class SimDevice(Backend):
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

    def block_calls(self) -> tuple[list, list]:
        """The device's work as kernels for the rig's block function, ``(before, after)``: before
        the rig's stages, the previous block's currents become this block's readings (what
        :meth:`read` does); after them, every group advances by the block just limited (what
        :meth:`write` does). Each entry is ``(name, kernel, args, status map)``."""
        before = [("sim read", deliver, (self._next, self.sensed), True)]
        after = [(f"sim group {i}", kernel, args, group_status) for i, (kernel, args) in enumerate(self._calls)]
        return before, after

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
