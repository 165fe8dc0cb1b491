"""The Examples sections of the public modules run and print what they say."""

import doctest
import importlib

import pytest

MODULES = [
    "rtctl.scene", "rtctl.safety", "rtctl.trace", "rtctl.perception",
    "rtctl.dsp.oscillator", "rtctl.dsp.pulse", "rtctl.dsp.lockin", "rtctl.dsp.envelope",
    "rtctl.plant.materials", "rtctl.plant.beam", "rtctl.plant.facts", "rtctl.plant.finger",
    "rtctl.plant.frontend", "rtctl.plant.lti", "rtctl.plant.bimorph",
    "rtctl.plant.sma", "rtctl.plant.pvdf", "rtctl.plant.hybrid", "rtctl.plant.contact",
    "rtctl.plant.solenoid", "rtctl.plant.em", "rtctl.plant.dot", "rtctl.numerics.runner",
    "rtctl.io.audio", "rtctl.io.protocol", "rtctl.sweep.spec", "rtctl.selfsense.rt", "rtctl.control.amplitude",
    "rtctl.jsonsafe",
]


@pytest.mark.parametrize("name", MODULES)
def test_examples(name):
    mod = importlib.import_module(name)
    res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert res.failed == 0, f"{res.failed} of {res.attempted} examples failed in {name}"
