"""Stability cases of the numerics report (quick sizes; the 1e8-sample run is slow), and the
contact hook on a toy plant."""

import naive_numerics as toy
import numpy as np
import pytest

from rtctl.numerics import stability as S

QUICK = [n for n in S.CASES if n != "energy_drift"]


@pytest.mark.parametrize("name", QUICK)
def test_case_passes_quick(name):
    cases = S.run_cases(quick=True, names=[name])
    assert cases
    for c in cases:
        assert c.passed is True, f"{c.case}: {c.detail}"


def test_energy_drift_quick():
    c, = S.run_cases(quick=True, names=["energy_drift"])
    assert c.passed, c.detail


@pytest.mark.slow
def test_energy_drift_1e8_samples():
    c, = S.run_cases(quick=False, names=["energy_drift"])
    assert c.passed, c.detail
    assert c.detail.startswith("1e+08 samples")


def test_exact_step_matches_closed_form():
    # First order low-pass: y = 1 - exp(-t / tau).
    tau = 1e-3
    t = np.array([0.0, 1e-4, 1e-3, 5e-3])
    y = S.exact_step([[-1 / tau]], [[1 / tau]], [[1.0]], [[0.0]], 2.0, t)
    np.testing.assert_allclose(y[0], 2.0 * (1 - np.exp(-t / tau)), rtol=1e-13, atol=1e-16)


def test_a_crashing_case_is_reported_failed_not_swallowed():
    @S.register_case("_boom")
    def boom(quick):
        raise RuntimeError("kaput")
    try:
        c, = S.run_cases(names=["_boom"])
    finally:
        del S.CASES["_boom"]
    assert c.passed is False and "kaput" in c.detail


def test_contact_hook_on_toy_end_stop():
    drive = 8.0 * np.sin(2 * np.pi * 200 * np.arange(4800) / 48000.0)
    c = S.contact_case("toy", lambda: toy.ToyGroup(48000.0, 1, substeps=4), drive,
                       force_bound=50.0, disp_bound=1e-3)   # impact: ~v sqrt(k_s m) ~ 20 N
    assert c.passed, c.detail
    # a bound the physics violates must fail the case
    c = S.contact_case("toy", lambda: toy.ToyGroup(48000.0, 1, substeps=4), drive,
                       force_bound=1e-3, disp_bound=1e-3)
    assert c.passed is False


def test_step_hook_flags_nonfinite():
    class Broken(toy.ToyGroup):
        def process(self, drive, sensed, truth):
            truth[:] = np.nan
            return 2
    c = S.group_step_case("broken", lambda: Broken(48000.0), 8.0, 100, disp_bound=1.0)
    assert c.passed is False
