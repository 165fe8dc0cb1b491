"""Work-precision problems: references against scipy, kernels against dlsim and naive twins,
convergence orders, and the generic group adapter on a toy nonlinear plant."""

import naive_numerics as toy
import numpy as np
import pytest
import scipy.signal

from rtctl.errors import ModelError
from rtctl.numerics import problems as P
from rtctl.numerics.runner import LtiRunner
from rtctl.numerics.workprecision import Entry, speedups
from rtctl.plant.lti import StateSpace, c2d


@pytest.fixture(scope="module")
def bimorph():
    return P.build("bimorph", quick=True)


@pytest.fixture(scope="module")
def errors(bimorph):
    ref = bimorph.reference_outputs()
    out = {}
    for st in bimorph.settings:
        out[(st.method, st.setting)] = (st.prepare()(), P.relative_error(st.prepare()(), ref))
    return out


def test_analytic_reference_matches_radau(bimorph):
    # The steady-state start and the phasor reference against an independent integrator.
    y, _ = P.integrate(bimorph, "Radau", 1e-11)
    assert P.relative_error(y, bimorph.reference_outputs()) < 1e-8


@pytest.mark.filterwarnings("ignore::scipy.signal.BadCoefficients")
def test_steady_state_phasor_against_scipy_freqresp():
    plant = P.default_bimorph_plant()
    s = plant.sys
    _, _, Y = P.sine_steady_state(StateSpace(s.A, s.B, s.C[:4], s.D[:4]), 250.0, 1.0)
    for row in range(4):
        _, h = scipy.signal.freqresp((s.A, s.B, s.C[row:row + 1], s.D[row:row + 1]),
                                     [2 * np.pi * 250.0])
        # scipy goes through a transfer function (polynomials, badly conditioned at 16
        # states: ~5e-8 relative), we solve (jwI - A) x = B directly.
        assert abs(Y[row] - h[0]) <= 1e-6 * abs(h[0])


def test_simgroup_equals_runner_and_dlsim_zoh(errors):
    sim = errors[("rtctl SimGroup zoh", "fs x1")][0]
    run = errors[("rtctl zoh", "fs x1")][0]
    dl = errors[("dlsim zoh", "fs x1")][0]
    assert P.relative_error(run, dl) < 1e-10
    assert P.relative_error(sim, dl) < 1e-10


def test_convergence_orders(errors):
    e = {k: v[1] for k, v in errors.items()}
    # zoh against a continuous sine: first order (half-sample hold delay)
    assert 3.0 < e[("rtctl zoh", "fs x1")] / e[("rtctl zoh", "fs x4")] < 5.0
    # foh: second order
    assert 12.0 < e[("rtctl foh", "fs x1")] / e[("rtctl foh", "fs x4")] < 20.0
    assert e[("rtctl foh", "fs x16")] <= 1e-6
    # foh of a sampled 250 Hz sine at 48 kHz is ~1e-4 off: (w dt)^2 / 12 = 8.9e-5 (docs/physics.md, Sec. 4.2)
    assert 3e-5 < e[("rtctl foh", "fs x1")] < 3e-4
    # oscillator states inside the plant: exact to round-off
    assert e[("rtctl tones", "fs x1")] < 1e-9
    assert e[("dlsim tones", "fs x1")] < 1e-9
    # same discrete matrices, same error
    assert e[("dlsim foh", "fs x4")] == pytest.approx(e[("rtctl foh", "fs x4")], rel=1e-6)


@pytest.mark.parametrize("form", ["auto", "dense"])
def test_runner_matches_dlsim_and_is_chunk_invariant(form):
    rng = np.random.default_rng(3)
    n = 6
    A = rng.normal(size=(n, n))
    A -= (np.max(np.linalg.eigvals(A).real) + 50.0) * np.eye(n)
    sys = StateSpace(A * 100, rng.normal(size=(n, 1)), rng.normal(size=(3, n)),
                     rng.normal(size=(3, 1)))
    sysd = c2d(sys, 1 / 48000)
    x0 = rng.normal(size=n)
    u = rng.normal(size=(1, 1000))
    run = LtiRunner(sysd, form=form, chunk=3, max_block=7)
    run.set_state(x0)
    y = np.empty((1, 3, 1000))
    assert run.process(u, y) == 0
    _, ref, _ = scipy.signal.dlsim((sysd.A, sysd.B, sysd.C, sysd.D, sysd.dt), u[0], x0=x0)
    np.testing.assert_allclose(y[0], ref.T, rtol=1e-9, atol=1e-10 * np.abs(ref).max())
    run.reset()
    y2 = np.empty_like(y)
    for a, b in ((0, 1), (1, 17), (17, 400), (400, 1000)):
        part = np.empty((1, 3, b - a))
        run.process(np.ascontiguousarray(u[:, a:b]), part)
        y2[:, :, a:b] = part
    np.testing.assert_allclose(y2, y, rtol=0, atol=1e-14 * np.abs(y).max())


def test_runner_refuses_nonzero_input_when_input_free():
    aug = c2d(StateSpace([[0.0, -1.0], [1.0, 0.0]], [[0.0], [0.0]], [[0.0, 1.0]], [[0.0]]), 0.1)
    run = LtiRunner(aug, input_free=True)
    with pytest.raises(ModelError, match="input_free"):
        run.process(np.ones((1, 4)), np.empty((1, 1, 4)))


def test_relative_error_flags_nonfinite_and_shape():
    ref = np.ones((2, 5))
    assert P.relative_error(ref * 1.1, ref) == pytest.approx(0.1)
    bad = ref.copy()
    bad[0, 2] = np.nan
    assert P.relative_error(bad, ref) == np.inf
    assert P.relative_error(ref[:, :4], ref) == np.inf


def test_speedups_at_equal_error():
    es = [Entry("p", "ours", "a", 1e-3, 1e-5, True), Entry("p", "ours", "b", 1e-7, 1e-4, True),
          Entry("p", "Radau", "r1", 1e-5, 0.1), Entry("p", "Radau", "r2", 1e-8, 0.5),
          Entry("p", "RK45", "r", 1e-2, 0.01)]
    s = {d["baseline"]: d for d in speedups(es)}
    assert s["Radau"]["ratio"] == pytest.approx(0.5 / 1e-4)
    assert s["Radau"]["ours"] == "ours b"
    assert s["RK45"]["ratio"] is None


def test_unknown_problem_is_refused():
    with pytest.raises(ModelError, match="registered"):
        P.build("no-such-plant")


# ---------------------------------------------------------------- generic adapter on the toy

FS = 48000.0


def toy_problem(substeps=(1, 4, 16)):
    return P.group_problem("toy", lambda fs, k: toy.ToyGroup(fs, 1, substeps=k), toy.rhs,
                           np.zeros(2), toy.outputs, fs=FS, levels=[0.0, 8.0, -4.0, 6.0],
                           hold_s=1e-3, substeps=substeps)


def test_toy_kernel_matches_naive_twin_and_is_chunk_invariant():
    rng = np.random.default_rng(5)
    drive = np.ascontiguousarray(rng.uniform(-8, 8, size=(1, 300)))
    g = toy.ToyGroup(FS, 1, substeps=3)
    truth = np.empty((1, 4, 300))
    assert g.process(drive, np.empty((0, 300)), truth) == 0
    np.testing.assert_allclose(truth[0], toy.naive_toy(FS, 3, drive[0]), rtol=1e-9, atol=1e-15)
    g.reset()
    t2 = np.empty_like(truth)
    for a, b in ((0, 5), (5, 6), (6, 300)):
        g.process(np.ascontiguousarray(drive[:, a:b]), np.empty((0, b - a)), t2[:, :, a:b])
    np.testing.assert_array_equal(t2, truth)


def test_group_adapter_on_toy_converges_to_radau_reference():
    prob = toy_problem()
    ref = prob.reference_outputs()
    assert np.max(ref[2]) > 0.0 and np.min(ref[2]) == 0.0   # the stop is hit and left
    errs = [P.relative_error(st.prepare()(), ref) for st in prob.settings]
    assert errs[0] > errs[1] > errs[2]
    assert errs[2] < 1e-2
    # an independent integrator agrees with the reference
    y, _ = P.integrate(prob, "LSODA", 1e-10)
    assert P.relative_error(y, ref) < 1e-5


def test_group_adapter_rejects_negative_lag():
    with pytest.raises(ModelError, match="truth_lag"):
        P.group_problem("toy", None, toy.rhs, np.zeros(2), toy.outputs, fs=FS, levels=[1.0],
                        hold_s=1e-3, truth_lag=-1, y_scale=np.ones(2))


def test_runner_docstring_example():
    import doctest

    import rtctl.numerics.runner as mod
    res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert res.attempted > 0 and res.failed == 0
