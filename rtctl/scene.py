"""Scenes: TOML files validated into frozen objects, with ``--set`` overrides.

>>> from rtctl import scene
>>> s = scene.load("line-bimorph-5", ["timing.duration=0.5"])
>>> s.timing.duration
0.5
>>> s.actuator[0].beam.layers[0].material
'PZT-5A'

Every error is a :class:`~rtctl.errors.SceneError` whose one-line message names the file, the
key, the offending value and what is allowed.
"""

from __future__ import annotations

import copy
import difflib
import math
import re
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .errors import SceneError
from .schema import REQUIRED, SCENE, Key, Table

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib

BUNDLED_DIR = Path(__file__).with_name("scenes")
#: Largest scene file or text: scenes are kilobytes; this keeps a wrong file from being read whole.
MAX_SCENE_BYTES = 1 << 20
#: Most dots on one line of a scene: scene keys are a few levels deep (see :func:`_check_dots`).
MAX_LINE_DOTS = 256
# Names only: the values live with the physics in rtctl.plant.materials (kept light here so
# validating a scene never imports a model).
BUILTIN_MATERIALS = ("PZT-5A", "PZT-5H", "PVDF")


class Frozen(Mapping):
    """A read-only mapping with attribute access; nested tables are Frozen, lists tuples."""

    __slots__ = ("_d",)

    def __init__(self, data: Mapping[str, Any]):
        object.__setattr__(self, "_d", {k: _freeze(v) for k, v in data.items()})

    def __getattr__(self, name: str) -> Any:
        try:
            return self._d[name]
        except KeyError:
            raise AttributeError(name) from None

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("scene objects are frozen; use --set or scene.load(..., overrides)")

    def __getitem__(self, key: str) -> Any:
        return self._d[key]

    def __iter__(self):
        return iter(self._d)

    def __len__(self) -> int:
        return len(self._d)

    def __repr__(self) -> str:
        return f"Frozen({self._d!r})"

    def to_dict(self) -> dict[str, Any]:
        """A plain, JSON-friendly copy."""
        return {k: _thaw(v) for k, v in self._d.items()}


def _freeze(v: Any) -> Any:
    if isinstance(v, Mapping):
        return Frozen(v)
    if isinstance(v, (list, tuple)):
        return tuple(_freeze(x) for x in v)
    return v


def _thaw(v: Any) -> Any:
    if isinstance(v, Frozen):
        return v.to_dict()
    if isinstance(v, tuple):
        return [_thaw(x) for x in v]
    return v


class Scene(Frozen):
    """A validated scene. ``source`` is where it came from, ``overrides`` the ``--set`` list."""

    __slots__ = ("source", "overrides")

    def __init__(self, data: Mapping[str, Any], source: str, overrides: Sequence[str] = ()):
        super().__init__(data)
        object.__setattr__(self, "source", source)
        object.__setattr__(self, "overrides", tuple(overrides))

    def group(self, name: str) -> Frozen:
        """The actuator group called ``name``."""
        for a in self.actuator:
            if a.name == name:
                return a
        raise SceneError(f"{self.source}: no actuator named {name!r} (have {[a.name for a in self.actuator]})")

    @property
    def n_channels(self) -> int:
        return sum(a.grid[0] * a.grid[1] for a in self.actuator)


# ----------------------------------------------------------------------------- finding files


def bundled() -> list[str]:
    """Names of the scenes shipped with rtctl."""
    return sorted(p.stem for p in BUNDLED_DIR.glob("*.toml"))


def resolve(source: str | Path) -> Path:
    """A path as given if it exists, else a bundled scene by name (with or without .toml)."""
    p = Path(source)
    if p.is_file():
        return p
    q = BUNDLED_DIR / (p.name if p.suffix == ".toml" else p.name + ".toml")
    if q.is_file() and p.parent == Path("."):
        return q
    if p.exists():  # a directory, a FIFO, ...: there, but no file to read (a bundled name goes first)
        from .outpath import kind_of

        raise SceneError(f"{source}: is {kind_of(p)}, not a scene file; give a scene .toml file or a bundled "
                         "scene name (see `rtctl scenes`)")
    hint = difflib.get_close_matches(p.stem, bundled(), n=1)
    more = f" (did you mean {hint[0]!r}?)" if hint else f" (bundled: {', '.join(bundled())})"
    raise SceneError(f"{source}: no such scene file or bundled scene{more}")


def load(source: str | Path, overrides: Sequence[str] = ()) -> Scene:
    """Read, override and validate a scene.

    Parameters
    ----------
    source : str or Path
        A TOML file, or the name of a bundled scene (``rtctl scenes`` lists them).
    overrides : sequence of str
        ``path.to.key=VALUE`` items applied before validation (see :func:`apply_override`).
    """
    path = resolve(source)
    try:
        if path.stat().st_size > MAX_SCENE_BYTES:  # before reading: a stray multi-GB file is not read
            raise SceneError(f"{path}: {path.stat().st_size} bytes; a scene file is at most "
                             f"{MAX_SCENE_BYTES >> 20} MiB (kilobytes in practice)")
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: cannot read: {e}") from None
    data = _parse_toml(text, str(path))
    for item in overrides:
        apply_override(data, item, origin=str(path))
    return Scene(validate(data, str(path)), str(path), overrides)


def loads(text: str, overrides: Sequence[str] = (), origin: str = "<scene>") -> Scene:
    """Like :func:`load` for TOML text."""
    data = _parse_toml(text, origin)
    for item in overrides:
        apply_override(data, item, origin=origin)
    return Scene(validate(data, origin), origin, overrides)


def _parse_toml(text: str, origin: str) -> dict:
    """``tomllib.loads`` with its every failure as one line: besides malformed TOML, nesting
    deeper than the parser's recursion allows and integers longer than Python converts."""
    if len(text) > MAX_SCENE_BYTES:
        raise SceneError(f"{origin}: {len(text)} characters; a scene is at most {MAX_SCENE_BYTES >> 20} MiB "
                         "(kilobytes in practice)")
    _check_dots(text, origin)
    try:
        return tomllib.loads(text.removeprefix("\ufeff"))  # a byte-order mark (Windows editors write one)
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{origin}: not valid TOML: {e}") from None
    except RecursionError:
        raise SceneError(f"{origin}: arrays or tables nested too deeply to read (no scene key is)") from None
    except ValueError:  # int(): more than sys.get_int_max_str_digits() digits
        raise SceneError(f"{origin}: an integer literal with more than {_max_digits()} digits") from None


#: a one-line TOML string, basic or literal: the dots of a long text in one do not count
_QUOTED = re.compile(r'"(?:[^"\\]|\\.)*"|\'[^\']*\'')
#: a float literal standing alone (``1.5``, ``-2.0e-3``), not a part of a dotted key of digits
#: (``1.2.3``): the decimal points of a long array of numbers are no nesting
_FLOAT = re.compile(r"(?<![\w.])[+-]?\d[\d_]*\.\d[\d_]*(?:[eE][+-]?\d+)?(?![\w.])")


def _key_dots(text: str) -> int:
    """The dots of ``text`` outside strings and float literals: those that can nest keys."""
    return _FLOAT.sub("", _QUOTED.sub("", text)).count(".")


def _check_dots(text: str, origin: str) -> None:
    """Refuse absurdly deep dotted keys before parsing: tomllib's time grows with the square of a
    key's depth (a 20000-part key takes seconds, a 100000-part one minutes)."""
    if text.count(".") <= MAX_LINE_DOTS:
        return
    for n, line in enumerate(text.splitlines(), 1):
        if line.count(".") > MAX_LINE_DOTS and _key_dots(line) > MAX_LINE_DOTS:
            raise SceneError(f"{origin}: line {n} has more than {MAX_LINE_DOTS} dots outside strings and numbers; "
                             "no scene key is nested that deep")


def _max_digits() -> int:
    return sys.get_int_max_str_digits() if hasattr(sys, "get_int_max_str_digits") else 4300


# ----------------------------------------------------------------------------- overrides


def parse_value(text: str) -> Any:
    """A TOML literal (``1e-3``, ``[1, 2]``, ``true``, ``"x"``, ``{k = 1}``), else the bare string."""
    if text.count(".") > MAX_LINE_DOTS and _key_dots(text) > MAX_LINE_DOTS:  # see _check_dots
        return text
    try:
        doc = tomllib.loads(f"v = {text}")
    except (ValueError, RecursionError):  # malformed, an over-long integer, nested too deeply
        return text
    # "1\nb = 2" parses as two keys: the value is then the text, not the 1 before a newline
    return doc["v"] if len(doc) == 1 else text


def apply_override(data: dict, item: str, origin: str = "--set") -> None:
    """Apply one ``path.to.key=VALUE`` to the raw scene dict in place.

    Path parts walk tables by key, arrays of tables by name (``actuator.lateral``, matching the
    item's ``name``) or by index (``stimulus.tones.0``). Missing tables are created, so any key
    can be added; validation then checks it like a key from the file.
    """
    if "=" not in item:
        raise SceneError(f"--set {_show(item)}: expected path.to.key=VALUE")
    path, _, raw = item.partition("=")
    parts = [p for p in path.strip().split(".")]
    if not all(parts):
        raise SceneError(f"--set {_show(item)}: empty part in key path {_show(path)}")
    value = parse_value(raw.strip())
    node: Any = data
    for i, part in enumerate(parts[:-1]):
        here = ".".join(parts[: i + 1])
        if isinstance(node, list):
            node = node[_list_index(node, part, here, item)]
        elif isinstance(node, dict):
            if part not in node:
                node[part] = {}
            node = node[part]
        else:
            raise SceneError(f"--set {_show(item)}: {_show(here)} is a value, not a table")
    last = parts[-1]
    if isinstance(node, list):
        idx = _list_index(node, last, path, item)
        node[idx] = value
    elif isinstance(node, dict):
        node[last] = value
    else:
        raise SceneError(f"--set {_show(item)}: {_show('.'.join(parts[:-1]))} is a value, not a table")


#: an array index in a key path: ASCII digits only (str.isdigit() also takes "²", which int() refuses)
_INDEX = re.compile(r"-?[0-9]+")


def _list_index(items: list, part: str, here: str, item: str) -> int:
    if _INDEX.fullmatch(part):
        idx = int(part)
        if -len(items) <= idx < len(items):
            return idx
        raise SceneError(f"--set {_show(item)}: {_show(here)}: index {idx} out of range (have {len(items)} items)")
    names = [x.get("name") for x in items if isinstance(x, dict)]
    if part in names:
        return names.index(part)
    raise SceneError(f"--set {_show(item)}: no item named {part!r} at {_show(here)} (have {_show(names)})")


# ----------------------------------------------------------------------------- validation


def validate(data: Mapping[str, Any], origin: str) -> dict[str, Any]:
    """Check ``data`` against :data:`rtctl.schema.SCENE`; return it with defaults filled in."""
    out = _table(SCENE, data, "", origin)
    _cross_checks(out, origin)
    return out


def _fail(origin: str, path: str, value: Any, problem: str) -> SceneError:
    return SceneError(f"{origin}: {path} = {_show(value)}: {problem}")


def _show(v: Any) -> str:
    s = repr(v)
    return s if len(s) <= 60 else s[:57] + "..."


def _table(spec: Table, data: Any, path: str, origin: str, required_ok: bool = False, kind: Any = None) -> dict:
    if not isinstance(data, Mapping):
        raise _fail(origin, path or "<top>", data, "must be a table")
    unknown = [k for k in data if k not in spec.keys]
    if unknown:
        k = unknown[0]
        full = f"{path}.{k}" if path else k
        hint = difflib.get_close_matches(k, list(spec.keys), n=1)
        more = f" (did you mean {(path + '.' if path else '') + hint[0]!r}?)" if hint else (
            f" (allowed: {', '.join(spec.keys)})"
        )
        raise SceneError(f"{origin}: unknown key {_show(full)}{more}")
    out: dict[str, Any] = {}
    # an actuator item's type (its sub-tables inherit it): keys of other types must be absent
    kind = data.get("type", kind)
    for name, sub in spec.keys.items():
        full = f"{path}.{name}" if path else name
        if sub.types and kind not in sub.types:
            if name in data:
                raise _fail(origin, full, data[name], f"applies to actuator type {' | '.join(sub.types)}, "
                            f"not {kind!r}")
            continue
        if isinstance(sub, Table):
            out[name] = _subtable(sub, data.get(name), full, origin, kind)
        elif name in data:
            out[name] = _value(sub, data[name], full, origin)
        elif sub.default is REQUIRED and not required_ok:
            raise SceneError(f"{origin}: missing required key {full!r} ({sub.doc})")
        elif sub.default is not REQUIRED:
            out[name] = sub.default
    return out


def _subtable(spec: Table, data: Any, path: str, origin: str, kind: Any = None) -> Any:
    if spec.many:
        if data is None:
            if not spec.optional:
                raise SceneError(f"{origin}: missing required {path!r} ({spec.doc})")
            return []
        if not isinstance(data, list):
            raise _fail(origin, path, data, "must be an array of tables")
        if len(data) < spec.min_items:
            raise _fail(origin, path, data, f"needs at least {spec.min_items} item(s)")
        return [_table(spec, x, f"{path}.{_item_name(x, i)}", origin) for i, x in enumerate(data)]
    if spec.named:
        if data is None:
            return {}
        if not isinstance(data, Mapping):
            raise _fail(origin, path, data, "must be a table of named tables")
        return {
            n: _table(spec, t, f"{path}.{n}", origin, required_ok=n in BUILTIN_MATERIALS)
            for n, t in data.items()
        }
    if data is None:
        if not spec.optional:
            raise SceneError(f"{origin}: missing required table [{path}] ({spec.doc})")
        data = {}
    return _table(spec, data, path, origin, kind=kind)


def _item_name(x: Any, i: int) -> str:
    """How errors (and ``--set``) address item ``i`` of an array of tables: by name if it has one."""
    name = x.get("name") if isinstance(x, Mapping) else None
    ok = isinstance(name, str) and name and "." not in name and len(name) <= 60
    return name if ok else str(i)


def _value(spec: Key, v: Any, path: str, origin: str) -> Any:
    kind = spec.kind
    if kind in ("floats", "ints", "strs"):
        if not isinstance(v, list):
            what = {"floats": "numbers", "ints": "integers", "strs": "strings"}[kind]
            raise _fail(origin, path, v, f"must be a list of {what}")
        if spec.length is not None and len(v) != spec.length:
            raise _fail(origin, path, v, f"must have exactly {spec.length} items")
        if len(v) < spec.min_items or (spec.max_items is not None and len(v) > spec.max_items):
            raise _fail(origin, path, v, f"must have {spec.min_items} to {spec.max_items} items")
        one = Key(kind[:-1], unit=spec.unit, lo=spec.lo, hi=spec.hi, open_lo=spec.open_lo, choices=spec.choices)
        return [_scalar(one, x, f"{path}.{i}", origin) for i, x in enumerate(v)]
    return _scalar(spec, v, path, origin)


def _scalar(spec: Key, v: Any, path: str, origin: str) -> Any:
    kind = spec.kind
    if kind == "table":
        if not isinstance(v, Mapping):
            raise _fail(origin, path, v, "must be a table")
        return copy.deepcopy(dict(v))
    if kind == "bool":
        if not isinstance(v, bool):
            raise _fail(origin, path, v, "must be true or false")
        return v
    if kind == "str":
        if not isinstance(v, str):
            raise _fail(origin, path, v, "must be a string")
        if spec.choices and v not in spec.choices:
            raise _fail(origin, path, v, f"must be one of {', '.join(spec.choices)}")
        return v
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _fail(origin, path, v, f"must be {'an integer' if kind == 'int' else 'a number'}")
    if kind == "int":
        if isinstance(v, float):
            if not v.is_integer():
                raise _fail(origin, path, v, "must be an integer")
            v = int(v)
    else:
        v = float(v)
        if math.isnan(v):
            raise _fail(origin, path, v, "must be a number, not nan")
    lo, hi = spec.lo, spec.hi
    bad = (lo is not None and (v < lo or (spec.open_lo and v == lo))) or (hi is not None and v > hi)
    if bad:
        unit = f" {spec.unit}" if spec.unit else ""
        raise _fail(origin, path, v, f"must be in {spec.describe_range()}{unit}")
    return v


def _cross_checks(s: dict, origin: str) -> None:
    t = s["timing"]
    if t["duration"] * t["fs"] < t["block"]:
        raise _fail(origin, "timing.duration", t["duration"],
                    f"shorter than one block ({t['block']} samples at {t['fs']:g} Hz)")
    name = s["scene"]["name"]
    if not name or not name.isprintable() or "/" in name or "\\" in name or name in (".", ".."):
        # it is a path part: the default output directory out/NAME (a "/" would write elsewhere)
        raise _fail(origin, "scene.name", name, "must be non-empty and printable, without '/' or '\\' "
                    "(it names the output directory out/NAME)")
    names = [a["name"] for a in s["actuator"]]
    for i, a in enumerate(s["actuator"]):
        p = f"actuator.{a['name']}"
        if names.count(a["name"]) > 1:
            raise _fail(origin, f"actuator.{i}.name", a["name"], "names must be unique")
        if "." in a["name"] or not a["name"] or not a["name"].isprintable():  # it names channels: NAME.INDEX
            raise _fail(origin, f"actuator.{i}.name", a["name"], "must be non-empty and printable, without dots")
        if "beam" not in a:
            continue
        segs = a["beam"]["segments"]
        if abs(sum(segs) - 1.0) > 1e-9:
            raise _fail(origin, f"{p}.beam.segments", segs, f"fractions must sum to 1 (sum {sum(segs):.6g})")
        for j, layer in enumerate(a["beam"]["layers"]):
            m = layer["material"]
            if m not in BUILTIN_MATERIALS and m not in s["materials"]:
                known = ", ".join(BUILTIN_MATERIALS + tuple(s["materials"]))
                raise _fail(origin, f"{p}.beam.layers.{j}.material", m,
                            f"unknown material (known: {known}; add a [materials.{m}] table)")
        if a["support"]["type"] == "elastic" and math.isinf(a["support"]["k"]) and math.isinf(a["support"]["k_rot"]):
            raise _fail(origin, f"{p}.support.k", a["support"]["k"], "an elastic support needs a finite k or k_rot")
    nyq = t["fs"] / 2
    for i, tone in enumerate(s["stimulus"]["tones"]):
        p = f"stimulus.tones.{i}"
        group = tone["actuator"] or names[0]
        if group not in names:
            raise _fail(origin, f"{p}.actuator", group, f"no such actuator group (have {', '.join(names)})")
        tone["actuator"] = group
        grid = s["actuator"][names.index(group)]["grid"]
        if tone["channel"] >= grid[0] * grid[1]:
            raise _fail(origin, f"{p}.channel", tone["channel"],
                        f"group {group!r} has channels 0..{grid[0] * grid[1] - 1}")
        top = tone["freq"] + tone["beat"] / 2
        if top >= nyq:
            raise _fail(origin, f"{p}.freq", tone["freq"], f"tone reaches {top:g} Hz, above Nyquist ({nyq:g} Hz)")
        if tone["freq"] - tone["beat"] / 2 <= 0:
            raise _fail(origin, f"{p}.beat", tone["beat"], f"must be below 2 * freq ({2 * tone['freq']:g} Hz)")
        if tone["start"] >= t["duration"]:
            raise _fail(origin, f"{p}.start", tone["start"], f"after the end of the run ({t['duration']:g} s)")
    c = s["control"]
    if c["calibrate"] == "auto" and c["calibration"]:
        # auto measures and fits a calibration of its own, which the run would use in the file's stead
        raise _fail(origin, "control.calibrate", c["calibrate"], f"measures a calibration of its own: with "
                    f"control.calibration = {c['calibration']!r} one of the two goes unused; give one of them")
    _play_checks(s, names, origin)
    if s["events"]:
        event_states(s, origin)


def _play_checks(s: dict, names: list, origin: str) -> None:
    """``stimulus.play`` names signals, groups and spatial items that exist (the signals
    themselves compile when the stimulus is built)."""
    from .spatial import check

    st = s["stimulus"]
    signals = [x["name"] for x in st["signals"]]
    spatial = [x["name"] for x in st["spatial"]]
    for i, sp in enumerate(st["spatial"]):
        if sp["actuator"] and sp["actuator"] not in names:
            raise _fail(origin, f"stimulus.spatial.{i}.actuator", sp["actuator"],
                        f"no such actuator group (have {', '.join(names)})")
        bad = check(sp, f"stimulus.spatial.{i}")
        if bad:
            raise SceneError(f"{origin}: {bad}")
    for i, pl in enumerate(st["play"]):
        p = f"stimulus.play.{i}"
        if st["kind"] != "tones":
            raise _fail(origin, f"{p}.signal", pl["signal"], f"signals play with stimulus.kind = 'tones', not "
                        f"{st['kind']!r}")
        if pl["signal"] not in signals:
            raise _fail(origin, f"{p}.signal", pl["signal"],
                        f"no such stimulus.signals item (have {', '.join(signals) or 'none'})")
        if pl["spatial"] and pl["spatial"] not in spatial:
            raise _fail(origin, f"{p}.spatial", pl["spatial"],
                        f"no such stimulus.spatial item (have {', '.join(spatial) or 'none'})")
        if pl["actuator"] and pl["actuator"] not in names:
            raise _fail(origin, f"{p}.actuator", pl["actuator"], f"no such actuator group (have {', '.join(names)})")
        if pl["start"] >= s["timing"]["duration"]:  # (as a tone's: it would play nothing, silently)
            raise _fail(origin, f"{p}.start", pl["start"], f"after the end of the run ({s['timing']['duration']:g} s)")
        if not pl["spatial"]:
            grid = s["actuator"][names.index(pl["actuator"] or names[0])]["grid"]
            if pl["channel"] >= grid[0] * grid[1]:
                raise _fail(origin, f"{p}.channel", pl["channel"], f"the group has channels 0..{grid[0] * grid[1] - 1}")


# ----------------------------------------------------------------------------- events

#: Scene keys an event may set during a run: ``N`` is an index into ``stimulus.tones``, ``NAME``
#: an actuator group (by name or index). Everything else is built once, before the first block.
EVENT_KEYS = ("finger.preload", "finger.contact", "finger.subject", "stimulus.tones.N.target_um",
              "actuator.NAME.em.preload", "actuator.NAME.dot.preload", "actuator.NAME.solenoid.preload")
_EVENT_KEY = re.compile(r"finger\.(preload|contact|subject)|stimulus\.tones\.\d+\.target_um"
                        r"|actuator\.[^.]+\.(em|dot|solenoid)\.preload")


def event_keys(table: Mapping, prefix: str = "", origin: str = "<scene>", where: str = "set") -> dict[str, Any]:
    """An event's ``set`` table as ``dotted.key -> value``: quoted keys (``"finger.preload" = 1``)
    and nested tables (``finger.preload = 1``, ``finger = {preload = 1}``) read the same. A key
    given twice in two spellings is refused (``where``: the table's place, for the message):
    TOML refuses a repeated key, but not a quoted one beside its nested spelling, and one of the
    two values would be dropped without a word."""
    out: dict[str, Any] = {}
    for k, v in table.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        for sub, value in (event_keys(v, key, origin, where).items() if isinstance(v, Mapping) else ((key, v),)):
            if sub in out:
                raise _fail(origin, f"{where}.{sub}", value, f"set twice in one event (also {_show(out[sub])})")
            out[sub] = value
    return out


def event_states(data: Mapping[str, Any], origin: str) -> list[dict[str, Any]]:
    """The validated scene after each of ``data["events"]``, in order (without events).

    Each event's keys are applied on top of the scene as the previous event left it, then the
    whole scene is validated as ``--set`` values are: a bad value stops with the same one-line
    message, prefixed with ``events.I``. A key outside :data:`EVENT_KEYS`, events out of time
    order, one at or after the end of the run, or an empty ``set`` are refused in one line.

    Parameters
    ----------
    data : mapping
        A validated scene (:func:`validate`'s result, or ``Scene.to_dict()``).
    origin : str
        Where the scene came from, for messages.
    """
    base = _plain(data)
    events = base.pop("events", None) or []
    base["events"] = []
    duration = base["timing"]["duration"]
    states, prev = [], None
    for i, ev in enumerate(events):
        where = f"events.{i}"
        at = ev["at"]
        if prev is not None and at < prev:
            raise _fail(origin, f"{where}.at", at, f"events must be in time order (events.{i - 1} is at {prev:g} s)")
        if at >= duration:
            raise _fail(origin, f"{where}.at", at, f"after the end of the run ({duration:g} s)")
        prev = at
        sets = event_keys(ev["set"], origin=origin, where=f"{where}.set")
        if not sets:
            raise _fail(origin, f"{where}.set", ev["set"], "an event sets at least one key")
        for key, value in sets.items():
            if not _EVENT_KEY.fullmatch(key):
                concrete = [k.replace("N", "0").replace("NAME", a["name"]) for k in EVENT_KEYS
                            for a in (base["actuator"] if "NAME" in k else base["actuator"][:1])]
                hint = difflib.get_close_matches(key, concrete, n=1, cutoff=0.8)
                more = f"; did you mean {hint[0]!r}?" if hint else ""
                raise SceneError(f"{origin}: {where}.set: {key!r} cannot change during a run (allowed: "
                                 f"{', '.join(EVENT_KEYS)}){more}")
            _event_set(base, key, value, f"{origin}: {where}.set")
        base = _plain(validate(base, f"{origin}: {where}"))
        states.append(_plain(base))
    return states


def _plain(v: Any) -> Any:
    """A deep copy as TOML would load it (tables dicts, arrays lists: defaults are tuples), so
    that a validated scene validates again unchanged."""
    if isinstance(v, Mapping):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def _event_set(data: dict, key: str, value: Any, where: str) -> None:
    """``data[key] = value`` along the dotted path (arrays of tables by name or index)."""
    parts = key.split(".")
    node: Any = data
    for i, part in enumerate(parts[:-1]):
        here = ".".join(parts[: i + 1])
        if isinstance(node, list):
            names = [x.get("name") for x in node if isinstance(x, dict)]
            if part in names:
                node = node[names.index(part)]
            elif _INDEX.fullmatch(part) and 0 <= int(part) < len(node):
                node = node[int(part)]
            elif _INDEX.fullmatch(part):
                raise SceneError(f"{where}: {key!r}: {here}: index {int(part)} out of range (have {len(node)} items)")
            else:
                raise SceneError(f"{where}: {key!r}: no item named {part!r} at {_show(here)} (have {_show(names)})")
        else:
            node = node.setdefault(part, {})
    node[parts[-1]] = value
