"""Transfer matrices vs finite elements: two independent models of one beam (docs/selfsense.md)."""

import math

import numpy as np
import pytest

from rtctl.plant.beam import BeamSpec, Layer, SupportSpec, build_beam
from rtctl.plant.facts import loaded_natural_frequencies
from rtctl.plant.finger import MaxwellLoad
from rtctl.plant.materials import BUILTIN
from rtctl.selfsense.tmm import TMMBeam

PZT = BUILTIN["PZT-5A"]
FINGER = MaxwellLoad(1e-4, 300.0, ((300.0, 0.004), (150.0, 0.07), (80.0, 1.4)))
# "moving": the bimodal display's root, an armature on springs (rtctl.plant.em defaults).
SUPPORTS = {"clamped": SupportSpec(), "elastic": SupportSpec("elastic", 5e4, 2.0),
            "moving": SupportSpec("elastic", 5e4, 2.0, mass=35e-6, inertia=1.9e-11)}


def fe_model(support="clamped", segments=(0.5, 0.5), elements=48):
    spec = BeamSpec(15e-3, 1.5e-3, (Layer(PZT, 0.3e-3), Layer(PZT, 0.3e-3)), "parallel",
                    segments, 0.01, elements)
    return build_beam(spec, SUPPORTS[support])


def fe_admittance(fe, f, load):
    """Full FE (all DOFs, modal damping) driven at 1 V on every segment; finger at the tip."""
    w = 2 * math.pi * f
    Z = fe.K - w * w * fe.M + 1j * w * fe.damping_matrix()
    Z = Z.astype(complex)
    if load is not None:
        Z[fe.tip, fe.tip] += load.dynamic_stiffness(w)
    q = np.linalg.solve(Z, fe.Theta.sum(axis=1))
    return 1j * w * (fe.Theta.T @ q + fe.Cp), q[fe.tip]


@pytest.mark.parametrize("support", list(SUPPORTS))
def test_natural_frequencies_agree(support):
    fe = fe_model(support)
    tm = TMMBeam.from_fe(fe)
    np.testing.assert_allclose(tm.natural_frequencies(4), fe.modes(4)[0], rtol=1e-3)


@pytest.mark.parametrize("support", list(SUPPORTS))
def test_loaded_natural_frequencies_agree(support):
    fe = fe_model(support)
    tm = TMMBeam.from_fe(fe)
    np.testing.assert_allclose(tm.loaded_frequencies(FINGER, 3), loaded_natural_frequencies(fe, FINGER, 3),
                               rtol=1e-3)


# Target: admittance within 1 % below the third mode. Measured with the modal damping of
# TMMBeam.response (<= 1e-5 admittance, <= 4.2e-4 motional current, tip <= 0.3 % of the static
# deflection); tolerances set a decade above.
@pytest.mark.parametrize("support", list(SUPPORTS))
@pytest.mark.parametrize("load", [None, FINGER], ids=["free", "finger"])
def test_admittance_below_third_mode(support, load):
    fe = fe_model(support)
    tm = TMMBeam.from_fe(fe)
    f3 = fe.modes(3)[0][2]
    freqs = np.geomspace(5.0, 0.9 * f3, 25)
    r = tm.response(freqs, load)
    worst_mot = 0.0
    for i, f in enumerate(freqs):
        cur, tip = fe_admittance(fe, f, load)
        # The current is 90 % capacitive: check the motional part too (current minus j w Cp V).
        assert abs(r["admittance"][i] / cur.sum() - 1) < 1e-4
        mot_fe = cur - 1j * 2 * math.pi * f * fe.Cp
        mot_tm = r["current"][i] - 1j * 2 * math.pi * f * tm.cp
        worst_mot = max(worst_mot, np.linalg.norm(mot_tm - mot_fe) / np.linalg.norm(mot_fe))
        # The tip response passes through antiresonances (zeros) between modes, where only its
        # damping-made imaginary part is left: bound the error by the static deflection too.
        assert abs(r["tip"][i] - tip) <= 1e-3 * (abs(tip) + abs(r["tip"][0]))
    assert worst_mot < 5e-3


@pytest.mark.parametrize("support", list(SUPPORTS))
def test_admittance_at_the_loaded_resonances(support):
    """At the finger-loaded resonances, where damping alone sets the response. A Kelvin-Voigt
    damping tuned per frequency to the nearest unloaded mode (TMMBeam.solve) damps the loaded
    modes 1.3 % too much (1st) and 4.7-6 % too little (2nd, 3rd): a loaded mode is a mix of
    unloaded modes, each of which the FE damps by its own 2 zeta w_n. That was the 3.1 % miss
    at 4.0 kHz (elastic support, 2nd loaded mode at 3949 Hz); TMMBeam.response, built on the
    modal receptance, has none."""
    fe = fe_model(support)
    tm = TMMBeam.from_fe(fe)
    f_l = np.asarray(loaded_natural_frequencies(fe, FINGER, 3))
    worst_kv = 0.0
    for f in np.concatenate([f_l, f_l * 1.005, f_l / 1.005]):
        cur, _ = fe_admittance(fe, f, FINGER)
        got = tm.response([f], FINGER)["admittance"][0]
        assert abs(got / cur.sum() - 1) < 5e-4   # measured <= 1.2e-4 (3rd loaded mode)
        kv = tm.solve(2 * math.pi * f, FINGER.dynamic_stiffness(2 * math.pi * f))["current"].sum()
        worst_kv = max(worst_kv, abs(kv / cur.sum() - 1))
    assert worst_kv > 1e-2   # the Kelvin-Voigt field solve is off here (measured 3.8-5.3 %)
