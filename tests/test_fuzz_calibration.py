"""Fuzzing the calibration-file reader (rtctl.engine.calibrate.read, ``control.calibration``): a
valid calibration of the scene with fields replaced by hostile JSON (huge integers, NaN, deep
nesting, wrong types), keys dropped, and random bytes. It returns the calibration or is one
:class:`~rtctl.errors.SceneError` line naming the file."""

import json

from fuzzing import clean_or_clear, fuzz
from hypothesis import given
from hypothesis import strategies as st

from rtctl import scene
from rtctl.engine.calibrate import FORMAT, Calibration, model_of, read
from rtctl.errors import SceneError
from rtctl.models import FACTORS

SCENE = scene.load("line-bimorph-5")
GOOD = {"format": FORMAT, "scene": SCENE.scene.name,
        "groups": {"lateral": {"factors": {k: 1.0 for k in FACTORS}, "uncertainty_pct": 1.0, "residual_pct": 0.05,
                               "model": model_of(SCENE, SCENE.actuator[0])}}}

hostile = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=10)
    | st.sampled_from([10**400, -(10**400), "x" * 5000]),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=8,
)
PLACES = [("format",), ("scene",), ("groups",), ("groups", "lateral"), ("groups", "lateral", "factors"),
          ("groups", "lateral", "uncertainty_pct"), ("groups", "lateral", "residual_pct"),
          *[("groups", "lateral", "factors", k) for k in FACTORS],
          ("groups", "lateral", "model"), ("groups", "lateral", "model", "beam"),
          ("groups", "lateral", "model", "beam", "length"), ("groups", "lateral", "model", "beam", "layers"),
          ("groups", "lateral", "model", "support", "k"), ("groups", "lateral", "model", "materials", "PZT-5A", "E")]


@fuzz(200)
@given(st.lists(st.tuples(st.sampled_from(PLACES), st.booleans(), hostile), min_size=1, max_size=3))
def test_damaged_calibrations_read_or_give_one_line(tmp_path_factory, edits):
    doc = json.loads(json.dumps(GOOD))
    for place, drop, value in edits:
        node = doc
        for k in place[:-1]:
            node = node.get(k) if isinstance(node, dict) else None
        if isinstance(node, dict):
            if drop:
                node.pop(place[-1], None)
            else:
                node[place[-1]] = value
    path = tmp_path_factory.mktemp("cal") / "calibration.json"
    path.write_text(json.dumps(doc))
    r = clean_or_clear(read, path, SCENE, errors=SceneError, names=[str(path)])
    assert isinstance(r, (Calibration, SceneError))


@fuzz(60)
@given(st.binary(max_size=200) | st.sampled_from([b"[" * 100000, b'{"a":' * 100000, b"1" * 5000]))
def test_random_bytes_as_a_calibration(tmp_path_factory, raw):
    path = tmp_path_factory.mktemp("cal") / "calibration.json"
    path.write_bytes(raw)
    clean_or_clear(read, path, SCENE, errors=SceneError, names=[str(path)])
