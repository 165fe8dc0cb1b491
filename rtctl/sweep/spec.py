"""``--vary KEY=SPEC``: the values of one scene key, and the cartesian product of several.

SPEC is ``a:b:n`` (n values from a to b, evenly spaced), ``a:b:n:log`` (n values, evenly spaced
in log) or a list ``[x, y, z]`` (TOML literals; a bare word that is not one is a string, so
``[PZT-5A, PZT-5H]`` needs no quotes). ``K1,K2=SPEC`` gives every listed key the same value at
each point (both layers of a bimorph: ``actuator.lateral.beam.layers.0.thickness,
actuator.lateral.beam.layers.1.thickness=0.1e-3:0.3e-3:5``).

>>> parse("actuator.lateral.beam.length=10e-3:20e-3:3").values
(0.01, 0.015, 0.02)
>>> parse("timing.block=[16, 32]").values
(16, 32)
>>> [p.overrides for p in product([parse("a.b=1:2:2"), parse("c=[x, y]")])][:2]
[('a.b=1', 'c="x"'), ('a.b=1', 'c="y"')]
"""

from __future__ import annotations

import itertools
import json
import math
import re
from dataclasses import dataclass

from ..errors import RtctlError
from ..scene import parse_value

#: More points than this is a typo (a missing colon, an extra zero), not a design question.
MAX_POINTS = 1_000_000


@dataclass(frozen=True)
class Vary:
    """One ``--vary``: the keys it sets, its values in order, and how they were spaced."""

    keys: tuple[str, ...]
    values: tuple
    log: bool
    text: str

    @property
    def name(self) -> str:
        """The table column of this ``--vary``: its key, or its keys joined by commas."""
        return ",".join(self.keys)


    @property
    def short(self) -> str:
        return short(self.name)


def short(name: str) -> str:
    """A column of varied keys as a label: its last two parts (``beam.length``; three with an
    index: ``layers.0.thickness``), and for keys varied together the first one and how many
    more (``layers.0.thickness+1``)."""
    first, *more = name.split(",")
    parts = first.split(".")
    head = ".".join(parts[-3:] if len(parts) > 2 and parts[-2].isdigit() else parts[-2:])
    return head + (f"+{len(more)}" if more else "")


@dataclass(frozen=True)
class Point:
    """One point of a sweep: its place in the product, the value of each ``--vary`` (in
    ``--vary`` order), and the ``--set`` strings that make it."""

    index: int
    values: tuple
    overrides: tuple[str, ...]


def parse(text: str) -> Vary:
    """One ``KEY=SPEC`` (see the module docstring); a bad one raises RtctlError naming it."""
    where = f"--vary {_short(text)}"
    key, eq, spec = text.partition("=")
    keys = tuple(k.strip() for k in key.split(","))
    if not eq or not all(keys) or not all(p for k in keys for p in k.split(".")):
        raise RtctlError(f"{where}: expected KEY=SPEC (e.g. actuator.lateral.beam.length=10e-3:20e-3:6)")
    spec = spec.strip()
    if spec.startswith("["):
        values, log = _list(spec, where), False
    elif ":" in spec:
        values, log = _range(spec, where)
    else:
        raise RtctlError(f"{where}: SPEC must be a:b:n, a:b:n:log or a list [x, y, ...], got {_short(spec)}")
    if len(set(keys)) != len(keys):
        raise RtctlError(f"{where}: a key is listed twice")
    return Vary(keys, tuple(values), log, text)


def _list(spec: str, where: str) -> list:
    if not spec.endswith("]"):
        raise RtctlError(f"{where}: a list SPEC ends with ']', got {_short(spec)}")
    whole = parse_value(spec)
    if isinstance(whole, list):  # a TOML array: numbers, quoted strings, nested lists
        items = whole
    else:  # bare words: split on commas, each item a TOML literal or a string
        items = [parse_value(x.strip()) for x in spec[1:-1].split(",")]
        if any(x == "" for x in items):
            raise RtctlError(f"{where}: empty item in the list {_short(spec)}")
    if not items:
        raise RtctlError(f"{where}: the list is empty")
    return items


def _range(spec: str, where: str) -> tuple[list, bool]:
    parts = [p.strip() for p in spec.split(":")]
    log = len(parts) == 4 and parts[3] == "log"
    if len(parts) not in (3, 4) or (len(parts) == 4 and not log):
        raise RtctlError(f"{where}: a range SPEC is a:b:n or a:b:n:log, got {_short(spec)}")
    try:
        a, b = float(parts[0]), float(parts[1])
        n = int(parts[2])
    except ValueError:
        raise RtctlError(f"{where}: in a:b:n, a and b must be numbers and n a whole number, "
                         f"got {_short(spec)}") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise RtctlError(f"{where}: a and b must be finite, got {_short(spec)}")
    if n < 1 or (n == 1 and a != b):
        raise RtctlError(f"{where}: n must be >= 2 (or 1 with a = b), got {n}")
    if n > MAX_POINTS:  # before spacing them: 0:1:10000000000 would fill memory for minutes
        raise RtctlError(f"{where}: n = {n} values, more than {MAX_POINTS}; narrow the range")
    if log and not (a > 0 and b > 0):
        raise RtctlError(f"{where}: a log range needs a > 0 and b > 0, got {_short(spec)}")
    if n == 1:
        raw = [a]
    elif log:
        la, lb = math.log(a), math.log(b)
        raw = [math.exp(la + (lb - la) * i / (n - 1)) for i in range(n)]
    else:
        raw = [a + (b - a) * i / (n - 1) for i in range(n)]
    # 12 significant digits: drops the last-bit noise of the spacing (0.30000000000000004), so a
    # value reads as typed in the table and names the same point when a sweep is resumed
    values = [float(f"{x:.12g}") for x in raw]
    values[0], values[-1] = a, b
    ints = all(p.lstrip("+-").isdigit() for p in parts[:2]) and all(v.is_integer() for v in values)
    return ([int(v) for v in values] if ints else values), log


def toml_literal(v) -> str:
    """``v`` as a TOML literal, the VALUE of a ``--set`` string that reads back as ``v``."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        return ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string: JSON's escapes are TOML's
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_literal(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {toml_literal(x)}" for k, x in v.items()) + "}"
    raise RtctlError(f"cannot write {_short(v)} as a scene value")


def canonical_key(data, key: str) -> str:
    """``key`` with each array part as its index from 0 in the raw scene ``data`` (an item's name
    or a negative index as ``--set`` reads them), so two spellings of one key compare equal:
    ``actuator.lateral.beam.length`` and ``actuator.-1.beam.length`` are ``actuator.0.beam.length``
    on a scene of one group. Parts it cannot walk are kept as typed."""
    parts, node = key.split("."), data
    for i, part in enumerate(parts):
        if isinstance(node, list):
            names = [x.get("name") if isinstance(x, dict) else None for x in node]
            if re.fullmatch(r"-?[0-9]+", part) and -len(node) <= int(part) < len(node):
                idx = int(part) % len(node)
            elif part in names:
                idx = names.index(part)
            else:
                break
            parts[i], node = str(idx), node[idx]
        elif isinstance(node, dict) and part in node:
            node = node[part]
        else:
            break
    return ".".join(parts)


def product(varies: list[Vary], data=None) -> list[Point]:
    """Every combination of the ``--vary`` values, the first ``--vary`` changing slowest. With the
    raw scene ``data``, keys are compared as :func:`canonical_key` spells them."""
    seen: dict[str, str] = {}
    for v in varies:
        for k in v.keys:
            # a key varied twice (under two spellings too) would be set by the later --vary at every
            # point while the table's column of the earlier one named values never computed
            c = k if data is None else canonical_key(data, k)
            if c in seen:
                raise RtctlError(f"--vary {_short(v.text)}: {k} is already varied by --vary {_short(seen[c])}")
            seen[c] = v.text
    n = math.prod(len(v.values) for v in varies)
    if n > MAX_POINTS:
        sizes = " x ".join(str(len(v.values)) for v in varies)
        raise RtctlError(f"{sizes} = {n} points: more than {MAX_POINTS}; narrow a --vary")
    out = []
    for i, combo in enumerate(itertools.product(*(v.values for v in varies))):
        sets = tuple(f"{k}={toml_literal(x)}" for v, x in zip(varies, combo) for k in v.keys)
        out.append(Point(i, combo, sets))
    return out


def _short(v, n: int = 80) -> str:
    """``repr(v)`` cut to ``n`` characters: a message quotes what was typed, not 10 kB of it."""
    r = repr(v)
    return r if len(r) <= n else r[: n - 3] + "..."
