"""The block-I/O contract every backend follows, and what the rig tells a backend about itself.

The rig owns two preallocated buffers: ``out`` (n_channels, block), drive volts after the final
limiter, and ``sensed`` (n_sensed, block), sensed currents in amperes. A backend moves them to and
from a device. Two kinds exist:

**Polled** backends (``sim``, ``serial``, ``daq``): the engine calls, once per block,
``read()`` (fill ``sensed`` with the newest complete block), the rig's block step, then
``write()`` (send ``out``). Both return status bits (:mod:`rtctl.safety`) and never block longer
than a block period; a lost device is reported as ``DEVICE_LOST``, not raised. ``paced`` says the
device's clock (or the wall clock) sets the pace, so the engine sleeps to real time.

**Callback** backends (``audio``): the device's thread calls the block step itself; the engine's
thread only schedules parameter changes and writes the trace from snapshots (see
:class:`Snapshots`). They have ``callback = True`` and a ``run(rig, n_blocks, on_block)`` method.

Every backend has ``close()``: outputs to zero where the hardware allows, device released;
idempotent and never raises. ``stats()`` returns a JSON-able dict for ``summary["io"]``.

Every backend derives from :class:`Backend`, which states the whole protocol with its defaults:
callers use the attributes, never probe for them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DeviceError, SceneError


@dataclass(frozen=True)
class Layout:
    """What a backend needs to know about the rig it serves.

    Attributes
    ----------
    fs : float
        Sample rate, Hz.
    block : int
        Samples per block.
    channel_names : tuple of str
        ``GROUP.INDEX`` per drive row of ``out``.
    channel_groups : tuple of str
        Actuator group name per drive row.
    channel_types : tuple of str
        Actuator type per drive row (``bimorph``, ``dot``, ``sma``, ...).
    sensed_names : tuple of str
        ``GROUP.INDEX.LABEL`` per row of ``sensed`` (e.g. ``lateral.0.seg1``), channel-major.
    sensed_channel : tuple of int
        Drive row each sensed row belongs to.
    """

    fs: float
    block: int
    channel_names: tuple
    channel_groups: tuple
    channel_types: tuple
    sensed_names: tuple
    sensed_channel: tuple

    @property
    def n_channels(self) -> int:
        return len(self.channel_names)

    @property
    def n_sensed(self) -> int:
        return len(self.sensed_names)


class Snapshots:
    """A ring of per-block copies a callback backend fills and the engine's thread reads.

    The device thread writes slot ``k % n`` after block ``k`` and counts it in its control
    array (one int store: no lock); the backend's engine-side loop publishes that count as
    ``done`` and hands the engine every slot below it that it has not read yet. A
    ring of ``n`` slots lets the engine fall ``n - 1`` blocks behind before ``overrun`` counts
    lost trace blocks.

    Attributes
    ----------
    out : ndarray (n, n_channels, block)
    sensed : ndarray (n, n_sensed, block)
    estimated : ndarray (n, n_channels, block)
        Observer tip waveform, m (NaN rows where nothing is observed).
    estimated_amp : ndarray (n, n_channels)
        Observer tip amplitude, m (NaN where nothing is observed).
    temperature : ndarray (n, n_channels)
    status : ndarray int64 (n,)
    compute_us : ndarray (n,)
        Time the callback spent in the block step.
    """

    def __init__(self, n: int, n_channels: int, n_sensed: int, block: int):
        self.n = int(n)
        self.out = np.zeros((n, n_channels, block))
        self.sensed = np.zeros((n, n_sensed, block))
        self.estimated = np.full((n, n_channels, block), np.nan)
        self.estimated_amp = np.full((n, n_channels), np.nan)
        self.temperature = np.zeros((n, n_channels))
        self.status = np.zeros(n, dtype=np.int64)
        self.compute_us = np.zeros(n)
        self.done = 0      # blocks completed by the device thread
        self.overrun = 0   # blocks the engine had not read before their slot was reused


def channel_map(values, n_rows: int, n_device: int | None, key: str, rows: str) -> np.ndarray:
    """The device channel of each of ``n_rows`` rows (``io.outputs`` / ``io.inputs``): ``values``,
    or 0, 1, ... when empty; ``n_device`` None when the device's channel count is not known here
    (a DAQ checks its channel names itself).

    Raises
    ------
    SceneError
        Wrong length or a device channel given twice.
    DeviceError
        A channel the device does not have.

    Examples
    --------
    >>> channel_map((), 3, 8, "io.outputs", "drive channels").tolist()
    [0, 1, 2]
    >>> channel_map((4, 2), 2, 8, "io.outputs", "drive channels").tolist()
    [4, 2]
    """
    m = np.arange(n_rows, dtype=np.int64) if len(values) == 0 else np.asarray(values, dtype=np.int64)
    if m.size != n_rows:
        raise SceneError(f"{key} has {m.size} entries but the scene has {n_rows} {rows}: give one "
                         f"device channel per row, or [] for 0..{n_rows - 1}")
    u, c = np.unique(m, return_counts=True)
    if np.any(c > 1):
        raise SceneError(f"{key} = {m.tolist()}: device channel {int(u[c > 1][0])} is given twice")
    if n_device is not None and m.size and (m.min() < 0 or m.max() >= n_device):
        bad = int(m.max()) if m.max() >= n_device else int(m.min())
        raise DeviceError(f"{key} = {m.tolist()}: the device has channels 0..{n_device - 1}, not {bad}")
    return m


class Backend:
    """The backend protocol, with the defaults a backend overrides where it differs.

    Attributes
    ----------
    callback : bool
        The device's thread runs the block function (``run(rig, n_blocks, on_block)``, ``bind``).
    paced : bool
        The device's (or the wall) clock sets the pace: the polled engine sleeps to real time.
    clocked : bool
        The device's own clock paces the loop (``read`` waits for its buffers): the loop must
        not wait on anything else, so a full trace ring drops records instead.
    latency_blocks : int
        Blocks from a drive block going out to the currents it caused coming back.
    truth : ndarray or None
        True plant states ``(n_channels, n_truth, block)`` (a simulation's); None on hardware.
    probe_names : sequence of (name, unit)
        Extra per-block signals in ``probe`` rows, traced as ``io.NAME``.
    commands_only : float or None
        The outputs are pin commands to a controller (fraction of ``max_voltage`` that means
        "up"/"down"), not coil voltages: see :meth:`rtctl.safety.Limiter.commands_only`.
    """

    callback = False
    paced = False
    clocked = False
    latency_blocks = 1
    truth = None
    probe_names: tuple = ()
    probe = None
    commands_only = None

    def block_calls(self):
        """``(before, after)`` kernel calls the rig's block function runs in place of
        :meth:`read` and :meth:`write` (a device simulated in the block function), or None."""
        return None

    def event_targets(self) -> list:
        """Arrays (2-D float64) the scene's ``[[events]]`` write on this device (a simulated
        finger's load, say); the engine hands them to its parameter queue. A real device has
        none: its finger moves by itself."""
        return []

    def event_posts(self, event) -> list:
        """``[(array, row, col, value)]`` to write at ``event.block`` (one of :meth:`event_targets`)."""
        return []

    def read(self) -> int:
        return 0

    def write(self) -> int:
        return 0

    def compile(self) -> None:
        """Compile (or load) the backend's kernels now, not in the first block."""

    def reset(self) -> None:
        """Back to the state before the first block."""

    def bind(self, rig) -> None:
        """A callback backend: build the device thread's callback around ``rig``'s block function."""

    def close(self) -> None:
        """Outputs to zero where the hardware allows, device released; idempotent, never raises."""

    def stats(self) -> dict:
        return {}
