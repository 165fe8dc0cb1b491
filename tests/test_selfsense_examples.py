"""The Examples sections of rtctl.selfsense run and print what they say."""

import doctest
import importlib

import pytest

MODULES = ["rtctl.selfsense.tmm", "rtctl.selfsense.frontend", "rtctl.selfsense.rt",
           "rtctl.selfsense.facts", "rtctl.selfsense.observer", "rtctl.selfsense.sweep"]


@pytest.mark.parametrize("name", MODULES)
def test_examples(name):
    mod = importlib.import_module(name)
    res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert res.attempted > 0
    assert res.failed == 0, f"{res.failed} of {res.attempted} examples failed in {name}"
