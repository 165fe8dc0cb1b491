"""Fuzzing the scene parser (rtctl.scene) and ``rtctl check``: random bytes, random TOML, the
bundled scenes with values swapped for hostile ones, keys dropped, added and renamed, arrays
repeated, tables nested deeply, text cut and spliced. Every case either validates or is one
:class:`~rtctl.errors.SceneError` line (exit 2 through the command line). The hand-made cases
that found bugs are in tests/corpus/scene (tests/test_fuzz_corpus.py)."""

import copy
import json
import sys

from fuzzing import clean_or_clear, fuzz, run_cli, toml_dumps
from hypothesis import given
from hypothesis import strategies as st

from rtctl import scene
from rtctl.errors import SceneError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

NAMES = scene.bundled()
TEXTS = {n: scene.resolve(n).read_text(encoding="utf-8") for n in NAMES}
DOCS = {n: tomllib.loads(t) for n, t in TEXTS.items()}

# Values a careless or hostile file holds: non-finite, huge, tiny, negative, wrong types, unicode
# (right-to-left marks, NUL, astral), empty and huge containers.
hostile_scalars = st.one_of(
    st.sampled_from([float("nan"), float("inf"), -float("inf"), 0.0, -0.0, -1.0, 5e-324, 1e308, -1e308,
                     2**63, -(2**63) - 1, 2**64 + 1, 10**300, 0, -1, 1, True, False, "", " ", "\u202e\u0000",
                     "\U0001f600", "a.b", "\n", "PZT-5A"]),
    st.integers(), st.floats(), st.text(max_size=20),
)
hostile = st.recursive(
    hostile_scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=8), inner, max_size=4)),
    max_leaves=12,
) | st.sampled_from([[1.0] * 5000, [[[[[[[[1]]]]]]]], [{}] * 3, {"name": "x"}])


def _spots(doc, path=()):
    """Every (container, key) in ``doc``: the places a mutation can hit."""
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    for k, v in items:
        yield doc, k
        yield from _spots(v, path + (k,))


@st.composite
def mutated_scenes(draw):
    """A bundled scene with 1-4 mutations: a value replaced, a key dropped, renamed, added,
    an array item repeated (duplicate names) or a value wrapped in deep nesting."""
    doc = copy.deepcopy(DOCS[draw(st.sampled_from(NAMES))])
    for _ in range(draw(st.integers(1, 4))):
        spots = list(_spots(doc))
        parent, k = spots[draw(st.integers(0, len(spots) - 1))]
        op = draw(st.sampled_from(["set", "set", "set", "drop", "rename", "add", "repeat", "nest"]))
        if op == "set":
            parent[k] = copy.deepcopy(draw(hostile))
        elif op == "drop":
            del parent[k]
        elif op == "rename" and isinstance(parent, dict):
            parent[draw(st.text(min_size=1, max_size=12))] = parent.pop(k)
        elif op == "add" and isinstance(parent, dict):
            parent[draw(st.text(max_size=12))] = copy.deepcopy(draw(hostile))
        elif op == "repeat" and isinstance(parent, list):
            parent.extend(copy.deepcopy([parent[k]] * draw(st.integers(1, 3))))
        elif op == "nest":
            for _ in range(draw(st.integers(1, 60))):
                parent[k] = draw(st.sampled_from([[parent[k]], {"x": parent[k]}]))
    return doc


def _load_text(text: str):
    return clean_or_clear(lambda t: scene.loads(t, origin="<fuzz>"), text, errors=SceneError, names=["<fuzz>"])


@fuzz(150)
@given(mutated_scenes())
def test_mutated_bundled_scenes_validate_or_give_one_line(doc):
    result = _load_text(toml_dumps(doc))
    if isinstance(result, scene.Scene):  # a clean result is a valid scene: it validates again, unchanged
        again = scene.validate(result.to_dict(), "<again>")
        assert json.dumps(again, sort_keys=True) == json.dumps(result.to_dict(), sort_keys=True)


@fuzz(60)
@given(st.dictionaries(st.sampled_from(list(scene.SCENE.keys) + ["x", ""]), hostile, max_size=6))
def test_random_top_level_tables_give_one_line(doc):
    _load_text(toml_dumps(doc))


@st.composite
def spliced_texts(draw):
    """A bundled scene's text cut, spliced, with lines repeated (duplicate tables and keys) or
    random characters (NUL, surrogate-free unicode, brackets, quotes) put in."""
    text = TEXTS[draw(st.sampled_from(NAMES))]
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, len(text)))
        op = draw(st.sampled_from(["cut", "insert", "repeat-line", "truncate"]))
        if op == "cut":
            text = text[:i] + text[i + draw(st.integers(1, 40)):]
        elif op == "insert":
            text = text[:i] + draw(st.text(alphabet=st.sampled_from("[]{}=\"'.,#\n\x00 é1e_-+") | st.characters(),
                                           max_size=12)) + text[i:]
        elif op == "repeat-line" and text:
            lines = text.splitlines(keepends=True)
            j = draw(st.integers(0, len(lines) - 1))
            text = "".join(lines[: j + 1] + lines[j:])
        elif op == "truncate":
            text = text[:i]
    return text


@fuzz(150)
@given(spliced_texts())
def test_spliced_scene_text_gives_one_line(text):
    _load_text(text)


@fuzz(60)
@given(st.binary(max_size=400) | st.builds(lambda b, n: TEXTS[n].encode()[:200] + b, st.binary(max_size=50),
                                            st.sampled_from(NAMES)))
def test_random_bytes_as_a_scene_file_exit_2(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("scene") / "fuzz.toml"
    path.write_bytes(data)
    status, out, err = run_cli(["check", str(path)])
    assert status == 2 or "valid" in out, (status, out, err)
