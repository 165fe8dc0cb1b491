"""Values as strict JSON takes them (``json.dumps(..., allow_nan=False)``): containers element by
element, every non-finite float replaced, anything else that is no JSON value as its ``str``."""

from __future__ import annotations

import math


def strict(v, nonfinite=lambda x: None):
    """``v`` with tuples as lists, keys as strings, each NaN or infinity as ``nonfinite(x)``
    (default None: JSON's null) and any other object that is no JSON value as its ``str``.

    >>> strict({"k": float("inf"), 1: (0.5, float("nan"))}), strict([float("-inf")], repr)
    ({'k': None, '1': [0.5, None]}, ['-inf'])
    """
    if isinstance(v, dict):
        return {str(k): strict(x, nonfinite) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [strict(x, nonfinite) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return nonfinite(v)
    return v if isinstance(v, (str, int, float, bool, type(None))) else str(v)
