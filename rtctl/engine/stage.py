"""A stage of the block function: one module-level numba kernel, its named arguments, its reset.

The rig is an ordered list of stages; :func:`rtctl.engine.compose.compose` turns the list into
one compiled block function. Adding a stage (a controller, say) means writing its kernel in the
room it belongs to (``rtctl/control``, knowing no scene) and appending one ``Stage`` where the
rig is built: nothing else changes, and a scene that does not need the stage neither imports nor
compiles its kernel. docs/engine.md walks through the observer stage as the worked example.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any


@dataclass
class Stage:
    """One step of the block function.

    Attributes
    ----------
    name : str
        What the stage is, for docs, errors and timing (``"limiter"``, ``"observer lateral"``).
    kernel : numba dispatcher
        A module-level ``@kernel`` (``rtctl._numba.kernel``), importable by module and name: the
        composed function imports it so numba can cache the composition. It must not allocate,
        raise or take the GIL.
    args : dict
        Its arguments, in call order: preallocated C-contiguous arrays (they are reached by
        address: never rebind or resize them), tuples of arrays of one dtype and rank, and
        int/float/bool constants.
    status : bool or numba dispatcher or None
        ``True``: the kernel returns rtctl status bits (:mod:`rtctl.safety`), ORed into the
        block's; a kernel: maps the kernel's result to status bits; ``None``: the result is
        ignored (kernels that return nothing).
    reset : callable, optional
        Back to the state before the first block (called between runs and after compiling).
    """

    name: str
    kernel: Any
    args: dict
    status: Any = True
    reset: Callable[[], None] | None = None
    meta: dict = field(default_factory=dict)

    def call(self) -> int:
        """Run the stage from Python (the uncomposed path and the tests); status bits."""
        r = self.kernel(*self.args.values())
        if self.status is None:
            return 0
        if self.status is True:
            return int(r)
        return int(self.status(r))
