"""A moving support: mass on the root of an elastic support (bimodal display, seed 000 3.3)."""

import math

import pytest

from rtctl.errors import ModelError
from rtctl.plant.beam import BeamSpec, Layer, SupportSpec, build_beam
from rtctl.plant.materials import BUILTIN

PZT = BUILTIN["PZT-5A"]
SPEC = BeamSpec(15e-3, 1.5e-3, (Layer(PZT, 0.3e-3), Layer(PZT, 0.3e-3)), "parallel", (0.5, 0.5), 0.01)


def test_soft_root_spring_gives_the_rigid_body_mode_of_beam_plus_root_mass():
    # k = 1 N/m against a beam of ~1e3 N/m tip stiffness: the first mode is the whole beam
    # translating on the spring, f = sqrt(k / (m_beam + m_root)) / 2 pi, to ~1e-5.
    m_root, k = 2e-3, 1.0
    fe = build_beam(SPEC, SupportSpec("elastic", k=k, k_rot=math.inf, mass=m_root))
    m_beam = SPEC.length * SPEC.width * 0.6e-3 * PZT.rho
    f, _ = fe.modes(1)
    assert f[0] == pytest.approx(math.sqrt(k / (m_beam + m_root)) / (2 * math.pi), rel=1e-4)


def test_root_mass_lowers_the_flexible_modes_and_zero_mass_changes_nothing():
    k = 5e4
    f0, _ = build_beam(SPEC, SupportSpec("elastic", k=k)).modes(2)
    f1, _ = build_beam(SPEC, SupportSpec("elastic", k=k, mass=0.0)).modes(2)
    f2, _ = build_beam(SPEC, SupportSpec("elastic", k=k, mass=5e-3)).modes(2)
    assert list(f0) == list(f1)
    assert f2[0] < f0[0]


@pytest.mark.parametrize("kw, msg", [
    (dict(kind="elastic", k=math.inf, k_rot=10.0, mass=1e-3), "mass = 0.001 sits on a rigid DOF"),
    (dict(kind="elastic", k=10.0, mass=-1.0), "mass must be finite and >= 0"),
    (dict(kind="elastic", k=10.0, k_rot=math.inf, inertia=1e-9), "inertia = 1e-09 sits on a rigid DOF"),
])
def test_bad_moving_support_is_refused(kw, msg):
    with pytest.raises(ModelError, match=msg):
        SupportSpec(**kw)
