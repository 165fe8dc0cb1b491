"""The ``sim`` backend: simulated plants behind the same block contract as hardware.

``write(drive)`` hands one block of drive voltages to the simulated groups, which advance and
produce the sensed currents of that block; ``read(sensed)`` returns them at the start of the
*next* block. That is one block of I/O latency, as on an audio interface, so a controller tested
here meets the same delay it meets on hardware. The true plant states (tip displacement and
friends) of the block just written are available in ``truth`` for the trace and the report: a
simulation knows the truth, hardware does not.

The simulated hardware is not its model: :func:`device_models` builds it with the relative factors
of ``io.mismatch`` (thickness, material constants, damping, finger), which only the simulated
devices read (this backend and the emulators). The rig's limiter, observer and controller design on
the scene's own values, as they would on a real device whose exact values nobody knows.
"""

from __future__ import annotations

import math

import numpy as np

from .._numba import kernel
from ..errors import ModelError, SceneError
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
                         n_modes=models.plant_modes(g))
    _check_shunt(models.scene, g, float(np.max(plant.fe.Cp)), fs)
    loads = [plant.finger]
    for finger in [*_event_fingers(models, g).values(), *_fault_fingers(models, g)]:
        if finger not in loads:
            loads.append(finger)
    if len(loads) == 1:
        return SimGroup(plant, fs, g.grid[0] * g.grid[1], max_block=max(block, 1))
    from ..plant.switching import SwitchedSimGroup

    plants = [plant] + [BimorphPlant(models.beam(g), Amplifier(g.amplifier.bandwidth), sense, f,
                                     n_modes=models.plant_modes(g)) for f in loads[1:]]
    return SwitchedSimGroup(plants, fs, g.grid[0] * g.grid[1], max_block=max(block, 1))


def _check_shunt(scene, g, cp, fs):
    """The simulated group's shunt bound (:data:`rtctl.plant.bimorph.SHUNT_RC_FS`) in the scene's
    words: the keys that set it, their values, and what to set them to."""
    from ..plant.bimorph import SHUNT_RC_FS

    rc = g.sense.shunt * cp
    if rc * fs <= SHUNT_RC_FS:
        return
    key = f"actuator.{g.name}.sense.shunt"
    raise SceneError(
        f"{scene.source}: {key} = {g.sense.shunt:g} ohm is too large for a segment capacitance of "
        f"{cp * 1e9:.3g} nF (set by actuator.{g.name}.beam: length {g.beam.length:g} m, width "
        f"{g.beam.width:g} m, its layers) at timing.fs = {fs:g} Hz: the current-sense shunt's time constant "
        f"R_s Cp = {rc:.3g} s must stay below {SHUNT_RC_FS:g} / fs, or its voltage drop on the piezo (which "
        f"the model leaves out) would matter; set {key} below {_down(SHUNT_RC_FS / (fs * cp)):g} ohm, or "
        f"timing.fs below {_down(SHUNT_RC_FS / rc):g} Hz")


def _down(x: float) -> float:
    """``x`` rounded down to 3 significant digits: a bound quoted to the user that really holds."""
    e = 10.0 ** (math.floor(math.log10(x)) - 2)
    return math.floor(x / e) * e


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


#: actuator types whose finger contact force is a per-pin ``preload`` (a hybrid model input)
PIN_TYPES = ("em", "dot", "solenoid")

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
    group = builder(models, g, gi, fs, block)
    group.events = _group_events(models, g, group)
    return group


def device_models(scene, nominal=None):
    """The models the simulated hardware is built from: the scene's, with the factors of
    ``io.mismatch`` (:class:`rtctl.models.Models` ``factors``) that the rig's models do not have.

    Parameters
    ----------
    scene : rtctl.scene.Scene
    nominal : rtctl.models.Models, optional
        The rig's models, returned as they are when every factor is 1 (nothing is built twice).

    Raises
    ------
    SceneError
        A factor makes a model impossible (a coupling k31^2 >= 1, a damping ratio >= 1, ...).
    """
    from ..models import Models

    factors = {k: float(v) for k, v in scene.io.mismatch.items() if v != 1.0}
    if not factors:
        return nominal if nominal is not None else Models(scene)
    models = Models(scene, factors)
    try:  # the impossible models now, named by the key that made them, not in the first block
        models.materials()
        for g in scene.actuator:
            if g.type == "bimorph":
                models.beam(g)
            models.finger(g)
    except ModelError as e:
        shown = ", ".join(f"{k} = {v:g}" for k, v in factors.items())
        raise SceneError(f"{scene.source}: io.mismatch ({shown}) makes the simulated device impossible: "
                         f"{e}") from None
    return models


# --- scene events -> writes into the groups' event targets ----------------------------------------

class GroupEvents:
    """What the scene's events write into one simulated group.

    Attributes
    ----------
    targets : list of ndarray
        The group's arrays the events write (2-D float64, C-contiguous); once a run starts only the
        block function writes them (the engine registers them with its parameter queue).
    writes : dict
        Event index (``Event.index``) -> ``[(array, row, col, value)]``.
    initial : list of ndarray
        The targets' values as built (:meth:`SimDevice.reset` puts them back).
    """

    def __init__(self, targets, writes):
        self.targets, self.writes = list(targets), dict(writes)
        self.initial = [t.copy() for t in self.targets]


def _event_fingers(models, g) -> dict:
    """Event index -> the finger load on group ``g`` after that event (built as ``models`` builds
    it, ``io.mismatch`` factors included); empty without events."""
    if not models.scene.events:
        return {}
    from ..events import schedule
    from ..models import Models

    return {e.index: Models(e.scene_after, models.factors).finger(g) for e in schedule(models.scene)}


def _fault_fingers(models, g) -> list:
    """The finger loads the scene's finger faults switch group ``g`` to: lifted (None) and slammed
    (:func:`rtctl.io.faults.slam_factor` times the force: the Maxwell stiffnesses and the moving
    skin mass scaled by it, a stiffening contact); empty without finger faults."""
    from .faults import slam_factor, wants_fingers

    if not wants_fingers(models.scene) or not models.scene.finger.contact:
        return []
    from ..models import Models

    s = slam_factor(models.scene)
    f = dict(models.factors or {})
    slammed = {k: f.get(k, 1.0) * s for k in ("finger_k0", "finger_branches", "finger_mass")}
    return [None, Models(models.scene, {**f, **slammed}).finger(g)]


def finger_states(group, models, g) -> tuple | None:
    """``(target, col, lift, slam)`` for :func:`rtctl.io.faults.inject_finger` on a built group:
    a bimorph group's load index (the lifted and slammed loads of :func:`_fault_fingers`), a pin
    group's preloads (0 N lifted, :func:`~rtctl.io.faults.slam_factor` times the preload slammed);
    None where no finger fault reaches it."""
    from .faults import slam_factor

    scene = models.scene
    extra = _fault_fingers(models, g)
    if not extra:
        return None
    if g.type == "bimorph":
        loads = list(getattr(group, "loads", ()))
        if not all(x in loads for x in extra):
            return None
        return group.load, 0, float(loads.index(extra[0])), float(loads.index(extra[1]))
    if g.type in PIN_TYPES:
        preload = float(group.params[0, 0])
        return group.params, 0, 0.0, preload * slam_factor(scene)
    return None


def _group_events(models, g, group):
    """The :class:`GroupEvents` of a built group, or None when no event changes it; an event the
    group's plant cannot follow is refused in one line."""
    if not models.scene.events:
        return None
    from ..events import schedule
    from ..models import Models

    events = schedule(models.scene)
    fingers = _event_fingers(models, g)
    where = f"{models.scene.source}: actuator.{g.name}"
    if g.type == "bimorph":
        from ..plant.switching import SwitchedSimGroup

        if not isinstance(group, SwitchedSimGroup):   # no event changes this group's load
            return None
        return GroupEvents([group.load], {i: [(group.load, 0, 0, float(group.loads.index(f)))]
                                          for i, f in fingers.items()})
    if g.type == "sma":   # the SMA taxel has no finger model (its finger force is sma.push)
        return None
    initial = models.finger(g)
    for e in events:
        if fingers[e.index] != initial:
            keys = ", ".join(k for k in e.sets if k.startswith("finger."))
            also = (f"its contact force is actuator.{g.name}.{g.type}.preload, which events may set"
                    if g.type in PIN_TYPES else "finger.preload alone moves its static finger force")
            raise SceneError(f"{where}: events.{e.index} ({keys}) changes the finger load on this {g.type!r} "
                             f"group, whose simulated plant cannot switch loads during a run (only bimorph "
                             f"groups can; {also})")
    if g.type in PIN_TYPES:
        # the pin's contact force is an input of its hybrid model, held per channel in params[:, 0]
        # (the models give it only with a finger: models.Models.em and friends)
        value = {e.index: e.scene_after.group(g.name)[g.type].preload if initial is not None else 0.0
                 for e in events}
        built = {float(group.params[0, 0])}
        for e in events:
            if value[e.index] not in built:   # a preload the pin cannot rest at is refused now
                try:
                    getattr(Models(e.scene_after, models.factors), g.type)(g)
                except ModelError as err:
                    raise SceneError(f"{where}: events.{e.index}: {err}") from None
                built.add(value[e.index])
        if len(built) == 1:
            return None
        return GroupEvents([group.params], {i: [(group.params, ch, 0, float(v)) for ch in range(group.n_channels)]
                                            for i, v in value.items()})
    if g.type == "pvdf" and initial is not None:
        # the finger's static force only offsets the plate's force output (its kernel's consts[1])
        consts = group.consts.reshape(1, -1)
        value = {e.index: float(e.scene_after.finger.preload) for e in events}
        if all(v == consts[0, 1] for v in value.values()):
            return None
        return GroupEvents([consts], {i: [(consts, 0, 1, v)] for i, v in value.items()})
    return None


class SimDevice(Backend):
    """Simulated groups, each driving a contiguous range of channels and sensed rows.

    Parameters
    ----------
    groups : list of (group, slice, slice)
        A simulated group, its rows in ``drive``/``truth`` and its rows in ``sensed``. Any
        plant's group works that follows the simulated-group contract: ``group.kernel(*group.args,
        drive, sensed, truth) -> status`` over preallocated arrays, ``reset()``, and ``probe``
        (group-level signals the kernel writes, ``(n_probe, >= block)``), and ``events``: what
        the scene's events write into it (:class:`GroupEvents`, or None; :func:`build_group` sets
        it). Status bits: 1 a sensor saturated, 2 a state is non-finite, 4 an actuator is over
        temperature.
    drive : ndarray, shape (n_channels, block)
        The rig's output buffer (read by :meth:`write`).
    sensed : ndarray, shape (n_sensed, block)
        The rig's input buffer (filled by :meth:`read`).
    n_truth : int
        Truth signals per channel.
    factors : dict, optional
        The ``io.mismatch`` factors the groups were built with (:func:`device_models`), for
        :meth:`stats` only.
    faults : rtctl.io.faults.Injector, optional
        The scene's ``[io.faults]``: the device misbehaving on its side of the contract. The
        plant then runs on a copy of the drive (what the amplifier passes), never on the rig's.
    fingers : list of tuple
        :func:`finger_states` of the groups a finger fault reaches.
    """

    def __init__(self, groups, drive: np.ndarray, sensed: np.ndarray, n_truth: int, factors=None,
                 faults=None, fingers=()):
        self.groups = groups
        self.factors = dict(factors or {})
        self.sensed = sensed
        self._next = np.zeros_like(sensed)
        self.truth = np.zeros((drive.shape[0], n_truth, drive.shape[1]))
        self.faults = faults
        self._rig_drive = drive
        self._drive = drive if faults is None else np.zeros_like(drive)
        self._fingers = list(fingers)
        # Kernel arguments fixed once, with views into the buffers: nothing is allocated or
        # checked per block (a group's process() would check shapes every call).
        self._calls = [(g.kernel, (*g.args, self._drive[ch], self._next[sr], self.truth[ch]))
                       for g, ch, sr in groups]

    #: Run the simulated groups inside the rig's block function (one call per block instead of
    #: three, and no numba dispatch of the groups' many arguments from Python) rather than from
    #: ``read`` and ``write``: 18-29 % less CPU time per block on every bundled scene but
    #: pvdf-6x8 (4 %), bitwise the same blocks. Composing the plant kernels into the block
    #: function recompiles them with it, about 4 s more on a run with an empty numba cache, which
    #: ``rtctl warm`` (the set-up step) takes for the demo.
    in_block = True

    def block_calls(self) -> tuple[list, list] | None:
        """With :attr:`in_block`, the device's work as kernels for the rig's block function,
        ``(before, after)``: before the rig's stages, the previous block's currents become this
        block's readings (what :meth:`read` does); after them, every group advances by the block
        just limited (what :meth:`write` does). Each entry is ``(name, kernel, args, status
        map)``. None otherwise: the engine calls :meth:`read` and :meth:`write`."""
        if not self.in_block or self.faults is not None:
            return None
        before = [("sim read", deliver, (self._next, self.sensed), True)]
        after = [(f"sim group {i}", kernel, args, group_status) for i, (kernel, args) in enumerate(self._calls)]
        return before, after

    def state_arrays(self) -> tuple:
        """Every array the simulated device writes or its events rewrite: its groups' kernel
        arguments (plant, finger and sensing-noise states, switched loads, pin preloads) and its
        buffers, for a checkpoint (:mod:`rtctl.engine.state`)."""
        return (self._next, self.sensed, self.truth, *(a for _, args in self._calls for a in args))

    def read(self) -> int:
        """Fill ``sensed`` with the currents of the previous block (one block of latency)."""
        np.copyto(self.sensed, self._next)
        if self.faults is None:
            return 0
        status = self.faults.sensed(self.sensed)  # what the faulty device delivers, and its own flags
        return status | self.faults.guard(status)

    def write(self) -> int:
        """Advance every simulated group by the block now in ``drive`` (volts)."""
        status = 0
        if self.faults is not None:
            for target in self._fingers:
                self.faults.finger(*target)
            self.faults.drive(self._rig_drive, self._drive)
            self.faults.count()
        for group_kernel, args in self._calls:
            status |= group_status(group_kernel(*args))
        return status

    def stats(self) -> dict:
        """``mismatch``: the factors the simulated device differs from the scene by (a report may
        know them; the rig does not use them), when there are any."""
        out = {"mismatch": dict(self.factors)} if self.factors else {}
        if self.faults is not None:
            out["faults"] = self.faults.describe()
            k = int(self.faults.ctl[0])
            if any(f.kind == "device_stopped" and f.start <= k for f in self.faults.faults):
                out["error"] = "the simulated device stopped answering (an injected fault)"
        return out

    def compile(self) -> None:
        """Run the kernel once on the real buffers (compiles or loads it), then reset."""
        self.write()
        self.reset()

    def event_targets(self) -> list:
        """The arrays the scene's events write (2-D float64, C-contiguous): the engine registers
        them with its parameter queue, whose drain is then their only writer while a run lasts.

        * a bimorph group whose finger load an event changes: its ``load``, shape (1, 1), the index
          of the load state the group runs (``group.loads``); a new value switches the load at the
          start of the next block the group advances, the state carried across
          (:mod:`rtctl.plant.switching`);
        * an ``em``/``dot``/``solenoid`` group whose pin preload an event changes: its ``params``,
          shape (n_channels, 1), each pin's finger contact force, N (an input of its hybrid model,
          held over the block);
        * a ``pvdf`` group whose finger preload an event changes: its kernel constants viewed as
          (1, n), column 1 the static finger force, N (an offset of the force output).
        """
        return [t for g, _, _ in self.groups if g.events is not None for t in g.events.targets]

    def event_posts(self, event) -> list:
        """``[(array, row, col, value)]`` to post at block ``event.block`` for a
        :class:`rtctl.events.Event` of this scene: ``array`` is one of :meth:`event_targets` (the
        same object), ``array[row, col] = value`` the write. Applied at the start of that block,
        before the groups advance; posting a value already there changes nothing."""
        return [w for g, _, _ in self.groups if g.events is not None
                for w in g.events.writes.get(event.index, ())]

    def reset(self) -> None:
        if self.faults is not None:
            self.faults.reset()
            self._drive[:] = 0.0
        self._next[:] = 0.0
        self.sensed[:] = 0.0
        self.truth[:] = 0.0
        for g, _, _ in self.groups:
            g.reset()
            if g.events is not None:   # what the events wrote, back to the scene's values
                for t, t0 in zip(g.events.targets, g.events.initial):
                    t[...] = t0
