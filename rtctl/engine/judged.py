"""The stretch of a run over which a channel that plays signals (``stimulus.play``) is judged.

A tone plays to the end of the run, so the summary judges it over the run's last analysis
window. A played signal may end early (an enveloped burst, a pattern shorter than the run) or
never hold still (transients, a chirp, a moving virtual source): judged at the run's end it
would read "not felt" and a wrong error. So a channel whose every tone is a played signal is
judged, from its voices' breakpoints (what was commanded, never the plant's truth), over:

* ``steady``: the last of its longest *steady stretches*, where every partial on the channel
  holds its frequency and amplitude and not all are 0 (an envelope's sustain, a whole-run
  tone after its fade-in). Its amplitude is fitted over the stretch's last analysis window,
  as a tone's is over the run's last, and its target is the level held there;
* ``peak``: with no steady stretch, its strongest moment: the highest of the amplitudes
  fitted over short windows (:func:`rtctl.engine.report.fit_window`) while any partial is
  non-zero, against the highest level commanded;
* ``stroke``: with no steady stretch and a partial whose frequency moves (a chirp, where
  no fixed-frequency fit holds), half the tip's peak-to-peak over that non-zero stretch.
"""

from __future__ import annotations

import numpy as np


def played_voices(rig, ch: int) -> list:
    """The voices on channel ``ch`` when every tone on it is a played signal, else []."""
    stim = getattr(rig, "stimulus", None)
    voices = [v for v, _, _ in getattr(stim, "voices", ())] if stim is not None else []
    mine = [v for v in voices if v.channel == ch]
    n_tones = sum(tn.channel == ch for tn in rig.tones)
    return mine if mine and len(mine) == n_tones else []


def judged_span(voices, n: int) -> dict | None:
    """``{"by", "from", "to", "level", "on", "off"}``: the rule (module docstring), the judged
    stretch ``[from, to)`` in samples within the run's ``n``, the summed amplitude commanded
    there (its highest for ``peak`` and ``stroke``) in the voices' unit, and the stretch
    ``[on, off)`` where any partial is non-zero. None if nothing sounds."""
    if not voices:
        return None
    xs = np.unique(np.concatenate([[0.0, float(n)]] + [v.x[(v.x > 0) & (v.x < n)] for v in voices]))
    amp = np.array([np.interp(xs, v.x, v.amp) for v in voices])  # held before and after
    freq = np.array([np.interp(xs, v.x, v.freq) for v in voices])
    total = amp.sum(axis=0)
    on = np.nonzero((total[:-1] > 0) | (total[1:] > 0))[0]
    if on.size == 0:
        return None
    flat = np.all((amp[:, :-1] == amp[:, 1:]) & (freq[:, :-1] == freq[:, 1:]), axis=0) & (total[:-1] > 0)
    best = None  # (length, start, end) of the longest run of steady segments at one level; the last wins
    i = 0
    while i < flat.size:
        if not flat[i]:
            i += 1
            continue
        j = i
        while j + 1 < flat.size and flat[j + 1] and np.array_equal(amp[:, j + 1], amp[:, i]) \
                and np.array_equal(freq[:, j + 1], freq[:, i]):
            j += 1
        length = xs[j + 1] - xs[i]
        if best is None or length >= best[0]:
            best = (length, i, j + 1)
        i = j + 1
    active = {"on": float(xs[on[0]]), "off": float(xs[on[-1] + 1])}
    if best is not None:
        _, a, b = best
        return {"by": "steady", "from": float(xs[a]), "to": float(xs[b]), "level": float(total[a]), **active}
    moving = any(np.ptp(v.freq) > 0.0 for v in voices)
    return {"by": "stroke" if moving else "peak", "from": active["on"], "to": active["off"],
            "level": float(total.max()), **active}
