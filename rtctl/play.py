"""``rtctl play``: a haptic pattern file turned into a scene's stimulus."""

from __future__ import annotations

from . import patterns
from . import scene as sc
from .errors import PatternError, SceneError
from .schema import SCENE

#: the longest run a scene may ask for, s (timing.duration's bound)
MAX_DURATION = SCENE.keys["timing"].keys["duration"].hi


def pattern_scene(pattern: str, source: str, overrides=(), duration: float | None = None):
    """The scene ``source`` (with ``overrides``) playing ``pattern`` instead of its own stimulus,
    and the warnings (the pattern's ignored keys and clamped values, dropped events). The run
    lasts the scene's duration, or longer to hold the whole pattern, or ``duration`` when given:
    the scene's events at or after the end of that run are dropped, with one warning saying so
    (``rtctl run`` refuses them instead, since there the user chose both), and so are the
    pattern's events that start at or after it."""
    pat = patterns.load(pattern)
    s = sc.load(source, list(overrides))
    data = s.to_dict()
    st = data["stimulus"]
    if st["kind"] != "tones":
        raise SceneError(f"{s.source}: stimulus.kind = {st['kind']!r}: a pattern plays on a tones scene")
    m = s.stimulus.pattern
    # checked here, not by the signals the band becomes: their messages name signals the user never wrote
    nyq = s.timing.fs / 2
    if not all(0.0 < f < nyq for f in m.band):
        raise SceneError(f"{s.source}: stimulus.pattern.band = {list(m.band)}: both ends must be in "
                         f"(0, fs / 2 = {nyq:g}) Hz")
    group = s.group(m.actuator or s.actuator[0].name)
    t = data["timing"]
    if duration is None:
        end = pat.end + tail(m, st)
        if end > MAX_DURATION:  # the pattern's time, not the scene's duration, is what is too long
            last, item = pat.last()
            raise PatternError(f"{pat.source}: {item} ends at {last:g} s: a run holding it would last {end:g} s, "
                               f"longer than the {MAX_DURATION:g} s a run may (give --duration to play its start)")
        duration = max(t["duration"], end)
    t["duration"] = duration
    dropped = []  # said after the pattern's own warnings (to_stimulus adds some)
    late = pat.drop_from(duration)
    if late:
        if not pat.continuous and not pat.transients:
            raise PatternError(f"{pat.source}: every event starts at or after the end of the run ({duration:g} s), "
                               f"the first at {late[0][0]:g} s: nothing to play")
        dropped.append(_dropped(pat.source, [w for _, w in late], [at for at, _ in late], duration))
    cut = [(w, end) for _, end, w in pat.events() if end > duration]
    if cut:
        dropped.append(f"{pat.source}: {_names([w for w, _ in cut])} (to {_ats([e for _, e in cut])} s) "
                        f"{'goes' if len(cut) == 1 else 'go'} on after the end of the run ({duration:g} s): cut off")
    signals, play = patterns.to_stimulus(pat, m, s.control.mode == "closed", s.timing.fs, group.max_voltage,
                                         s.control.margin_db)
    warnings = pat.warnings + dropped
    late = [i for i, ev in enumerate(data["events"]) if ev["at"] >= duration]
    if late:
        which = f"events.{late[0]}" if len(late) == 1 else f"events.{late[0]}..{late[-1]}"
        warnings.append(_dropped(s.source, [which], [data["events"][i]["at"] for i in late], duration))
        data["events"] = data["events"][:late[0]]  # in time order: the late ones are the last
    # the scene's own tones give way to the pattern, and so do events that re-target them
    tied = [i for i, ev in enumerate(data["events"]) if any(k.startswith("stimulus.tones") for k in
                                                            sc.event_keys(ev["set"]))]
    if tied:
        raise SceneError(f"{s.source}: events.{tied[0]} changes a tone of the scene, which the pattern replaces")
    st.update(tones=[], signals=signals, play=play)
    return sc.Scene(sc.validate(data, s.source), s.source, s.overrides), warnings


def _names(items: list[str], most: int = 3) -> str:
    return ", ".join(items[:most]) + (f" and {len(items) - most} more" if len(items) > most else "")


def _ats(times: list[float], most: int = 3) -> str:
    return ", ".join(f"{x:g}" for x in times[:most]) + (", ..." if len(times) > most else "")


def _dropped(source: str, items: list[str], times: list[float], duration: float) -> str:
    """The one warning line for things of ``source`` (scene events, pattern events) at ``times``
    that come at or after the end of the run and are left out."""
    verb = "comes" if len(times) == 1 else "come"
    return (f"{source}: {_names(items)} (at {_ats(times)} s) {verb} at or after the end of the run "
            f"({duration:g} s): dropped")


def tail(mapping, stimulus: dict) -> float:
    """Seconds the run goes on after the pattern's last event: a transient, a fade-out, 50 ms."""
    return mapping.transient_s + stimulus["ramp"] + 0.05
