"""The loop's whole state, saved between blocks and put back: :class:`Checkpoint`.

What a block does depends on nothing but the arrays the block function reaches and a few values
the engine's thread keeps between blocks. So the state is, by construction:

* every array a stage takes (the composed function's table): oscillator phases, frequencies and
  pending ramps; pulse-train positions and levels; the limiter's memory (last output, slew,
  temperature, running means, fade, counters); observer lock-in accumulators, delay lines and
  rings; controller integrators and targets; the parameter queue's ring and indices;
* the simulated device's arrays (its groups' kernel arguments and buffers): plant and finger
  states, Maxwell branches, contact modes, switched loads, the sensing noise generators'
  positions, the currents of the block in flight;
* the rig's own buffers (drive, readings, estimates, trace targets);
* between blocks, outside any array: the blocks run so far, the rendered stimulus' position
  (frame shown, path update), and nothing else (:meth:`Stimulus.position`).

An array is saved as the stages see it (a view saved as that view: an aligned buffer's padding,
which no kernel reaches, is not state, and its offset differs between two rigs), each view once.
Constant parameters are saved too: an event may have rewritten one (a pin's preload), and a
saved constant is put back unchanged. A new stage's state is covered without touching this
module, since everything it keeps must be one of its arguments.

A checkpoint of a hardware backend's rig holds the rig's side only: the device's state is the
device's.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


def _add(x, out: dict) -> None:
    """Add the arrays in ``x`` (an array, or a tuple/list of them) to ``out``, each view once."""
    if isinstance(x, (tuple, list)):
        for y in x:
            _add(y, out)
        return
    if not isinstance(x, np.ndarray) or not x.flags.writeable:
        return  # a read-only array is a constant no block can change
    key = (x.__array_interface__["data"][0], x.shape, x.strides, x.dtype.str)
    out.setdefault(key, x)


def state_arrays(rig) -> list:
    """Every writable array the rig's loop reaches, each view once, in a fixed order."""
    found: dict = {}
    for s in rig.stages:
        for a in s.args.values():
            _add(a, found)
    _add(rig.queue.targets, found)  # the parameter queue reaches them by address
    dev = rig.device
    if hasattr(dev, "state_arrays"):
        _add(dev.state_arrays(), found)
    _add((rig.out, rig.sensed, rig.estimated, rig.estimated_amp, rig.targets_um), found)
    if rig.truth is not None:
        _add(rig.truth, found)
    if rig.render is not None and getattr(rig.render, "pending", None) is not None:
        _add(rig.render.pending, found)
    return list(found.values())


@dataclass
class Checkpoint:
    """A rig's whole state between two blocks (:meth:`rtctl.engine.rig.Rig.checkpoint`).

    Attributes
    ----------
    block : int
        Blocks run so far: the next block to schedule and run is ``block``.
    arrays : list of ndarray
        Copies of :func:`state_arrays`, in that order.
    position : tuple
        The stimulus' between-block position (:meth:`rtctl.stimulus.Stimulus.position`).
    layout : tuple
        ``(shape, dtype)`` per array: a checkpoint goes back only into a rig of the same layout.
    scene : str
        A digest of the scene the rig was built from (overrides applied): a checkpoint goes back
        only into a rig of the same scene, or its arrays would land in another run's meaning.
    """

    block: int
    arrays: list
    position: tuple
    layout: tuple = field(default=())
    scene: str = ""

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in self.arrays))

    def save(self, path) -> Path:
        """Write the checkpoint to ``path`` (numpy ``.npz``, uncompressed; returns the path)."""
        path = Path(path)
        head = {"block": int(self.block), "position": list(self.position), "scene": self.scene}
        with open(path, "wb") as f:  # an open file: numpy appends no ".npz" to the name
            np.savez(f, head=np.array(json.dumps(head)), **{f"a{i}": a for i, a in enumerate(self.arrays)})
        return path

    @classmethod
    def load(cls, path) -> Checkpoint:
        """Read a checkpoint :meth:`save` wrote.

        Raises
        ------
        ValueError
            ``path`` is not a checkpoint (one line naming the file and what is wrong).
        """
        try:
            with np.load(path, allow_pickle=False) as z:
                head = json.loads(str(z["head"]))
                arrays = [z[f"a{i}"] for i in range(len(z.files) - 1)]
            cp = cls(int(head["block"]), arrays, tuple(head["position"]), layout_of(arrays), str(head["scene"]))
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise ValueError(f"{path}: not an rtctl checkpoint ({e})") from None
        return cp


def scene_digest(scene) -> str:
    """The digest :attr:`Checkpoint.scene` compares (sha256 of the scene's JSON, sorted keys)."""
    return hashlib.sha256(json.dumps(scene.to_dict(), sort_keys=True, default=str).encode()).hexdigest()[:16]


def layout_of(arrays) -> tuple:
    return tuple((a.shape, a.dtype.str) for a in arrays)


def save(rig, into: Checkpoint | None = None) -> Checkpoint:
    """The rig's state now (between blocks); into ``into``'s arrays when given (no allocation)."""
    arrays = rig.state_arrays
    if into is None:
        return Checkpoint(rig.blocks, [a.copy() for a in arrays], rig.stimulus.position(), layout_of(arrays),
                          rig.scene_digest)
    _check(rig, into)
    for dst, src in zip(into.arrays, arrays):
        np.copyto(dst, src)
    into.block, into.position = rig.blocks, rig.stimulus.position()
    return into


def load(rig, cp: Checkpoint) -> None:
    """Put ``cp`` back into ``rig``'s own arrays (nothing rebound or allocated)."""
    _check(rig, cp)
    for dst, src in zip(rig.state_arrays, cp.arrays):
        np.copyto(dst, src)
    rig.blocks = int(cp.block)
    rig.stimulus.seek(cp.position)


def _check(rig, cp: Checkpoint) -> None:
    if cp.scene != rig.scene_digest:
        raise ValueError(f"a checkpoint of another scene (digest {cp.scene}, this rig's {rig.scene_digest}): "
                         "restore it into a rig built from the same scene and overrides")
    if cp.layout != layout_of(rig.state_arrays):
        raise ValueError(f"a checkpoint of another rig layout ({len(cp.layout)} state arrays, this rig "
                         f"has {len(rig.state_arrays)}, or their shapes differ): restore it into a rig built "
                         "from the same scene and overrides")
