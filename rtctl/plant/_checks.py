"""Argument checks shared by the plant models (one wording for every model's errors)."""

import math

from rtctl.errors import ModelError


def positive(owner: str, name: str, value, zero_ok: bool = False) -> float:
    """``value`` as a float, or a ModelError naming ``owner``'s parameter if it is not finite
    and > 0 (``>= 0`` with ``zero_ok``)."""
    v = float(value)
    if not (math.isfinite(v) and (v >= 0.0 if zero_ok else v > 0.0)):
        raise ModelError(f"{owner} {name} must be finite and {'>=' if zero_ok else '>'} 0, got {value!r}")
    return v
