"""Haptic patterns from design tools: Apple Core Haptics ``.ahap`` and Meta Haptics Studio
``.haptic`` files, read into scene signals (:mod:`rtctl.signals`) for ``rtctl play``.

What is read (everything else is ignored with a warning; a value out of range is clamped and
reported; an event that plays nothing is left out with a warning; a file that is not the format,
or has nothing to play, is refused in one line):

* ``.ahap`` (JSON, Apple's "Representing haptic patterns in AHAP files"): ``Pattern`` items
  ``Event`` (``HapticTransient``; ``HapticContinuous`` with ``EventDuration``; parameters
  ``HapticIntensity`` and ``HapticSharpness``, each 0..1), ``ParameterCurve`` and ``Parameter``
  with ``HapticIntensityControl`` (multiplies the intensity, 0..1) and
  ``HapticSharpnessControl`` (adds to the sharpness, -1..1). A curve is straight between its
  control points and holds its last value until the next curve or parameter of its kind, which
  takes over from its start even before the curve has ended.
* ``.haptic`` (JSON, Meta's open format, version 1): ``signals.continuous.envelopes`` with
  ``amplitude`` breakpoints (``time``, ``amplitude`` 0..1, optional ``emphasis`` with
  ``amplitude`` and ``frequency`` 0..1: a transient there) and ``frequency`` breakpoints
  (``time``, ``frequency`` 0..1), each straight between its points.

The scene's ``stimulus.pattern`` maps them: intensity / amplitude 1 is ``full`` (volts open loop,
tip um closed loop), sharpness / frequency 0..1 is ``band`` in Hz, straight between; a transient
is a raised-cosine bump ``transient_s`` long at the sharpness' frequency. Closed loop holds each
event at one frequency (the observer locks in on fixed tones): its first; open loop follows the
sharpness curve or frequency envelope as a chirp.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .errors import PatternError
from .schema import SIGNAL

#: breakpoints a signal may have: an event with more cannot be played as one
MAX_POINTS = SIGNAL.keys["times"].max_items

FORMATS = (".ahap", ".haptic")
#: Example patterns shipped with rtctl, played by file name (``rtctl play heartbeat.ahap ...``).
BUNDLED_DIR = Path(__file__).with_name("scenes") / "patterns"


def bundled() -> list[str]:
    """File names of the example patterns."""
    return sorted(p.name for p in BUNDLED_DIR.iterdir() if p.suffix in FORMATS)


class Pattern:
    """A pattern as events: ``continuous`` ``(t0, times, levels, ftimes, fvalues)`` (times relative
    to ``t0``, values 0..1) and ``transients`` ``(t, level, sharpness)``; ``warnings`` lists what
    was ignored or clamped, one line each."""

    def __init__(self, source: str):
        self.source = source
        self.continuous: list[tuple] = []
        self.transients: list[tuple] = []
        self.warnings: list[str] = []
        #: the item each event was read from (``Pattern[2].Event``), in the order of ``continuous``
        #: and ``transients``: messages about an event name it
        self.continuous_from: list[str] = []
        self.transients_from: list[str] = []
        #: why events were read but left out (intensity 0 throughout, no length): said when none is left
        self.skipped: list[str] = []

    @property
    def end(self) -> float:
        """When the last event ends, s (transients counted as instants)."""
        ends = [t0 + times[-1] for t0, times, *_ in self.continuous] + [t for t, *_ in self.transients]
        return max(ends, default=0.0)

    def warn(self, msg: str) -> None:
        self.warnings.append(f"{self.source}: {msg}")

    def skip(self, msg: str) -> None:
        """An event that plays nothing: warned, and remembered in case it was the only one."""
        self.skipped.append(msg)
        self.warn(f"{msg} (ignored)")

    def events(self) -> list[tuple[float, float, str]]:
        """``(start, end, item)`` of every event, in the order of ``continuous`` then ``transients``."""
        return ([(t0, t0 + times[-1], w) for (t0, times, *_), w in zip(self.continuous, self.continuous_from)]
                + [(t, t, w) for (t, *_), w in zip(self.transients, self.transients_from)])

    def last(self) -> tuple[float, str]:
        """``(end, item)`` of the event that ends last."""
        return max(((end, w) for _, end, w in self.events()), key=lambda e: e[0])

    def drop_from(self, t_end: float) -> list[tuple[float, str]]:
        """Leave out the events that start at or after ``t_end`` (they would never play);
        ``(start, item)`` of each, in time order."""
        keep_c = [i for i, (t0, *_) in enumerate(self.continuous) if t0 < t_end]
        keep_t = [i for i, (t, *_) in enumerate(self.transients) if t < t_end]
        dropped = sorted([(t0, w) for (t0, *_), w in zip(self.continuous, self.continuous_from) if t0 >= t_end]
                         + [(t, w) for (t, *_), w in zip(self.transients, self.transients_from) if t >= t_end])
        self.continuous = [self.continuous[i] for i in keep_c]
        self.continuous_from = [self.continuous_from[i] for i in keep_c]
        self.transients = [self.transients[i] for i in keep_t]
        self.transients_from = [self.transients_from[i] for i in keep_t]
        return dropped


def load(path) -> Pattern:
    """Read an ``.ahap`` or ``.haptic`` file (by its extension); a bare name that is no file here
    is looked for among the examples (:func:`bundled`)."""
    p = Path(path)
    if not p.exists() and p.parent == Path(".") and (BUNDLED_DIR / p.name).is_file():
        p = BUNDLED_DIR / p.name
    if p.suffix.lower() not in FORMATS:
        raise PatternError(f"{path}: not a pattern file (expected {' or '.join(FORMATS)})")
    try:
        data = json.loads(p.read_text(encoding="utf-8"), parse_int=_int)
    except FileNotFoundError:
        raise PatternError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise PatternError(f"{path}: cannot read: {e}") from None
    except json.JSONDecodeError as e:
        raise PatternError(f"{path}: not valid JSON: {e.msg} at line {e.lineno} column {e.colno}") from None
    except RecursionError:  # the decoder recurses per level: thousands of [ or { exhaust the stack
        raise PatternError(f"{path}: arrays or objects nested too deeply to read (no pattern item is)") from None
    pat = Pattern(str(path))
    if not isinstance(data, dict):
        raise PatternError(f"{path}: the top level must be a JSON object")
    (_ahap if p.suffix.lower() == ".ahap" else _haptic)(data, pat)
    if not pat.continuous and not pat.transients:
        if pat.skipped:
            why = "; ".join(pat.skipped[:3]) + ("; ..." if len(pat.skipped) > 3 else "")
            raise PatternError(f"{path}: nothing to play: {why}")
        raise PatternError(f"{path}: no haptic events in the pattern")
    return pat


# ----------------------------------------------------------------------------- reading values

#: digits an integer literal may have: more is no time or level (a float holds at most 309), and
#: Python refuses to convert more than 4300 at all
MAX_DIGITS = 300


class _Huge(str):
    """An integer literal too long to be a number here, kept as its text for the message."""


def _int(text: str):
    return int(text) if len(text) <= MAX_DIGITS else _Huge(text)


def _show(v) -> str:
    """``v`` for a one-line message: short, whatever it is (a container is not spelled out: it
    may be nested thousands deep)."""
    if isinstance(v, _Huge):
        return f"an integer of {len(v.lstrip('-'))} digits"
    if isinstance(v, dict):
        return "a JSON object"
    if isinstance(v, list):
        return "a JSON array"
    s = repr(v) if isinstance(v, str) else json.dumps(v)
    return s if len(s) <= 40 else s[:37] + "..."


def _num(pat, v, where, lo=None, hi=None):
    """A finite number at ``where``, clamped into [lo, hi] with a warning."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        why = "too large for a time or a level" if isinstance(v, _Huge) else "must be a finite number"
        raise PatternError(f"{pat.source}: {where} = {_show(v)}: {why}")
    v = float(v)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        c = min(max(v, lo if lo is not None else v), hi if hi is not None else v)
        pat.warn(f"{where} = {v:g} is outside [{lo:g}, {hi:g}]: clamped to {c:g}")
        v = c
    return v


def _str(pat, v, where):
    """A string at ``where``: a name compared with the ones the format knows."""
    if not isinstance(v, str) or isinstance(v, _Huge):
        raise PatternError(f"{pat.source}: {where} = {_show(v)}: must be a string")
    return v


def _obj(pat, v, where):
    if not isinstance(v, dict):
        raise PatternError(f"{pat.source}: {where} must be a JSON object")
    return v


def _list(pat, v, where):
    if not isinstance(v, list):
        raise PatternError(f"{pat.source}: {where} must be a JSON array")
    return v


def _unknown(pat, d, known, where):
    for k in d:
        if k not in known:
            name = k if len(k) <= 40 and k.isprintable() else _show(k)  # one short line
            pat.warn(f"{where}.{name}: not used (ignored)")


def _need(pat, d, key, where):
    if key not in d:
        raise PatternError(f"{pat.source}: {where}: missing {key!r}")
    return d[key]


# ----------------------------------------------------------------------------- .ahap

_AHAP_TOP = ("Version", "Metadata", "Pattern")
_CURVES = {"HapticIntensityControl": (0.0, 1.0), "HapticSharpnessControl": (-1.0, 1.0)}


def _ahap(data, pat):
    _unknown(pat, data, _AHAP_TOP, "")
    items = _list(pat, _need(pat, data, "Pattern", "top level"), "Pattern")
    events, curves = [], {k: [] for k in _CURVES}
    for i, item in enumerate(items):
        where = f"Pattern[{i}]"
        item = _obj(pat, item, where)
        if len(item) != 1:
            raise PatternError(f"{pat.source}: {where} must hold one of Event, ParameterCurve, Parameter")
        (kind, body), = item.items()
        where = f"{where}.{kind}"
        body = _obj(pat, body, where)
        if kind == "Event":
            events.append((where, body))
        elif kind in ("ParameterCurve", "Parameter"):
            pid = _str(pat, _need(pat, body, "ParameterID", where), f"{where}.ParameterID")
            if pid not in _CURVES:
                pat.warn(f"{where}.ParameterID = {_show(pid)}: not used (ignored)")
                continue
            lo, hi = _CURVES[pid]
            t0 = _num(pat, _need(pat, body, "Time", where), f"{where}.Time", 0.0, math.inf)
            if kind == "Parameter":
                _unknown(pat, body, ("ParameterID", "Time", "ParameterValue"), where)
                pts = [(t0, _num(pat, _need(pat, body, "ParameterValue", where), f"{where}.ParameterValue", lo, hi))]
            else:
                _unknown(pat, body, ("ParameterID", "Time", "ParameterCurveControlPoints"), where)
                key = "ParameterCurveControlPoints"
                cps = _list(pat, _need(pat, body, key, where), f"{where}.{key}")
                pts = []
                for j, cp in enumerate(cps):
                    w = f"{where}.ParameterCurveControlPoints[{j}]"
                    cp = _obj(pat, cp, w)
                    _unknown(pat, cp, ("Time", "ParameterValue"), w)
                    pts.append((t0 + _num(pat, _need(pat, cp, "Time", w), f"{w}.Time", 0.0, math.inf),
                                _num(pat, _need(pat, cp, "ParameterValue", w), f"{w}.ParameterValue", lo, hi)))
                if not pts or any(b[0] < a[0] for a, b in zip(pts, pts[1:])):
                    raise PatternError(f"{pat.source}: {where}.ParameterCurveControlPoints: need at least one "
                                       "point, in time order")
            curves[pid].append(pts)
        else:
            pat.warn(f"{where}: not used (ignored)")
    gain = _held(curves["HapticIntensityControl"], 1.0)
    shift = _held(curves["HapticSharpnessControl"], 0.0)
    for where, ev in events:
        _ahap_event(pat, where, ev, gain, shift)


def _held(curves, rest):
    """A control as breakpoints ``(t, v, rest)``, ``t`` never decreasing (two points at one time:
    a step), ``rest`` before the first; read with :func:`_left` and :func:`_right`.

    Each curve is straight between its points and holds its last value until the next curve
    begins; a curve that begins before the one before it has ended takes over from its start (as
    Core Haptics schedules a curve: applied from its start time, from whatever value the
    parameter has then). Curves that begin at one time: the later in the file."""
    ts, vs = [], []
    curves = sorted(curves, key=lambda p: p[0][0])  # stable: file order among equal starts
    for k, pts in enumerate(curves):
        nxt = curves[k + 1][0][0] if k + 1 < len(curves) else math.inf
        if nxt <= pts[0][0]:
            continue  # replaced at once by the next
        for t, v in pts:
            if t >= nxt:
                break
            ts.append(t)
            vs.append(v)
        if nxt < math.inf:  # up to the next curve: the rest of this one (cut there) or its last value held
            pt, pv = [p[0] for p in pts], [p[1] for p in pts]
            ts.append(nxt)
            vs.append(float(np.interp(nxt, pt, pv)) if pt[-1] > nxt else pv[-1])
    if not ts:
        return np.array([0.0]), np.array([rest]), rest
    return np.array(ts), np.array(vs), rest


def _right(ctl, t):
    """The control at ``t`` (an array): after a step there (a curve that starts at ``t`` applies)."""
    ts, vs, rest = ctl
    t = np.asarray(t, float)
    j = np.searchsorted(ts, t, side="right")  # ts[j - 1] <= t < ts[j]
    lo, hi = np.maximum(j - 1, 0), np.minimum(j, len(ts) - 1)
    span = ts[hi] - ts[lo]
    frac = np.where(span > 0, (t - ts[lo]) / np.where(span > 0, span, 1.0), 0.0)
    v = vs[lo] + frac * (vs[hi] - vs[lo])
    return np.where(j == 0, rest, np.where(j == len(ts), vs[-1], v))


def _left(ctl, t):
    """The control just before ``t`` (an array): before a step there."""
    ts, vs, rest = ctl
    t = np.asarray(t, float)
    i = np.searchsorted(ts, t, side="left")  # ts[i - 1] < t <= ts[i]
    lo, hi = np.maximum(i - 1, 0), np.minimum(i, len(ts) - 1)
    span = ts[hi] - ts[lo]
    frac = np.where(span > 0, (t - ts[lo]) / np.where(span > 0, span, 1.0), 0.0)
    v = vs[lo] + frac * (vs[hi] - vs[lo])
    return np.where(i == 0, rest, np.where(i == len(ts), vs[-1], v))


def _ahap_event(pat, where, ev, gain, shift):
    etype = _str(pat, _need(pat, ev, "EventType", where), f"{where}.EventType")
    _unknown(pat, ev, ("Time", "EventType", "EventDuration", "EventParameters", "EventWaveformPath"), where)
    if etype not in ("HapticTransient", "HapticContinuous"):
        pat.warn(f"{where}.EventType = {_show(etype)}: not a haptic event (ignored)")
        return
    t0 = _num(pat, _need(pat, ev, "Time", where), f"{where}.Time", 0.0, math.inf)
    params = {"HapticIntensity": 1.0, "HapticSharpness": 0.5}  # Core Haptics' defaults
    for j, prm in enumerate(_list(pat, ev.get("EventParameters", []), f"{where}.EventParameters")):
        w = f"{where}.EventParameters[{j}]"
        prm = _obj(pat, prm, w)
        pid = _str(pat, _need(pat, prm, "ParameterID", w), f"{w}.ParameterID")
        if pid not in params:
            pat.warn(f"{w}.ParameterID = {_show(pid)}: not used (ignored)")
            continue
        params[pid] = _num(pat, _need(pat, prm, "ParameterValue", w), f"{w}.ParameterValue ({pid})", 0.0, 1.0)
    inten, sharp = params["HapticIntensity"], params["HapticSharpness"]
    if etype == "HapticTransient":
        g = float(_right(gain, t0))
        s = min(max(sharp + float(_right(shift, t0)), 0.0), 1.0)
        if inten * g <= 0.0:
            pat.skip(f"{where}: intensity 0 at {t0:g} s (HapticIntensity {inten:g} x HapticIntensityControl "
                     f"{g:g}): plays nothing")
            return
        pat.transients.append((t0, inten * g, s))
        pat.transients_from.append(where)
        return
    dur = _num(pat, _need(pat, ev, "EventDuration", where), f"{where}.EventDuration", 0.0, 30.0)
    if dur <= 0.0:
        pat.skip(f"{where}.EventDuration = 0: nothing to play")
        return
    # the event's span, with every control point inside it; where a control steps (a curve taking
    # over), two points at that time: the value before and after
    end = t0 + dur
    inner = np.unique([t for t in np.concatenate([gain[0], shift[0]]) if t0 < t < end])
    t = np.concatenate([[t0], inner, [end]])
    lg, rg, ls, rs = _left(gain, t), _right(gain, t), _left(shift, t), _right(shift, t)
    lg[0], ls[0], rg[-1], rs[-1] = rg[0], rs[0], lg[-1], ls[-1]  # the event starts after, ends before a step
    step = (lg != rg) | (ls != rs)
    t = np.concatenate([t[step], t])
    g = np.concatenate([lg[step], rg])
    sh = np.concatenate([ls[step], rs])
    order = np.argsort(t, kind="stable")  # the value before a step first
    t, g, sh = t[order], g[order], sh[order]
    levels = inten * g
    if not np.any(levels > 0.0):
        pat.skip(f"{where}: intensity 0 throughout (HapticIntensity {inten:g} x HapticIntensityControl): "
                 "plays nothing")
        return
    sharps = np.clip(sharp + sh, 0.0, 1.0)
    pat.continuous.append((t0, t - t0, levels, t - t0, sharps))
    pat.continuous_from.append(where)


# ----------------------------------------------------------------------------- .haptic


def _haptic(data, pat):
    _unknown(pat, data, ("version", "metadata", "signals"), "")
    ver = _obj(pat, _need(pat, data, "version", "top level"), "version")
    major = ver.get("major")
    if isinstance(major, bool) or major != 1:  # true == 1 in Python, not in the format
        raise PatternError(f"{pat.source}: version.major = {_show(major)}: only version 1 is read")
    sig = _obj(pat, _need(pat, data, "signals", "top level"), "signals")
    _unknown(pat, sig, ("continuous",), "signals")
    cont = _obj(pat, _need(pat, sig, "continuous", "signals"), "signals.continuous")
    _unknown(pat, cont, ("envelopes",), "signals.continuous")
    env = _obj(pat, _need(pat, cont, "envelopes", "signals.continuous"), "signals.continuous.envelopes")
    _unknown(pat, env, ("amplitude", "frequency"), "signals.continuous.envelopes")
    w = "signals.continuous.envelopes.amplitude"
    amp = _list(pat, _need(pat, env, "amplitude", "signals.continuous.envelopes"), w)
    ta, va = [], []
    for i, bp in enumerate(amp):
        wi = f"{w}[{i}]"
        bp = _obj(pat, bp, wi)
        _unknown(pat, bp, ("time", "amplitude", "emphasis"), wi)
        t = _num(pat, _need(pat, bp, "time", wi), f"{wi}.time", 0.0, math.inf)
        ta.append(t)
        va.append(_num(pat, _need(pat, bp, "amplitude", wi), f"{wi}.amplitude", 0.0, 1.0))
        if "emphasis" in bp:
            em = _obj(pat, bp["emphasis"], f"{wi}.emphasis")
            _unknown(pat, em, ("amplitude", "frequency"), f"{wi}.emphasis")
            ea = _num(pat, _need(pat, em, "amplitude", f"{wi}.emphasis"), f"{wi}.emphasis.amplitude", 0.0, 1.0)
            ef = _num(pat, _need(pat, em, "frequency", f"{wi}.emphasis"), f"{wi}.emphasis.frequency", 0.0, 1.0)
            if ea > 0.0:  # an emphasis of 0 adds nothing to the envelope under it
                pat.transients.append((t, ea, ef))
                pat.transients_from.append(f"{wi}.emphasis")
    if len(ta) < 2 or any(b < a for a, b in zip(ta, ta[1:])):
        raise PatternError(f"{pat.source}: {w}: needs at least 2 breakpoints, in time order")
    tf, vf = [], []
    w = "signals.continuous.envelopes.frequency"
    for i, bp in enumerate(_list(pat, env.get("frequency", []), w)):
        wi = f"{w}[{i}]"
        bp = _obj(pat, bp, wi)
        _unknown(pat, bp, ("time", "frequency"), wi)
        tf.append(_num(pat, _need(pat, bp, "time", wi), f"{wi}.time", 0.0, math.inf))
        vf.append(_num(pat, _need(pat, bp, "frequency", wi), f"{wi}.frequency", 0.0, 1.0))
    if any(b < a for a, b in zip(tf, tf[1:])):
        raise PatternError(f"{pat.source}: {w}: breakpoints must be in time order")
    w = "signals.continuous.envelopes.amplitude"
    if ta[-1] == ta[0]:
        pat.skip(f"{w}: every breakpoint at {ta[0]:g} s: the envelope lasts no time, plays nothing")
        return
    if max(va) <= 0.0:
        pat.skip(f"{w}: every amplitude is 0: plays nothing")
        return
    t0 = ta[0]
    ta = np.array(ta) - t0
    if tf:  # on the amplitude's span, straight between, held outside
        tt = np.unique(np.concatenate([ta, [x - t0 for x in tf if t0 < x < t0 + ta[-1]]]))
        fv = np.interp(tt + t0, tf, vf)
    else:
        tt, fv = np.array([0.0]), np.array([0.5])
    pat.continuous.append((t0, ta, np.array(va), tt, fv))
    pat.continuous_from.append(w)


# ----------------------------------------------------------------------------- to signals


def to_stimulus(pat: Pattern, mapping, closed: bool, fs: float, max_voltage: float, margin_db: float):
    """``(signals, play)`` tables for the scene: one sine or chirp times one envelope per event.

    ``mapping`` is the validated ``stimulus.pattern`` table; ``max_voltage`` (open loop) and
    ``margin_db`` (closed loop: over the receptor's threshold) stand in for ``full = 0``."""
    lo, hi = mapping["band"]
    hz = lambda s: lo + (hi - lo) * np.asarray(s, float)  # noqa: E731 - the band map, one line
    where = {"actuator": mapping["actuator"], "channel": mapping["channel"], "spatial": mapping["spatial"]}
    full = mapping["full"]
    if not closed:
        unit, amp = {"unit": "V"}, full if full > 0 else max_voltage / 2
    elif full > 0:
        unit, amp = {"unit": "um"}, full
    else:
        unit, amp = {"unit": "threshold", "db": margin_db}, 1.0
    signals, play = [], []
    for i, (t0, times, levels, ftimes, fvals) in enumerate(pat.continuous):
        n = f"c{i}"
        f = hz(fvals)
        chirp = np.ptp(f) > 0.0 and not closed
        points = max(len(times), len(ftimes) if chirp else 0)
        if points > MAX_POINTS:  # said here: the signal's own limit would name a signal the user never wrote
            raise PatternError(f"{pat.source}: {pat.continuous_from[i]} (at {t0:g} s) has {points} breakpoints "
                               f"with the control points within it; an event plays at most {MAX_POINTS}")
        if np.ptp(f) == 0.0 or closed:
            if np.ptp(f) > 0.0:
                pat.warn(f"event {i} at {t0:g} s: closed loop holds it at {f[0]:.4g} Hz (its sharpness or "
                         f"frequency moves over {f.min():.4g} ... {f.max():.4g} Hz)")
            tone = {"name": f"{n}.tone", "type": "sine", "freq": float(f[0]), "amp": amp}
        else:
            ft = np.round(np.asarray(ftimes) * fs) / fs
            tone = {"name": f"{n}.tone", "type": "chirp", "times": [float(x) for x in ft],
                    "freqs": [float(x) for x in f], "amp": amp}
        env = {"name": f"{n}.env", "type": "breakpoints", "times": [float(x) for x in times],
               "levels": [float(x) for x in levels], "curve": "linear"}
        signals += [tone, env, {"name": n, "type": "product", "of": [f"{n}.tone", f"{n}.env"]}]
        play.append({"signal": n, "start": float(t0), **where, **unit})
    td = mapping["transient_s"]
    for i, (t, level, sharp) in enumerate(pat.transients):
        if level <= 0.0:
            continue
        n = f"t{i}"
        signals += [{"name": f"{n}.tone", "type": "sine", "freq": float(hz(sharp)), "amp": amp},
                    {"name": f"{n}.env", "type": "breakpoints", "times": [0.0, td / 4, td],
                     "levels": [0.0, level, 0.0]},
                    {"name": n, "type": "product", "of": [f"{n}.tone", f"{n}.env"]}]
        play.append({"signal": n, "start": float(t), **where, **unit})
    return signals, play
