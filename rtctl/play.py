"""``rtctl play``: a haptic pattern file turned into a scene's stimulus."""

from __future__ import annotations

from . import patterns
from . import scene as sc
from .errors import SceneError


def pattern_scene(pattern: str, source: str, overrides=(), duration: float | None = None):
    """The scene ``source`` (with ``overrides``) playing ``pattern`` instead of its own stimulus,
    and the warnings (the pattern's ignored keys and clamped values, dropped events). The run
    lasts the scene's duration, or longer to hold the whole pattern, or ``duration`` when given:
    the scene's events at or after the end of that run are dropped, with one warning saying so
    (``rtctl run`` refuses them instead, since there the user chose both)."""
    pat = patterns.load(pattern)
    s = sc.load(source, list(overrides))
    data = s.to_dict()
    st = data["stimulus"]
    if st["kind"] != "tones":
        raise SceneError(f"{s.source}: stimulus.kind = {st['kind']!r}: a pattern plays on a tones scene")
    m = s.stimulus.pattern
    group = s.group(m.actuator or s.actuator[0].name)
    signals, play = patterns.to_stimulus(pat, m, s.control.mode == "closed", s.timing.fs, group.max_voltage,
                                         s.control.margin_db)
    t = data["timing"]
    t["duration"] = duration if duration is not None else max(t["duration"], pat.end + tail(m, st))
    warnings = list(pat.warnings)
    late = [i for i, ev in enumerate(data["events"]) if ev["at"] >= t["duration"]]
    if late:
        at = ", ".join(f"{data['events'][i]['at']:g}" for i in late)
        which = f"events.{late[0]}" if len(late) == 1 else f"events.{late[0]}..{late[-1]}"
        warnings.append(f"{s.source}: {which} (at {at} s) come at or after the end of the run "
                        f"({t['duration']:g} s): dropped")
        data["events"] = data["events"][:late[0]]  # in time order: the late ones are the last
    # the scene's own tones give way to the pattern, and so do events that re-target them
    tied = [i for i, ev in enumerate(data["events"]) if any(k.startswith("stimulus.tones") for k in
                                                            sc.event_keys(ev["set"]))]
    if tied:
        raise SceneError(f"{s.source}: events.{tied[0]} changes a tone of the scene, which the pattern replaces")
    st.update(tones=[], signals=signals, play=play)
    return sc.Scene(sc.validate(data, s.source), s.source, s.overrides), warnings


def tail(mapping, stimulus: dict) -> float:
    """Seconds the run goes on after the pattern's last event: a transient, a fade-out, 50 ms."""
    return mapping.transient_s + stimulus["ramp"] + 0.05
