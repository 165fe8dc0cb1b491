"""``--vary KEY=SPEC``: the values each SPEC form gives, the product's order, and that every
point's ``--set`` strings read back (through the scene loader's own parser) as the value swept."""

import math

import numpy as np
import pytest

from rtctl import scene
from rtctl.errors import RtctlError
from rtctl.sweep.spec import MAX_POINTS, parse, product, short, toml_literal


def test_linear_log_and_list_specs():
    v = parse("actuator.lateral.beam.length=10e-3:20e-3:6")
    assert v.keys == ("actuator.lateral.beam.length",) and not v.log
    # numpy's linspace is the reference; values are rounded to 12 significant digits
    assert np.allclose(v.values, np.linspace(10e-3, 20e-3, 6), rtol=1e-12, atol=0)
    assert v.values[0] == 10e-3 and v.values[-1] == 20e-3 and 0.014 in v.values
    g = parse("finger.preload=0.1:10:5:log")
    assert g.log and np.allclose(g.values, np.geomspace(0.1, 10, 5), rtol=1e-12)
    assert parse("timing.block=16:64:4").values == (16, 32, 48, 64)  # whole numbers stay integers
    assert parse("x=[1, 2.5, 3]").values == (1, 2.5, 3)
    assert parse("m=[PZT-5A, PZT-5H]").values == ("PZT-5A", "PZT-5H")  # bare words need no quotes
    assert parse('m=["PZT-5A", "PVDF"]').values == ("PZT-5A", "PVDF")
    assert parse("s=[[0.5, 0.5], [0.3, 0.7]]").values == ([0.5, 0.5], [0.3, 0.7])
    assert parse("c=[true, false]").values == (True, False)
    assert parse("a=2:2:1").values == (2,)


def test_keys_varied_together_get_the_same_value():
    v = parse("actuator.lateral.beam.layers.0.thickness, actuator.lateral.beam.layers.1.thickness=[1e-4, 2e-4]")
    pts = product([v])
    assert pts[1].overrides == ("actuator.lateral.beam.layers.0.thickness=0.0002",
                                "actuator.lateral.beam.layers.1.thickness=0.0002")
    assert short(v.name) == "layers.0.thickness+1" and short("actuator.lateral.beam.length") == "beam.length"


def test_product_order_indices_and_override_strings():
    a, b = parse("a.x=1:3:3"), parse("b=[p, q]")
    pts = product([a, b])
    assert [p.index for p in pts] == list(range(6))
    # the first --vary changes slowest, as nested loops in --vary order
    assert [p.values for p in pts] == [(1, "p"), (1, "q"), (2, "p"), (2, "q"), (3, "p"), (3, "q")]
    assert pts[3].overrides == ("a.x=2", 'b="q"')


@pytest.mark.parametrize("value", [0.012, 1e-5, 3.0000000000000004e-4, 1e300, -2.5, 7, 0, True, False, "PZT-5A",
                                   'a "quoted" \\ word', [0.5, 0.5], ["x", 1], math.inf, {"k": 300.0, "tau": 0.004}])
def test_every_value_reads_back_through_the_scene_parser(value):
    # scene.parse_value is what --set uses; the point must set exactly the value swept
    assert scene.parse_value(toml_literal(value)) == value


def test_points_validate_through_the_scene_loader():
    v = parse("actuator.lateral.beam.length=0.012:0.018:3")
    for p in product([v]):
        s = scene.load("line-bimorph-5", list(p.overrides))
        assert s.actuator[0].beam.length == p.values[0]


@pytest.mark.parametrize("text, words", [
    ("actuator.lateral.beam.length", ["expected KEY=SPEC"]),
    ("=1:2:3", ["expected KEY=SPEC"]),
    ("a..b=1:2:3", ["expected KEY=SPEC"]),
    ("k=0.01:0.02", ["a:b:n or a:b:n:log"]),
    ("k=0.01:0.02:3:lin", ["a:b:n or a:b:n:log"]),
    ("k=a:b:3", ["must be numbers"]),
    ("k=1:2:2.5", ["whole number"]),
    ("k=1:2:1", ["n must be >= 2"]),
    ("k=0:1:3:log", ["log range needs a > 0"]),
    ("k=1:inf:3", ["finite"]),
    ("k=[]", ["empty"]),
    ("k=[1,,2]", ["empty item"]),
    ("k=[1, 2", ["ends with ']'"]),
    ("k=0.012", ["SPEC must be a:b:n"]),
    ("k,k=[1, 2]", ["listed twice"]),
])
def test_bad_specs_are_refused_naming_them(text, words):
    with pytest.raises(RtctlError) as e:
        parse(text)
    msg = str(e.value)
    assert "\n" not in msg and repr(text) in msg
    for w in words:
        assert w in msg, (w, msg)


def test_product_refuses_a_key_varied_twice_and_too_many_points():
    with pytest.raises(RtctlError, match="already varied"):
        product([parse("a=1:2:2"), parse("b,a=[1, 2]")])
    n = int(round(MAX_POINTS ** 0.5)) + 1
    with pytest.raises(RtctlError, match="more than"):
        product([parse(f"a=1:2:{n}"), parse(f"b=1:2:{n}")])
