"""Exact discretization, tone augmentation and the modal form (rtctl.plant.lti)."""

import numpy as np
import pytest
import scipy.linalg
import scipy.signal
from scipy.integrate import solve_ivp

from rtctl.errors import ModelError
from rtctl.plant.lti import StateSpace, augment_tones, c2d, to_modal, tone_state

FS = 48000.0
DT = 1.0 / FS


def random_stable(seed, n=5, m=2, p=3):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    A -= (np.max(np.linalg.eigvals(A).real) + rng.uniform(0.1, 2.0)) * np.eye(n)
    return StateSpace(A, rng.normal(size=(n, m)), rng.normal(size=(p, n)), rng.normal(size=(p, m)))


def mode(f_hz, zeta):
    """Unit-DC-gain mass-spring-damper, output displacement."""
    w = 2 * np.pi * f_hz
    return StateSpace([[0.0, 1.0], [-w * w, -2 * zeta * w]], [[0.0], [w * w]], [[1.0, 0.0]],
                      [[0.0]])


@pytest.mark.parametrize("method", ["zoh", "foh"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_c2d_matches_scipy(method, seed):
    sys = random_stable(seed)
    dt = 0.05 * (seed + 1)
    d = c2d(sys, dt, method)
    ref = scipy.signal.cont2discrete((sys.A, sys.B, sys.C, sys.D), dt, method=method)
    for mine, theirs in zip((d.A, d.B, d.C, d.D), ref[:4]):
        np.testing.assert_allclose(mine, theirs, rtol=1e-12, atol=1e-13)
    assert d.dt == dt


def radau(sys, u_of_t, t_eval, x0=None, method="Radau"):
    """Reference solution of the continuous model (``sys.rhs``) by ``solve_ivp``."""
    x0 = np.zeros(sys.n_states) if x0 is None else x0
    kw = dict(jac=lambda t, x: sys.A) if method == "Radau" else {}
    sol = solve_ivp(lambda t, x: sys.rhs(t, x, u_of_t(t)), (0.0, t_eval[-1]), x0,
                    method=method, t_eval=t_eval, rtol=1e-12, atol=1e-20, **kw)
    assert sol.success
    return np.array([sys.outputs(x, u_of_t(t)) for t, x in zip(sol.t, sol.y.T)])


def test_zoh_step_is_exact():
    sys = mode(1500.0, 0.02)
    n = 100
    y, _ = c2d(sys, DT).simulate(np.ones(n))
    ref = radau(sys, lambda t: np.array([1.0]), np.arange(n) * DT)
    np.testing.assert_allclose(y[:, 0], ref[:, 0], rtol=0, atol=1e-9)


def test_zoh_held_pulse_is_exact():
    """A one-sample DAC pulse: the continuous model under the held input, solved in two legs."""
    sys = mode(3000.0, 0.05)
    n = 80
    u = np.zeros(n)
    u[0] = 1.0
    y, _ = c2d(sys, DT).simulate(u)
    first = solve_ivp(lambda t, x: sys.rhs(t, x, [1.0]), (0, DT), np.zeros(2),
                      method="Radau", rtol=1e-12, atol=1e-20)
    ref = radau(sys, lambda t: np.array([0.0]), np.arange(n - 1) * DT, x0=first.y[:, -1])
    np.testing.assert_allclose(y[1:, 0], ref[:, 0], rtol=0, atol=1e-10 * np.abs(ref).max())


class TestSineInputModel:
    """docs/references.md (numerics): a sampled 250 Hz sine at 48 kHz through a lightly damped mode.

    Truth: ``solve_ivp`` (DOP853, rtol 1e-12; the mode is not stiff and Radau takes 25x longer)
    with the continuous sine. Expectations derived
    here: a ZOH staircase is the sine delayed by dt/2, so the steady error is w dt / 2 = 1.64e-2
    of the amplitude, and the start-up transient this delay excites lifts the whole-run maximum
    to ~2.7e-2; the triangle hold (FOH) attenuates the fundamental by sinc^2(w dt / 2), an error
    of (w dt)^2 / 12 = 8.9e-5 ("1e-4"); the augmented oscillator is exact to round-off.
    """

    f, n = 250.0, int(0.1 * FS)

    @pytest.fixture(scope="class")
    @classmethod
    def truth(cls):
        sys = mode(1500.0, 0.01)
        t = np.arange(cls.n) * DT
        w = 2 * np.pi * cls.f
        return sys, t, radau(sys, lambda tt: np.array([np.sin(w * tt)]), t, method="DOP853")[:, 0]

    def rel_err(self, y, ref, steady=False):
        sl = slice(self.n // 2, None) if steady else slice(None)
        return np.max(np.abs(y[sl] - ref[sl])) / np.max(np.abs(ref[sl]))

    def test_zoh(self, truth):
        sys, t, ref = truth
        y, _ = c2d(sys, DT, "zoh").simulate(np.sin(2 * np.pi * self.f * t))
        wdt = 2 * np.pi * self.f * DT
        assert self.rel_err(y[:, 0], ref, steady=True) == pytest.approx(wdt / 2, rel=0.03)
        assert self.rel_err(y[:, 0], ref) == pytest.approx(2.7e-2, rel=0.1)

    def test_foh(self, truth):
        sys, t, ref = truth
        y, _ = c2d(sys, DT, "foh").simulate(np.sin(2 * np.pi * self.f * t))
        wdt = 2 * np.pi * self.f * DT
        err = self.rel_err(y[:, 0], ref)
        assert err == pytest.approx(wdt**2 / 12, rel=0.05)
        assert 5e-5 < err < 1.5e-4

    def test_augmented_tone_is_exact(self, truth):
        sys, t, ref = truth
        aug = augment_tones(sys, [self.f])
        x0 = np.concatenate([np.zeros(sys.n_states), tone_state([1.0])])
        y, _ = c2d(aug, DT).simulate(np.zeros(self.n), x0)
        assert self.rel_err(y[:, 0], ref) < 1e-8


def test_tone_state_and_augment_shapes():
    sys = random_stable(3, n=3, m=2, p=2)
    aug = augment_tones(sys, [100.0, 300.0], input_index=1)
    assert aug.n_states == 7 and aug.n_inputs == 2
    x0 = np.zeros(7)
    x0[3:] = tone_state([2.0, 0.5], [0.3, 1.0])
    # Output at t = 0 includes D times the tones' sine components on input 1.
    expect = sys.D[:, 1] * (2.0 * np.sin(0.3) + 0.5 * np.sin(1.0))
    np.testing.assert_allclose(aug.outputs(x0, [0.0, 0.0]), expect, rtol=1e-14)


def impulse(sysd, n=400):
    y = np.zeros((n, sysd.n_outputs, sysd.n_inputs))
    for j in range(sysd.n_inputs):
        u = np.zeros((n, sysd.n_inputs))
        u[0, j] = 1.0
        y[:, :, j] = sysd.simulate(u)[0]
    return y


def plantlike():
    """Mode + amplifier + a driven filter with states of wildly different units."""
    w1, w2, wa, wf = 2 * np.pi * 1200, 2 * np.pi * 7500, 2 * np.pi * 20e3, 2 * np.pi * 15e3
    A = np.zeros((7, 7))
    A[0, 1], A[1, 0], A[1, 1] = 1.0, -w1**2, -0.02 * w1
    A[2, 3], A[3, 2], A[3, 3] = 1.0, -w2**2, -0.02 * w2
    A[1, 4], A[3, 4] = 3e-4, -2e-4   # volts drive modal accelerations
    A[4, 4] = -wa
    A[5, 6], A[6, 5], A[6, 6] = wf, -wf, -wf * np.sqrt(2)
    A[6, 1], A[6, 4] = 1e-3 * wf, -1e-9 * wa * wf   # current from velocity and dV/dt
    B = np.zeros((7, 1))
    B[4, 0] = wa
    B[6, 0] = 1e-9 * wa * wf
    C = np.zeros((3, 7))
    C[0, 0], C[0, 2], C[1, 4], C[2, 5] = 1e-3, 1e-3, 1.0, 1.0
    return StateSpace(A, B, C, np.zeros((3, 1)))


@pytest.mark.parametrize("make", [lambda: random_stable(5, n=6, m=2, p=3), plantlike],
                         ids=["random", "plantlike"])
def test_modal_form_preserves_io_map(make):
    sysd = c2d(make(), DT if make is plantlike else 0.01)
    mf = to_modal(sysd)
    assert mf.form == "modal" and np.isfinite(mf.cond) and mf.cond < 1e8
    assert 2 * mf.n_pairs + mf.n_real == sysd.n_states
    h, hm = impulse(sysd), impulse(mf.sys)
    assert np.max(np.abs(hm - h)) <= 1e-12 * np.max(np.abs(h)) * 100
    np.testing.assert_allclose(mf.T @ np.linalg.solve(mf.T, np.eye(sysd.n_states)),
                               np.eye(sysd.n_states), atol=1e-12)
    # The block structure the kernel relies on: zero outside the 2x2/1x1 blocks.
    pairs, reals = mf.blocks()
    A = np.zeros_like(mf.sys.A)
    for p, (sg, om) in enumerate(pairs):
        A[2 * p:2 * p + 2, 2 * p:2 * p + 2] = [[sg, om], [-om, sg]]
    k = 2 * mf.n_pairs
    A[k:, k:] = np.diag(reals)
    np.testing.assert_array_equal(mf.sys.A, A)


def test_jordan_block_falls_back_to_dense():
    sysd = StateSpace([[0.9, 1.0], [0.0, 0.9]], [[0.0], [1.0]], [[1.0, 0.0]], [[0.0]], dt=DT)
    mf = to_modal(sysd)
    assert mf.form == "dense" and "dense" in mf.reason
    np.testing.assert_allclose(impulse(mf.sys), impulse(sysd), rtol=1e-12, atol=1e-14)
    with pytest.raises(ModelError, match="unsafe"):
        to_modal(sysd, form="modal")


def test_nearly_equal_coupled_modes_never_garbage():
    """Two damped modes 1e-9 apart and coupled: nearly defective. Dense or error, not garbage."""
    w, eps = 2 * np.pi * 1000, 1e-9
    lam = -0.01 * w + 1j * w
    J = np.array([[lam, 1.0], [0.0, lam * (1 + eps)]])
    # Real 4x4 realization of the complex 2x2 (a near-Jordan pair of conjugate pairs).
    A = np.block([[J.real, -J.imag], [J.imag, J.real]])
    sys = StateSpace(A, [[0.0], [1.0], [0.0], [0.0]], [[1.0, 0.0, 0.0, 0.0]], [[0.0]])
    sysd = c2d(sys, DT)
    mf = to_modal(sysd)
    assert mf.form == "dense" and "fell back" in mf.reason
    np.testing.assert_allclose(impulse(mf.sys), impulse(sysd), rtol=1e-10,
                               atol=1e-12 * np.abs(impulse(sysd)).max())


def test_repeated_but_decoupled_eigenvalues_stay_modal():
    """Two identical, independent filters (like the AA filter of two segments) are fine."""
    f = mode(15000.0, 0.7)
    A = np.kron(np.eye(2), f.A)
    B = np.kron(np.eye(2), f.B)
    C = np.kron(np.eye(2), f.C)
    sysd = c2d(StateSpace(A, B, C, np.zeros((2, 2))), DT)
    mf = to_modal(sysd)
    assert mf.form == "modal" and mf.cond < 10


@pytest.mark.parametrize("bad", [
    dict(A=[[1.0, 0.0]], B=[[1.0]], C=[[1.0]], D=[[0.0]]),
    dict(A=[[1.0]], B=[[1.0, 2.0], [0.0, 1.0]], C=[[1.0]], D=[[0.0]]),
    dict(A=[[np.nan]], B=[[1.0]], C=[[1.0]], D=[[0.0]]),
    dict(A=[[1.0]], B=[[1.0]], C=[[1.0]], D=[[0.0]], dt=-1.0),
], ids=["nonsquare", "B-shape", "nan", "negative-dt"])
def test_statespace_validation(bad):
    with pytest.raises(ModelError):
        StateSpace(**bad)


def test_frequency_response_continuous_and_discrete_agree_below_nyquist():
    sys = mode(800.0, 0.05)
    f = np.array([10.0, 100.0, 250.0])
    hc = sys.frequency_response(f)[:, 0, 0]
    hd = c2d(sys, 1 / 1e6).frequency_response(f)[:, 0, 0]  # ZOH at 1 MHz: delay 0.5 us
    np.testing.assert_allclose(hd * np.exp(1j * 2 * np.pi * f * 0.5e-6), hc, rtol=1e-5)


def cascade():
    """Amplifier -> two coupled modes -> two identical anti-alias filters (one per 'segment').

    States: mode 1 (0, 1), mode 2 (2, 3), amplifier (4), filter 1 (5, 6), filter 2 (7, 8).
    Outputs: displacement (modes + amplifier), voltage, filter 1, filter 2. Returns the system
    and its blocks, upstream first.
    """
    w1, w2, wa, wf = 2 * np.pi * 1200, 2 * np.pi * 7500, 2 * np.pi * 20e3, 2 * np.pi * 15e3
    A = np.zeros((9, 9))
    A[0, 1], A[1, 0], A[1, 1] = 1.0, -w1**2, -0.02 * w1
    A[2, 3], A[3, 2], A[3, 3] = 1.0, -w2**2, -0.02 * w2
    A[1, 3], A[3, 1] = -50.0, -80.0            # the modes couple (damping not diagonal)
    A[1, 4], A[3, 4] = 3e-4, -2e-4
    A[4, 4] = -wa
    for f, (vel, sign) in zip((5, 7), ((1, 1.0), (3, -1.0))):
        A[f, f + 1], A[f + 1, f], A[f + 1, f + 1] = wf, -wf, -wf * np.sqrt(2)
        A[f + 1, vel], A[f + 1, 4] = sign * 1e-3 * wf, -1e-9 * wa * wf
    B = np.zeros((9, 1))
    B[4, 0] = wa
    B[6, 0] = B[8, 0] = 1e-9 * wa * wf
    C = np.zeros((4, 9))
    C[0, 0], C[0, 2], C[0, 4] = 1e-3, 1e-3, 2e-7
    C[1, 4] = 1.0
    C[2, 5] = C[3, 7] = 1.0
    return StateSpace(A, B, C, np.zeros((4, 1))), ([4], [0, 1, 2, 3], [5, 6], [7, 8])


def test_cascade_modal_has_exact_structural_zeros_and_the_same_io_map():
    sys, blocks = cascade()
    sysd = c2d(sys, DT)
    mf = to_modal(sysd, blocks=blocks)
    assert mf.form == "modal" and mf.is_cascade and "cascade" in mf.reason
    assert mf.n_pairs == 4 and mf.n_real == 1
    assert sorted(np.bincount(mf.state_block).tolist()) == [1, 2, 2, 4]
    C, sb = mf.sys.C, mf.state_block
    # What each output cannot depend on is exactly zero; what it can is not.
    must_be_zero = {0: (2, 3), 1: (1, 2, 3), 2: (3,), 3: (2,)}
    for o in range(4):
        for k in range(4):
            part = C[o, sb == k]
            if k in must_be_zero[o]:
                assert np.all(part == 0.0), (o, k)
            else:
                assert np.any(part != 0.0), (o, k)
    # The same impulse response as the dense discrete model, output by output.
    h, hm = impulse(sysd, 800), impulse(mf.sys, 800)
    for o in range(4):
        assert np.max(np.abs(hm[:, o] - h[:, o])) <= 1e-12 * np.max(np.abs(h[:, o]))
    # x = T z along a trajectory.
    u = np.random.default_rng(0).normal(size=300)
    _, x = sysd.simulate(u)
    _, z = mf.sys.simulate(u)
    assert np.all(np.abs(z @ mf.T.T - x) <= 1e-12 * np.abs(x).max(axis=0))
    # The plain eigendecomposition mixes the subsystems: same map, no exact zeros.
    plain = to_modal(sysd)
    assert not plain.is_cascade and np.count_nonzero(plain.sys.C) > np.count_nonzero(C)


def test_c2d_keeps_a_cascade_exact_whatever_the_matrix_exponential_leaves(monkeypatch):
    """SciPy 1.18's expm leaves round-off (~1e-14) where a cascade's upstream blocks must be 0;
    c2d sets them from the coupling graph, so the cascade realization does not depend on it."""
    sys, blocks = cascade()
    exact = c2d(sys, DT)
    real_expm = scipy.linalg.expm

    def fill(M):   # an exponential with round-off in every zero entry
        E = real_expm(M)
        E[E == 0.0] = 1e-13 * np.abs(E).max()
        return E

    monkeypatch.setattr(scipy.linalg, "expm", fill)
    sysd = c2d(sys, DT)
    for i, bi in enumerate(blocks):
        for bj in blocks[i + 1:]:
            assert np.all(sysd.A[np.ix_(bi, bj)] == 0.0)
    assert np.array_equal(sysd.A == 0.0, exact.A == 0.0) and np.array_equal(sysd.B, exact.B)
    assert to_modal(sysd, blocks=blocks).is_cascade


def test_unit_input_scales_each_mode_exactly():
    sys, blocks = cascade()
    sysd = c2d(sys, DT)
    mf = to_modal(sysd, blocks=blocks)
    mu = mf.unit_input()
    b = mu.sys.B[:, 0]
    assert np.array_equal(b[:2 * mu.n_pairs:2], np.ones(mu.n_pairs))
    assert np.array_equal(b[1:2 * mu.n_pairs:2], np.zeros(mu.n_pairs))
    assert np.array_equal(b[2 * mu.n_pairs:], np.ones(mu.n_real))
    assert np.array_equal(mu.sys.A, mf.sys.A)
    assert np.array_equal(mu.sys.C == 0.0, mf.sys.C == 0.0)   # structural zeros stay exact
    h, hm = impulse(sysd, 800), impulse(mu.sys, 800)
    for o in range(4):
        assert np.max(np.abs(hm[:, o] - h[:, o])) <= 1e-12 * np.max(np.abs(h[:, o]))
    u = np.random.default_rng(1).normal(size=300)
    _, x = sysd.simulate(u)
    _, z = mu.sys.simulate(u)
    assert np.all(np.abs(z @ mu.T.T - x) <= 1e-12 * np.abs(x).max(axis=0))


def test_unit_input_of_a_mode_the_input_does_not_reach():
    """b = 0: the mode stays at zero from a zero state; scaled, it runs with input 1 but is
    invisible (zero columns in C and T)."""
    A = np.diag([0.9, 0.5, 0.7])
    mf = to_modal(StateSpace(A, [[1.0], [0.0], [2.0]], [[1.0, 3.0, 1.0]], [[0.0]], dt=DT))
    mu = mf.unit_input()
    dead = np.flatnonzero(np.isclose(np.diag(mu.sys.A), 0.5))
    assert mu.sys.B[dead, 0] == 1.0 and np.all(mu.sys.C[:, dead] == 0.0)
    assert np.all(mu.T[:, dead] == 0.0)
    np.testing.assert_allclose(impulse(mu.sys), impulse(mf.sys), rtol=1e-14, atol=0)


def test_cascade_blocks_out_of_order_fall_back_to_the_plain_modal_form():
    sys, blocks = cascade()
    sysd = c2d(sys, DT)
    mf = to_modal(sysd, blocks=blocks[::-1])
    assert mf.form == "modal" and not mf.is_cascade
    assert "cascade realization failed" in mf.reason and "upstream first" in mf.reason
    np.testing.assert_allclose(impulse(mf.sys), impulse(sysd), rtol=0,
                               atol=1e-12 * np.abs(impulse(sysd)).max())


@pytest.mark.parametrize("blocks", [([0], [1]), ([0, 1], [1, 2]), ([0, 1, 2], []), "abc"],
                         ids=["missing", "twice", "empty", "not-indices"])
def test_cascade_blocks_must_partition_the_states(blocks):
    sysd = StateSpace(np.diag([0.9, 0.5, 0.7]), np.ones((3, 1)), np.ones((1, 3)), [[0.0]], dt=DT)
    with pytest.raises(ModelError, match="blocks"):
        to_modal(sysd, blocks=blocks)


def test_cascade_of_equal_coupled_poles_never_garbage():
    """Two identical first-order stages in series share their pole and couple: a Jordan block.
    The Sylvester equation is singular and the plain basis defective: dense, or an error."""
    a = 2 * np.pi * 3000
    sysd = c2d(StateSpace([[-a, 0.0], [a, -a]], [[a], [0.0]], [[0.0, 1.0]], [[0.0]]), DT)
    mf = to_modal(sysd, blocks=([0], [1]))
    assert mf.form == "dense" and "cascade realization failed" in mf.reason
    np.testing.assert_allclose(impulse(mf.sys), impulse(sysd), rtol=1e-12, atol=1e-14)
    with pytest.raises(ModelError, match="unsafe"):
        to_modal(sysd, form="modal", blocks=([0], [1]))
