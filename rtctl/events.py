"""Scene events: what changes during a run, and at which block.

A scene's ``[[events]]`` (see ``docs/scene.md``) each set a few scene keys at a time ``at``:

```toml
[[events]]
at = 1.0
set = { "finger.preload" = 1.96 }      # the finger presses harder
[[events]]
at = 1.5
set = { "finger.contact" = false }     # lifts off
[[events]]
at = 1.8
set = { "finger.contact" = true }      # comes back
```

:func:`schedule` turns them into :class:`Event` s: the block each takes effect in and the scene as
it stands after it (validated exactly as a ``--set`` would be: :func:`rtctl.scene.event_states`).
Nothing here knows the engine or a device: the simulated device says what each event writes
(``SimDevice.event_posts``), the engine posts it through its parameter queue.

**Quantization.** An event takes effect at the start of block ``floor(at * fs / block)``, the
block that holds its time: up to one block (``block / fs``, 0.67 ms at 48 kHz and 32 samples)
late, never early. A time within 1e-9 (relative) below a block boundary counts as that boundary,
so ``at = 0.7`` is block 1050 at 48 kHz and 32 samples whatever its binary rounding. Several
events in one block all take effect there, in order: the last one's values hold.

What the finger keys mean for each plant:

* ``finger.contact``: the finger's Maxwell load is on the tips or not (bimorph groups switch
  load; see :mod:`rtctl.plant.switching` for the state carried across).
* ``finger.preload`` picks, with ``finger.subject`` set, the subject's Maxwell set measured
  nearest that preload (:func:`rtctl.models.finger_params`): a different set is a different load.
  Without ``finger.subject`` every preload uses the same ``finger.lateral``/``finger.normal``
  table, so a preload change alone changes nothing for a bimorph (the linear load has no static
  force in it); it moves the static finger force a PVDF plate reports. The pins' contact force
  is their own ``actuator.NAME.em|dot|solenoid.preload`` (per pin), which events may set too.
* ``stimulus.tones.N.target_um``: a closed-loop amplitude target (the engine's controllers).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from .scene import Scene, event_keys, event_states

__all__ = ["Event", "block_of", "schedule"]

#: A time this close (relative) below a block boundary is that boundary (binary rounding of ``at``).
_SNAP = 1e-9


@dataclass(frozen=True)
class Event:
    """One scene event, resolved.

    Attributes
    ----------
    at : float
        Time from the scene, s.
    block : int
        The block it takes effect at the start of (:func:`block_of`).
    sets : dict
        The keys it sets (dotted, e.g. ``"finger.preload"``) and their validated values.
    scene_after : Scene
        The whole scene after this event and every earlier one (validated; no events of its own).
    index : int
        Position in the scene's ``events``.
    """

    at: float
    block: int
    sets: dict
    scene_after: Scene
    index: int


def block_of(at: float, fs: float, block: int) -> int:
    """``floor(at * fs / block)``, a time within 1e-9 below a boundary counted as on it."""
    x = float(at) * float(fs) / int(block)
    return int(math.floor(x + _SNAP * max(1.0, x)))


def duration_blocks(duration: float, fs: float, block: int) -> int:
    """Blocks a run of ``duration`` seconds lasts: ``ceil(duration * fs / block)``, at least 1, a
    product within 1e-9 above a whole number of blocks counted as on it (0.07 s at 48 kHz, block
    32, is 105.00000000000001 blocks in floating point: a 106th block would play past the end of
    every signal sampled to the duration)."""
    x = float(duration) * float(fs) / int(block)
    return max(1, int(math.ceil(x - _SNAP * max(1.0, x))))


def schedule(scene: Scene) -> list[Event]:
    """The scene's events in time order, each with its block and the scene after it.

    Raises
    ------
    SceneError
        As :func:`rtctl.scene.event_states` (a key events may not set, a bad value, events out of
        order or past the end of the run), or a ``finger.subject`` an event selects that has no
        set for a direction the scene's groups use.
    """
    if not scene.events:
        return []
    from .errors import SceneError
    from .models import finger_params

    states = event_states(scene.to_dict(), scene.source)
    fs, blk = scene.timing.fs, scene.timing.block
    out = []
    for i, (ev, data) in enumerate(zip(scene.events, states)):
        after = Scene(data, scene.source, scene.overrides)
        if after.finger.contact:
            for direction in sorted({g.direction for g in after.actuator}):
                try:
                    finger_params(after, direction)
                except SceneError as e:
                    msg = str(e).removeprefix(f"{scene.source}: ")
                    raise SceneError(f"{scene.source}: events.{i}: {msg}") from None
        sets = {k: _get(after, k) for k in event_keys(ev.set)}
        out.append(Event(float(ev.at), block_of(ev.at, fs, blk), sets, after, i))
    return out


def _get(scene: Scene, key: str) -> Any:
    """The value at a dotted key of a validated scene (arrays of tables by name or index)."""
    node: Any = scene
    for part in key.split("."):
        if isinstance(node, tuple):
            names = [x.get("name") for x in node]
            node = node[names.index(part)] if part in names else node[int(part)]
        else:
            node = node[part]
    return node
