"""Fuzzing the haptic pattern readers (rtctl.patterns.load, ``rtctl play``): a valid .ahap and a
valid .haptic with values replaced by hostile JSON (huge integers, NaN, deep nesting, wrong
types), keys dropped, and random bytes. Each reads or is one :class:`~rtctl.errors.PatternError`
line naming the file."""

import json

from fuzzing import clean_or_clear, fuzz
from hypothesis import given
from hypothesis import strategies as st

from rtctl import patterns
from rtctl.errors import PatternError

AHAP = {"Version": 1.0, "Pattern": [
    {"Event": {"Time": 0.1, "EventType": "HapticTransient",
               "EventParameters": [{"ParameterID": "HapticIntensity", "ParameterValue": 0.8}]}},
    {"Event": {"Time": 0.2, "EventType": "HapticContinuous", "EventDuration": 0.5,
               "EventParameters": [{"ParameterID": "HapticSharpness", "ParameterValue": 0.4}]}},
    {"ParameterCurve": {"ParameterID": "HapticIntensityControl", "Time": 0.2,
                        "ParameterCurveControlPoints": [{"Time": 0.0, "ParameterValue": 0.2},
                                                        {"Time": 0.3, "ParameterValue": 1.0}]}},
    {"Parameter": {"ParameterID": "HapticSharpnessControl", "Time": 0.4, "ParameterValue": 0.1}}]}
HAPTIC = {"version": {"major": 1, "minor": 0}, "signals": {"continuous": {"envelopes": {
    "amplitude": [{"time": 0.0, "amplitude": 0.1},
                  {"time": 0.3, "amplitude": 0.9, "emphasis": {"amplitude": 1.0, "frequency": 0.7}},
                  {"time": 0.6, "amplitude": 0.0}],
    "frequency": [{"time": 0.0, "frequency": 0.2}, {"time": 0.6, "frequency": 0.8}]}}}}

hostile = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=10)
    | st.sampled_from([10**400, -(10**400), "x" * 5000, "HapticIntensity", "HapticIntensityControl"]),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=8,
)


def _places(doc, path=()):
    """Every key and list index path in ``doc``."""
    out = [path] if path else []
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    for k, v in items:
        out += _places(v, (*path, k))
    return out


def _edit(doc, edits):
    doc = json.loads(json.dumps(doc))
    for place, drop, value in edits:
        node = doc
        for k in place[:-1]:
            ok = isinstance(node, dict) and k in node or isinstance(node, list) and isinstance(k, int) and k < len(node)
            node = node[k] if ok else None
        if isinstance(node, dict) or isinstance(node, list) and isinstance(place[-1], int) and place[-1] < len(node):
            if drop:
                node.pop(place[-1]) if isinstance(node, list) else node.pop(place[-1], None)
            else:
                node[place[-1]] = value
    return doc


def _read(tmp_path_factory, name, text):
    path = tmp_path_factory.mktemp("pat") / name
    path.write_text(text) if isinstance(text, str) else path.write_bytes(text)
    r = clean_or_clear(patterns.load, path, errors=PatternError, names=[str(path)])
    assert isinstance(r, (patterns.Pattern, PatternError))
    return r


@fuzz(200)
@given(st.lists(st.tuples(st.sampled_from(_places(AHAP)), st.booleans(), hostile), min_size=1, max_size=3))
def test_damaged_ahap_files_read_or_give_one_line(tmp_path_factory, edits):
    _read(tmp_path_factory, "p.ahap", json.dumps(_edit(AHAP, edits)))


@fuzz(200)
@given(st.lists(st.tuples(st.sampled_from(_places(HAPTIC)), st.booleans(), hostile), min_size=1, max_size=3))
def test_damaged_haptic_files_read_or_give_one_line(tmp_path_factory, edits):
    _read(tmp_path_factory, "p.haptic", json.dumps(_edit(HAPTIC, edits)))


@fuzz(60)
@given(st.sampled_from(["p.ahap", "p.haptic"]),
       st.binary(max_size=200) | st.sampled_from([b"[" * 100000, b'{"a":' * 100000, b"1" * 5000,
                                                  b'{"Pattern": [' + b"7" * 5000 + b"]}"]))
def test_random_bytes_as_a_pattern(tmp_path_factory, name, raw):
    _read(tmp_path_factory, name, raw)
