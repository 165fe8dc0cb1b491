"""Scenes: the documented scene contract, validation messages, --set overrides, docs in sync."""

from pathlib import Path

import pytest

from rtctl import scene, schema
from rtctl.errors import SceneError

ROOT = Path(__file__).resolve().parents[1]

# The documented contract example, verbatim: these keys are a contract with tests outside the repo.
CONTRACT = """
[scene]
name = "bimodal-4x4"
[timing]
fs = 48000            # Hz
block = 32            # samples per block
duration = 2.0        # s
[io]
backend = "sim"       # sim | audio | daq | serial | replay
[finger]
preload = 0.49        # N
[finger.lateral]      # generalized Maxwell: F = k0 x + sum_i f_i,  f_i' = k_i x' - f_i / tau_i
mass = 1.0e-4         # kg, skin mass moving with the contact
k0 = 300.0            # N/m
branches = [{k = 300.0, tau = 0.004}, {k = 150.0, tau = 0.07}, {k = 80.0, tau = 1.4}]
[[actuator]]
name = "lateral"
type = "bimorph"      # bimorph | pvdf | em | solenoid | dot | sma
grid = [4, 4]
direction = "lateral" # lateral | normal
max_voltage = 150.0   # V peak, enforced by the limiter
[actuator.beam]
length = 15.0e-3      # m, free length
width = 1.5e-3        # m
connection = "parallel"          # series | parallel
layers = [{material = "PZT-5A", thickness = 0.3e-3}, {material = "PZT-5A", thickness = 0.3e-3}]
segments = [0.5, 0.5] # electrode split, fractions of the length from the clamp
damping = 0.01        # modal damping ratio
[actuator.support]
type = "clamped"      # clamped | elastic | actuator (moves with another actuator group)
[materials.PZT-5A]    # built-ins exist for PZT-5A, PZT-5H, PVDF; a table overrides them
E = 60.98e9           # Pa, 1/s11^E
d31 = -171e-12        # m/V
eps33T = 1700         # relative permittivity at constant stress
rho = 7750            # kg/m^3
[stimulus]
kind = "image"        # image | tones | braille | shape
method = "beat"       # roi | canny | frequency | beat | tones
[control]
mode = "closed"       # open | closed
margin_db = 6.0       # target = threshold * 10^(margin_db/20)
"""


def test_the_scene_format_example_validates_with_its_values():
    s = scene.loads(CONTRACT)
    a = s.group("lateral")
    assert (s.timing.fs, s.timing.block, s.timing.duration) == (48000.0, 32, 2.0)
    assert a.grid == (4, 4) and s.n_channels == 16
    assert a.beam.segments == (0.5, 0.5)
    assert [b.tau for b in s.finger.lateral.branches] == [0.004, 0.07, 1.4]
    assert s.materials["PZT-5A"].d31 == -171e-12
    assert (s.stimulus.kind, s.control.mode, s.control.margin_db) == ("image", "closed", 6.0)


@pytest.mark.parametrize("name", scene.bundled())
def test_bundled_scenes_load(name):
    s = scene.load(name)
    assert s.scene.name == name


def test_scene_objects_are_frozen():
    s = scene.load("line-bimorph-5")
    with pytest.raises(AttributeError, match="frozen"):
        s.timing.fs = 1.0
    with pytest.raises(TypeError):
        s.timing["fs"] = 1.0  # Mapping, not MutableMapping


@pytest.mark.parametrize(
    "item, get, want",
    [
        ("actuator.lateral.beam.length=0.012", lambda s: s.group("lateral").beam.length, 0.012),
        ("materials.PZT-5A.E=62e9", lambda s: s.materials["PZT-5A"].E, 62e9),
        ("finger.lateral.branches=[]", lambda s: s.finger.lateral.branches, ()),
        ("io.backend=audio", lambda s: s.io.backend, "audio"),
        ("stimulus.tones.2.freq=55", lambda s: s.stimulus.tones[2].freq, 55.0),
        ("actuator.lateral.beam.segments.1=0.5", lambda s: s.group("lateral").beam.segments, (0.5, 0.5)),
        ("timing.duration=0.25", lambda s: s.timing.duration, 0.25),
        ('scene.description="two words"', lambda s: s.scene.description, "two words"),
    ],
    ids=["group-by-name", "material", "empty-branches", "bare-word", "list-index", "list-value-index",
         "float", "quoted"],
)
def test_set_overrides(item, get, want):
    assert get(scene.load("line-bimorph-5", [item])) == want


def test_set_can_add_a_key_that_then_validates():
    s = scene.load("line-bimorph-5", ["actuator.lateral.support.k_rot=12.5", "actuator.lateral.support.type=elastic"])
    assert s.group("lateral").support.k_rot == 12.5


@pytest.mark.parametrize(
    "item, words",
    [
        ("timing.blok=64", ["timing.blok", "did you mean 'timing.block'"]),
        ("timing.fs=-5", ["timing.fs", "-5.0", "[1000, 384000] Hz"]),
        ("timing.block=1.5", ["timing.block", "1.5", "integer"]),
        ("io.backend=foo", ["io.backend", "'foo'", "sim, audio, daq, serial, replay"]),
        ("actuator.lateral.max_voltage=0", ["actuator.lateral.max_voltage", "0.0", "(0, 2000] V"]),
        ("actuator.lateral.beam.segments=[0.5,0.6]", ["actuator.lateral.beam.segments", "sum to 1"]),
        ("actuator.lateral.beam.layers.0.material=PZT-9", ["layers.0.material", "'PZT-9'", "PZT-5A"]),
        ("actuator.lateral.grid=[1,2,3]", ["actuator.lateral.grid", "exactly 2"]),
        ("stimulus.tones.0.freq=30000", ["stimulus.tones.0.freq", "30000.0", "(0, 20000] Hz"]),
        ("stimulus.tones.0.channel=9", ["stimulus.tones.0.channel", "0..4"]),
        ("timing.fs=1000;stimulus.tones.4.freq=600", ["stimulus.tones.4.freq", "above Nyquist (500 Hz)"]),
        ("stimulus.tones.4.beat=900", ["stimulus.tones.4.beat", "below 2 * freq (500 Hz)"]),
        ("finger.lateral.branches=[{k=1.0}]", ["finger.lateral.branches.0.tau", "missing"]),
        ("finger.contact=yes", ["finger.contact", "'yes'", "true or false"]),
        ("actuator.x.type=em", ["no item named 'x'", "lateral"]),
        ("timing.duration", ["path.to.key=VALUE"]),
        ("actuator.lateral.support.type=elastic", ["support.k", "finite k or k_rot"]),
    ],
    ids=lambda v: v if isinstance(v, str) else None,
)
def test_errors_name_key_value_and_allowed(item, words):
    with pytest.raises(SceneError) as e:
        scene.load("line-bimorph-5", item.split(";"))
    msg = str(e.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, (w, msg)


def test_unreadable_and_missing_files(tmp_path):
    with pytest.raises(SceneError, match="no such scene"):
        scene.load(tmp_path / "nope.toml")
    with pytest.raises(SceneError, match="did you mean 'line-bimorph-5'"):
        scene.load("line-bimorph5")
    bad = tmp_path / "bad.toml"
    bad.write_text("[timing\nfs = 1")
    with pytest.raises(SceneError, match="not valid TOML"):
        scene.load(bad)
    bad.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(SceneError, match="bad.toml"):
        scene.load(bad)


def test_missing_required_names_the_key():
    with pytest.raises(SceneError, match=r"missing required key 'actuator\.lateral\.max_voltage'"):
        scene.loads(CONTRACT.replace("max_voltage = 150.0", ""))
    with pytest.raises(SceneError, match="missing required 'actuator'"):
        scene.loads('[scene]\nname = "x"\n')


def test_custom_material_needs_all_keys_builtin_override_does_not():
    base = CONTRACT.replace('material = "PZT-5A", thickness = 0.3e-3}, {', 'material = "mine", thickness = 0.3e-3}, {')
    with pytest.raises(SceneError, match="materials.mine.E"):
        scene.loads(base + "\n[materials.mine]\nd31 = 1e-12\neps33T = 10\nrho = 1000\n")
    s = scene.loads(base + "\n[materials.mine]\nE = 1e9\nd31 = 1e-12\neps33T = 10\nrho = 1000\n")
    assert s.materials["mine"].E == 1e9


def test_docs_scene_md_is_generated_from_the_schema():
    assert (ROOT / "docs" / "scene.md").read_text() == schema.markdown(), "run `make docs`"


def test_every_schema_key_is_documented_with_a_doc_string():
    for path, spec in schema._walk(schema.SCENE, ""):
        assert spec.doc, path


def test_long_arrays_of_numbers_are_values_not_deep_keys(tmp_path):
    """The decimal points of many numbers are no nesting: 300 tones with float frequencies, as
    ``--set`` and as one line of a scene file, parse; a dotted key of 300 parts (letters or
    digits) is still refused before parsing (its parse time grows with the square of its depth)."""
    tones = ", ".join(f"{{channel = 0, freq = {40.5 + i * 0.25:.3f}, voltage = 1.5}}" for i in range(300))
    assert scene.parse_value(f"[{tones}]")[299]["freq"] == 40.5 + 299 * 0.25
    f = tmp_path / "many.toml"
    f.write_text(scene.resolve("line-bimorph-5").read_text()
                 + f"\n[extra]\nvalues = [{', '.join(f'{i}.5' for i in range(400))}]\n")
    with pytest.raises(SceneError) as e:  # parsed, then refused for its unknown key, not for its dots
        scene.load(str(f))
    assert "extra" in str(e.value) and "dots" not in str(e.value)
    for deep in (".".join(["a"] * 300), ".".join(["1"] * 300), ".".join(["1.5"] * 150)):
        assert scene.parse_value(f"{{{deep} = 1}}") == f"{{{deep} = 1}}"  # text, never parsed
