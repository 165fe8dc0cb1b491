"""``stimulus.play``: the scene's signals put on channels, as voices the oscillator bank plays.

Each voice is one bank tone (:class:`rtctl.signals.Voice`). Open loop, its amplitude is volts
and :func:`schedule` turns its breakpoints into bank changes: at breakpoint ``x[i]`` the tone
ramps to ``(freq[i + 1], amp[i + 1])`` over ``x[i + 1] - x[i]`` samples, handed over at the start
of the block holding ``x[i]`` (block ``floor(x[i] / block)``, as tones start). With the block
dividing every breakpoint this is the signal sample for sample; otherwise a change comes up to a
block early, its ramp as long as written. Closed loop, its amplitude is a tip target in metres
that the amplitude controller follows, block by block (:func:`target_schedule`).
"""

from __future__ import annotations

import math

import numpy as np

from . import perception
from .errors import SceneError
from .signals import Signals, place, shift


def build(scene, offsets: dict, fs: float, n_run: float, max_ramp: int, block: int = 1) -> list:
    """Every played partial as ``(Voice, closed, receptor)``: closed voices' amplitudes in metres."""
    st = scene.stimulus
    if not st.play:
        return []
    closed = scene.control.mode == "closed"
    sigs = Signals(st.signals, fs, scene.source, block)
    spatial = {sp.name: (i, sp) for i, sp in enumerate(st.spatial)}
    ramp = float(max(1, round(st.ramp * fs)))
    out = []
    for j, pl in enumerate(st.play):
        where = f"{scene.source}: stimulus.play.{j}"
        unit = pl.unit if pl.unit != "auto" else ("um" if closed else "V")
        if (unit == "V") == closed:
            raise SceneError(f"{where}.unit = {pl.unit!r}: {'closed' if closed else 'open'} loop plays "
                             f"{'tip targets (um or threshold)' if closed else 'volts (V)'}")
        s0 = float(round(pl.start * fs))
        partials, _ = sigs.get(pl.signal, s0)
        partials = [shift(p, s0, fs) for p in partials]
        if pl.spatial:
            if pl.spatial not in spatial:
                raise SceneError(f"{where}.spatial = {pl.spatial!r}: no such stimulus.spatial item "
                                 f"(have {', '.join(spatial) or 'none'})")
            from .spatial import gains

            sp = spatial[pl.spatial][1]
            g = scene.group(sp.actuator or scene.actuator[0].name)
            _, tracks = gains(sp, g.grid, fs, n_run)
            targets = [(offsets[g.name] + c, tr) for c, tr in enumerate(tracks) if tr.v.max() > 0.0]
        else:
            g = scene.group(pl.actuator or scene.actuator[0].name)
            if pl.channel >= g.grid[0] * g.grid[1]:
                raise SceneError(f"{where}.channel = {pl.channel}: group {g.name!r} has channels "
                                 f"0..{g.grid[0] * g.grid[1] - 1}")
            targets = [(offsets[g.name] + pl.channel, None)]
        for p in partials:
            if closed and p.freq.v.max() <= 0.0:
                raise SceneError(f"{where}.signal = {pl.signal!r}: closed loop holds tones, not levels "
                                 "(a dc or an envelope on its own): multiply it by a tone")
            scale, receptor = 1.0, None
            f0 = float(p.freq.v[0])
            if unit == "threshold":
                receptor = perception.auto_receptor(f0) if pl.receptor == "auto" else pl.receptor
                thr = perception.threshold_m(f0, receptor) if receptor else math.nan
                if not np.isfinite(thr):
                    raise SceneError(f"{where}.unit = 'threshold': no receptor threshold at {f0:g} Hz "
                                     f"(signal {pl.signal!r}); give um")
                scale = thr * 10 ** (pl.db / 20) * 1e6
            if closed:
                scale *= 1e-6  # um -> m
                if np.ptp(p.freq.v) > 0.0:
                    raise SceneError(f"{where}.signal = {pl.signal!r}: closed loop needs tones of fixed "
                                     "frequency (the observer locks in on them); a chirp or a product with "
                                     "one plays open loop")
            for ch, gain in targets:
                p2 = p if scale == 1.0 else _scaled(p, scale)
                v = place(p2, ch, gain, n_run, ramp, max_ramp, pl.signal, block)
                if v is not None:
                    if closed and g.type != "bimorph":  # the amplitude controller's groups only
                        raise SceneError(f"{scene.source}: stimulus.play: channel {g.name}.{ch - offsets[g.name]} "
                                         "plays a tip target but is not under amplitude control (bimorph "
                                         "groups with self-sensing only)")
                    if v.freq.max() >= fs / 2:
                        raise SceneError(f"{where}.signal = {pl.signal!r}: a tone reaches {v.freq.max():g} Hz, "
                                         f"at or above fs / 2 = {fs / 2:g} Hz")
                    out.append((v, closed, receptor))
    return out


def _scaled(p, k):
    from dataclasses import replace

    from .signals import Track

    return replace(p, amp=Track(p.amp.x, p.amp.v * k))


def schedule(voice, tone: int, block: int) -> dict[int, list]:
    """Open loop: block -> ``[(tone, freq, amp, ramp samples)]`` (see the module docstring)."""
    out: dict[int, list] = {}
    x = voice.x
    for i in range(len(x) - 1):
        r = int(x[i + 1] - x[i])
        if r <= 0:
            continue
        out.setdefault(int(x[i] // block), []).append((tone, float(voice.freq[i + 1]), float(voice.amp[i + 1]), r))
    return out


def target_schedule(voice, tone: int, block: int, n_blocks: int) -> dict[int, list]:
    """Closed loop: block -> ``[(tone, target m)]`` where the target at the block's last sample
    changes (0: the tone switches off; from 0: it switches on under control)."""
    k = np.arange(n_blocks)
    tgt = np.interp((k + 1.0) * block, voice.x, voice.amp)
    prev = np.concatenate([[0.0], tgt[:-1]])
    out: dict[int, list] = {}
    for kb in np.nonzero(tgt != prev)[0]:
        out.setdefault(int(kb), []).append((tone, float(tgt[kb])))
    return out
