"""build(scene) -> Rig: the components a scene uses, preallocated and compiled, nothing else.

The rig owns the block buffers (``out``: drive volts, ``sensed``: segment currents, both
``(rows, block)`` float64), the synthesis bank, the final limiter and the I/O backend, and
advances them one block at a time with :meth:`Rig.advance`. Everything a scene leaves out (see
:mod:`rtctl.needs`) is neither imported nor compiled: e.g. an open-loop scene never touches
``rtctl.selfsense`` or ``cv2``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import perception
from ._numba import kernel
from .errors import SceneError
from .needs import needs, unavailable_message


@dataclass(frozen=True)
class Tone:
    """One scene tone (or beat pair) on one channel, with its perception target."""

    channel: int              # global channel index
    freq: float               # Hz, carrier for a beat pair
    beat: float               # Hz, 0 for a single tone
    voltage: float            # V peak (envelope peak for a pair)
    receptor: str | None
    threshold_m: float        # m, NaN when no receptor responds at freq
    target_m: float           # m
    start: float              # s
    freqs: tuple              # Hz, the oscillator tones that make it (two for a beat pair)
    shape: str = "sine"       # sine (oscillator bank) | square | pulse (pulse trains)


def check_available(scene) -> None:
    """Refuse, in one line, a scene needing a component this version does not have."""
    n = needs(scene)
    if n.unavailable:
        c = n.unavailable[0]
        raise SceneError(f"{scene.source}: {unavailable_message(c, n.needed[c])}")


def _materials(scene):
    from .plant.materials import BUILTIN, material

    names = {layer.material for a in scene.actuator if a.type == "bimorph" for layer in a.beam.layers}
    out = {}
    for name in names:
        table = scene.materials.get(name)
        out[name] = material(name, dict(table) if table else None) if (table or name not in BUILTIN) else BUILTIN[name]
    return out


def beam_model(group, materials, scene=None):
    """The finite-element beam of a bimorph actuator group (no finger).

    A ``support.type = "actuator"`` root sits on the moving part of the group named by
    ``support.actuator`` (an ``em`` group: the bimodal display), whose suspension and armature
    give the elastic root with its mass (``EMPlant.support_spec``); that needs ``scene``.
    """
    from .plant.beam import BeamSpec, Layer, SupportSpec, build_beam

    b = group.beam
    layers = tuple(Layer(materials[layer.material], layer.thickness) for layer in b.layers)
    spec = BeamSpec(b.length, b.width, layers, b.connection, tuple(b.segments), b.damping, b.elements)
    sup = group.support
    if sup.type == "actuator":
        return build_beam(spec, carrier_support(scene, group))
    return build_beam(spec, SupportSpec(sup.type, sup.k, sup.k_rot))


def carrier_support(scene, group):
    """The moving root of a bimorph carried by another actuator group (seed 000 Sec. 3.3, R_m)."""
    name = group.support.actuator
    where = f"actuator.{group.name}.support.actuator"
    if scene is None:
        raise SceneError(f"{where}: a moving support needs the scene to find its carrier")
    carrier = scene.group(name)  # a SceneError naming the groups there are
    if carrier.type != "em":
        raise SceneError(f"{scene.source}: {where} = {name!r} is a {carrier.type!r} group; a bimorph can ride "
                         "on an electromagnetic ('em') actuator")
    if tuple(carrier.grid) != tuple(group.grid):
        raise SceneError(f"{scene.source}: {where} = {name!r}: grids differ ({list(carrier.grid)} vs "
                         f"{list(group.grid)}); each bimorph rides on its own carrier pin")
    from .simgroups import em_plant

    return em_plant(scene, carrier).support_spec()


def finger_params(scene, direction: str):
    """The finger's Maxwell parameter table for ``direction``: ``finger.lateral``/``normal``, or
    with ``finger.subject`` set, that subject's set in ``direction`` whose preload is nearest
    ``finger.preload`` (nearest on a log scale: loads scale roughly with preload ratios).
    Returns ``(table, where)``, ``where`` naming the set for reports."""
    f = scene.finger
    if not f.subject:
        return f[direction], f"finger.{direction}"
    sets = [(i, s) for i, s in enumerate(f.subjects) if s.name == f.subject and s.direction == direction]
    if not sets:
        have = sorted({f"{s.name}/{s.direction}" for s in f.subjects}) or ["none"]
        raise SceneError(f"{scene.source}: finger.subject = {f.subject!r} has no {direction} set in "
                         f"finger.subjects (have {', '.join(have)})")
    p = max(f.preload, 1e-6)
    i, best = min(sets, key=lambda t: abs(math.log(max(t[1].preload, 1e-6) / p)))
    return best, f"finger.subjects.{i} ({best.name}, {direction}, {best.preload:g} N)"


def finger_load(scene, group):
    """The generalized Maxwell finger on ``group``'s tips, or None without contact."""
    from .plant.finger import MaxwellLoad

    if not scene.finger.contact:
        return None
    f, _ = finger_params(scene, group.direction)
    return MaxwellLoad(f.mass, f.k0, tuple((b.k, b.tau) for b in f.branches))


def model_facts(scene) -> dict:
    """``rtctl model``: per actuator group, the facts of :func:`rtctl.plant.facts.model_facts`
    with ``loaded_natural_frequencies_hz`` under the scene's full finger load."""
    from .plant.facts import loaded_natural_frequencies
    from .plant.facts import model_facts as beam_facts

    mats = _materials(scene)
    out = {}
    for g in scene.actuator:
        if g.type != "bimorph":
            out[g.name] = {"type": g.type, "note": "no model facts for this actuator type yet"}
            continue
        fe = beam_model(g, mats, scene)
        facts = beam_facts(fe)
        finger = finger_load(scene, g)
        if finger is not None:
            facts["loaded_natural_frequencies_hz"] = loaded_natural_frequencies(fe, finger, 4)
        else:
            facts["loaded_natural_frequencies_hz"] = list(facts["natural_frequencies_hz"])
        # the transfer-matrix model of the same beam, an independent check of the FE values
        from .selfsense.facts import tmm_facts

        facts.update(tmm_facts(fe, finger))
        out[g.name] = facts
    return out


#: Largest condition number of the in-loop observer's inversion: the two-segment designs of the
#: bundled beams sit at 5-8; beyond 1e4 the current noise would dominate the estimate.
OBSERVER_MAX_COND = 1e4


def sensed_layout(scene):
    """Sensed rows on hardware: each bimorph channel's segment currents, channel-major (the rows
    the simulated bimorph writes); other actuator types sense nothing. Returns ``(row names,
    drive channel of each row)``."""
    rows, owner, ch0 = [], [], 0
    for g in scene.actuator:
        n = g.grid[0] * g.grid[1]
        if g.type == "bimorph":
            n_seg = len(g.beam.segments)
            rows += [f"{g.name}.{i}.seg{j}" for i in range(n) for j in range(n_seg)]
            owner += [ch0 + i for i in range(n) for _ in range(n_seg)]
        ch0 += n
    return rows, owner


class Rig:
    """What :func:`build` returns. Call :meth:`advance` once per block."""

    def __init__(self, scene):
        self.scene = scene
        self.fs = float(scene.timing.fs)
        self.block = int(scene.timing.block)
        self.needs = needs(scene)
        names, groups, limits = [], [], []
        for g in scene.actuator:
            n = g.grid[0] * g.grid[1]
            names += [f"{g.name}.{i}" for i in range(n)]
            groups += [g.name] * n
            limits += [g] * n
        self.channel_names, self.channel_groups = names, groups
        self.n_channels = len(names)
        self.out = np.zeros((self.n_channels, self.block))
        self.device = None
        self.truth = None
        self.sensed = np.zeros((0, self.block))
        self.sensed_names: list[str] = []  # row names of ``sensed``, for trace readers
        self._group_loads = {}
        self.probes = []
        self.truth_names = ()
        self.estimated = np.full((self.n_channels, self.block), np.nan)  # observer tip wave, m
        self.estimated_amp = np.full(self.n_channels, np.nan)  # observer tip amplitude, m
        if scene.io.backend == "sim":
            self._build_sim(scene)
        else:
            self._build_backend(scene)
        loads = [self._drive_load(scene, g) for g in groups]
        self._build_tones(scene)
        self._build_limiter(limits, loads)
        self._observers = []
        if scene.control.observe or scene.control.mode == "closed":
            self._build_observers(scene)
        self._compile()

    # --- construction -----------------------------------------------------------------------

    def _drive_load(self, scene, name: str) -> tuple:
        """``(capacitance, resistance)`` of a channel's load (the limiter's current bound), from
        its model whatever the backend: the same ``limits.current`` must mean the same thing."""
        if name not in self._group_loads:
            from .simgroups import drive_load

            self._group_loads[name] = drive_load(scene, scene.group(name))
        return self._group_loads[name]

    def _build_sim(self, scene):
        from .io.sim import SimDevice
        from .plant import TRUTH_NAMES
        from .simgroups import build_group

        groups, ch0, row0 = [], 0, 0
        self.probes = []  # (trace signal name, unit, group object, row)
        for gi, g in enumerate(scene.actuator):
            n = g.grid[0] * g.grid[1]
            sim = build_group(scene, g, gi, self.fs, self.block)
            rows = n * sim.n_sensed
            groups.append((sim, slice(ch0, ch0 + n), slice(row0, row0 + rows)))
            self.sensed_names += [f"{g.name}.{i}.{lab}" for i in range(n) for lab in sim.sensed_labels]
            self.probes += [(f"{g.name}.{pn}", unit, sim, r) for r, (pn, unit) in enumerate(sim.probe_names)]
            if sim.capacitance:  # a piezo: its model is built already (a PVDF plate takes ~1 s)
                self._group_loads[g.name] = (sim.capacitance, 0.0)
            ch0, row0 = ch0 + n, row0 + rows
        self.truth_names = TRUTH_NAMES
        self.sensed = np.zeros((row0, self.block))
        self.device = SimDevice(groups, self.out, self.sensed, len(TRUTH_NAMES))
        self.truth = self.device.truth

    def _build_backend(self, scene):
        """A hardware backend (``rtctl.io.<backend>.open_backend``), opened now so a missing
        device is reported before anything runs."""
        import importlib

        from .io.base import Layout

        rows, owner = sensed_layout(scene)
        self.sensed_names = rows
        self.sensed = np.zeros((len(rows), self.block))
        types = [scene.group(g).type for g in self.channel_groups]
        self.layout = Layout(self.fs, self.block, tuple(self.channel_names), tuple(self.channel_groups),
                             tuple(types), tuple(rows), tuple(owner))
        mod = importlib.import_module(f"rtctl.io.{scene.io.backend}")
        self.device = mod.open_backend(scene, self.layout, self.out, self.sensed)
        self.truth = getattr(self.device, "truth", None)
        self.probes = [(f"io.{pn}", unit, self.device, r)
                       for r, (pn, unit) in enumerate(getattr(self.device, "probe_names", ()))]

    def _build_observers(self, scene):
        """One self-sensing observer per bimorph group, on the scene's tone frequencies."""
        from .selfsense.frontend import FrontEnd
        from .selfsense.rt import Observer
        from .selfsense.tmm import TMMBeam

        if scene.stimulus.kind != "tones":
            raise SceneError(f"{scene.source}: control.observe needs stimulus.kind = 'tones' (the observer "
                             f"is designed on the tone frequencies; rendered stimuli change them), got "
                             f"{scene.stimulus.kind!r}")
        mats = _materials(scene)
        ch0, row0 = 0, 0
        latency = scene.io.latency_blocks or int(getattr(self.device, "latency_blocks", 1))
        for g in scene.actuator:
            n = g.grid[0] * g.grid[1]
            if g.type != "bimorph":
                ch0 += n
                continue
            n_seg = len(g.beam.segments)
            per = [[f for tn in self.tones if tn.channel == c for f in tn.freqs] for c in range(ch0, ch0 + n)]
            width = max(1, max(len(p) for p in per))
            freqs = np.array([p + [0.0] * (width - len(p)) for p in per])
            fe = beam_model(g, mats, scene)
            front = FrontEnd(self.fs, g.amplifier.bandwidth, g.sense.aa_cutoff, g.sense.aa_order)
            # an ill-conditioned tone is refused by the design itself (ModelError naming it)
            obs = Observer(TMMBeam.from_fe(fe), freqs, self.fs, self.block, front,
                           image_load=finger_load(scene, g), max_cond=OBSERVER_MAX_COND)
            obs.wave = self.estimated[ch0:ch0 + n]
            delay = np.zeros((max(1, latency), n, self.block))
            head = np.zeros(1, dtype=np.int64)
            rows = self.sensed[row0:row0 + n * n_seg]
            self._observers.append((obs, (*obs.args, delay, head, self.out[ch0:ch0 + n], rows,
                                          self.estimated_amp[ch0:ch0 + n])))
            ch0 += n
            row0 += n * n_seg

    def _build_tones(self, scene):
        tones, chans, freqs = [], [], []
        offsets = {}
        k = 0
        for g in scene.actuator:
            offsets[g.name] = k
            k += g.grid[0] * g.grid[1]
        self._schedule: dict[int, list] = {}
        scene_tones = scene.stimulus.tones if scene.stimulus.kind == "tones" else ()
        if scene_tones:
            from .dsp import OscillatorBank, beat_tones
        pulses = {}  # channel -> (block, freq, duty, high, low): square and pulse tones
        for i, t in enumerate(scene_tones):
            ch = offsets[t.actuator] + t.channel
            receptor = perception.auto_receptor(t.freq) if t.receptor == "auto" else t.receptor
            thr = perception.threshold_m(t.freq, receptor) if receptor else math.nan
            tgt = perception.target_m(t.freq, receptor, scene.control.margin_db) if receptor else math.nan
            if t.shape != "sine":
                if t.beat > 0:
                    raise SceneError(f"{scene.source}: stimulus.tones.{i}.beat = {t.beat:g}: a beat pair "
                                     "needs shape = 'sine'")
                if ch in pulses:
                    raise SceneError(f"{scene.source}: stimulus.tones.{i}: channel {t.actuator}.{t.channel} "
                                     "already plays a square/pulse tone (one per channel)")
                kb = int(math.floor(t.start * self.fs / self.block))
                high, low, duty = (t.voltage, -t.voltage, 0.5) if t.shape == "square" else (t.voltage, 0.0, t.duty)
                pulses[ch] = (kb, t.freq, duty, high, low)
                tones.append(Tone(ch, t.freq, 0.0, t.voltage, receptor, thr, tgt, t.start, (t.freq,), t.shape))
                continue
            if t.beat > 0:  # a pair of half amplitude each: the envelope peaks at the pair voltage
                fr, am = (tuple(float(x) for x in a) for a in beat_tones(t.freq, t.beat, t.voltage))
            else:
                fr, am = (t.freq,), (t.voltage,)
            tones.append(Tone(ch, t.freq, t.beat, t.voltage, receptor, thr, tgt, t.start, fr))
            # Every tone switches on ramped over one block at the block holding its start time.
            kb = int(math.floor(t.start * self.fs / self.block))
            self._schedule.setdefault(kb, []).extend(zip(range(len(freqs), len(freqs) + len(fr)), am))
            chans += [ch] * len(fr)
            freqs += fr
        self.tones = tones
        self.targets_um = np.full(self.n_channels, np.nan)
        for tone in tones:
            self.targets_um[tone.channel] = tone.target_m * 1e6
        self.bank = None
        if freqs:
            self.bank = OscillatorBank(self.n_channels, np.array(chans), self.fs, np.array(freqs),
                                       np.zeros(len(freqs)), ramp=self.block)
        self.pulses = None
        self.render = None
        self._pulse_schedule: dict[int, list] = {}
        if scene.stimulus.kind != "tones":
            from .stimulus import RenderStage

            self.render = RenderStage(scene, offsets, self.n_channels, self.fs, self.block)
            self.bank, self.pulses = self.render.bank, self.render.pulses
        if pulses:
            from .dsp import PulseTrain

            # Silent (frequency 0, both levels 0) until a channel's start block.
            self.pulses = PulseTrain(self.n_channels, self.fs, 0.0, 0.5, 0.0, 0.0)
            for ch, (kb, f, duty, high, low) in pulses.items():
                self._pulse_schedule.setdefault(kb, []).append((ch, f, duty, high, low))

    def _build_limiter(self, groups, loads):
        from .safety import Limiter

        lim = [g.limits for g in groups]
        self.limiter = Limiter(
            self.fs,
            max_voltage=[g.max_voltage for g in groups],
            slew=[x.slew for x in lim], current=[x.current for x in lim],
            capacitance=[c for c, _ in loads], resistance=[r for _, r in loads],
            temperature=[x.temperature for x in lim], ambient=[x.ambient for x in lim],
            loss_tangent=[x.loss_tangent for x in lim], thermal_resistance=[x.thermal_resistance for x in lim],
            thermal_tau=[x.thermal_tau for x in lim],
            # mean bounds from the group's type (the schema admits them only there); a bound of 1
            # can never be reached, so it costs nothing
            dc_offset=[g.max_voltage * x.dc_offset if getattr(x, "dc_offset", 1.0) < 1.0 else np.inf
                       for g, x in zip(groups, lim)],
            dc_tau=[getattr(x, "dc_tau", 1.0) for x in lim],
            duty=[x.duty if getattr(x, "duty", 1.0) < 1.0 else np.inf for x in lim],
            duty_tau=[getattr(x, "duty_tau", 1.0) for x in lim],
        )
        if self.scene.io.backend == "serial":
            from .io.serial import COMMAND_THRESHOLD

            self.limiter.commands_only(COMMAND_THRESHOLD * np.array([g.max_voltage for g in groups]))

    def _compile(self):
        """Compile (or load from numba's cache) every kernel now, not in the first block."""
        from . import _step

        if self.bank is not None and self.pulses is not None:
            self._step = _step.step_tones_pulses
            self._step_args = (*self.bank.args, *self.pulses.args, *self.limiter.args, self.out)
        elif self.pulses is not None:
            self._step = _step.step_pulses
            self._step_args = (*self.pulses.args, *self.limiter.args, self.out)
        elif self.bank is not None:
            self._step = _step.step_tones
            self._step_args = (*self.bank.args, *self.limiter.args, self.out)
        else:
            self._step = _step.step_silent
            self._step_args = (*self.limiter.args, self.out)
        saved = [a.copy() for a in self._step_args]
        self._step(*self._step_args)
        if self._observers:
            from ._observe import observe_stage

            self._observe = observe_stage
            for obs, args in self._observers:
                observe_stage(*args)
                obs.reset()
                args[-5][...] = 0.0  # the delay ring
                args[-4][0] = 0
            self.estimated[...] = np.nan
            for obs, args in self._observers:
                obs.wave[...] = 0.0
                args[-1][...] = 0.0
        self._calls = self.kernel_calls()
        if self.device is not None:
            self.device.compile()
        for a, s in zip(self._step_args, saved):
            a[...] = s
        if hasattr(self.device, "bind"):  # a callback backend: build its callback now, not at run()
            self.device.bind(self)

    # --- per block ----------------------------------------------------------------------------

    def apply_schedule(self, k: int) -> None:
        """Write the parameter changes due at block ``k`` (ramped across that block)."""
        for i, amp in self._schedule.get(k, ()):
            self.bank.set(i, amp=amp)
        for ch, f, duty, high, low in self._pulse_schedule.get(k, ()):
            self.pulses.set(ch, freq=f, duty=duty, high=high, low=low)
        if self.render is not None:
            self.render.apply(k)

    def kernel_calls(self) -> list:
        """The block step as ``[(kernel, args), ...]``: synthesis and limiter, then one observer
        stage per observed group. A C audio callback calls these kernels itself."""
        return [(self._step, self._step_args)] + [(self._observe, a) for _, a in self._observers]

    def step(self) -> int:
        """The block step without I/O (each call a nogil numba kernel over preallocated arrays;
        a callback backend calls this from its thread)."""
        status = 0
        for fn, args in self._calls:
            status |= fn(*args)
        return status

    def snapshot_call(self, snaps) -> tuple:
        """``(kernel, args)`` of :meth:`snapshot` into ``snaps``; the slot is the last argument."""
        return (_snapshot, (self.out, self.sensed, self.estimated, self.estimated_amp, self.limiter.temperature,
                            snaps.out, snaps.sensed, snaps.estimated, snaps.estimated_amp, snaps.temperature))

    def advance(self) -> int:
        """One block: read the sensed currents, the block step, write; status bits."""
        status = 0
        if self.device is not None:
            status |= self.device.read()
        status |= self.step()
        if self.device is not None:
            status |= self.device.write()
        return status

    def snapshot(self, snaps, slot: int) -> None:
        """Copy this block's outputs, readings, estimates and temperatures into ``snaps`` (a
        :class:`rtctl.io.base.Snapshots`) at ``slot``, for the trace (no allocation)."""
        fn, args = self.snapshot_call(snaps)
        fn(*args, slot)

    # --- trace ----------------------------------------------------------------------------------

    def trace_signals(self) -> dict:
        sig = {"drive": ("V", self.n_channels), "sensed": ("A", self.sensed.shape[0])}
        if self.truth is not None:
            sig.update({"tip_um": ("um", self.n_channels), "tip_velocity": ("m/s", self.n_channels),
                        "tip_force": ("N", self.n_channels), "voltage": ("V", self.n_channels)})
        for name, unit, _, _ in self.probes:
            sig[name] = (unit, 1)
        sig["target_um"] = ("um", self.n_channels, 0)
        sig["estimated_um"] = ("um", self.n_channels, 0)
        if self._observers:  # the rebuilt tip waveform, one io latency behind the drive
            sig["estimated_tip_um"] = ("um", self.n_channels)
        sig["temperature"] = ("degC", self.n_channels, 0)
        return sig

    def record(self, rec, status: int, compute_us: float, snaps=None, slot: int = 0) -> None:
        """Fill trace record ``rec`` from the rig's buffers, or from ``snaps[slot]`` (a callback
        backend's ring, the only consistent copy while the device thread runs on) when given."""
        if snaps is None:
            out, sensed, est, amp, temp = (self.out, self.sensed, self.estimated, self.estimated_amp,
                                           self.limiter.temperature)
        else:
            out, sensed, est, amp, temp = (snaps.out[slot], snaps.sensed[slot], snaps.estimated[slot],
                                           snaps.estimated_amp[slot], snaps.temperature[slot])
        rec["status"] = status
        rec["compute_us"] = compute_us
        rec["drive"][...] = out
        rec["sensed"][...] = sensed
        if self.truth is not None:  # only a simulation, always polled
            rec["tip_um"][...] = self.truth[:, 0, :]
            rec["tip_um"] *= 1e6
            rec["tip_velocity"][...] = self.truth[:, 1, :]
            rec["tip_force"][...] = self.truth[:, 2, :]
            rec["voltage"][...] = self.truth[:, 3, :]
        for name, _, sim, r in self.probes:
            rec[name][0] = sim.probe[r, :self.block]
        rec["target_um"][...] = self.targets_um
        rec["estimated_um"][...] = amp
        rec["estimated_um"] *= 1e6
        if self._observers:
            rec["estimated_tip_um"][...] = est
            rec["estimated_tip_um"] *= 1e6
        rec["temperature"][...] = temp


@kernel
def _snapshot(out, sensed, estimated, amp, temperature, s_out, s_sensed, s_est, s_amp, s_temp, slot):
    s_out[slot, :, :] = out
    s_sensed[slot, :, :] = sensed
    s_est[slot, :, :] = estimated
    s_amp[slot, :] = amp
    s_temp[slot, :] = temperature


def build(scene) -> Rig:
    """Construct, import and compile exactly what ``scene`` needs.

    Raises
    ------
    SceneError
        If the scene needs a component this version of rtctl does not have.
    """
    check_available(scene)
    return Rig(scene)
