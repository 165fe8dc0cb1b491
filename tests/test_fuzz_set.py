"""Fuzzing ``--set KEY=VALUE`` (rtctl.scene.apply_override) and the sweep's ``--vary KEY=SPEC``
(rtctl.sweep.spec): every key path of the schema, addressed by name, index, negative index and
garbage, given hostile TOML literals and random text. Each item either loads a valid scene or is
one :class:`~rtctl.errors.SceneError` line (exit 2 through ``rtctl check``)."""

from fuzzing import _value, clean_or_clear, fuzz, run_cli
from hypothesis import given
from hypothesis import strategies as st
from test_fuzz_scene import NAMES, hostile

from rtctl import scene
from rtctl.errors import RtctlError, SceneError
from rtctl.schema import SCENE, Table
from rtctl.sweep import spec


def _paths(table, prefix=""):
    """Every key path of the schema, arrays of tables at item 0 and named tables at PZT-5A."""
    for name, sub in table.keys.items():
        p = f"{prefix}{name}"
        if isinstance(sub, Table):
            yield p
            inner = p + (".0" if sub.many else ".PZT-5A" if sub.named else "")
            yield from _paths(sub, inner + ".")
        else:
            yield p


PATHS = sorted(set(_paths(SCENE)))
# how a path part can go wrong: another index, a name, unicode digits, empty, a dot too many
index_swaps = st.sampled_from(["0", "1", "-1", "-99", "99", "lateral", "dots", "x", "\u00b2", "\u0661", "", "0.0",
                               " 0", "00"])


@st.composite
def set_items(draw):
    path = draw(st.sampled_from(PATHS) | st.text(max_size=30))
    if draw(st.booleans()):
        parts = path.split(".")
        parts[draw(st.integers(0, len(parts) - 1))] = draw(index_swaps)
        path = ".".join(parts)
    value = draw(st.one_of(hostile.map(_value), st.text(max_size=30),
                           st.sampled_from(["", "[", "{", "nan", "-inf", "1e999", "0x", "1_", "'", '"',
                                            "1\nb = 2", "[1, 2", "{a = 1", "true false"])))
    return f"{path}{draw(st.sampled_from(['=', ' = ', '==', '=']))}{value}"


@fuzz(300)
@given(st.sampled_from(NAMES), st.lists(set_items(), min_size=1, max_size=3))
def test_set_items_load_or_give_one_line(name, items):
    clean_or_clear(scene.load, name, items, errors=SceneError)


@fuzz(100)
@given(st.text(max_size=60))
def test_arbitrary_text_as_a_set_item(item):
    clean_or_clear(scene.load, "line-bimorph-5", [item], errors=SceneError)


@fuzz(40)
@given(st.sampled_from(NAMES), set_items())
def test_set_through_the_command_line_exits_0_or_2(name, item):
    status, _, _ = run_cli(["check", name, f"--set={item}"])
    assert status in (0, 2)


specs = st.one_of(
    st.builds(lambda a, b, n, log: f"{a}:{b}:{n}" + (":log" if log else ""),
              st.sampled_from(["0", "-1", "1e-3", "nan", "inf", "1e999", "x", "", "9" * 5000]) | st.floats().map(repr),
              st.sampled_from(["1", "0", "-inf", "2e308"]) | st.floats().map(repr),
              # n up to 10**4 points: a million is allowed and takes a second to space
              st.sampled_from(["0", "1", "2", "-3", "10000001", "1.5", "9" * 5000])
              | st.integers(max_value=10**4).map(str),
              st.booleans()),
    st.lists(hostile.map(_value), max_size=5).map(lambda xs: "[" + ", ".join(xs) + "]"),
    st.text(max_size=30),
)


@fuzz(200)
@given(st.sampled_from(PATHS) | st.text(max_size=20), specs)
def test_vary_specs_parse_or_give_one_line(key, text):
    clean_or_clear(spec.parse, f"{key}={text}", errors=RtctlError)
