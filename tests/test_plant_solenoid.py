"""Solenoid pin array (seed 003): stroke, roll-off, end stops, contact, energy, numerics."""

import math

import naive_hybrid as nh
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rtctl.dsp.pulse import PulseTrain
from rtctl.errors import ModelError
from rtctl.plant.solenoid import SolenoidGroup, SolenoidPin

FS = 48000.0
STROKE = 200e-6          # seed 003: maximum pin stroke 200 um


@pytest.fixture(scope="module")
def pin():
    return SolenoidPin()


def pulses(freqs, seconds, high=5.0, duty=0.5):
    n = int(round(seconds * FS))
    drive = np.zeros((len(freqs), n))
    PulseTrain(len(freqs), FS, freq=list(freqs), duty=duty, high=high).process(drive)
    return drive


def run(group, drive, block=32):
    """Block by block as the loop does; returns truth, sensed and the probe rows per sample."""
    nc, n = drive.shape
    truth = np.empty((nc, 4, n))
    sensed = np.empty((nc * group.n_sensed, n))
    probe = np.empty((len(group.probe_names), n))
    status = 0
    for a in range(0, n, block):
        b = min(n, a + block)
        t, s = np.empty((nc, 4, b - a)), np.empty((nc * group.n_sensed, b - a))
        status |= group.process(np.ascontiguousarray(drive[:, a:b]), s, t)
        truth[:, :, a:b], sensed[:, a:b], probe[:, a:b] = t, s, group.probe[:, :b - a]
    return status, truth, sensed, probe


def stroke_pp(truth, settle):
    x = truth[:, 0, settle:]
    return x.max(axis=1) - x.min(axis=1)


def test_full_stroke_at_low_pulse_rates_and_roll_off_toward_340_hz(pin):
    freqs = (20.0, 100.0, 150.0, 250.0, 340.0)
    g = SolenoidGroup(pin, FS, len(freqs))
    _, truth, _, _ = run(g, pulses(freqs, 0.25))
    pp = stroke_pp(truth, int(0.1 * FS))
    # Stop to stop (plus sub-micrometre penetration) up to 150 Hz ...
    assert np.all(np.abs(pp[:3] - STROKE) < 1e-6), pp
    # ... then the coil's L/R = 1 ms no longer lets the current build up within a pulse.
    assert pp[3] < 0.9 * STROKE and pp[4] < 0.75 * STROKE, pp
    assert pp[4] < pp[3]


def test_coil_current_rises_with_the_electrical_time_constant(pin):
    # While the pin still rests on its bottom stop (K i below the spring and finger preloads)
    # the coil is a plain R-L circuit: i = V/R (1 - exp(-t R/L)).
    g = SolenoidGroup(pin, FS, 1, adc_bits=0)
    _, _, sensed, _ = run(g, np.full((1, 8), 5.0))
    t = np.arange(8) / FS
    exact = 5.0 / pin.R * (1.0 - np.exp(-t / pin.time_constant))
    stuck = pin.K * exact < pin.F_s + pin.preload
    assert stuck[:4].all()
    # 1e-5: the penalty stop lets the pin creep up by dF/k_e as the force grows (~1e-10 m),
    # whose back-EMF K v is ~1e-6 of the 5 V.
    np.testing.assert_allclose(sensed[0, stuck], exact[stuck], rtol=1e-5, atol=1e-15)


def test_held_on_the_top_stop_at_the_static_force_balance():
    # No finger: K V/R - F_s - k_r x - k_e (x - stroke) = 0.
    pin = SolenoidPin(finger=None)
    x_exact = (pin.K * 5.0 / pin.R - pin.F_s + pin.k_e * pin.stroke) / (pin.k_r + pin.k_e)
    assert pin.static_height(5.0) == pytest.approx(x_exact, rel=1e-12)
    g = SolenoidGroup(pin, FS, 1)
    _, truth, _, probe = run(g, np.full((1, int(0.05 * FS)), 5.0))
    assert truth[0, 0, -1] == pytest.approx(x_exact, rel=1e-9)
    assert g.probe_names == (("top_stop_share", ""), ("bottom_stop_share", ""))
    assert probe[0, -1] == 1.0 and probe[1, -1] == 0.0


def test_rest_state_carries_the_finger_preload(pin):
    # At rest on the bottom stop: F_c = (F_p + k0 x_pin) / (1 + k0/k_c) (contact.py).
    f = pin.outputs(pin.y0, 0.0)[2]
    assert f == pytest.approx(pin.skin.rest_force(pin.preload, pin.y0[0]), rel=1e-9)
    g = SolenoidGroup(pin, FS, 2)
    g.params[1, 0] = 0.05                        # press harder on channel 1
    _, truth, _, _ = run(g, np.zeros((2, int(0.02 * FS))))
    assert truth[0, 2, -1] == pytest.approx(pin.preload, rel=1e-3)
    assert truth[1, 2, -1] == pytest.approx(0.05, rel=2e-3)
    g.reset()
    assert g.params[1, 0] == pin.preload


def test_end_stop_penetration_is_bounded_by_the_impact_energy(pin):
    g = SolenoidGroup(pin, FS, 3)
    _, truth, sensed, _ = run(g, pulses((20.0, 150.0, 340.0), 0.2))
    x, v = truth[:, 0], truth[:, 1]
    # A spring stop absorbs the impact m v^2/2 = k_e p^2/2, plus a static force F pressing on
    # it (at most 2 F / k_e dynamically); damping only lowers the penetration p.
    v_max = np.abs(v).max()
    f_max = pin.K * np.abs(sensed).max() + pin.F_s + pin.k_r * STROKE + truth[:, 2].max()
    bound = v_max * math.sqrt(pin.m / pin.k_e) + 2.0 * f_max / pin.k_e
    assert x.max() - STROKE < bound and -x.min() < bound
    assert x.max() - STROKE > 0.0               # the stop is a penalty: it is reached
    assert bound < 2e-6                          # and it is stiff (um scale)


def test_contact_is_lost_on_fast_retraction_and_regained(pin):
    g = SolenoidGroup(pin, FS, 1)
    assert g.probe_names[0] == ("contact_share", "")
    _, truth, _, probe = run(g, pulses((100.0,), 0.1))
    contact = probe[0]
    force = truth[0, 2]
    assert force.min() >= 0.0                    # never pulls
    assert np.all(force[contact == 0.0] == 0.0)  # no force without contact
    lost = np.flatnonzero(np.diff(contact) < 0)
    regained = np.flatnonzero(np.diff(contact) > 0)
    assert lost.size >= 5 and regained.size >= 5
    # Lost in every cycle while the pin moves down fast (it retracts faster than the skin
    # follows); also when the pin stops on its top stop and the skin flies on, pin at rest.
    falling = lost[truth[0, 1, lost + 1] < -0.05]
    assert np.unique(falling // int(FS / 100.0)).size >= 9
    assert contact[-int(0.004 * FS):].max() == 1.0


def energy(pin, X):
    """Stored energy of the pin, coil, stops, contact and skin, J; X shape (n_samples, n)."""
    xp, vp, i, xs, vs = X[:, 0], X[:, 1], X[:, 2], X[:, 3], X[:, 4]
    f = pin.skin.finger
    e = 0.5 * pin.L * i**2 + 0.5 * pin.m * vp**2 + pin.F_s * xp + 0.5 * pin.k_r * xp**2
    e += 0.5 * pin.k_e * (np.minimum(xp, 0.0)**2 + np.maximum(xp - pin.stroke, 0.0)**2)
    e += 0.5 * pin.skin.k_contact * np.maximum(xp - xs, 0.0)**2
    e += 0.5 * f.mass * vs**2 + 0.5 * f.k0 * (xs - pin.skin.surface)**2 + pin.preload * xs
    for j, (k, _tau) in enumerate(f.branches):
        e += X[:, 5 + j]**2 / (2.0 * k)
    return e


def test_energy_never_grows_without_drive(pin):
    # Passive without a drive: every element stores or dissipates, penalties included (a
    # Kelvin-Voigt element that lets go at zero force only loses its spring energy).
    g = SolenoidGroup(pin, FS, 1)
    x0 = pin.y0.copy()
    x0[:3] = [150e-6, 0.3, 0.1]                   # flying up, current flowing
    g.state[0] = x0
    X = [g.state[0].copy()]
    for _ in range(int(0.02 * FS)):
        g.process(np.zeros((1, 1)), np.empty((1, 1)), np.empty((1, 4, 1)))
        X.append(g.state[0].copy())
    E = energy(pin, np.array(X))
    scale = E[0] - energy(pin, pin.y0[None, :])[0]
    assert np.max(np.diff(E)) <= 1e-6 * scale
    assert E[-1] - energy(pin, pin.y0[None, :])[0] < 0.01 * scale


def test_bounds_under_pulse_drive(pin):
    g = SolenoidGroup(pin, FS, 2)
    status, truth, sensed, _ = run(g, pulses((50.0, 340.0), 0.1))
    assert status == 0
    v_max = np.abs(truth[:, 1]).max()
    assert np.abs(sensed).max() <= (5.0 + pin.K * v_max) / pin.R + g.adc[0, 0]
    assert np.array_equal(truth[:, 3], pulses((50.0, 340.0), 0.1))   # ideal voltage drive


@settings(max_examples=10, deadline=None)
@given(cuts=st.lists(st.integers(1, 959), max_size=6, unique=True))
def test_any_block_split_gives_the_same_samples(pin, cuts):
    drive = pulses((120.0, 340.0), 0.02)
    whole = SolenoidGroup(pin, FS, 2, max_block=960)
    t_ref = np.empty((2, 4, 960))
    s_ref = np.empty((2, 960))
    whole.process(drive, s_ref, t_ref)
    parts = SolenoidGroup(pin, FS, 2, max_block=960)
    edges = [0, *sorted(cuts), 960]
    for a, b in zip(edges[:-1], edges[1:]):
        t, s = np.empty((2, 4, b - a)), np.empty((2, b - a))
        parts.process(np.ascontiguousarray(drive[:, a:b]), s, t)
        assert np.array_equal(t, t_ref[:, :, a:b]) and np.array_equal(s, s_ref[:, a:b])


def test_kernel_matches_the_loop_twin(pin):
    drive = pulses((300.0,), 0.008)[0]
    g = SolenoidGroup(pin, FS, 1, adc_bits=0)
    t = np.empty((1, 4, drive.size))
    s = np.empty((1, drive.size))
    g.process(drive[None, :].copy(), s, t)
    y, xend = nh.process(pin.model, g.PG, pin.y0, [pin.preload], drive, g.substeps, g.levels,
                         g.max_events, [0, 1, 2, 3, 4], g.dt)
    # Summation order (FMA) differs from numpy's: a switch value within round-off of zero at a
    # bisection point may move a switching time by < h 2^-levels (test_plant_hybrid).
    scale = np.abs(y).max(axis=1)
    err = np.max(np.abs(np.vstack([t[0], s]) - y), axis=1) / scale
    assert err[0] < 1e-6 and err[1] < 1e-5 and err[2] < 1e-4 and err[4] < 1e-6, err


@pytest.mark.slow
def test_kernel_converges_to_radau_of_the_same_rhs(pin):
    # solve_ivp(Radau, rtol=1e-10) with terminal events on every switch (tests/naive_hybrid.py)
    # on one 4 ms, 5 V pulse (impact on the top stop, contact loss, return): maximum height
    # error over the 12 ms. Measured (nm) at 1, 2, 4, 8 substeps: levels 16 -> 0.24, 0.14,
    # 0.067, 0.027; levels 10 -> 68, 31, 13, 3.5; levels 0 (switches at substep boundaries)
    # -> 35000 at all four. Inside a mode every step is exact, so the error follows the
    # switching-time resolution h 2^-levels.
    n = int(0.012 * FS)
    drive = np.zeros(n)
    drive[:int(0.004 * FS)] = 5.0
    atol = np.array([1e-13, 1e-9, 1e-12, 1e-13, 1e-9, 1e-12, 1e-12, 1e-12])
    ref = nh.reference(pin.model, pin.y0, [pin.preload], drive, FS, rtol=1e-10, atol=atol)
    err = {}
    for levels in (0, 10, 16):
        for substeps in (1, 2, 4, 8):
            g = SolenoidGroup(pin, FS, 1, substeps=substeps, levels=levels, adc_bits=0)
            t = np.empty((1, 4, n))
            g.process(drive[None, :].copy(), np.empty((1, n)), t)
            err[levels, substeps] = np.abs(t[0, 0] - ref[:-1, 0]).max()
    assert err[16, 1] < 1e-9                      # the default group
    assert err[10, 1] > err[10, 2] > err[10, 4] > err[10, 8]
    assert err[16, 8] < err[16, 1] < err[10, 8]
    assert min(err[0, s] for s in (1, 2, 4, 8)) > 10e-6
    # rhs/outputs (the public reference interface) agree with the mode tables.
    y = ref[60]
    assert np.allclose(pin.rhs(0.0, y, 0.0), pin.model.M[pin.mode(y, 0.0)] @
                       np.concatenate([y, [0.0, pin.preload, 1.0]]))


@pytest.mark.slow
def test_underdamped_stop_bounces_are_resolved():
    # A stop at damping ratio 0.2 (restitution 0.53) swings out and back within one 21 us
    # substep: the engine shortens pieces on it (piece_levels) and checks for excursions
    # between piece ends. Against Radau as above; measured 23 nm at the defaults.
    pin = SolenoidPin(stop_damping_ratio=0.2)
    n = int(0.012 * FS)
    drive = np.zeros(n)
    drive[:int(0.004 * FS)] = 5.0
    atol = np.array([1e-13, 1e-9, 1e-12, 1e-13, 1e-9, 1e-12, 1e-12, 1e-12])
    ref = nh.reference(pin.model, pin.y0, [pin.preload], drive, FS, rtol=1e-10, atol=atol)
    g = SolenoidGroup(pin, FS, 1, adc_bits=0)
    assert g.kmin.max() >= 4                     # pieces <= h/16 on the stop
    t = np.empty((1, 4, n))
    g.process(drive[None, :].copy(), np.empty((1, n)), t)
    assert np.abs(t[0, 0] - ref[:-1, 0]).max() < 100e-9


def test_sensed_current_saturates_and_sets_the_status_bit(pin):
    g = SolenoidGroup(pin, FS, 1, current_full_scale=0.1)
    status, _, sensed, _ = run(g, np.full((1, 480), 5.0))
    assert status & 1 and sensed.max() == pytest.approx(0.1, abs=1e-4)


def test_nonfinite_drive_sets_the_sticky_status(pin):
    g = SolenoidGroup(pin, FS, 1)
    d = np.full((1, 4), np.nan)
    assert run(g, d)[0] & 2
    assert run(g, np.zeros((1, 4)))[0] & 2
    g.reset()
    assert run(g, np.zeros((1, 4)))[0] == 0


def test_group_contract_attributes(pin):
    g = SolenoidGroup(pin, FS, 9, max_block=32)
    assert (g.n_channels, g.n_sensed, g.sensed_labels, g.capacitance) == (9, 1, ("coil_a",), 0.0)
    assert g.probe.shape == (3, 32) and any(a is g.probe for a in g.args)
    assert any(a is g.params for a in g.args)
    assert pin.y0.shape == (pin.n_states,) and pin.outputs(pin.y0, 0.0).shape == (4,)


@pytest.mark.parametrize("kw", [{"resistance": 0.0}, {"mass": -1.0}, {"stroke": float("nan")},
                                {"stop_stiffness": float("inf")}],
                         ids=["R=0", "m<0", "stroke=nan", "k_e=inf"])
def test_rejects_bad_parameters(kw):
    with pytest.raises(ModelError):
        SolenoidPin(**kw)
