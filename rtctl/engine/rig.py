"""build(scene) -> Rig: the buffers and the ordered stage list a scene needs, nothing else.

The rig owns the block buffers (``out``: drive volts, ``sensed``: segment currents, both
``(rows, block)`` float64) and runs one block with :meth:`Rig.advance`: the backend's read, the
block function, the backend's write. The block function is the stage list composed into one
compiled function (:mod:`rtctl.engine.compose`)::

    params        drain the parameter queue into the pending arrays (schedule changes)
    [sim read]    the simulated device: last block's currents become this block's readings
    clear         zero the drive block
    oscillators   sine tones and beat pairs              (scenes with sines)
    pulses        square and pulse trains, held levels   (scenes with them)
    limiter       the final limiter: always, and always after every stage that writes ``out``
    observer G    self-sensing of bimorph group G        (control.observe, closed loop)
    control G     next block's tone amplitudes of every channel of group G from their
                  estimates (closed loop; one per group, after its observer)
    [sim group i] the simulated plants advance by the limited block
                  ([bracketed]: the simulated device's, with ``SimDevice.in_block``; else the
                  engine calls its read and write around the block function)

Everything a scene leaves out (see :mod:`rtctl.needs`) is neither imported nor compiled: e.g. an
open-loop scene never touches ``rtctl.selfsense`` or ``cv2``.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import SceneError
from ..models import Models, n_channels, n_segments, sensed_layout
from ..needs import needs, unavailable_message
from ..stimulus import check_control, tone_receptor, tone_target_m
from .kernels import clear, snapshot
from .queue import ParamQueue, drain
from .stage import Stage


def check_available(scene) -> None:
    """Refuse, in one line, a scene needing a component this version does not have."""
    n = needs(scene)
    if n.unavailable:
        c = n.unavailable[0]
        raise SceneError(f"{scene.source}: {unavailable_message(c, n.needed[c])}")


class Rig:
    """What :func:`build` returns. Call :meth:`advance` once per block.

    Threading: :meth:`apply_schedule` (the engine's thread) only posts to the parameter queue;
    the block function, wherever it runs, is the one writer of every array its stages use.
    """

    def __init__(self, scene, device_in_block: bool = True):
        self.scene = scene
        self._want_in_block = device_in_block
        self.fs = float(scene.timing.fs)
        self.block = int(scene.timing.block)
        self.needs = needs(scene)
        from .calibrate import scene_calibration

        # control.calibration: the rig's models take the device's fitted factors (None: nominal)
        self.calibration = scene_calibration(scene)
        self.models = self.calibration.models(scene) if self.calibration else Models(scene)
        names, groups, offsets = [], [], {}
        for g in scene.actuator:
            offsets[g.name] = len(names)
            names += [f"{g.name}.{i}" for i in range(n_channels(g))]
            groups += [g.name] * n_channels(g)
        self.channel_names, self.channel_groups = names, groups
        self.n_channels = len(names)
        self.out = np.zeros((self.n_channels, self.block))
        self.device = None
        self.truth = None
        self.sensed = np.zeros((0, self.block))
        self.sensed_names: list[str] = []  # row names of ``sensed``, for trace readers
        # each group's rows of ``sensed``: what its device writes there (on sim a coil's current
        # too, which hardware does not sense), so an observer reads its own group's rows
        self.sensed_rows: dict[str, slice] = {}
        self.probes = []  # (trace signal name, unit, object with .probe, row)
        self.truth_names = ()
        self.estimated = np.full((self.n_channels, self.block), np.nan)  # observer tip wave, m
        self.estimated_amp = np.full(self.n_channels, np.nan)  # observer tip amplitude, m
        if scene.io.backend == "sim":
            self._build_sim(scene)
        else:
            self._build_backend(scene)
        from ..stimulus import Stimulus

        self.stimulus = Stimulus(scene, offsets, self.n_channels, self.fs, self.block)
        self.tones, self.targets_um = self.stimulus.tones, self.stimulus.targets_um
        self.bank, self.pulses, self.render = self.stimulus.bank, self.stimulus.pulses, self.stimulus.render
        self._build_limiter(scene)
        self.closed = scene.control.mode == "closed"
        # the block function's observers, one per observed bimorph group: (group name,
        # ObserverStage, group, its first channel)
        self.observer_stages = []
        # what is observed, per group: (name, ObserverStage, group, first channel); controllers,
        # one per observed group with a controlled tone: (group name, its ObserverStage, controller);
        # lift-off and landing tests, one per controlled group: (ObserverStage, controller,
        # LiftTest)
        self.observers, self.controllers, self.lifts = [], [], []
        #: what the build found that the run's summary should say (a target under the noise floor)
        self.warnings = []
        #: per controlled bank tone, the rms of its tip estimate's noise, m (Observer.noise_floor)
        self.control_noise = {}
        if scene.control.observe or self.closed:
            check_control(scene, self.stimulus.voices)  # as `rtctl check` refuses it
            self._build_observers(scene)
        if self.closed:
            self._build_control(scene)
            loose = [i for i in self.stimulus.closed_voices if i not in self.controlled]
            if loose:
                ch = self.channel_names[self.bank.chan[loose[0]]]
                raise SceneError(f"{scene.source}: stimulus.play: channel {ch} plays a tip target but is not "
                                 "under amplitude control (bimorph groups with self-sensing only)")
            self._open_tones(scene)
        # per event (its index in the scene's events): the tones whose target it sets, and that target in m
        self.events, self._events_at, self.event_targets = [], {}, {}
        if scene.get("events"):
            from ..events import schedule

            self.events = schedule(scene)
            for ev in self.events:
                self._events_at.setdefault(ev.block, []).append(ev)
            self.event_targets = self._resolve_event_targets(scene)
            self._warn_event_noise()
        self.stages = self._stages()
        # the blocks at which apply_schedule has work, sorted (None: any block may; next_busy)
        busy = self.stimulus.busy_blocks()
        self._busy = None if busy is None else np.array(sorted(set(busy) | set(self._events_at)), dtype=np.int64)
        self.blocks = 0  # blocks the block function has run since the last reset
        self._compile()
        from .state import scene_digest, state_arrays

        self.state_arrays = state_arrays(self)  # what a checkpoint saves (rtctl.engine.state)
        self.scene_digest = scene_digest(scene)

    # --- construction -----------------------------------------------------------------------

    def _build_sim(self, scene):
        from ..io.sim import SimDevice, build_group, device_models
        from ..plant import TRUTH_NAMES

        # the simulated hardware is built from its own models; the rig's are the scene's, or a
        # calibration's, which the device must not become: only nominal ones are shared
        hardware = device_models(scene, None if (self.models.factors or self.models.group_factors) else self.models)
        groups, ch0, row0 = [], 0, 0
        for gi, g in enumerate(scene.actuator):
            n = n_channels(g)
            sim = build_group(hardware, g, gi, self.fs, self.block)
            rows = n * sim.n_sensed
            groups.append((sim, slice(ch0, ch0 + n), slice(row0, row0 + rows)))
            self.sensed_rows[g.name] = slice(row0, row0 + rows)
            self.sensed_names += [f"{g.name}.{i}.{lab}" for i in range(n) for lab in sim.sensed_labels]
            self.probes += [(f"{g.name}.{pn}", unit, sim, r) for r, (pn, unit) in enumerate(sim.probe_names)]
            ch0, row0 = ch0 + n, row0 + rows
        self.truth_names = TRUTH_NAMES
        self.sensed = np.zeros((row0, self.block))
        injector, fingers = None, []
        from ..io import faults

        if faults.active(scene):
            from ..io.sim import finger_states

            ctx = faults.context(scene, n_sensed=row0, names=self.sensed_names)
            injector = faults.sim_injector(scene, faults.plan(scene, ctx), ctx)
            fingers = [t for (sim, _, _), g in zip(groups, scene.actuator)
                       if (t := finger_states(sim, hardware, g)) is not None]
        self.device = SimDevice(groups, self.out, self.sensed, len(TRUTH_NAMES), hardware.factors,
                                injector, fingers)
        if not self._want_in_block:  # driven from outside the block function (rtctl replay --mode plant)
            self.device.in_block = False
        self.truth = self.device.truth

    def _build_backend(self, scene):
        """A hardware backend (``rtctl.io.<backend>.open_backend``), opened now so a missing
        device is reported before anything runs."""
        import importlib

        from ..io.base import Layout

        rows, owner = sensed_layout(scene)
        self.sensed_names = rows
        row0 = 0
        for g in scene.actuator:
            self.sensed_rows[g.name] = slice(row0, row0 + n_channels(g) * n_segments(g))
            row0 += n_channels(g) * n_segments(g)
        self.sensed = np.zeros((len(rows), self.block))
        types = [scene.group(g).type for g in self.channel_groups]
        self.layout = Layout(self.fs, self.block, tuple(self.channel_names), tuple(self.channel_groups),
                             tuple(types), tuple(rows), tuple(owner))
        mod = importlib.import_module(f"rtctl.io.{scene.io.backend}")
        self.device = mod.open_backend(scene, self.layout, self.out, self.sensed)
        self.truth = self.device.truth
        self.probes = [(f"io.{pn}", unit, self.device, r) for r, (pn, unit) in enumerate(self.device.probe_names)]

    def _build_observers(self, scene):
        """Self-sensing observers on the scene's tone frequencies: one stage per bimorph group.
        Under closed-loop control each channel's lock-in window holds whole periods of its own
        tones only (a 250 Hz channel is not made to wait for a 2 Hz one); else the window holds
        whole periods of every tone of the group, or, where no window within 1 s does, each
        channel reads over its own as under closed loop."""
        from ..selfsense.rt import block_window, holds_whole_periods, prefilter_cutoffs, short_windows
        from ..selfsense.stage import ObserverStage

        self.latency = scene.io.latency_blocks or int(self.device.latency_blocks)
        ch0 = 0
        for g in scene.actuator:
            n, n_seg = n_channels(g), n_segments(g)
            if g.type == "bimorph":
                c1 = ch0 + n
                # one column per distinct frequency: the observer reads one amplitude there, that
                # of whatever plays at it (two tones or voices at one frequency: their sum)
                per = [list(dict.fromkeys(f for tn in self.tones if tn.channel == c for f in tn.freqs))
                       for c in range(ch0, c1)]
                width = max(1, max(len(p) for p in per))
                freqs = np.array([p + [0.0] * (width - len(p)) for p in per])
                # open loop: the group's one window of whole periods, unless none within its 1 s
                # bound holds them (3.3 Hz: 3.3 s), where a lock-in over it leaks (that tone read
                # 50 % high): then each channel's own, by least squares where it must
                window, lstsq, hop = (short_windows(freqs, self.fs, self.block)
                                      if self.closed or not holds_whole_periods(freqs, block_window(
                                          freqs, self.fs, self.block)[0], self.fs)
                                      else (None, False, None))
                obs = self.models.observer(g, freqs, self.fs, self.block, wave=self.estimated[ch0:c1],
                                           window=window, hop=hop, lstsq=lstsq,
                                           prefilter=(prefilter_cutoffs(freqs, self.fs, self.models.lowest_mode(g))
                                                      if self.closed else None),
                                           rows=1)  # the tip: all the controller and the waveform read
                rows = self.sensed_rows[g.name]
                if rows.stop - rows.start != n * n_seg:
                    raise SceneError(f"{scene.source}: actuator.{g.name}: the device senses {rows.stop - rows.start} "
                                     f"rows for it, where its observer reads {n * n_seg} (segment currents)")
                st = ObserverStage(obs, self.latency, self.out[ch0:c1], self.sensed[rows],
                                   self.estimated_amp[ch0:c1])
                self.observer_stages.append((g.name, st, g, ch0))
                self.observers.append((g.name, st, g, ch0))
            ch0 += n

    def _build_control(self, scene):
        """Amplitude control of every sine tone with a target, one controller per observed group:
        a column per tone, each waiting for and watching its channel's own window (a stage per
        channel would pay the call's fixed cost once per channel, and a composed function of a
        thousand calls takes LLVM longer to build than anyone waits)."""
        from ..control import AmplitudeController
        from ..control.amplitude import RELEASE_WINDOW, RELEASE_Z
        from .report import fit_window

        self.controlled = {}  # bank tone index -> (controller, its column)
        per_channel = {}
        for tone, bank in zip(self.tones, self.stimulus.bank_index):
            per_channel[tone.channel] = per_channel.get(tone.channel, 0) + len(bank)
        for name, st, g, c0 in self.observers:
            obs = st.observer
            finger = self.models.finger(g)
            cols = []
            for tone, bank in zip(self.tones, self.stimulus.bank_index):
                c = tone.channel - c0
                if not bank or not (0 <= c < obs.n_channels) or not np.isfinite(tone.target_m):
                    continue
                for f, b in zip(tone.freqs, bank):
                    slot = int(np.nonzero(obs.freqs[c] == f)[0][0])
                    # each tone's share of max_voltage, a hair below it: a sine at exactly the
                    # bound would count as limited on rounding alone
                    cols.append((c, slot, b, tone.channel, f, tone.target_m / len(bank),
                                 g.max_voltage * (1.0 - 1e-9) / per_channel[tone.channel],
                                 fit_window(tone.freqs) * self.fs))  # what the tone's amplitude is fitted over
            if not cols:
                continue
            c_, slot, bank, chan, f, target, amax, wamp = (np.array(x) for x in zip(*cols))
            # the model's tip per commanded volt under the assumed finger (amplifier included)
            amp = np.abs(1.0 + 1j * f / g.amplifier.bandwidth)
            tip = np.abs(obs.beam.response(f, finger)["tip"]) / amp
            # and under the most responsive load it allows for: the drive's floor
            loads = self.models.spread_loads(g)
            gains = np.array([np.abs(obs.beam.response(f, load)["tip"]) for load in loads]) / amp
            top = gains.max(axis=0)
            ring = int(np.ceil(self.models.ring_time(g) * self.fs / self.block))
            # each tone waits for its own channel's window and its low-pass's memory
            window = self._window_blocks(obs, c_)
            rise = int(round(scene.control.rise_s * self.fs / self.block))
            beat, tau = self.models.nearest_modes(g, f)  # in turns per block and blocks
            beside = (beat * self.block / self.fs, tau * self.fs / self.block)
            self._noise_floor(g, obs, c_, slot, bank, chan, f, target)
            noise = np.array([self.control_noise[int(b)] for b in bank])  # each estimate's, m rms
            # the release rule where the most responsive load is the lifted beam (the drop then
            # puts the target on the lifted tip) and the window is long (a lift-off swings there
            # for a window; where it is short the loop's own correction comes soon, and a drop in
            # one block rings the lifted beam for longer than it saves)
            lifted = np.array([x is None for x in loads])
            free = gains[lifted].max(axis=0) if lifted.any() else np.zeros_like(top)
            release = np.where((free >= top * (1.0 - 1e-9)) & (obs.windows[c_] >= RELEASE_WINDOW * self.fs),
                               RELEASE_Z * noise, -1.0)
            ctl = AmplitudeController(c_, slot, bank, chan, tip, amax, target, self.latency, window, self.block,
                                      ring, rise, beside, np.maximum(top, tip), release, f * self.block / self.fs,
                                      noise, obs.windows[c_], wamp)
            self.controllers.append((name, st, ctl))
            for j, b in enumerate(bank):
                self.controlled[int(b)] = (ctl, j)
            # a lift-off (for the release rule) or a landing (for the observer's images) told
            # from the first block of currents read after it
            from ..selfsense.lift import LiftTest

            lift = LiftTest(obs, np.unique(c_), np.unique(c_[release >= 0.0]))
            if lift.active:
                self.lifts.append((st, ctl, lift))
            elif lift.why:
                self.warnings.append(f"actuator.{g.name}: no lift-off test ({lift.why}); a lift-off is "
                                     f"told by the estimates alone, a landing by the observer's votes")

    def _open_tones(self, scene) -> None:
        """Closed loop holds the tips self-sensing reads (bimorph groups), at a target: the tones
        it leaves open loop are named in a warning (a scene with none it holds was refused
        before the observers were built, by :func:`rtctl.stimulus.check_control`)."""
        open_ = {}
        for tone, bank in zip(self.tones, self.stimulus.bank_index):
            if not any(int(b) in self.controlled for b in bank):  # (a square or pulse tone has no sines)
                g = scene.group(self.channel_groups[tone.channel])
                why = (f"{g.type}, which self-sensing does not read" if g.type != "bimorph"
                       else "no target: give target_um" if not math.isfinite(tone.target_m)
                       else "a square or pulse tone, which it does not hold")
                open_.setdefault(f"actuator {g.name!r} ({why})", []).append(self.channel_names[tone.channel])
        if not open_:
            return
        where = "; ".join(f"{', '.join(chs)} on {what}" for what, chs in open_.items())
        self.warnings.append(f"control.mode = closed: these tones play open loop: {where}")

    def _noise_floor(self, g, obs, c_, slot, bank, chan, f, target) -> None:
        """Each controlled tone's estimate noise from the group's current sense (its ADC's noise
        and step, over the shunt), and a warning for a target within NOISE_MARGIN of it."""
        from ..plant.frontend import CurrentSense

        s = g.sense
        sense = CurrentSense(s.shunt, s.aa_cutoff, s.aa_order, s.bits, s.full_scale, s.noise)
        floor = obs.noise_floor(math.hypot(sense.noise_rms_v, sense.lsb_v / math.sqrt(12.0)) / sense.shunt_ohm)
        for c, k, b, ch, fk, r in zip(c_, slot, bank, chan, f, target):
            noise = float(floor[c, k])
            self.control_noise[int(b)] = noise
            self._warn_noise(int(ch), fk, r, noise, g.name)

    def _warn_noise(self, ch: int, f: float, r: float, noise: float, group: str, when: str = "") -> None:
        """A warning for a controlled sine's target ``r`` (m) within NOISE_MARGIN of its estimate's
        noise floor ``noise`` (m rms); ``when``: what set it, if not the scene."""
        from ..control.amplitude import NOISE_MARGIN

        if r >= NOISE_MARGIN * noise:
            return
        what = (f"the estimate reads high by about {25.0 * (noise / r) ** 2:.2g} %, the loop holds the tip that "
                "much low and its corrections follow the noise (held up to about 20 / (target / floor) % off, "
                "settling in up to a second)" if r > 2.0 * noise else
                "the estimate is mostly that noise, and the loop cannot hold the tip there")
        self.warnings.append(
            f"channel {self.channel_names[ch]}: the {f:g} Hz target {r * 1e6:.3g} um{when} is "
            f"{r / noise:.2g} times the self-sensing noise floor there ({noise * 1e6:.2g} um rms over the "
            f"observer's window, from actuator.{group}.sense noise, bits and shunt): {what}; a target "
            f"at least {NOISE_MARGIN:g} times the floor is held within 1 % at the loop's pace")

    def estimate_lag(self, ch: int) -> int | None:
        """Blocks from a change of channel ``ch``'s plant to its first estimate that holds none
        of the time before it (the I/O latency, the low-pass's memory and the lock-in window, in
        whole blocks, plus one), or None where no observer reads the channel."""
        for _, st, _, c0 in self.observers:
            c = ch - c0
            if 0 <= c < st.observer.n_channels:
                return self.latency + int(self._window_blocks(st.observer, c)) + 1
        return None

    def _window_blocks(self, obs, c):
        """Observer channel(s) ``c``'s lock-in window and low-pass memory, in whole blocks."""
        return -(-(obs.windows + obs.prefilter_memory)[c] // self.block)

    def hold_control(self) -> None:
        """A requested stop: every amplitude controller holds its command from now on, so
        feedback does not answer the release (the falling amplitude it sees) by raising the
        drive, and its final state is the run's. Called between blocks by the loop's thread."""
        if not self.controllers:
            return
        from ..control._kernels import BEFORE, WAIT

        for _, _, ctl in self.controllers:
            ctl.state[WAIT] = np.inf  # a tone waiting for its estimate changes nothing
            ctl.state[BEFORE] = 0.0  # ... nor watches for a finger letting go meanwhile

    def _start_controlled(self, i: int) -> bool:
        """The stimulus' start of bank tone ``i``: a controlled tone starts under control."""
        hit = self.controlled.get(i)
        if hit is None:
            return False
        from ..control._kernels import ENABLE

        ctl, j = hit
        self.queue.post(self.queue.target_id(ctl.target), ENABLE, j, 1.0)
        return True

    def _target_controlled(self, i: int, target_m: float) -> None:
        """A closed-loop voice's new target (bank tone ``i``): 0 switches it off (ramped to
        silence), a target from 0 switches it on under control."""
        from ..control._kernels import ENABLE, TARGET

        ctl, j = self.controlled[i]
        tid = self.queue.target_id(ctl.target)
        if target_m > 0.0:
            self.queue.post(tid, TARGET, j, target_m)
        self.queue.post(tid, ENABLE, j, 1.0 if target_m > 0.0 else 0.0)
        self.targets_um[self.bank.chan[i]] = target_m * 1e6

    def _build_limiter(self, scene):
        from ..safety import Limiter

        groups = [scene.group(name) for name in self.channel_groups]
        loads = {g.name: self.models.drive_load(g) for g in scene.actuator}
        lim = [g.limits for g in groups]
        self.limiter = Limiter(
            self.fs,
            max_voltage=[g.max_voltage for g in groups],
            slew=[x.slew for x in lim], current=[x.current for x in lim],
            capacitance=[loads[g.name][0] for g in groups], resistance=[loads[g.name][1] for g in groups],
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
        if self.device.commands_only is not None:  # pin commands: the firmware pulses the coils
            self.limiter.commands_only(self.device.commands_only * np.array([g.max_voltage for g in groups]))
        from .settle import settle_time

        # a requested stop (end of run, Ctrl-C): its raised-cosine fade, then blocks of 0 V while
        # the tips settle (a fault fades over one block and ends the run)
        self.stop_fade = max(1, int(round(scene.timing.stop_fade * self.fs)))
        self.settle_s = settle_time(self.models, scene)
        self.settle_blocks = int(math.ceil(self.settle_s * self.fs / self.block - 1e-9))

    def _stages(self) -> list:
        """The block function's stages, in order (see the module docstring)."""
        from ..safety import limit_block

        pending = [x.pending for x in (self.bank, self.pulses) if x is not None]
        self.queue = ParamQueue(pending + [ctl.target for _, _, ctl in self.controllers]
                                + list(self.device.event_targets()))
        if self.controllers:
            self.stimulus.start_hook = self._start_controlled
            self.stimulus.target_hook = self._target_controlled
        for x in (self.bank, self.pulses):
            if x is not None:
                tid = self.queue.target_id(x.pending)
                x.route(lambda row, cols, values, tid=tid: self.queue.post(tid, row, cols, values))
        calls = self.device.block_calls()
        self._device_in_block = calls is not None
        before, after = calls or ([], [])
        wrap = [Stage(name, k, dict(enumerate(args)), status) for name, k, args, status in before]
        played = []
        if self.stimulus.played is not None:
            from ..dsp._kernels import osc_schedule

            sched = self.stimulus.played
            played = [Stage("played signals", osc_schedule,
                            dict(zip(("pos", "blocks", "first", "tone", "freq", "amp", "ramp"), sched.args),
                                 pending=self.bank.pending), reset=sched.reset)]
            self.stimulus.played_in_block = True
        stages = [*played, Stage("params", drain, dict(zip(("ring", "heads", "targets"), self.queue.args)),
                                 reset=self.queue.reset), *wrap,
                  Stage("clear", clear, {"out": self.out}, status=None)]
        if self.bank is not None:
            from ..dsp import osc_bank_process

            stages.append(Stage("oscillators", osc_bank_process,
                                dict(zip(("state", "pending", "chan"), self.bank.args), out=self.out), status=None))
        if self.pulses is not None:
            from ..dsp import pulse_process

            stages.append(Stage("pulses", pulse_process,
                                dict(zip(("state", "pending"), self.pulses.args), out=self.out), status=None))
        stages.append(Stage("limiter", limit_block,
                            dict(zip(("x", "state", "params", "fade", "counts"), (self.out, *self.limiter.args))),
                            reset=self.limiter.reset))
        if self.observer_stages:
            from ..selfsense.stage import observe_stage

            for name, st, _, _ in self.observer_stages:
                for seen, ctl, lift in self.lifts:
                    if seen is st:  # before the observer: its drive ring still holds the block's drive
                        from ..selfsense.lift import lift_stage

                        stages.append(Stage(f"contact {name}", lift_stage, lift.stage_args(st.args, ctl),
                                            status=None, reset=lift.reset))
                stages.append(Stage(f"observer {name}", observe_stage, st.args, reset=st.reset))
                # the next block's amplitudes, from this block's estimates of the group's channels
                for cname, seen, ctl in self.controllers:
                    if seen is not st:
                        continue
                    from ..control import amplitude_control

                    stages.append(Stage(f"control {cname}", amplitude_control,
                                        dict(est=st.observer.est, drive_est=st.observer.u_out, **ctl.args,
                                             pending=self.bank.pending,
                                             lim_counts=self.limiter.counts, ramp=float(self.block)),
                                        reset=ctl.reset))
        stages += [Stage(name, k, dict(enumerate(args)), status) for name, k, args, status in after]
        return stages

    def _compile(self):
        """Compose the stages into one block function and compile (or load from numba's cache)
        it and every kernel now, not in the first block; then everything back to rest."""
        from .compose import compose

        try:
            self._block = compose(self.stages)
            self.compose_note = "composed"
        except TypeError as e:  # the stages run one by one from Python instead
            self._block = None
            self.compose_note = f"stages called from Python ({e})"
        self.step()
        if not self._device_in_block:  # else its kernels just compiled inside the block function
            self.device.compile()
        self.reset()
        self.device.bind(self)  # a callback backend builds its callback now, not at run()

    def reset(self) -> None:
        """Every stage and the buffers back to rest (no block function may run meanwhile)."""
        self.blocks = 0
        self.out[...] = 0.0
        self.targets_um[...] = self.stimulus.targets_um0
        self.estimated[...] = np.nan  # observed channels' rows: zeros, by their stage's reset
        self.stimulus.reset()
        for s in self.stages:
            if s.reset is not None:
                s.reset()
        if self._device_in_block:
            self.device.reset()

    # --- per block ----------------------------------------------------------------------------

    @property
    def block_function(self):
        """The composed block function (:class:`rtctl.engine.compose.BlockFunction`), or None
        when the stages run one by one from Python."""
        return self._block

    @property
    def device_in_block(self) -> bool:
        """Whether the block function holds the device's read and write (the simulated device)."""
        return self._device_in_block

    def next_busy(self, k: int) -> int:
        """The first block after ``k`` at which :meth:`apply_schedule` may have work (a large
        number when none will): the blocks between need nothing from Python."""
        busy = self._busy
        if busy is None:
            return k + 1
        i = int(np.searchsorted(busy, k, side="right"))
        return int(busy[i]) if i < busy.size else 1 << 62

    def apply_schedule(self, k: int) -> None:
        """Hand the parameter changes due at block ``k`` to the block function (it applies them,
        ramped across that block, before anything else in the block): the stimulus' and the
        scene's events. Engine thread only."""
        self.stimulus.apply(k)
        for ev in self._events_at.get(k, ()):
            self._apply_event(ev)
        self.queue.publish()

    def _resolve_event_targets(self, scene) -> dict:
        """Per event (by its index in the scene's ``events``), the tones whose target it sets and that
        target in m, resolved as the scene means it (0: the receptor's threshold raised by
        ``control.margin_db``), once before the run. A controlled tone's must resolve: a tone no
        receptor answers has no threshold to ask for."""
        controlled = getattr(self, "controlled", {})
        out = {}
        for ev in self.events:
            i = ev.index
            for key in ev.sets:
                if not (key.startswith("stimulus.tones.") and key.endswith(".target_um")):
                    continue
                n = int(key.split(".")[2])
                t = ev.scene_after.stimulus.tones[n]
                target_m = tone_target_m(ev.scene_after, t)
                if any(b in controlled for b in self.stimulus.bank_index[n]) and not math.isfinite(target_m):
                    r = tone_receptor(t)
                    why = f"receptor {r!r} has none at {t.freq:g} Hz" if r else f"no receptor answers at {t.freq:g} Hz"
                    raise SceneError(f"{scene.source}: events.{i}.set: {key} = 0 asks for the receptor's threshold, "
                                     f"and {why}: give the target in um")
                out.setdefault(i, []).append((n, target_m))
        return out

    def _warn_event_noise(self) -> None:
        """The noise floor's warning for the targets events set, as for the scene's own."""
        for ev in self.events:
            for n, target_m in self.event_targets.get(ev.index, ()):
                tone, bank = self.tones[n], self.stimulus.bank_index[n]
                for f, b in zip(tone.freqs, bank):
                    if self.controllers and int(b) in self.controlled:
                        self._warn_noise(tone.channel, f, target_m / len(bank), self.control_noise[int(b)],
                                         self.channel_groups[tone.channel], f" (events.{ev.index}, at {ev.at:g} s)")

    def _apply_event(self, ev) -> None:
        """An event's writes: the device's (a simulated finger's load) and new tone targets
        (the controllers', and the trace's target line)."""
        for arr, row, col, value in self.device.event_posts(ev):
            self.queue.post(self.queue.target_id(arr), row, col, value)
        for n, target_m in self.event_targets.get(ev.index, ()):
            tone, bank = self.tones[n], self.stimulus.bank_index[n]
            self.stimulus.tone_targets_um[n] = target_m * 1e6
            self.stimulus.sum_targets(tone.channel)
            for b in bank:
                hit = self.controlled.get(b) if self.controllers else None
                if hit is not None:
                    from ..control._kernels import TARGET

                    ctl, j = hit
                    self.queue.post(self.queue.target_id(ctl.target), TARGET, j, target_m / len(bank))

    def kernel_calls(self) -> list:
        """The block function as ``[(kernel, args)]``, for a callback backend's compiled callback."""
        if self._block is not None:
            return [(self._block.fn, (self._block.table,))]
        return [(s.kernel, tuple(s.args.values())) for s in self.stages]

    def step(self) -> int:
        """The block function without the backend's I/O: status bits (a callback backend calls
        this from its thread)."""
        self.blocks += 1
        if self._block is not None:
            return self._block()
        status = 0
        for s in self.stages:
            status |= s.call()
        return status

    def snapshot_call(self, snaps) -> tuple:
        """``(kernel, args)`` of :meth:`snapshot` into ``snaps``; the slot is the last argument."""
        return (snapshot, (self.out, self.sensed, self.estimated, self.estimated_amp, self.limiter.temperature,
                           snaps.out, snaps.sensed, snaps.estimated, snaps.estimated_amp, snaps.temperature))

    def advance(self) -> int:
        """One block: the backend's read, the block function, the backend's write; status bits."""
        if self._device_in_block:
            return self.step()
        status = self.device.read()
        status |= self.step()
        status |= self.device.write()
        return status

    def snapshot(self, snaps, slot: int) -> None:
        """Copy this block's outputs, readings, estimates and temperatures into ``snaps`` (a
        :class:`rtctl.io.base.Snapshots`) at ``slot``, for the trace (no allocation)."""
        fn, args = self.snapshot_call(snaps)
        fn(*args, slot)

    # --- state -------------------------------------------------------------------------------

    def checkpoint(self, into=None):
        """The loop's whole state between two blocks, as a :class:`rtctl.engine.state.Checkpoint`
        (``checkpoint.block``: the next block to run). With ``into`` (an earlier checkpoint of this
        rig) its arrays are reused: nothing is allocated. Call it between blocks only: never while
        a device thread runs the block function."""
        from .state import save

        return save(self, into)

    def restore(self, cp) -> None:
        """Put checkpoint ``cp`` back (this rig's, or one of a rig built from the same scene and
        overrides): continuing with ``apply_schedule(cp.block)`` and ``advance()`` gives the
        blocks a run straight through gives, bitwise. Between blocks only.

        Raises
        ------
        ValueError
            ``cp`` is of another scene (overrides included) or a rig with other state arrays.
        """
        from .state import load

        load(self, cp)

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
        if self.observers:  # the rebuilt tip waveform, one io latency behind the drive
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
        if self.observers:
            rec["estimated_tip_um"][...] = est
            rec["estimated_tip_um"] *= 1e6
        rec["temperature"][...] = temp


def build(scene, device_in_block: bool = True) -> Rig:
    """Construct, import and compile exactly what ``scene`` needs.

    ``device_in_block=False`` keeps the simulated device out of the block function: the caller
    drives it with :meth:`SimDevice.write` and :meth:`SimDevice.read` (a recorded drive replayed
    into the plant), and :meth:`Rig.step` leaves the plant alone.

    Raises
    ------
    SceneError
        If the scene needs a component this version of rtctl does not have.
    """
    check_available(scene)
    return Rig(scene, device_in_block)
