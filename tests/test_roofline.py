"""bench/roofline.py, the machine's limit beside the benches' figures: its count of the simulated
plant's operations per channel-sample must be what the realization's own matrices hold, in both
of the kernel's forms."""

import doctest

import numpy as np
import pytest
from bench_module import load

from rtctl.plant import BUILTIN, Amplifier, BeamSpec, BimorphPlant, CurrentSense, Layer, MaxwellLoad, SimGroup, build_fe

roofline = load("roofline")


def _group(form, n_modes=4, finger=True):
    pzt = BUILTIN["PZT-5A"]
    fe = build_fe(BeamSpec(15e-3, 1.5e-3, (Layer(pzt, 0.3e-3), Layer(pzt, 0.3e-3)), "parallel", (0.5, 0.5), 0.01))
    load = MaxwellLoad(1e-4, 300.0, ((300.0, 0.004), (150.0, 0.07), (80.0, 1.4))) if finger else None
    plant = BimorphPlant(fe, Amplifier(20e3), CurrentSense(100.0, 15e3), load, n_modes=n_modes)
    return SimGroup(plant, 48000.0, 8, form=form)


def test_examples():
    res = doctest.testmod(roofline)
    assert res.attempted >= 3 and res.failed == 0


@pytest.mark.parametrize("n_modes,finger", [(2, False), (4, True), (8, True)])
def test_the_modal_count_is_the_realizations_nonzeros_less_its_unit_input_gains(n_modes, finger):
    # the modal state matrix and input column as numbers: each of a row's nonzero terms is a
    # multiply and all but one an add, except that the kernel adds a unit input gain's u unmultiplied
    g = _group("modal", n_modes, finger)
    ms = g.modal.sys
    A, b = np.asarray(ms.A), np.asarray(ms.B)[:, 0]
    n_terms = np.count_nonzero(A, axis=1) + (b != 0)
    expected = int(np.sum(2 * n_terms - 1) - np.count_nonzero(b == 1.0))
    counted = roofline.plant_flops(g)
    assert counted["recursion"] == expected
    # the kernel's pairs (what the count multiplies by 7) are the matrix's 2 x 2 blocks
    assert g.args[1].shape[0] == np.count_nonzero(np.diag(A, 1)) > 0
    # and the block-diagonal form is what saves the recursion's work: the same plant's dense
    # realization costs several times more per step (about 4x, docs/physics.md; 3.6x for 9 states
    # without a finger, whose dense matrix has zeros, 12x for 24)
    assert roofline.plant_flops(_group("dense", n_modes, finger))["recursion"] >= 3 * counted["recursion"]


def test_the_output_count_is_a_sparse_products_and_the_dense_form_counts_every_entry():
    g = _group("dense")
    a, b = g.args[1], g.args[3]
    n = a.shape[0]
    # a full matrix: n products and n - 1 sums per row, plus b u and its sum
    full = np.ones((n, n))
    assert roofline.recursion_flops(1, full, np.zeros(0), np.ones(n)) == n * (2 * n + 1)
    # the dense realization's exact zeros cost nothing: fewer than a full matrix's
    assert roofline.recursion_flops(1, a, np.zeros(0), b) < n * (2 * n + 1) and np.count_nonzero(a) < n * n
    # rows without a term cost nothing; a feedthrough alone is one product
    c = np.zeros((3, 5))
    c[0, [1, 4]] = 2.0
    assert roofline.output_flops(c, np.array([0.0, 0.0, 3.0])) == 3 + 0 + 1
    assert roofline.at_peak_ns(100.0, 50.0) == pytest.approx(2.0)
