"""Unilateral finger contact: preload statics, contact loss threshold, free flight and regain."""

import math

import numpy as np
import pytest
import scipy.linalg as sla

from rtctl.errors import ModelError
from rtctl.plant.contact import SkinContact, kinematic_pin_model
from rtctl.plant.finger import MaxwellLoad
from rtctl.plant.hybrid import HybridGroup

FS = 48000.0
FINGER = MaxwellLoad(1e-4, 300.0, ((300.0, 0.004), (150.0, 0.07), (80.0, 1.4)))


def group(skin, preload, pin_height=0.0, **kw):
    model = kinematic_pin_model(skin)
    x0, _ = model.equilibrium([0.0, preload], fixed={0: pin_height})
    probes = [("contact_share", "", model.mask("contact_gap", "contact_push"))]
    return HybridGroup(model, FS, 1, x0=x0, params=[preload], probes=probes, **kw)


def run_states(g, drive):
    """Sample by sample: truth (4, n), contact probe (n,), states before each sample (n, ns)."""
    n = drive.size
    truth, probe, X = np.empty((4, n)), np.empty(n), np.empty((n, g.model.n_states))
    for k in range(n):
        X[k] = g.state[0]
        t = np.empty((1, 4, 1))
        g.process(drive[None, k:k + 1].copy(), np.empty((0, 1)), t)
        truth[:, k], probe[k] = t[0, :, 0], g.probe[0, 0]
    return truth, probe, X


@pytest.mark.parametrize("preload,height", [(0.0, 0.0), (0.1, 0.0), (0.1, 50e-6), (0.0, -20e-6)],
                         ids=["zero", "preload", "pin-up", "gap"])
def test_rest_force_is_the_static_balance(preload, height):
    # Skin static balance: F_c = k0 (x_s - surface) + F_p, contact x_s = x_pin - F_c / k_c.
    skin = SkinContact(FINGER)
    model = kinematic_pin_model(skin)
    x, mode = model.equilibrium([0.0, preload], fixed={0: height})
    f_exact = max(0.0, (preload + FINGER.k0 * height) / (1.0 + FINGER.k0 / skin.k_contact))
    f = model.outputs(x, [0.0, preload])[2]
    assert f == pytest.approx(f_exact, rel=1e-12, abs=1e-15)
    assert skin.rest_force(preload, height) == pytest.approx(f_exact, rel=1e-12, abs=1e-15)
    # The discrete model holds it: a rest state stays at rest.
    g = group(skin, preload, height)
    truth, _, _ = run_states(g, np.zeros(200))
    assert np.allclose(truth[2], f_exact, rtol=1e-9, atol=1e-12)


def test_preload_indents_the_skin_by_preload_over_k0():
    # Without the pin the preloaded skin rests F_p / k0 below its unloaded surface; a pin held
    # there touches it with zero force.
    skin = SkinContact(FINGER)
    x, _ = kinematic_pin_model(skin).equilibrium([0.0, 0.1], fixed={0: -0.1 / FINGER.k0})
    assert x[1] == pytest.approx(-0.1 / FINGER.k0, rel=1e-9)
    assert skin.rest_force(0.1, -0.1 / FINGER.k0) == pytest.approx(0.0, abs=1e-15)


@pytest.mark.parametrize("ratio,keeps", [(0.9, True), (1.1, False)], ids=["below", "above"])
def test_sine_loses_contact_only_above_the_rigid_following_threshold(ratio, keeps):
    # A skin following the pin rigidly needs F_c = F_p + k0 x + m x'' >= 0; for x = X sin(w t)
    # that is |k0 - m w^2| X <= F_p. Pure spring finger (no branches), 20 Hz, amplitude ramped
    # in over 50 ms; the height enters as its sample differences (zero-order-hold velocity).
    finger = MaxwellLoad(1e-4, 300.0, ())
    f_p, f = 0.05, 20.0
    w = 2 * math.pi * f
    X = ratio * f_p / abs(finger.k0 - finger.mass * w * w)
    t = np.arange(int(0.15 * FS) + 1) / FS
    h = X * np.sin(w * t) * np.minimum(t / 0.05, 1.0)
    g = group(SkinContact(finger), f_p)
    truth, contact, _ = run_states(g, np.diff(h) * FS)
    steady = t[:-1] > 0.06
    np.testing.assert_allclose(truth[0], h[:-1], atol=1e-12)     # pin height is exact at samples
    assert truth[2].min() >= 0.0
    if keeps:
        assert contact[steady].min() == 1.0
        # The rigid-following force, to the penalty's compliance and the 48 kHz staircase.
        f_rigid = f_p + (finger.k0 - finger.mass * w * w) * h[:-1]
        assert np.max(np.abs(truth[2, steady] - f_rigid[steady])) < 0.02 * f_p
    else:
        assert contact[steady].min() == 0.0
        assert np.all(truth[2, contact == 0.0] == 0.0)


def test_fast_retraction_frees_the_skin_and_it_lands_on_the_pin_again():
    # The pin drops 250 um within one sample and stays; the skin (preload 0.1 N, so its free
    # rest is 333 um down) flies free on its tissue, then lands on the pin and contact returns.
    # The free flight is checked against expm of the skin alone.
    f_p, drop = 0.1, 250e-6
    skin = SkinContact(FINGER)
    g = group(skin, f_p)
    n = 200
    v = np.zeros(n)
    v[1] = -drop * FS
    truth, contact, X = run_states(g, v)
    # Released at once: the damper would pull a pin leaving at 12 m/s.
    assert contact[0] == 1.0 and contact[1] == 0.0 and truth[2, 0] > 0.0
    assert truth[2].min() >= 0.0 and np.all(truth[2, contact == 0.0] == 0.0)
    # Skin alone: states (x_s, v_s, f_1..f_3), x' = A x + b (the preload), from the state at
    # the end of sample 1 (contact released).
    m, k0 = FINGER.mass, FINGER.k0
    nb = FINGER.n_branches
    A = np.zeros((2 + nb, 2 + nb))
    A[0, 1] = 1.0
    A[1, 0] = -k0 / m
    A[1, 2:] = -1.0 / m
    A[2:, 1] = FINGER.k
    A[2:, 2:] = np.diag(-1.0 / FINGER.tau)
    bvec = np.zeros(2 + nb)
    bvec[1] = -f_p / m
    aug = np.zeros((3 + nb, 3 + nb))
    aug[:-1, :-1], aug[:-1, -1] = A, bvec
    s0 = np.concatenate([X[2, 1:], [1.0]])
    want = np.array([sla.expm(aug * (k - 2) / FS) @ s0 for k in range(2, n)])[:, :-1]
    touch = 2 + np.argmax(want[:, 0] <= -drop)       # first sample start below the pin
    assert touch > 10
    np.testing.assert_allclose(X[2:touch, 1:], want[:touch - 2], rtol=1e-9,
                               atol=1e-12 * np.abs(want).max())
    assert np.all(contact[1:touch] == 0.0)
    # It lands within the sample where the free flight reaches the pin. (It does not stay:
    # the Maxwell branches, stretched by the fall, lift it off again until they relax.)
    assert contact[touch:touch + 3].max() == 1.0
    assert truth[2, touch:touch + 3].max() > 0.0


def test_rejects_a_massless_skin_and_bad_penalties():
    with pytest.raises(ModelError, match="mass"):
        SkinContact(MaxwellLoad(0.0, 300.0, ()))
    with pytest.raises(ModelError, match="k_contact"):
        SkinContact(FINGER, k_contact=0.0)
    with pytest.raises(ModelError, match="c_contact"):
        SkinContact(FINGER, c_contact=-1.0)


def test_default_damping_is_0_7_of_critical_on_the_skin_mass():
    skin = SkinContact(FINGER, k_contact=4e6)
    assert skin.c == pytest.approx(2 * 0.7 * math.sqrt(4e6 * FINGER.mass))
