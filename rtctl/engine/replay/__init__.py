"""``rtctl replay``: what a recorded trace says, checked against the simulation.

Three modes (:mod:`rtctl.engine.replay.cli`):

* ``resim`` (:mod:`.resim`): re-run the recorded scene, overrides and seed on the simulated rig
  and compare the traces record by record: bitwise where the code, libraries and machine match.
* ``plant`` (:mod:`.plant`): feed the recorded drive (any backend's) into the simulated plant of
  the scene's *model* (no simulated device's mismatch) and compare its sensed currents with the recorded
  ones: where the model and the device differ.
* ``observer`` (:mod:`.observer`): run the recorded drive and sensed currents through the scene's
  observer and controller offline, their estimates and commands beside the recorded ones.

Each rebuilds the scene from the trace's meta (:func:`scene_of`): the validated scene as it ran,
so a scene file edited since does not change what is replayed.
"""

from __future__ import annotations

import copy

from ...trace import TraceError


def scene_of(reader, overrides=(), backend: str | None = None, model_only: bool = False, latency: bool = False,
             quiet: bool = False):
    """The scene a trace was recorded with, as a :class:`rtctl.scene.Scene`, with ``overrides``
    (``--set`` items) on top; ``backend`` replaces ``io.backend``; ``model_only`` removes the
    simulated device's mismatch table (the scene's model, not a device's secret);
    ``latency`` fixes ``io.latency_blocks`` at the recorded backend's latency; ``quiet`` sets
    every actuator's ``sense.noise`` to 0 (the model's currents without a sensor's noise)."""
    from ... import scene as scenes

    meta = reader.meta
    data = meta.get("scene")
    if not isinstance(data, dict):
        raise TraceError(f"{reader.path}: the trace records no scene (written by "
                         f"{meta.get('source', 'an earlier rtctl')}): nothing to replay")
    data = copy.deepcopy(data)
    io = data.setdefault("io", {})
    if backend is not None:
        io["backend"] = backend
    if model_only:
        io.pop("mismatch", None)
    if latency and meta.get("latency_blocks"):
        io["latency_blocks"] = int(meta["latency_blocks"])
    if quiet:
        for act in data.get("actuator", []):
            act.setdefault("sense", {})["noise"] = 0.0
    origin = f"{reader.path} (recorded scene {meta.get('scene_name', '?')})"
    for item in overrides:
        scenes.apply_override(data, item)
    return scenes.Scene(scenes.validate(data, origin), meta.get("source", origin), tuple(meta.get("overrides", ()))
                        + tuple(overrides))
