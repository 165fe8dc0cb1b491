"""The display plants registered in the work-precision report converge to their Radau
references: the SMA kernel first order in the mechanical step, the PVDF kernel exact (zoh)."""

import numpy as np
import pytest

from rtctl.numerics.problems import PROBLEMS, build, relative_error


def ours(problem):
    return {s.setting: s.prepare()() for s in problem.settings if s.method.startswith("rtctl")}


@pytest.mark.slow
def test_sma_pin_height_converges_with_the_mechanical_step():
    p = build("sma", quick=True)
    ref = p.reference()
    err = {k: relative_error(y, ref) for k, y in ours(p).items()}
    assert err["substeps 4"] < 0.5 * err["substeps 16"]      # first order: 4x the rate, ~1/4 the error
    assert err["substeps 4"] < 0.03


@pytest.mark.slow
def test_pvdf_kernel_equals_the_integrated_staircase_response():
    p = build("pvdf", quick=True)
    ref = p.reference()
    (y,) = ours(p).values()
    assert relative_error(y, ref) < 1e-8


@pytest.mark.slow
@pytest.mark.parametrize("name", ["solenoid", "em", "dot"])
def test_switched_pin_plants_converge_with_substeps(name):
    # errors are the worst truth row relative to its peak, force rows (contact impacts) included
    p = build(name, quick=True)
    ref = p.reference()
    err = {k: relative_error(y, ref) for k, y in ours(p).items()}
    assert err["substeps 4"] < err["substeps 1"] and err["substeps 4"] < 0.05


def test_display_plants_are_registered():
    assert {"bimorph", "skin_contact", "sma", "pvdf", "solenoid", "em", "dot"} <= set(PROBLEMS)
    assert np.isfinite(build("sma", quick=True).y0).all()
