"""The reduced bimorph channel against the full finite-element model, and SimGroup runs."""

import dataclasses

import numpy as np
import pytest
from numba import njit

from rtctl.errors import ModelError
from rtctl.plant import (
    BUILTIN,
    TRUTH_NAMES,
    Amplifier,
    BeamSpec,
    BimorphPlant,
    CurrentSense,
    Layer,
    MaxwellLoad,
    SimGroup,
    build_fe,
    c2d,
    sim_group_process,
    to_modal,
)

FS = 48000.0
FREQS = np.array([1.0, 20.0, 100.0, 250.0, 500.0, 800.0, 1000.0])


@pytest.fixture(scope="module")
def fe():
    pzt = BUILTIN["PZT-5A"]
    return build_fe(BeamSpec(15e-3, 1.5e-3, (Layer(pzt, 0.3e-3), Layer(pzt, 0.3e-3)),
                             "parallel", (0.5, 0.5), 0.01))


@pytest.fixture(scope="module")
def finger():
    # A three-branch finger as in docs/references.md (Pawluk & Howe; tau ~ 4 ms, 70 ms, 1.4 s); values are test data.
    return MaxwellLoad(1e-4, 300.0, ((300.0, 0.004), (150.0, 0.07), (80.0, 1.4)))


AMP = Amplifier(20e3)
SENSE = CurrentSense(100.0, 15e3, aa_order=2, bits=24, full_scale_v=2.5, noise_rms_v=1e-5, seed=7)


def full_fe_response(fe, freqs, finger=None):
    """Tip displacement and segment currents per commanded volt, all FE DOFs, solved directly.

    ``(-w^2 M + j w C + K + K_f(w) e e^T) q = theta V``, ``V = amp(w) u``,
    ``I = j w (Theta^T q + Cp V)``; ``K_f`` is the finger's dynamic stiffness (skin mass
    included).
    """
    C = fe.damping_matrix()
    theta = fe.Theta.sum(axis=1)
    tip = fe.tip
    tips, cur = [], []
    for f in freqs:
        w = 2 * np.pi * f
        V = AMP.omega / (1j * w + AMP.omega)
        Z = -w * w * fe.M + 1j * w * C + fe.K
        if finger is not None:
            Z = Z.astype(complex)
            Z[tip, tip] += finger.dynamic_stiffness(w)
        q = np.linalg.solve(Z, theta * V)
        tips.append(q[tip])
        cur.append(1j * w * (fe.Theta.T @ q + fe.Cp * V))
    return np.array(tips), np.array(cur)


@pytest.mark.parametrize("with_finger", [False, True], ids=["free", "finger"])
def test_reduced_matches_full_fe_to_1khz(fe, finger, with_finger):
    load = finger if with_finger else None
    plant = BimorphPlant(fe, AMP, SENSE, load, n_modes=4)
    h = plant.frequency_response(FREQS)
    tip_ref, cur_ref = full_fe_response(fe, FREQS, load)
    np.testing.assert_allclose(h[:, 0], tip_ref, rtol=1e-2)
    np.testing.assert_allclose(h[:, 4:4 + plant.n_seg], cur_ref, rtol=1e-2)
    # Velocity is j w times displacement; force is the tissue stiffness times displacement.
    w = 2 * np.pi * FREQS
    np.testing.assert_allclose(h[:, 1], 1j * w * h[:, 0], rtol=1e-9)
    if with_finger:
        np.testing.assert_allclose(h[:, 2], finger.tissue_stiffness(w) * h[:, 0], rtol=1e-9)


def test_static_correction_makes_dc_exact(fe):
    for n_modes in (1, 2, 4):
        plant = BimorphPlant(fe, AMP, SENSE, n_modes=n_modes)
        dc = plant.frequency_response([0.0])[0, 0].real
        assert dc == pytest.approx(fe.deflection_per_volt(), rel=1e-9)
        # Static capacitance: charge per volt = current / (j w V) as w -> 0 (1 mHz here).
        f = 1e-3
        h = plant.frequency_response([f])[0]
        q_per_v = h[4:4 + plant.n_seg].sum() / (2j * np.pi * f) / h[3]
        assert q_per_v.real == pytest.approx(fe.capacitance(), rel=1e-9)
    # Without the correction one mode alone misses a few percent of the DC deflection.
    theta = fe.Theta.sum(axis=1)
    f1, phi1 = fe.modes(1)
    one_mode = phi1[fe.tip, 0] * (phi1[:, 0] @ theta) / (2 * np.pi * f1[0]) ** 2
    assert abs(one_mode / fe.deflection_per_volt() - 1) > 1e-2


def test_current_is_capacitive_plus_motional(fe):
    # Capacitive part alone: no coupling, I_j = Cp_j j w V(w) exactly.
    blocked = dataclasses.replace(fe, Theta=np.zeros_like(fe.Theta))
    h0 = BimorphPlant(blocked, AMP, SENSE).frequency_response(FREQS)
    w = 2 * np.pi * FREQS
    V = AMP.omega / (1j * w + AMP.omega)
    np.testing.assert_allclose(h0[:, 4:6], (1j * w * V)[:, None] * fe.Cp[None, :], rtol=1e-10)
    np.testing.assert_allclose(h0[:, 0], 0.0, atol=1e-30)
    # With coupling the difference is the motional current Theta_j^T q'.
    h = BimorphPlant(fe, AMP, SENSE).frequency_response(FREQS)
    tip_ref, cur_ref = full_fe_response(fe, FREQS)
    motional = h[:, 4:6] - h0[:, 4:6]
    np.testing.assert_allclose(motional, cur_ref - h0[:, 4:6], rtol=1e-2)
    assert np.all(np.abs(motional) > 1e-3 * np.abs(h0[:, 4:6]))


def test_finger_lowers_tip_amplitude_as_dynamic_stiffness_predicts(fe, finger):
    """x_loaded = x_free / (1 + H(w) K_f(w)), H: tip compliance FRF of the free beam (full FE)."""
    free = BimorphPlant(fe, AMP, SENSE).frequency_response(FREQS)[:, 0]
    loaded = BimorphPlant(fe, AMP, SENSE, finger).frequency_response(FREQS)[:, 0]
    C = fe.damping_matrix()
    e = np.zeros(fe.n_dof)
    e[fe.tip] = 1.0
    w = 2 * np.pi * FREQS
    H = np.array([np.linalg.solve(-wi * wi * fe.M + 1j * wi * C + fe.K, e)[fe.tip] for wi in w])
    predicted = free / (1 + H * finger.dynamic_stiffness(w))
    np.testing.assert_allclose(loaded, predicted, rtol=1e-2)
    # Below the loaded resonance (~600 Hz: skin mass on the stiffer contact) the finger holds
    # the tip back; near it the mass can raise the amplitude, as K_f(w) says.
    low = FREQS <= 250.0
    assert np.all(np.abs(loaded[low]) < 0.8 * np.abs(free[low]))
    # At DC the finger is the spring k0 in series with the beam's compliance.
    dc = BimorphPlant(fe, AMP, SENSE, finger).frequency_response([0.0])[0, 0].real
    c_tip = fe.static_compliance()
    assert dc == pytest.approx(fe.deflection_per_volt() / (1 + c_tip * finger.k0), rel=1e-9)


def test_maxwell_branches_relax_with_their_time_constants(finger):
    """Ramp the contact by x0 over T0, hold: each branch decays as exp(-(t - T0) / tau_i)."""
    ss = finger.state_space()
    dt, T0, x0 = 1e-4, 2e-3, 1e-5
    n_ramp, n = int(round(T0 / dt)), 30000
    u = np.zeros(n)
    u[:n_ramp] = x0 / T0
    y, _ = c2d(ss, dt).simulate(u)
    t = np.arange(n) * dt
    hold = t >= T0
    th = t[hold] - T0
    # Closed form: during the ramp f_i = k_i v tau_i (1 - exp(-t/tau_i)); then free decay.
    expect = finger.k0 * x0 + sum(k * (x0 / T0) * tau * (1 - np.exp(-T0 / tau)) * np.exp(-th / tau)
                                  for k, tau in finger.branches)
    np.testing.assert_allclose(y[hold, 0], expect, rtol=1e-9)
    # Long after, only k0 holds the displacement; early on, nearly the instantaneous stiffness.
    assert y[-1, 0] == pytest.approx(finger.k0 * x0, rel=0.15)  # 3 s = 2.1 tau_3
    assert y[n_ramp, 0] > 0.7 * finger.relaxation(0.0) * x0


def sine_fit(y, t, f):
    M = np.column_stack([np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t), np.ones_like(t)])
    coef, *_ = np.linalg.lstsq(M, y, rcond=None)
    return np.hypot(coef[0], coef[1])


def run_group(group, drive, block=32):
    nc, n = drive.shape
    sensed = np.empty((nc * group.n_seg, n))
    truth = np.empty((nc, len(TRUTH_NAMES), n))
    status = 0
    for s in range(0, n, block):
        sl = slice(s, s + block)
        ss = np.empty((nc * group.n_seg, drive[:, sl].shape[1]))
        tt = np.empty((nc, len(TRUTH_NAMES), drive[:, sl].shape[1]))
        status |= group.process(np.ascontiguousarray(drive[:, sl]), ss, tt)
        sensed[:, sl], truth[:, :, sl] = ss, tt
    return sensed, truth, status


def test_simgroup_steady_state_sine_matches_frequency_response(fe):
    plant = BimorphPlant(fe, AMP, SENSE)
    group = SimGroup(plant, FS, n_channels=3)
    assert group.modal.form == "modal"
    f, amp = 250.0, 20.0
    n = int(0.25 * FS)
    t = np.arange(n) / FS
    drive = np.tile(amp * np.sin(2 * np.pi * f * t), (3, 1))
    sensed, truth, status = run_group(group, drive)
    assert status == 0
    steady = t > 0.1    # first mode: tau = 1 / (zeta w1) = 13 ms
    h = plant.frequency_response([f])[0]
    # The DAC staircase's fundamental is the sine times sinc(w dt / 2) (4.5e-5 here).
    tip = sine_fit(truth[1, 0, steady], t[steady], f)
    assert tip == pytest.approx(amp * abs(h[0]), rel=1e-3)
    assert sine_fit(truth[2, 3, steady], t[steady], f) == pytest.approx(amp * abs(h[3]), rel=1e-3)
    # ADC readings: the anti-aliased current plus noise and 24-bit quantization. The current
    # is ~ j w V, so the staircase's images near fs (5e-3 of the fundamental, raised ~7x by
    # the differentiation, 2nd-order AA at 15 kHz) alias back by ~4 %: real, and exactly what
    # the ZOH model's own discrete response says (matrix solve, independent of the kernels).
    i_amp = sine_fit(sensed[2 * 2 + 1, steady], t[steady], f)
    hd = group.sysd.frequency_response([f])[0, :, 0]
    assert i_amp == pytest.approx(amp * abs(hd[4 + 1]), rel=1e-3)
    assert abs(abs(hd[4 + 1]) / abs(h[4 + 2 + 1]) - 1) > 1e-2
    assert np.array_equal(truth[0], truth[1])  # identical channels, identical drive


@njit
def _loop(args, drive, sensed, truth):
    """How the real-time loop calls a group from its own compiled code."""
    return sim_group_process(*args, drive, sensed, truth)


def test_simgroup_reset_and_njit_call_convention(fe, finger):
    group = SimGroup(BimorphPlant(fe, AMP, SENSE, finger), FS, n_channels=4)
    assert group.n_states == 16
    drive = np.random.default_rng(0).normal(size=(4, 96)) * 10
    s1, t1, _ = run_group(group, drive)
    assert np.any(group.state != 0)
    # physical_state: the amplifier voltage state is what the next sample reports as truth.
    i_v = group.plant.sys.state_names.index("voltage_v")
    v_state = group.physical_state()[i_v]
    _, t_next, _ = run_group(group, np.zeros((4, 1)))
    np.testing.assert_allclose(t_next[:, 3, 0], v_state, rtol=1e-9)
    group.reset()
    assert np.all(group.state == 0)
    s2, t2 = np.empty_like(s1), np.empty_like(t1)
    assert _loop(group.args, drive, s2, t2) == 0
    np.testing.assert_array_equal(t2, t1)   # reset restarts the states and the noise
    np.testing.assert_array_equal(s2, s1)


def test_simgroup_rejects_a_large_shunt(fe):
    big = CurrentSense(1e5, 15e3)
    with pytest.raises(ModelError, match="shunt"):
        SimGroup(BimorphPlant(fe, AMP, big), FS, 2)
    with pytest.raises(ModelError, match="AA filter"):
        SimGroup(BimorphPlant(fe, AMP, SENSE), FS, 2, sense=CurrentSense(100.0, 10e3))


def test_simgroup_runs_a_cascade_realization_with_exact_zeros(fe, finger):
    """Amplifier -> beam + finger -> one anti-alias filter per segment: the tip signals do not
    depend on the filters, the voltage only on the amplifier, current j not on filter k."""
    plant = BimorphPlant(fe, AMP, SENSE, finger)
    group = SimGroup(plant, FS, n_channels=2)
    mf = group.modal
    assert mf.form == "modal" and mf.is_cascade and mf.n_pairs == 6 and mf.n_real == 4
    amp, mech, aa0, aa1 = range(4)   # plant.cascade order
    C, sb = mf.sys.C, mf.state_block
    assert np.all(C[0:3][:, np.isin(sb, (aa0, aa1))] == 0.0)
    assert np.all(C[3][sb != amp] == 0.0) and C[3][sb == amp] != 0.0
    assert np.all(C[4][sb == aa1] == 0.0) and np.all(C[5][sb == aa0] == 0.0)
    assert np.count_nonzero(C) == 65
    # Unit input gains (the modal kernel has no input multiplies) and a plan that skips the
    # zeros: 69 multiply-adds in tiles + 1 feedthrough (velocity) instead of 16 x 6.
    b = mf.sys.B[:, 0]
    assert np.array_equal(b, np.r_[np.tile([1.0, 0.0], 6), np.ones(4)])
    plan = group.args[5]
    assert sum(int(nr * w) for nr, *_, w, _start in plan[:, :6]) == 69
    assert np.count_nonzero(mf.sys.D) == 1


def test_simgroup_impulse_matches_the_dense_discrete_model(fe, finger):
    plant = BimorphPlant(fe, AMP, SENSE, finger)
    group = SimGroup(plant, FS, n_channels=3)
    n = 2000
    drive = np.zeros((3, n))
    drive[:, 0] = 1.0
    sensed, truth = np.empty((3 * plant.n_seg, n)), np.empty((3, len(TRUTH_NAMES), n))
    assert group.process(drive, sensed, truth) == 0
    h, _ = group.sysd.simulate(drive[0])
    err = np.max(np.abs(truth[1].T - h[:, :4]), axis=0) / np.max(np.abs(h[:, :4]), axis=0)
    # The tip signals sum modal terms that cancel (static correction): ~5e-12, the same as
    # the plain eigenbasis; the voltage is one state.
    assert np.all(err[:3] < 2e-11) and err[3] < 1e-14
    # The plain eigenbasis is in the same accuracy class: both errors are the round-off of the
    # computed eigenbasis (cond ~170), not of the recursion (either form run in long double moves
    # them by < 4e-15). Which of the two comes out ahead depends on the LAPACK build and the BLAS
    # kernel it picks: cascade / plain was 0.06 to 3.3 over SciPy 1.15-1.18 with and without
    # OPENBLAS_CORETYPE=Haswell (each 2.5e-13 to 8.4e-12), so both are held to one bound, unordered.
    plain = to_modal(group.sysd)
    hp, _ = plain.sys.simulate(drive[0])
    err_plain = np.max(np.abs(hp[:, :3] - h[:, :3]), axis=0) / np.max(np.abs(h[:, :3]), axis=0)
    assert np.all(err_plain < 2e-11)
    # The anti-aliased currents (before the ADC) of the realization that runs.
    rows = slice(4, 4 + plant.n_seg)
    hz, _ = group.modal.sys.simulate(drive[0])
    np.testing.assert_allclose(hz[:, rows], h[:, rows], rtol=0,
                               atol=1e-13 * np.abs(h[:, rows]).max())


def test_simgroup_chunk_is_performance_only(fe, finger):
    """Any chunk length (and any split into calls) gives bitwise the same samples, with enough
    channels that the loops run vectorized."""
    plant = BimorphPlant(fe, AMP, SENSE, finger)
    nc, n = 48, 150
    drive = np.random.default_rng(4).normal(size=(nc, n)) * 20
    ref = None
    for chunk, block in ((8, 32), (1, 7), (3, 64), (13, 150), (32, 1)):
        group = SimGroup(plant, FS, nc, chunk=chunk, max_block=64)
        sensed, truth, status = run_group(group, drive, block=block)
        assert status == 0
        if ref is None:
            ref = sensed, truth
        assert np.array_equal(sensed, ref[0]) and np.array_equal(truth, ref[1]), (chunk, block)
