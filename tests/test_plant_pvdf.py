"""PVDF cells on a plate (seed 004) against closed forms, scipy, a naive twin and the seed's claim."""

import math

import naive_pvdf
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import dblquad
from scipy.signal import dlsim, find_peaks, hilbert

from rtctl.errors import ModelError
from rtctl.plant import pvdf
from rtctl.plant.finger import MaxwellLoad
from rtctl.plant.lti import c2d
from rtctl.plant.pvdf import PvdfGroup, PvdfPlate

FS = 48000.0
EPS0 = 8.8541878128e-12
# Seed 004: 153 x 93 x 0.8 mm panel, 80 um PVDF, 6 x 8 cells, 1.5 mm apart. Glass plate and
# MEAS film values are the model's stated defaults; the test re-derives everything from them.
A, B, H, TF = 0.153, 0.093, 0.8e-3, 80e-6
E, NU, RHO = 70e9, 0.22, 2500.0
EF, NUF, RHOF, D31, D32 = 2.5e9, 0.34, 1780.0, 23e-12, 3e-12
FINGER = MaxwellLoad(1e-4, 300.0, ((300.0, 0.004), (150.0, 0.07), (80.0, 1.4)))  # test data


@pytest.fixture(scope="module")
def plate():
    return PvdfPlate()


@pytest.fixture(scope="module")
def small():
    # Few modes keep the dlsim references cheap; the residual mode still covers the rest.
    return PvdfPlate(max_mode_hz=2000.0)


def navier_hz(m, n, a=A, b=B, h=H, E=E, nu=NU, rho=RHO, film=RHOF * TF):
    """Simply supported Kirchhoff plate (Leissa, Vibration of Plates, NASA SP-160, Eq. 4.20)."""
    D = E * h**3 / (12 * (1 - nu**2))
    return math.pi / 2 * (m**2 / a**2 + n**2 / b**2) * math.sqrt(D / (rho * h + film))


def run(group, drive, split=None):
    nc, n = drive.shape
    truth = np.empty((nc, 4, n))
    sensed = np.empty((nc * group.n_sensed, n))
    probe = np.empty((3, n))
    step = split or group.probe.shape[1]
    for s0 in range(0, n, step):
        s1 = min(n, s0 + step)
        t = np.empty((nc, 4, s1 - s0))
        s = np.empty((nc * group.n_sensed, s1 - s0))
        assert group.process(np.ascontiguousarray(drive[:, s0:s1]), s, t) == 0
        truth[:, :, s0:s1], sensed[:, s0:s1] = t, s
        probe[:, s0:s1] = group.probe[:, :s1 - s0] if s1 - s0 <= group.probe.shape[1] else np.nan
    return truth, sensed, probe


# -- physics ------------------------------------------------------------------------------
@pytest.mark.parametrize("kw", [{}, dict(plate_E=3.2e9, plate_nu=0.35, plate_rho=1190.0,
                                         plate_length=0.12, plate_thickness=1e-3)],
                         ids=["glass-panel", "acrylic"])
def test_natural_frequencies_match_navier(kw):
    p = PvdfPlate(**kw)
    args = dict(a=kw.get("plate_length", A), h=kw.get("plate_thickness", H),
                E=kw.get("plate_E", E), nu=kw.get("plate_nu", NU), rho=kw.get("plate_rho", RHO))
    want = sorted(navier_hz(m, n, **args) for m in range(1, 30) for n in range(1, 30))
    want = np.array([f for f in want if f <= 4000.0])
    np.testing.assert_allclose(p.modes_hz, want, rtol=1e-12)
    if not kw:
        assert p.modes_hz[0] == pytest.approx(301.04, abs=0.01)


def test_discrete_blocks_have_the_plate_frequencies(plate):
    # Each 2x2 block of the kernel is exp(A_k dt): |log(eig)| / dt = omega_k, angle = damped.
    g = PvdfGroup(plate, FS)
    L = g.args[3]
    lam = np.array([np.linalg.eigvals(L[b])[0] for b in range(L.shape[0])])
    s = np.log(lam.astype(complex)) * FS
    np.testing.assert_allclose(np.sort(np.abs(s)) / (2 * np.pi), plate.modes_hz, rtol=1e-9)
    np.testing.assert_allclose(-s.real / np.abs(s), 0.02, rtol=1e-9)


def test_modal_force_matches_quadrature(plate):
    # Theta_kj = (h + t)/2 int_cell (e_x W_xx + e_y W_yy) dA, by scipy's dblquad.
    ex = EF * (D31 + NUF * D32) / (1 - NUF**2)
    ey = EF * (D32 + NUF * D31) / (1 - NUF**2)
    norm = 1 / math.sqrt((RHO * H + RHOF * TF) * A * B / 4)
    hw, hh = (A / 8 - 1.5e-3) / 2, (B / 6 - 1.5e-3) / 2
    for k in (0, 3, 7):
        m, n = plate.mode_indices[k]
        al, be = m * math.pi / A, n * math.pi / B
        for j in (0, 19, 47):
            xc, yc = plate.cell_centres[j]

            def f(y, x, al=al, be=be):
                return -(ex * al**2 + ey * be**2) * norm * math.sin(al * x) * math.sin(be * y)

            val, _ = dblquad(f, xc - hw, xc + hw, yc - hh, yc + hh, epsabs=0, epsrel=1e-11)
            assert plate.theta[k, j] == pytest.approx((H + TF) / 2 * val, rel=1e-8, abs=1e-12)
    assert plate.capacitance == pytest.approx(EPS0 * 12 * (2 * hw) * (2 * hh) / TF, rel=1e-9)


def full_series_response(f_hz, x, y, cell, plate, m_max=200, n_max=120):
    """Displacement at (x, y) per commanded volt on ``cell``: every Navier mode to (m_max,
    n_max), each with its own dynamics (no truncation, no residual), written here anew."""
    w = 2 * math.pi * f_hz
    ex = EF * (D31 + NUF * D32) / (1 - NUF**2)
    ey = EF * (D32 + NUF * D31) / (1 - NUF**2)
    rho_h = RHO * H + RHOF * TF
    D = E * H**3 / (12 * (1 - NU**2))
    xc, yc = plate.cell_centres[cell]
    hw, hh = (A / 8 - 1.5e-3) / 2, (B / 6 - 1.5e-3) / 2
    m = np.arange(1, m_max + 1)[:, None]
    n = np.arange(1, n_max + 1)[None, :]
    al, be = m * np.pi / A, n * np.pi / B
    Ix = (np.cos(al * (xc - hw)) - np.cos(al * (xc + hw))) / al
    Iy = (np.cos(be * (yc - hh)) - np.cos(be * (yc + hh))) / be
    force = -(H + TF) / 2 * (ex * al**2 + ey * be**2) * Ix * Iy       # generalized, un-normalized
    wk = (al**2 + be**2) * math.sqrt(D / rho_h)
    mass = rho_h * A * B / 4
    amp = 1 / (1 + 1j * w / (2 * np.pi * 20e3))
    eta = force / (mass * (wk**2 - w**2 + 2j * 0.02 * wk * w))
    return amp * np.sum(eta * np.sin(al * x) * np.sin(be * y))


@pytest.mark.parametrize("f_hz", [0.5, 100.0, 110.0, 600.0])
def test_reduced_plate_matches_full_modal_series(plate, f_hz):
    # 18 modes + one lumped residual mode vs 24 000 modes each with its own dynamics.
    H_ = plate.frequency_response([f_hz])[0]
    nc = plate.n_cells
    for out, (x, y) in ((19, plate.cell_centres[19]), (4 * nc, plate.probe_xy)):
        want = full_series_response(f_hz, x, y, 19, plate)
        got = H_[out, 19]
        assert abs(got - want) <= 2e-3 * abs(want), (out, got, want)


def test_residual_makes_truncation_harmless():
    # The static residual turns a 4-mode and an 80-mode plate into the same low-frequency
    # model; without it the cell-centre displacement depends on the truncation by ~30 %.
    f = [100.0]
    few, many = PvdfPlate(max_mode_hz=1000.0), PvdfPlate(max_mode_hz=16000.0)
    a, b = few.frequency_response(f)[0, 19, 19], many.frequency_response(f)[0, 19, 19]
    assert abs(a - b) < 2e-3 * abs(b)
    bare = PvdfPlate(max_mode_hz=1000.0, residual=False).frequency_response(f)[0, 19, 19]
    assert abs(bare - b) > 0.2 * abs(b)


def test_finger_raises_the_first_mode_as_rayleigh_says():
    # One-mode Rayleigh quotient with the finger's dynamic stiffness at the loaded frequency.
    p = PvdfPlate(finger=FINGER)
    g = PvdfGroup(p, FS)
    phi = p.mode_shape(*p.finger_xy)[0, 0]
    w = 2 * np.pi * p.modes_hz[0]
    for _ in range(5):
        ks = FINGER.tissue_stiffness(w).real
        w = math.sqrt((p.modes_hz[0] ** 2 * 4 * np.pi**2 + ks * phi**2) / (1 + FINGER.mass * phi**2))
    L = g.args[3]
    lam = np.concatenate([np.linalg.eigvals(L[b]) for b in range(L.shape[0])])
    s = np.log(lam[lam != 0].astype(complex)) * FS
    got = np.min(np.abs(s.imag[s.imag > 1000]))
    assert got == pytest.approx(w, rel=3e-3)
    assert got > 2 * np.pi * p.modes_hz[0] * 1.001   # and it did move


# -- kernel against scipy and the naive twin ---------------------------------------------
@pytest.mark.parametrize("finger", [None, FINGER], ids=["bare", "finger"])
def test_kernel_matches_dlsim_of_the_continuous_model(finger):
    p = PvdfPlate(max_mode_hz=2000.0, finger=finger, preload=0.3 if finger else 0.0)
    g = PvdfGroup(p, FS, currents=True)
    rng = np.random.default_rng(4)
    u = rng.normal(scale=100.0, size=(48, 700))
    truth, sensed, probe = run(g, u, split=50)
    sd = c2d(p.sys, 1 / FS, "zoh")
    _, y, _ = dlsim((sd.A, sd.B, sd.C, sd.D, 1 / FS), u.T)
    nc = 48
    ref = y[:, :4 * nc].T.reshape(4, nc, -1).transpose(1, 0, 2)
    if finger:
        ref[p.finger_channel, 2] += 0.3
    for r in range(4):
        np.testing.assert_allclose(truth[:, r], ref[:, r], rtol=0,
                                   atol=1e-10 * np.max(np.abs(ref[:, r])) + 1e-300)
    np.testing.assert_allclose(probe, y[:, 4 * nc:4 * nc + 3].T, rtol=0,
                               atol=1e-10 * np.max(np.abs(y[:, 4 * nc:4 * nc + 3])))
    np.testing.assert_allclose(sensed, y[:, 4 * nc + 3:].T, rtol=0,
                               atol=1e-10 * np.max(np.abs(y[:, 4 * nc + 3:])))
    # physical_state maps the kernel's states back to the continuous model's.
    _, _, x = dlsim((sd.A, sd.B, np.eye(sd.n_states), np.zeros((sd.n_states, nc)), 1 / FS),
                    np.vstack([u.T, np.zeros((1, nc))]))
    np.testing.assert_allclose(g.physical_state(), x[-1], rtol=0,
                               atol=1e-9 * np.max(np.abs(x[-1])))


@pytest.mark.parametrize("finger", [None, FINGER], ids=["bare", "finger"])
def test_kernel_matches_naive_twin(small, finger):
    p = small if finger is None else PvdfPlate(max_mode_hz=2000.0, finger=finger, preload=0.1)
    g = PvdfGroup(p, FS, currents=True)
    rng = np.random.default_rng(5)
    warm = rng.normal(scale=50.0, size=(48, 37))
    run(g, warm)
    u = rng.normal(scale=50.0, size=(48, 150))
    want_t, want_s, want_p, (Z, G, V) = naive_pvdf.pvdf_group(g, u, 1)
    truth, sensed, probe = run(g, u, split=64)
    for got, want in ((truth, want_t), (sensed, want_s), (probe, want_p)):
        np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-11 * np.max(np.abs(want)))
    for got, want in zip((g.args[7], g.args[8], g.args[9]), (Z, G, V)):
        np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-11 * np.max(np.abs(want)))


def idle_drive(n, rng):
    """Most cells undriven; cell 19 plays, cell 21 (in cell 19's tiles) gets one tiny kick whose
    ring decays to exact zero, cell 5 starts and stops, cell 33 starts late."""
    t = np.arange(n) / FS
    u = np.zeros((48, n))
    u[19] = 250.0 * np.sin(2 * np.pi * 100.0 * t)
    u[21, 3] = 1e-185
    u[5, 600:900] = rng.normal(scale=30.0, size=300)
    u[33, 2500:] = 50.0 * np.sin(2 * np.pi * 300.0 * t[2500:])
    return u


@pytest.mark.parametrize("finger", [None, FINGER], ids=["bare", "finger"])
def test_undriven_cells_left_out_match_naive_twin(small, finger):
    # cells at rest and undriven are not stepped and their tiles not run: against the twin, which
    # steps every cell, through a cell going quiet beside a driven one and cells waking up
    p = small if finger is None else PvdfPlate(max_mode_hz=2000.0, finger=finger, preload=0.1)
    g = PvdfGroup(p, FS, currents=True, max_block=32)
    u = idle_drive(4800, np.random.default_rng(7))
    quiet = g.args[pvdf._QUIET]
    run(g, u[:, :32])
    assert quiet[21] == 0 and quiet[0] == 1   # kicked: stepped; never driven: left out
    want_t, want_s, want_p, (Z, G, V) = naive_pvdf.pvdf_group(g, u[:, 32:], 1)
    truth, sensed, probe = run(g, u[:, 32:], split=32)
    assert quiet[21] == 1 and quiet[19] == 0 and quiet[33] == 0  # the kick rang out to exact zero
    # the contract the left-out tiles rest on: a quiet cell's sources hold exact zeros (its last
    # live chunk's ring is ~1e-195 there, under any output's rounding, but not zero)
    n_e, nc, X, Y2 = g.args[0][5], 48, g.args[pvdf._QUIET + 3], g.args[pvdf._QUIET + 5]
    for j in np.flatnonzero(quiet):
        assert not X[n_e + j::nc][:5].any() and not Y2[j].any()
    for got, want in ((truth, want_t), (sensed, want_s), (probe, want_p)):
        np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-11 * np.max(np.abs(want)))
    for got, want in zip((g.args[7], g.args[8], g.args[9]), (Z, G, V)):
        np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-11 * np.max(np.abs(want)))


def test_undriven_cells_left_out_bitwise(plate):
    # the tiles left out hold exact zeros: the same outputs, bit for bit, as every tile run
    u = idle_drive(3200, np.random.default_rng(8))
    g1 = PvdfGroup(plate, FS, currents=True, max_block=32)
    g2 = PvdfGroup(plate, FS, currents=True, max_block=32)
    for k in pvdf._CELLS:
        g2.args[k][:] = -1                    # every source read, as if no cell were quiet
    for got, want in zip(run(g1, u, split=32), run(g2, u, split=32)):
        assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))


@given(splits=st.lists(st.integers(1, 90), min_size=1, max_size=12))
@settings(max_examples=25, deadline=None)
def test_chunk_invariance(small, splits):
    rng = np.random.default_rng(6)
    n = 400
    u = rng.normal(scale=80.0, size=(48, n))
    g1 = PvdfGroup(small, FS, currents=True, max_block=64)
    ref_t, ref_s, _ = run(g1, u, split=n)          # one call, split internally at 64
    g2 = PvdfGroup(small, FS, currents=True, max_block=97)
    cuts = np.cumsum(splits)
    cuts = [0] + [int(c) for c in cuts if c < n] + [n]
    for s0, s1 in zip(cuts[:-1], cuts[1:]):
        t = np.empty((48, 4, s1 - s0))
        s = np.empty((48, s1 - s0))
        g2.process(np.ascontiguousarray(u[:, s0:s1]), s, t)
        np.testing.assert_allclose(t, ref_t[:, :, s0:s1], rtol=1e-13, atol=1e-22)
        np.testing.assert_allclose(s, ref_s[:, s0:s1], rtol=1e-13, atol=1e-22)


def lockin(x, f_hz, fs=FS):
    """Complex amplitude of the f_hz component of x (whole number of periods assumed)."""
    t = np.arange(x.size) / fs
    return 2 * np.mean(x * np.exp(-2j * np.pi * f_hz * t))


def sampled_staircase_response(plate, f_hz, k_max=12):
    """Continuous response to the DAC staircase of a unit sine, sampled (Poisson summation):
    every image f + k fs of the staircase, weighted by the hold's sinc and half-sample delay,
    passes through the continuous model and aliases back onto f."""
    f = f_hz + FS * np.arange(-k_max, k_max + 1)
    Hc = plate.frequency_response(f)
    hold = np.sinc(f / FS) * np.exp(-1j * np.pi * f / FS)
    return np.einsum("f,fij->ij", hold, Hc)


@pytest.mark.parametrize("f_hz", [100.0, 300.0, 1500.0])
def test_sine_steady_state_matches_continuous_response(plate, f_hz):
    g = PvdfGroup(plate, FS)
    n_settle, n_meas = 14400, 9600             # 0.3 s (26 ms decay), then 0.2 s exactly
    t = np.arange(n_settle + n_meas) / FS
    u = np.zeros((48, t.size))
    u[19] = 100.0 * np.sin(2 * np.pi * f_hz * t)
    truth, _, probe = run(g, u)
    Hs = sampled_staircase_response(plate, f_hz)
    nc = 48
    sl = slice(n_settle, None)
    phase0 = np.exp(-2j * np.pi * f_hz * n_settle / FS)
    # (The acceleration probe is left to the dlsim test: a staircase's images reach it with
    # weight (f_image / f)^2, so this image sum converges too slowly to be a cheap check.)
    for row, x in ((19, truth[19, 0]), (20, truth[20, 0]), (nc + 19, truth[19, 1]),
                   (4 * nc, probe[0]), (4 * nc + 1, probe[1])):
        got = lockin(x[sl], f_hz) * phase0
        want = 100.0 * Hs[row, 19] / 1j  # sin = Im e^{jwt}: amplitude a -> a/j
        assert abs(got - want) < 2e-4 * abs(want), (row, got, want)


# -- the seed's superposition claim --------------------------------------------------------
def drive_pair(fa, va, fb, vb, n):
    t = np.arange(n) / FS
    u = np.zeros((48, n))
    u[19] = va * np.sin(2 * np.pi * fa * t)
    u[20] = vb * np.sin(2 * np.pi * fb * t)
    return u


def test_beat_superposition_at_the_measurement_point(plate):
    """Seed 004, Fig. 8: 500 Vpp 100 Hz + 500 Vpp 110 Hz on neighbours -> 10 Hz envelope on a
    105 Hz carrier whose peaks match 1000 Vpp at 100 Hz on one cell."""
    g = PvdfGroup(plate, FS)
    n_settle, n = 14400, 14400 + 48000
    sl = slice(n_settle, None)
    peaks = {}
    for name, (fa, va, fb, vb) in {"1000": (100, 500, 100, 0), "500": (100, 250, 100, 0),
                                    "500+500": (100, 250, 100, 250),
                                    "beat": (100, 250, 110, 250)}.items():
        g.reset()
        _, _, probe = run(g, drive_pair(fa, va, fb, vb, n))
        peaks[name] = (probe[0, sl], probe[2, sl])
    d1000, a1000 = (np.max(np.abs(x)) for x in peaks["1000"])
    # Linearity (Fig. 8a, b) and symmetry of the pair about the probe (Fig. 8c).
    assert np.max(np.abs(peaks["500"][0])) == pytest.approx(d1000 / 2, rel=1e-9)
    assert np.max(np.abs(peaks["500+500"][0])) == pytest.approx(d1000, rel=1e-9)
    disp, acc = peaks["beat"]
    # Steady state of the discrete (ZOH) model at each tone: what the kernel must produce.
    nc = 48
    Hd = c2d(plate.sys, 1 / FS, "zoh").frequency_response([100.0, 110.0])
    t = np.arange(n)[sl] / FS
    for row, x, _x1000, seed_carrier_tol in ((4 * nc, disp, d1000, 0.1),
                                             (4 * nc + 2, acc, a1000, 1.0)):
        h1, h2 = 250 * Hd[0, row, 19] / 1j, 250 * Hd[1, row, 20] / 1j
        a1, a2 = abs(h1), abs(h2)
        z = hilbert(x)
        env = np.abs(z)[2400:-2400]                 # drop Hilbert edge effects (50 ms)
        phase = np.unwrap(np.angle(z))[2400:-2400]
        pk, _ = find_peaks(env, distance=int(0.05 * FS))
        # Envelope: 10 Hz (the difference frequency), from the spacing of its maxima.
        assert FS / np.mean(np.diff(pk)) == pytest.approx(10.0, abs=0.01)
        # Carrier by phase at the envelope maxima: the amplitude-weighted mean frequency
        # (a1 f1 + a2 f2) / (a1 + a2), which is the seed's (f1 + f2)/2 for equal amplitudes.
        inst = np.gradient(phase)[pk] * FS / (2 * np.pi)
        assert np.mean(inst) == pytest.approx((100 * a1 + 110 * a2) / (a1 + a2), abs=0.01)
        assert np.mean(inst) == pytest.approx(105.0, abs=seed_carrier_tol)
        pred = (h1 * np.exp(2j * np.pi * 100 * t) + h2 * np.exp(2j * np.pi * 110 * t)).real
        assert np.max(np.abs(x)) == pytest.approx(np.max(np.abs(pred)), rel=2e-4)
    # The seed's claim: beat peaks ~ 1000 Vpp on one cell. Displacement within 3 %; the
    # acceleration ~12 % higher (the 110 Hz half carries (110/100)^2 more).
    ratio_d = np.max(np.abs(disp)) / d1000
    ratio_a = np.max(np.abs(acc)) / a1000
    assert 0.97 < ratio_d < 1.03, ratio_d
    assert 1.05 < ratio_a < 1.15, ratio_a
    print(f"beat/1000Vpp peak ratio: displacement {ratio_d:.4f}, acceleration {ratio_a:.4f}")


# -- contract --------------------------------------------------------------------------------
def test_group_contract_and_errors(plate):
    g = PvdfGroup(plate, FS)
    assert g.n_channels == 48 and g.n_sensed == 0 and g.sensed_labels == ()
    assert [n for n, _ in g.probe_names] == ["probe_displacement", "probe_velocity",
                                             "probe_acceleration"]
    assert g.probe is g.args[-1] and g.capacitance == plate.capacitance
    gc = PvdfGroup(plate, FS, currents=True)
    assert gc.n_sensed == 1 and gc.sensed_labels == ("current",)
    # No finger: the force row is written as zeros even over garbage.
    truth = np.full((48, 4, 10), 7.0)
    g.process(np.ones((48, 10)), np.empty((0, 10)), truth)
    assert not truth[:, 2].any()
    # NaN: status bit 2, sticky until reset.
    bad = np.zeros((48, 8))
    bad[3, 2] = np.nan
    assert g.process(bad, np.empty((0, 8)), np.empty((48, 4, 8))) == 2
    assert g.process(np.zeros((48, 8)), np.empty((0, 8)), np.empty((48, 4, 8))) == 2
    g.reset()
    assert g.process(np.zeros((48, 8)), np.empty((0, 8)), np.empty((48, 4, 8))) == 0
    with pytest.raises(ModelError, match="drives all 48 cells"):
        PvdfGroup(plate, FS, n_channels=16)
    with pytest.raises(ModelError, match="truth must be"):
        g.process(np.zeros((48, 8)), np.empty((0, 8)), np.empty((48, 3, 8)))
    with pytest.raises(ModelError, match="adjacent"):
        PvdfPlate(probe_cells=((0, 0), (2, 2)))
    with pytest.raises(ModelError, match="does not fit"):
        PvdfPlate(pitch_x=0.03)


def test_continuous_reference_contract(plate):
    # rhs/outputs of one channel agree with the full model driven on ref_channel alone.
    rng = np.random.default_rng(2)
    y = rng.normal(size=plate.y0.size) * 1e-3
    u = np.zeros(48)
    u[plate.ref_channel] = 3.0
    np.testing.assert_allclose(plate.rhs(0.0, y, 3.0), plate.sys.A @ y + plate.sys.B @ u)
    full = plate.sys.C @ y + plate.sys.D @ u
    ch = plate.ref_channel
    np.testing.assert_allclose(plate.outputs(y, 3.0), full[[ch, 48 + ch, 96 + ch, 144 + ch]])
