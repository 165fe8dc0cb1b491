"""Thresholds are seed 000's numbers (docs/references.md, Thresholds)."""

import math

import pytest

from rtctl import perception


@pytest.mark.parametrize(
    "receptor, band, um",
    [("meissner", (1, 300), 6.0), ("merkel", (0, 30), 30.0), ("ruffini", (0, 15), 300.0),
     ("pacinian", (5, 1000), 0.08)],
)
def test_seed_000_bands_and_thresholds(receptor, band, um):
    lo, hi = band
    assert perception.threshold_m((lo + hi) / 2, receptor) == pytest.approx(um * 1e-6)
    assert math.isnan(perception.threshold_m(hi * 1.01 + 1, receptor))


@pytest.mark.parametrize("freq, want", [(0.5, "ruffini"), (12, "ruffini"), (20, "merkel"), (100, "meissner"),
                                        (500, "pacinian"), (2000, None)])
def test_auto_receptor_is_the_slowest_that_responds(freq, want):
    assert perception.auto_receptor(freq) == want


def test_target_applies_the_margin():
    assert perception.target_m(250, "pacinian", 6.0) == pytest.approx(0.08e-6 * 10 ** 0.3)
    assert perception.target_m(250, "pacinian", -20.0) == pytest.approx(0.008e-6)
