"""What a scene plays: its tones (single tones, beat pairs, square and pulse trains) with their
perception targets and schedule, or a rendered stimulus; both become per-channel parameter
changes handed to the block function between blocks (:class:`Stimulus`).

Rendered stimuli: images (along an HIA path), Braille text and shapes.

The renderer (:mod:`rtctl.render`) produces per-pin parameters at the render rate; this stage maps
them onto the synthesis the display needs, ramped or switched by the dsp kernels in the next block.
The drive per pin, by render method:

* ``beat`` (PVDF, piezo): a sine at the pin's ``freq_hz`` (cell pairs at f_c -+ f_b/2), amplitude
  ``amplitude * voltage``, ramped over a block with phase continuity;
* ``frequency`` (solenoid pins): a pulse train at ``freq_hz`` between 0 and ``voltage`` (0 Hz:
  held at 0 V);
* ``roi``, ``canny``, Braille, shapes (binary pins): a held level, ``voltage`` when up; when down
  ``-voltage`` for bipolar pins (Dot, SMA: the current direction commands down), else 0 V.

Only :meth:`RenderStage.apply` runs between blocks; all image-wide work happens at build time.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from . import perception
from .errors import SceneError

BIPOLAR = ("dot", "sma")  # pins whose "down" is a command of the opposite polarity
#: Pins driven between end stops: their stroke is set by the stops, not by the drive amplitude,
#: so a perception-margin amplitude target (and an error against it) means nothing.
END_STOP_TYPES = ("solenoid", "dot")


def tone_receptor(t) -> str | None:
    """The receptor of scene tone ``t`` (``stimulus.tones[i]``): its own, or with ``auto`` the one
    that answers at its frequency (None: none does)."""
    return perception.auto_receptor(t.freq) if t.receptor == "auto" else t.receptor


def tone_target_m(scene, t) -> float:
    """Scene tone ``t``'s target tip amplitude, m: its ``target_um``, or with 0 its receptor's
    threshold raised by ``control.margin_db``; NaN where there is neither, and on pins that move
    between end stops (no amplitude to hold)."""
    if scene.group(t.actuator).type in END_STOP_TYPES:
        return math.nan
    if t.target_um > 0:
        return t.target_um * 1e-6
    receptor = tone_receptor(t)
    return perception.target_m(t.freq, receptor, scene.control.margin_db) if receptor else math.nan


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


def channel_offsets(scene) -> dict:
    """Each actuator group's first channel, the rig's numbering: groups one after another."""
    from .models import n_channels

    offsets, n = {}, 0
    for g in scene.actuator:
        offsets[g.name], n = n, n + n_channels(g)
    return offsets


def check(scene) -> None:
    """Refuse what building ``scene``'s stimulus would refuse, in the same one line, without
    building plants, banks or kernels: its tones' combinations, and its signals compiled and put
    on channels (:func:`rtctl.voices.build`, the code the run uses), an image's file read by the
    renderer's loader, and what observing or closed loop needs of them (:func:`check_control`).
    ``rtctl check`` calls it, so a bad chirp, product, sequence or image file is caught there,
    not at ``run``. What rendering itself refuses (an image's content, Braille text, shapes) is
    checked when it renders, as the run builds.

    Raises
    ------
    SceneError
    """
    if scene.stimulus.kind == "image":
        load_image(scene)
    if scene.stimulus.kind != "tones":
        check_control(scene, [])
        return
    offsets = channel_offsets(scene)
    _check_tones(scene, offsets)
    voices = []
    if scene.stimulus.play:
        from .dsp._kernels import MAX_RAMP  # a constant: importing compiles nothing
        from .events import duration_blocks
        from .voices import build

        fs, block = float(scene.timing.fs), int(scene.timing.block)
        voices = build(scene, offsets, fs, float(duration_blocks(scene.timing.duration, fs, block) * block), MAX_RAMP,
                       block)
    check_control(scene, voices)


def check_control(scene, voices) -> None:
    """Refuse what the rig refuses of ``control.observe`` and ``control.mode = closed`` before it
    builds an observer, in the same one line: an observer is designed on the tone frequencies, so
    it needs ``stimulus.kind = 'tones'``; under closed loop a frequency of a channel is held by
    one tone (:func:`_one_reader_per_frequency`); closed loop holds at a target the sine tones on
    bimorph groups (the tips self-sensing reads), so a scene with none of them, and no played
    voice (:func:`rtctl.voices.build` refuses a closed-loop voice anywhere else), would run open
    loop saying nothing. ``voices``: the played voices, ``(Voice, closed, receptor)`` as
    :func:`rtctl.voices.build` returns them. The rig (:class:`rtctl.engine.rig.Rig`) and
    ``rtctl check`` both call it.

    Raises
    ------
    SceneError
    """
    ctl, st = scene.control, scene.stimulus
    closed = ctl.mode == "closed"
    if not (closed or ctl.observe):
        return
    if st.kind != "tones":
        raise SceneError(f"{scene.source}: control.{'mode = closed' if closed else 'observe'} needs "
                         f"stimulus.kind = 'tones' (the observer is designed on the tone frequencies; "
                         f"rendered stimuli change them), got {st.kind!r}")
    if not closed:
        return
    _one_reader_per_channel(scene, voices)
    if voices:
        return
    open_ = {}
    for t in st.tones:
        g = scene.group(t.actuator)
        target = tone_target_m(scene, t)
        if g.type == "bimorph" and t.shape == "sine" and math.isfinite(target):
            return  # a tone the controller holds
        why = (f"{g.type}, which self-sensing does not read" if g.type != "bimorph"
               else "no target: give target_um" if not math.isfinite(target)
               else "a square or pulse tone, which it does not hold")
        open_.setdefault(f"actuator {g.name!r} ({why})", []).append(f"{g.name}.{t.channel}")
    where = "; ".join(f"{', '.join(chs)} on {what}" for what, chs in open_.items())
    raise SceneError(f"{scene.source}: control.mode = closed: no tone to hold at a target: closed loop "
                     f"holds the bimorph tips self-sensing reads, and this scene plays {where}")


def _one_reader_per_channel(scene, voices) -> None:
    """:func:`_one_reader_per_frequency` on every channel of every bimorph group, from the scene's
    tones (a beat pair's two sines, split by the oscillator's own ``beat_tones``) and the played
    voices, the frequencies the rig's observers are built on."""
    from .models import n_channels

    offsets = channel_offsets(scene)
    held: dict[int, list] = {}
    for t in scene.stimulus.tones:
        if t.shape == "sine" and t.beat > 0:
            from .dsp.oscillator import beat_tones

            freqs = [float(f) for f in beat_tones(t.freq, t.beat, t.voltage)[0]]
        else:
            freqs = [t.freq]
        held.setdefault(offsets[t.actuator] + t.channel, []).extend(freqs)
    played: dict[int, list] = {}
    for v, _, _ in voices:
        played.setdefault(v.channel, []).append(float(v.freq[0]))
    for g in scene.actuator:
        if g.type != "bimorph":
            continue
        for c in range(offsets[g.name], offsets[g.name] + n_channels(g)):
            _one_reader_per_frequency(scene, f"{g.name}.{c - offsets[g.name]}", held.get(c, []),
                                     played.get(c, []))


def _one_reader_per_frequency(scene, channel: str, held: list, played: list) -> None:
    """Under closed loop, a frequency of a channel is held by one tone: its controller reads the
    observer's one amplitude there, so a second tone (or beat pair's sine) of the scene at it, or
    a played voice at a scene tone's frequency, would have each controller read the sum of both.
    A played signal's voices take turns, so they may share one. ``held``: the frequencies of the
    scene's tones on ``channel`` (a beat pair's two), ``played``: its voices'.

    Raises
    ------
    SceneError
    """
    twice = sorted({f for f in held if held.count(f) > 1})
    both = sorted({f for f in played if f in held})
    if twice or both:
        what = (f"{' and '.join(f'{f:g}' for f in twice)} Hz in more than one tone (or beat pair)" if twice
                else f"{' and '.join(f'{f:g}' for f in both)} Hz in a tone and in a played voice")
        raise SceneError(
            f"{scene.source}: control.mode = closed: channel {channel} plays {what}, and "
            "its observer reads one amplitude at a frequency, so their controllers would each read "
            "their sum: make them one tone with the sum of their targets")


def image_path(scene) -> str:
    """The file ``stimulus.image`` names: relative to the scene file when it is there, else as
    given; refused in one line when the method cannot render an image or no file is named."""
    st = scene.stimulus
    if st.method not in ("roi", "canny", "frequency", "beat"):
        raise SceneError(f"{scene.source}: stimulus.method = {st.method!r}: an image needs roi | canny | "
                         "frequency | beat")
    if not st.image:
        raise SceneError(f"{scene.source}: stimulus.image is empty: name the image file to render")
    path = st.image
    if not os.path.isabs(path) and scene.source and not scene.source.startswith("<"):
        cand = os.path.join(os.path.dirname(scene.source), path)
        path = cand if os.path.exists(cand) else path
    return path


def load_image(scene):
    """``stimulus.image`` read and checked by the renderer's loader
    (:func:`rtctl.render.image.load_image`): a missing, unreadable or refused file in its one
    line. The build renders what this returns; ``rtctl check`` calls it to refuse the file
    without rendering."""
    from .render.image import load_image as load

    return load(image_path(scene))


def _check_tones(scene, offsets: dict) -> None:
    """Square and pulse tones: no beat pairs, one per channel."""
    pulsed = set()
    for i, t in enumerate(scene.stimulus.tones if scene.stimulus.kind == "tones" else ()):
        if t.shape == "sine":
            continue
        if t.beat > 0:
            raise SceneError(f"{scene.source}: stimulus.tones.{i}.beat = {t.beat:g}: a beat pair "
                             "needs shape = 'sine'")
        ch = offsets[t.actuator] + t.channel
        if ch in pulsed:
            raise SceneError(f"{scene.source}: stimulus.tones.{i}: channel {t.actuator}.{t.channel} "
                             "already plays a square/pulse tone (one per channel)")
        pulsed.add(ch)


def _last_per_tone(items) -> tuple:
    """A block's ``[(tone, freq, amp, ramp)]`` as arrays, each tone once with its last entry's
    values (what setting them one by one would leave)."""
    last = {}
    for i, f, amp, r in items:
        last[i] = (f, amp, r)
    idx = np.fromiter(last, dtype=np.int64, count=len(last))
    f, amp, r = (np.array(c) for c in zip(*last.values()))
    return idx, f.astype(np.float64), amp.astype(np.float64), r.astype(np.int64)


class Stimulus:
    """The synthesis a scene needs and the parameter changes due at each block.

    Attributes
    ----------
    tones : list of Tone
    targets_um : ndarray, shape (n_channels,)
        Target per channel, um: the sum of its tones' (NaN where a tone has none).
    tone_targets_um : ndarray, shape (n_tones,)
        Target per tone, um (events change it; :meth:`sum_targets` carries it to the channel's).
    bank : OscillatorBank or None
        Sine tones and beat pairs (or the beat method's rendered sines).
    pulses : PulseTrain or None
        Square and pulse tones (or the other rendering methods' pulse trains and levels).
    render : RenderStage or None
    """

    def __init__(self, scene, offsets: dict, n_channels: int, fs: float, block: int):
        self.fs, self.block, self.n_channels = float(fs), int(block), int(n_channels)
        tones, chans, freqs = [], [], []
        self.bank_index: list[tuple] = []  # per tone, its oscillators in the bank (none for pulses)
        self.start_hook = None  # see apply()
        self._schedule: dict[int, list] = {}
        scene_tones = scene.stimulus.tones if scene.stimulus.kind == "tones" else ()
        if scene_tones:
            from .dsp import OscillatorBank, beat_tones
            from .dsp._kernels import MAX_RAMP
        pulses = {}  # channel -> (block, freq, duty, high, low): square and pulse tones
        _check_tones(scene, offsets)
        for t in scene_tones:
            ch = offsets[t.actuator] + t.channel
            receptor = tone_receptor(t)
            thr = perception.threshold_m(t.freq, receptor) if receptor else math.nan
            tgt = tone_target_m(scene, t)
            kb = int(math.floor(t.start * self.fs / self.block))
            if t.shape != "sine":
                high, low, duty = (t.voltage, -t.voltage, 0.5) if t.shape == "square" else (t.voltage, 0.0, t.duty)
                pulses[ch] = (kb, t.freq, duty, high, low)
                tones.append(Tone(ch, t.freq, 0.0, t.voltage, receptor, thr, tgt, t.start, (t.freq,), t.shape))
                self.bank_index.append(())
                continue
            if t.beat > 0:  # a pair of half amplitude each: the envelope peaks at the pair voltage
                fr, am = (tuple(float(x) for x in a) for a in beat_tones(t.freq, t.beat, t.voltage))
            else:
                fr, am = (t.freq,), (t.voltage,)
            tones.append(Tone(ch, t.freq, t.beat, t.voltage, receptor, thr, tgt, t.start, fr))
            self.bank_index.append(tuple(range(len(freqs), len(freqs) + len(fr))))
            # Every tone switches on at the block holding its start time, ramped over t.ramp
            # (samples, whatever the block) or, by default, over that block.
            r = max(1, min(int(round(t.ramp * self.fs)), MAX_RAMP)) if t.ramp > 0 else None
            first = len(freqs)
            self._schedule.setdefault(kb, []).extend((first + j, a, r) for j, a in enumerate(am))
            chans += [ch] * len(fr)
            freqs += fr
        phases = [0.0] * len(freqs)
        self.target_hook = None  # see apply()
        self._sig_schedule: dict[int, list] = {}
        self._target_schedule: dict[int, list] = {}
        self.closed_voices: list[int] = []  # bank tones of closed-loop voices (under control)
        self.voices: list = []  # (Voice, closed, receptor) per stimulus.play partial and channel
        if scene.stimulus.play:
            self._add_voices(scene, offsets, tones, chans, freqs, phases)
        self.tones = tones
        # per tone, and per channel the sum of its tones' (a channel's amplitude is the sum of its
        # tones' amplitudes, as a beat pair's envelope peak is its two sines'); NaN where a tone has none
        self.tone_targets_um = np.array([tone.target_m * 1e6 for tone in tones], dtype=float)
        self.tone_targets_um0 = self.tone_targets_um.copy()
        self.targets_um = np.full(self.n_channels, np.nan)
        for ch in {tone.channel for tone in tones}:
            self.sum_targets(ch)
        for i in self.closed_voices:  # until its envelope starts
            self.targets_um[chans[i]] = 0.0
        self.targets_um0 = self.targets_um.copy()  # as the scene starts (events change targets_um)
        self.bank = None
        if freqs:
            if not scene_tones:
                from .dsp import OscillatorBank
            self.bank = OscillatorBank(self.n_channels, np.array(chans), self.fs, np.array(freqs),
                                       np.zeros(len(freqs)), np.array(phases), ramp=self.block)
        self.pulses = None
        self.render = None
        self._pulse_schedule: dict[int, list] = {}
        if scene.stimulus.kind != "tones":
            self.render = RenderStage(scene, offsets, self.n_channels, self.fs, self.block)
            self.bank, self.pulses = self.render.bank, self.render.pulses
        if pulses:
            from .dsp import PulseTrain

            # Silent (frequency 0, both levels 0) until a channel's start block.
            self.pulses = PulseTrain(self.n_channels, self.fs, 0.0, 0.5, 0.0, 0.0)
            for ch, (kb, f, duty, high, low) in pulses.items():
                self._pulse_schedule.setdefault(kb, []).append((ch, f, duty, high, low))
        # the played signals' changes (stimulus.play needs kind = "tones": no render), applied by
        # a stage of the rig's block function; apply() runs the same kernel when no rig does
        self.played = None
        if self._sig_schedule:
            self.played = PlayedSchedule(self.bank, {k: _last_per_tone(v) for k, v in self._sig_schedule.items()})
        self.played_in_block = False

    def _add_voices(self, scene, offsets, tones, chans, freqs, phases) -> None:
        """``stimulus.play``: one bank tone per voice (:mod:`rtctl.voices`), with its schedule."""
        from .dsp._kernels import MAX_RAMP
        from .events import duration_blocks
        from .voices import build, schedule, target_schedule

        # the run plays whole blocks: the voices go on to its last sample, so that its last block
        # plays the signals as defined, not their level at the duration held (a held level reads as
        # a steady stretch, rtctl.engine.judged)
        n_blocks = duration_blocks(scene.timing.duration, self.fs, self.block)
        n_run = float(n_blocks * self.block)
        self.voices = build(scene, offsets, self.fs, n_run, MAX_RAMP, self.block)
        for v, closed, receptor in self.voices:
            i = len(freqs)
            f0 = float(v.freq[0])
            receptor = receptor or perception.auto_receptor(f0) if f0 > 0 else receptor
            thr = perception.threshold_m(f0, receptor) if receptor else math.nan
            on = np.nonzero(v.amp > 0.0)[0]
            start = float(v.x[max(on[0] - 1, 0)]) / self.fs
            peak = float(v.amp.max())
            tones.append(Tone(v.channel, f0, 0.0, 0.0 if closed else peak, receptor, thr,
                              peak if closed else math.nan, start, (f0,)))
            self.bank_index.append((i,))
            chans.append(v.channel)
            freqs.append(f0)
            phases.append(v.phase % (2 * math.pi))
            if closed:
                self.closed_voices.append(i)
                parts = target_schedule(v, i, self.block, n_blocks)
                dest = self._target_schedule
            else:
                parts = schedule(v, i, self.block)
                dest = self._sig_schedule
            for kb, items in parts.items():
                dest.setdefault(kb, []).extend(items)

    def apply(self, k: int) -> None:
        """The parameter changes due at block ``k`` (ramped across that block), through the
        banks' :meth:`route` when the engine set one. A tone under amplitude control starts
        through ``start_hook(bank tone index)`` instead (it returns True for such tones); a
        closed-loop voice's target changes go to ``target_hook(bank tone index, target m)``."""
        for i, amp, ramp in self._schedule.get(k, ()):
            if self.start_hook is not None and self.start_hook(i):
                continue
            self.bank.set(i, amp=amp, ramp=ramp)
        if self.played is not None and not self.played_in_block:
            self.played.apply(k, self.bank.pending)
        if self.target_hook is not None:  # the rig sets it whenever there are closed-loop voices
            for i, target_m in self._target_schedule.get(k, ()):
                self.target_hook(i, target_m)
        for ch, f, duty, high, low in self._pulse_schedule.get(k, ()):
            self.pulses.set(ch, freq=f, duty=duty, high=high, low=low)
        if self.render is not None:
            self.render.apply(k)

    def busy_blocks(self):
        """The blocks at which :meth:`apply` has work, or None when that can be any block (a
        rendered stimulus)."""
        if self.render is not None:
            return None
        played = set() if self.played_in_block else set(self._sig_schedule)
        return set(self._schedule) | played | set(self._target_schedule) | set(self._pulse_schedule)

    def position(self) -> tuple:
        """Where the stimulus is between blocks, outside its arrays: the rendered stimulus' frame
        shown and path update (empty for tones, whose schedule is a function of the block)."""
        return self.render.position() if self.render is not None else ()

    def seek(self, position: tuple) -> None:
        """Back to a :meth:`position` (a checkpoint's restore)."""
        if self.render is not None:
            self.render.seek(position)

    def sum_targets(self, ch: int) -> None:
        """``targets_um[ch]``: the sum of channel ``ch``'s tones' targets (in place; between blocks)."""
        total = 0.0
        for k, tone in enumerate(self.tones):
            if tone.channel == ch:
                total += self.tone_targets_um[k]
        self.targets_um[ch] = total

    def reset(self) -> None:
        """Back to the start: banks at rest (no block may run meanwhile), render at its first frame."""
        self.tone_targets_um[...] = self.tone_targets_um0
        if self.bank is not None:
            self.bank.reset()
        if self.pulses is not None:
            self.pulses.reset()
        if self.render is not None:
            self.render.reset()
        if self.played is not None:
            self.played.reset()


class PlayedSchedule:
    """The played signals' changes of the oscillator bank (open loop), known before the run, as
    the arrays :func:`rtctl.dsp._kernels.osc_schedule` reads: a stage of the block function
    applies them at the start of their blocks, so a sweep that moves tones every few blocks needs
    no Python between those blocks. Checked here (:meth:`OscillatorBank.check_many`)."""

    def __init__(self, bank, per_block: dict):
        ks = sorted(per_block)
        checked = [bank.check_many(*per_block[k]) for k in ks]
        self.blocks = np.array(ks, dtype=np.int64)
        self.first = np.zeros(len(ks) + 1, dtype=np.int64)
        np.cumsum([c[0].size for c in checked], out=self.first[1:])
        self.tone, self.freq, self.amp, self.ramp = (np.ascontiguousarray(np.concatenate([c[f] for c in checked]))
                                                     for f in range(4))
        for a in (self.blocks, self.first, self.tone, self.freq, self.amp, self.ramp):
            a.flags.writeable = False  # constants of the run (a checkpoint saves only pos)
        self.pos = np.zeros(2, dtype=np.int64)  # this block's number, the next entry

    @property
    def args(self) -> tuple:
        return self.pos, self.blocks, self.first, self.tone, self.freq, self.amp, self.ramp

    def apply(self, k: int, pending) -> None:
        """Block ``k``'s changes into ``pending`` from Python (a stimulus no rig runs: the
        bank's own, unrouted ``pending``), with the block function's kernel."""
        from .dsp._kernels import osc_schedule

        self.pos[:] = k, np.searchsorted(self.blocks, k)
        osc_schedule(*self.args, pending)

    def reset(self) -> None:
        self.pos[:] = 0


class RenderStage:
    """Per-block parameter updates for ``stimulus.kind`` in image | braille | shape.

    Parameters
    ----------
    scene : Scene
    offsets : dict
        Actuator group name -> its first global channel.
    n_channels : int
    fs, block : float, int

    Attributes
    ----------
    bank : OscillatorBank or None
        Sines of the beat method (one per pin).
    pulses : PulseTrain or None
        Pulse trains and held levels of the other methods.
    channels : slice
        Global channels the rendered group occupies.
    """

    def __init__(self, scene, offsets, n_channels, fs, block):
        st = scene.stimulus
        name = st.actuator or scene.actuator[0].name
        g = scene.group(name)  # a SceneError naming the groups there are
        self.group = g
        R, C = g.grid
        c0 = offsets[g.name]
        self.channels = slice(c0, c0 + R * C)
        self.voltage = st.voltage or g.max_voltage
        self.low = -self.voltage if g.type in BIPOLAR else 0.0
        self.fs, self.block = float(fs), int(block)
        self.kind, self.method = st.kind, st.method
        self.bank = self.pulses = None
        self._frames = None
        if st.kind == "image":
            self._build_image(scene, st, (R, C), n_channels)
        else:
            self._build_frames(scene, st, (R, C), n_channels)

    # --- construction ----------------------------------------------------------------------------

    def _build_image(self, scene, st, grid, n_channels):
        from .render.factory import make_renderer
        from .render.path import Path, from_csv, raster

        image = load_image(scene)
        kw = {"grid": grid}
        if st.hia:
            kw["hia"] = st.hia
        if st.method == "frequency":
            kw["f_pmax"] = st.f_pmax
        if st.method == "beat":
            if st.px_size:
                kw["px_size"] = st.px_size
            kw.update(min_blob_area=st.min_blob_area, beat_band=tuple(st.beat_band),
                      carrier_band=tuple(st.carrier_band), normalize=st.normalize)
        if st.method == "roi":
            kw["threshold"] = st.threshold
        self.renderer = make_renderer(st.method, **kw).prepare(image)
        h, w = self.renderer.image_shape
        if st.path == "raster":
            self.path = raster(w, h, st.speed, st.rate, step=float(self.renderer.shape[0]))
        elif st.path == "fixed":
            self.path = Path(np.array([0.0]), np.array([float(st.at[0])]), np.array([float(st.at[1])]), st.rate)
        else:
            self.path = from_csv(st.path, st.rate)
        from .render.path import PathPlayer

        self.player = PathPlayer(self.renderer, self.path, self.fs, self.block)
        self.pending = self.renderer.empty()
        n = grid[0] * grid[1]
        if st.method == "beat":
            from .dsp import OscillatorBank

            chans = np.arange(self.channels.start, self.channels.stop)
            self.bank = OscillatorBank(n_channels, chans, self.fs, np.full(n, 100.0), np.zeros(n),
                                       ramp=self.block)
        else:
            from .dsp import PulseTrain

            self.pulses = PulseTrain(n_channels, self.fs, 0.0, 0.5, 0.0, 0.0)

    def _build_frames(self, scene, st, grid, n_channels):
        from .dsp import PulseTrain

        if st.kind == "braille":
            from .render.braille import braille_frames

            if st.dots not in (6, 8):
                raise SceneError(f"{scene.source}: stimulus.dots = {st.dots}: Braille cells have 6 or 8 dots")
            if not st.text:
                raise SceneError(f"{scene.source}: stimulus.text is empty: give the text to show in Braille")
            frames = braille_frames(st.text, grid, st.dots)
        else:
            from .render.shapes import shape

            frames = shape(st.shape, grid)[None]
        self._frames = frames.reshape(frames.shape[0], -1)
        self.pulses = PulseTrain(n_channels, self.fs, 0.0, 0.5, 0.0, 0.0)
        self._frame_blocks = max(1, int(round(st.frame_s * self.fs / self.block)))
        self._shown = -1

    # --- between blocks --------------------------------------------------------------------------

    def reset(self) -> None:
        """Before the first block: nothing shown yet."""
        self._shown = -1
        if self._frames is None:
            self.player.index = -1

    def position(self) -> tuple:
        """``(frame shown, path update in force)``; -1: none yet."""
        return (self._shown, -1 if self._frames is not None else self.player.index)

    def seek(self, position: tuple) -> None:
        self._shown = int(position[0])
        if self._frames is None:
            self.player.index = int(position[1])

    def apply(self, k: int) -> None:
        """Write the parameter changes due at block ``k``."""
        if self._frames is not None:
            i = (k // self._frame_blocks) % self._frames.shape[0]
            if i != self._shown:
                self._shown = i
                self._levels(self._frames[i])
            return
        if not self.player.step(k, self.pending):
            return
        p = self.pending
        if self.method == "beat":
            f = np.clip(p[:, 1], 1e-3, self.fs / 2 - 1.0)
            self.bank.set_all(freq=f, amp=p[:, 4] * self.voltage)
        elif self.method == "frequency":
            self._pulse(p[:, 1])
        else:
            self._levels(p[:, 0] > 0.5)

    def _levels(self, up) -> None:
        lev = np.where(np.asarray(up, bool), self.voltage, self.low)
        self._set(np.zeros(self._n_pins()), lev, lev)

    def _pulse(self, freq) -> None:
        on = freq > 0.0
        self._set(freq, np.where(on, self.voltage, 0.0), np.zeros(freq.size))

    def _set(self, freq, high, low) -> None:
        self.pulses.set_range(self.channels, freq=freq, high=high, low=low)

    def _n_pins(self) -> int:
        return self.channels.stop - self.channels.start
