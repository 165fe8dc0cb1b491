"""Transfer-matrix beam against closed forms (docs/references.md) and its own naive twins."""

import math

import numpy as np
import pytest
from naive_selfsense import piece_matrix as naive_piece

from rtctl.plant.materials import BUILTIN
from rtctl.selfsense.tmm import Support, TMMBeam, laminate_of, piece_matrix

PZT = BUILTIN["PZT-5A"]
ROOTS = (1.8751040687, 4.6940911330, 7.8547574382, 10.995540735)


def bimorph(h=0.6e-3, L=15e-3, w=1.5e-3, segments=(0.5, 0.5), zeta=0.0, support=None, conn="parallel"):
    lam = laminate_of(w, [(PZT, h / 2), (PZT, h / 2)], conn)
    return TMMBeam(lam, L, segments, zeta, support)


@pytest.mark.parametrize("lam", [1e-3, 3.0e8, -2e9 + 5e8j], ids=["lowf", "midf", "damped"])
def test_piece_matrix_matches_expm(lam):
    EI, x = 1.6e-3 * (1 + 0.01j), 0.9 / abs(lam) ** 0.25
    np.testing.assert_allclose(piece_matrix(lam, EI, x), naive_piece(lam, EI, x), rtol=1e-12, atol=1e-14)


def test_cantilever_roots():
    b = bimorph()
    f = b.natural_frequencies(4)
    expect = np.array(ROOTS) ** 2 / (2 * math.pi * b.length**2) * math.sqrt(b.lam.EI / b.lam.rhoA)
    np.testing.assert_allclose(f, expect, rtol=1e-9)


def test_tip_mass_and_spring_roots():
    b = bimorph()
    rhoAL = b.lam.rhoA * b.length
    f_scale = math.sqrt(b.lam.EI / (b.lam.rhoA * b.length**4)) / (2 * math.pi)
    # mu = 1: l_1 = 1.247917 (REFERENCES).
    assert b.natural_frequencies(1, tip_mass=rhoAL)[0] == pytest.approx(1.247917**2 * f_scale, rel=2e-6)
    # Very stiff tip spring -> clamped-pinned 3.926602.
    k = 1e8 * b.lam.EI / b.length**3
    assert b.natural_frequencies(1, tip_k=k)[0] == pytest.approx(3.926602**2 * f_scale, rel=1e-6)


def test_static_smits_choi():
    h, L, w = 0.6e-3, 15e-3, 1.5e-3
    b = bimorph(h, L, w)
    s11 = 1.0 / PZT.E
    om = 2 * math.pi * 1e-4
    tipF = b.solve(om, volts=[0, 0], tip_force=1.0)["y"][-1]
    assert tipF[0].real == pytest.approx(4 * s11 * L**3 / (w * h**3), rel=1e-9)
    assert tipF[1].real == pytest.approx(6 * s11 * L**2 / (w * h**3), rel=1e-9)
    tipM = b.solve(om, volts=[0, 0], tip_moment=1.0)["y"][-1]
    assert tipM[0].real == pytest.approx(6 * s11 * L**2 / (w * h**3), rel=1e-9)
    sol = b.solve(om)
    # Parallel: twice the series V column; charge row doubled, capacitance x4.
    assert sol["y"][-1][0].real == pytest.approx(2 * 3 * abs(PZT.d31) * L**2 / (2 * h**2), rel=1e-9)
    cap = (sol["current"].sum() / (1j * om)).real
    assert cap == pytest.approx(4 * PZT.eps33T * 8.8541878128e-12 * w * L * (1 - PZT.k31_sq / 4) / h, rel=1e-9)


def test_series_deflection_per_volt():
    h, L = 0.6e-3, 15e-3
    b = bimorph(h, L, conn="series")
    y = b.solve(2 * math.pi * 1e-4)["y"][-1]
    assert y[0].real == pytest.approx(3 * abs(PZT.d31) * L**2 / (2 * h**2), rel=1e-9)


@pytest.mark.parametrize("beta_l", [5.0, 20.0, 40.0])
def test_high_frequency_receptance_is_stable(beta_l):
    """Tip receptance of a clamped-free beam, closed form divided by cosh (stable at any beta L):
    w/F = (sin x cosh x - cos x sinh x) / (EI beta^3 (1 + cos x cosh x))."""
    b = bimorph()
    L, EI = b.length, b.lam.EI
    beta = beta_l / L
    om = math.sqrt(beta**4 * EI / b.lam.rhoA)
    num = math.sin(beta_l) - math.cos(beta_l) * math.tanh(beta_l)
    den = EI * beta**3 * (1.0 / math.cosh(beta_l) + math.cos(beta_l))
    got = b.solve(om, volts=[0, 0], tip_force=-1.0)["y"][-1][0]   # external force up = -Q(L)
    assert got.real == pytest.approx(-num / den, rel=1e-9)


def test_seed_product_equals_banded_solve():
    """Eq. (1)/(2) as a literal product of the 5x5 velocity-form matrices, clamped root:
    the tip must be free (M = F = 0) for the solved root state."""
    b = bimorph(zeta=0.01)
    om = 2 * math.pi * 300.0
    sol = b.solve(om)
    A1, A2 = b.seed_matrices(om)
    z0 = np.array([0, 0, sol["y"][0][2], sol["y"][0][3], 1.0], dtype=complex)
    z1 = A1 @ z0
    assert z1[4] == pytest.approx(sol["current"][0], rel=1e-9)
    z1[4] = 1.0
    z2 = A2 @ z1
    assert z2[4] == pytest.approx(sol["current"][1], rel=1e-9)
    assert z2[0] == pytest.approx(1j * om * sol["y"][-1][0], rel=1e-9)
    assert abs(z2[2]) < 1e-9 * abs(sol["y"][0][2]) and abs(z2[3]) < 1e-9 * abs(sol["y"][0][3])


def test_elastic_support_static():
    """Root springs add a rigid motion: w_tip = F/k + F L^2/k_rot + F L^3 / 3EI."""
    k, kr = 2e4, 0.5
    b = bimorph(support=Support(k, kr))
    L, EI = b.length, b.lam.EI
    y = b.solve(2 * math.pi * 1e-4, volts=[0, 0], tip_force=1.0)["y"][-1]
    assert y[0].real == pytest.approx(1 / k + L**2 / kr + L**3 / (3 * EI), rel=1e-9)


def test_eq1_point_matrices_finger_and_elastic_support():
    """Eq. (1) literally: L_m A R_m carries the solved root state to a free outer end."""
    from rtctl.plant.finger import MaxwellLoad
    from rtctl.selfsense.tmm import load_point_matrix, support_point_matrix

    finger = MaxwellLoad(1e-4, 300.0, ((300.0, 0.004), (150.0, 0.07)))
    b = bimorph(zeta=0.01, support=Support(5e4, 2.0))
    om = 2 * math.pi * 400.0
    K = finger.dynamic_stiffness(om)
    sol = b.solve(om, K)
    w0, psi0 = sol["y"][0][:2]
    ks, kr = b.support_stiffness(om)
    y = support_point_matrix(ks, kr) @ np.array([w0, psi0, 0.0, 0.0])   # ground side free
    np.testing.assert_allclose(y, sol["y"][0], rtol=1e-9)
    for j in range(b.n_seg):
        T, t, _ = b.segment_matrix(j, om)
        y = T @ y + t
    out = load_point_matrix(K) @ y
    assert abs(out[2]) < 1e-9 * abs(sol["y"][0][2]) and abs(out[3]) < 1e-9 * abs(sol["y"][0][3])


def cantilever_omegas(b, n):
    """Clamped-free natural frequencies, rad/s: REFERENCES roots, then (n - 1/2) pi (the error
    of the asymptote falls like exp(-beta L): 2e-7 at n = 5)."""
    roots = list(ROOTS) + [(k - 0.5) * math.pi for k in range(len(ROOTS) + 1, n + 1)]
    return np.array(roots[:n]) ** 2 / b.length**2 * math.sqrt(b.lam.EI / b.lam.rhoA)


def test_modal_participations_of_a_cantilever():
    """A mass-normalized clamped-free mode has phi(L)^2 = 4 / (rhoA L) (every mode)."""
    b = bimorph(zeta=0.01)
    wn, A, _ = b._modal()
    np.testing.assert_allclose(wn, cantilever_omegas(b, wn.size), rtol=1e-6)
    np.testing.assert_allclose(A[:, b.n_seg] ** 2 * b.lam.rhoA * b.length / 4.0, 1.0, rtol=1e-6)


@pytest.mark.parametrize("f", [10.0, 250.0, 1000.0, 3000.0, 20000.0])
def test_port_receptance_has_modal_damping(f):
    """Tip force -> tip deflection of a modally damped cantilever, closed form as a modal sum
    over 2000 modes: sum 4 / (rhoA L (w_n^2 - w^2 + 2 j zeta w_n w)). Measured: <= 1.3e-5, the
    damping-made imaginary part (0.02-22 % of it) <= 6e-5. Reciprocity: G is symmetric."""
    b = bimorph(zeta=0.01)
    w = 2 * math.pi * f
    wn = cantilever_omegas(b, 2000)
    want = np.sum(4.0 / (b.lam.rhoA * b.length * (wn**2 - w * w + 2j * 0.01 * wn * w)))
    G = b.port_receptance(w)
    n = b.n_seg
    assert abs(G[n, n] / want - 1) < 1e-4
    assert abs(G[n, n].imag / want.imag - 1) < 3e-4
    np.testing.assert_allclose(G, G.T, rtol=0, atol=1e-12 * np.abs(G).max())


def test_port_receptance_undamped_equals_field_solve():
    """Without damping the receptance is the banded field solve itself (tip force column)."""
    b = bimorph(zeta=0.0)
    om = 2 * math.pi * 700.0
    G = b.port_receptance(om)
    y = b.solve(om, volts=[0, 0], tip_force=1.0)["y"]
    assert G[2, 2] == pytest.approx(y[-1][0], rel=1e-12)
    assert G[3, 2] == pytest.approx(y[-1][1], rel=1e-12)


@pytest.mark.parametrize("zeta, segments, support", [
    (0.01, (0.5, 0.5), None),
    (0.01, (0.25, 0.25, 0.25, 0.25), Support(2e5, 3.0, 1e-4, 1e-9)),
    (0.0, (0.3, 0.7), Support(math.inf, 5.0)),
], ids=["clamped", "springs-4seg", "undamped-rot-spring"])
def test_currents_of_many_frequencies_are_each_solve_bitwise(zeta, segments, support):
    """The batched solve (an observer's aliased images: tones up to 900 Hz folded 40 times
    each way at 48 kHz, from a few pieces per segment to dozens) against one banded solve per
    frequency, under a finger-like load per frequency (a Python complex, as an observer's
    design hands it over): the same currents to the last bit."""
    beam = bimorph(segments=segments, zeta=zeta, support=support)
    rng = np.random.default_rng(3)
    k = np.concatenate((np.arange(-40, 0), np.arange(1, 41)))
    om = np.abs(2 * np.pi * rng.uniform(2.0, 900.0, 6)[:, None] + 2 * np.pi * 48000.0 * k[None, :]).ravel()
    load = -om * om * 1e-4 + 300.0 + 1j * rng.uniform(0.0, 50.0, om.size)
    want = np.array([beam.solve(w, complex(K))["current"] for w, K in zip(om, load)])
    got = beam.currents(om, load)
    assert got.shape == want.shape and got.tobytes() == want.tobytes()
