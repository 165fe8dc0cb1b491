"""SMA antagonistic taxel (seed 002): closed forms, published numbers, scipy, naive twins."""

import math

import naive_sma
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from rtctl.errors import ModelError
from rtctl.plant import _sma_kernels as K
from rtctl.plant.sma import SmaGroup, SmaTaxel, sma_group_process

FS = 48000.0
T_DRIVE = 110.0   # degC: the drive settles the heated spring here (docs/plants/sma.md)


def run(group, volts, seconds, f_ext=0.0, block=960, every=48):
    """Run ``group`` with a constant (per-channel) or callable drive; returns truth rows
    decimated to ``fs / every`` and the OR of the statuses."""
    nc = group.n_channels
    group.f_ext[:] = f_ext
    sensed, truth = np.zeros((0, block)), np.zeros((nc, 4, block))
    rows, status = [], 0
    n0 = getattr(group, "_t", 0)
    for i in range(0, int(round(seconds * FS)), block):
        t = (n0 + i + np.arange(block)) / FS
        v = volts(t) if callable(volts) else np.broadcast_to(np.reshape(volts, (-1, 1)), (nc, block))
        status |= group.process(np.ascontiguousarray(np.broadcast_to(v, (nc, block))), sensed, truth)
        rows.append(truth[:, :, ::every].copy())
    group._t = n0 + int(round(seconds * FS))
    return np.concatenate(rows, axis=2), status


@pytest.fixture(scope="module")
def still():
    return SmaTaxel(cooling="still")


@pytest.fixture(scope="module")
def forced():
    return SmaTaxel(cooling="forced")


# ---- the spring law ------------------------------------------------------------------------

@pytest.mark.parametrize("temp,load", [(20.0, 0.180), (85.0, 0.410), (105.0, 0.720)],
                         ids=["20C", "85C", "105C"])
def test_load_curve_hits_seed_fig4a(still, temp, load):
    # Seed 002, Fig. 4(a): 10 mm deflection needs ~180 mN at 20 C, 410 mN at 85 C, 720 at 105 C.
    assert still.load_curve(10e-3, temp) == pytest.approx(load, rel=0.01)


def test_load_curve_elastic_slope_is_wahl_free_spring_rate(still):
    # Eq. (1) elastic branch: G d^4 / (8 N D^3); 0.1 mm is far below delta_e.
    k = 10.5e9 * (200e-6) ** 4 / (8 * 12 * 1.3e-3 ** 3)
    assert still.load_curve(0.1e-3, 20.0) / 0.1e-3 == pytest.approx(k, rel=1e-12)


@pytest.mark.parametrize("temp", [20.0, 85.0, 105.0], ids=["20C", "85C", "105C"])
def test_shells_reproduce_eq1_under_monotone_loading(temp):
    # Rate-independent shells (w = 1) loaded in small steps from the memorized shape follow the
    # closed-form Tobushi-Tanaka curve (elastic core + transformed rim); Gauss quadrature of a
    # kinked integrand: 1 % with 16 radii.
    p = SmaTaxel(n_shells=16)
    g, tl, tu = (float(p.shear_modulus(temp)), float(p.tau_load(temp)), float(p.tau_unload(temp)))
    gt = np.zeros(p.n_shells)
    deltas = np.linspace(0.0, 10e-3, 401)[1:]
    forces = []
    for d in deltas:
        f, _ = K.spring_eval(gt, p.s, p.wq, p.kappa, d, g, tl, tu, 1.0, True)
        forces.append(f)
    ref = p.load_curve(deltas, temp)
    assert np.max(np.abs(np.array(forces) - ref)) < 0.01 * ref.max()


def test_unloading_at_room_temperature_leaves_set_and_heating_recovers(still):
    # Seed Fig. 4: austenite recovers its shape on unloading, martensite (R) keeps a set.
    p = still
    gt = np.zeros(p.n_shells)
    for temp, expect_set in ((20.0, True), (105.0, False)):
        gt[:] = 0.0
        args = (float(p.shear_modulus(temp)), float(p.tau_load(temp)), float(p.tau_unload(temp)))
        for d in np.linspace(0, 8e-3, 200)[1:]:
            K.spring_eval(gt, p.s, p.wq, p.kappa, d, *args, 1.0, True)
        for d in np.linspace(8e-3, 0, 200):
            f, _ = K.spring_eval(gt, p.s, p.wq, p.kappa, d, *args, 1.0, True)
        assert (gt.max() > 1e-3) == expect_set
    # Heating the set spring at zero deflection recovers it (shape memory effect).
    hot = (float(p.shear_modulus(105.0)), float(p.tau_load(105.0)), float(p.tau_unload(105.0)))
    K.spring_eval(gt, p.s, p.wq, p.kappa, 0.0, *hot, 1.0, True)
    assert gt.max() == 0.0


# ---- kernels against their naive twins -----------------------------------------------------

@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_spring_eval_matches_numpy_twin(seed):
    rng = np.random.default_rng(seed)
    p = SmaTaxel()
    gt = rng.uniform(0, 0.02, p.n_shells) * (rng.random(p.n_shells) < 0.7)
    temp = rng.uniform(10, 140)
    g, tl, tu = float(p.shear_modulus(temp)), float(p.tau_load(temp)), float(p.tau_unload(temp))
    d = rng.uniform(0, 8e-3)
    w = rng.uniform(0.05, 1.0)
    f_ref, g_ref = naive_sma.shells_step(gt, p.s, p.wq, p.kappa, d, g, tl, tu, w)
    work = gt.copy()
    f, k = K.spring_eval(work, p.s, p.wq, p.kappa, d, g, tl, tu, w, True)
    assert f == pytest.approx(f_ref, rel=1e-12, abs=1e-15)
    np.testing.assert_allclose(work, g_ref, rtol=1e-12, atol=1e-18)
    # The returned stiffness is the derivative (central difference on a linear piece).
    e = 1e-10
    fp, _ = K.spring_eval(gt.copy(), p.s, p.wq, p.kappa, d + e, g, tl, tu, w, False)
    fm, _ = K.spring_eval(gt.copy(), p.s, p.wq, p.kappa, d - e, g, tl, tu, w, False)
    assert k > 0 and (fp - fm) / (2 * e) == pytest.approx(k, rel=1e-4)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_solve_pin_matches_brentq_twin(seed):
    rng = np.random.default_rng(seed)
    p = SmaTaxel()
    gi = p.installed_strains()
    gtu = gi * rng.uniform(0, 1.5) + rng.uniform(0, 2e-3, p.n_shells)
    gtl = gi * rng.uniform(0, 1.5) + rng.uniform(0, 2e-3, p.n_shells)
    tu, tl = rng.uniform(15, 130, 2)
    fe = rng.choice([0.0, rng.uniform(0, 0.6)])
    w = rng.uniform(0.1, 1.0)
    fp = p.kernel_params(FS, 1)
    fp[15] = w
    x_ref, net_ref, gu_ref, gl_ref = naive_sma.pin_step(p, gtu, gtl, tu, tl, fe, w)
    a, b = gtu.copy(), gtl.copy()
    x, net = K.solve_pin(a, b, p.s, p.wq, fp, rng.uniform(-2e-3, 2e-3), tu, tl, fe)
    assert x == pytest.approx(x_ref, abs=1e-12)
    assert net == pytest.approx(net_ref, abs=1e-9)
    np.testing.assert_allclose(a, gu_ref, atol=1e-12)
    np.testing.assert_allclose(b, gl_ref, atol=1e-12)


@pytest.mark.parametrize("crossbar, t_cut", [(False, math.inf), (True, math.inf), (False, 90.0)],
                         ids=["direct", "crossbar", "thermal-cutoff"])
def test_group_matches_sample_loop_twin(crossbar, t_cut):
    fs, k, n = 4800.0, 6, 1500
    p = SmaTaxel(cooling="forced", relax_time=1e-3, t_cut=t_cut)
    g = SmaGroup(p, fs, 4, max_block=n, mech_fs=fs / k, crossbar=crossbar, rows=2, slot=5 / fs)
    rng = np.random.default_rng(3)
    v = p.voltage_for(140.0) * 2.0
    drive = np.ascontiguousarray(np.repeat(rng.choice([-v, 0.0, v], (4, 6)), n // 6, axis=1))
    f_ext = np.array([0.0, 0.08, 0.3, 2.0])
    g.f_ext[:] = f_ext
    truth = np.zeros((4, 4, n))
    g.process(drive, np.zeros((0, n)), truth)
    ref, temp, probe = naive_sma.group_run(p, fs, k, drive, f_ext, crossbar, 2, 5)
    np.testing.assert_allclose(truth[:, 0], ref[:, 0], atol=1e-12)
    np.testing.assert_allclose(truth[:, 1], ref[:, 1], atol=1e-12 * fs)
    np.testing.assert_allclose(truth[:, 2:], ref[:, 2:], atol=1e-9)
    np.testing.assert_allclose(g.temperatures, temp, rtol=1e-12)
    np.testing.assert_allclose(g.probe, probe, rtol=1e-12)
    assert np.ptp(ref[:, 0]) > 1e-3           # the run did move the pins


@settings(max_examples=15, deadline=None)
@given(st.lists(st.integers(1, 200), min_size=1, max_size=12))
def test_chunk_invariance(splits):
    p = SmaTaxel(cooling="forced")
    n = 2400
    rng = np.random.default_rng(0)
    v = p.voltage_for(150.0)
    drive = np.ascontiguousarray(np.repeat(rng.choice([-v, v], (3, 8)), n // 8, axis=1))
    one = SmaGroup(p, FS, 3, max_block=n, mech_fs=2000.0, crossbar=True, rows=3, slot=1e-4)
    one.f_ext[:] = (0.0, 0.1, 0.4)
    ref = np.zeros((3, 4, n))
    one.process(drive, np.zeros((0, n)), ref)
    two = SmaGroup(p, FS, 3, max_block=n, mech_fs=2000.0, crossbar=True, rows=3, slot=1e-4)
    two.f_ext[:] = (0.0, 0.1, 0.4)
    out = np.zeros((3, 4, n))
    i = 0
    for m in splits * (n // max(1, sum(splits)) + 1):
        m = min(m, n - i)
        if m == 0:
            break
        tr = np.zeros((3, 4, m))
        two.process(np.ascontiguousarray(drive[:, i:i + m]), np.zeros((0, m)), tr)
        out[:, :, i:i + m] = tr
        i += m
    assert i == n
    np.testing.assert_array_equal(out, ref)


# ---- physics against closed forms and scipy ------------------------------------------------

def test_temperature_is_exact_first_order_response(still):
    # m c T' = V^2/R - h A (T - T_amb): T = T_amb + dT (1 - exp(-t / tau)) for a constant drive.
    g = SmaGroup(still, FS, 2, max_block=960)
    v = still.voltage_for(90.0)
    run(g, np.array([v, -v]), 1.0)
    t = 1.0
    expect = 20.0 + 70.0 * (1 - math.exp(-t / still.thermal_time_constant))
    np.testing.assert_allclose(np.diag(g.temperatures), expect, rtol=1e-10)   # 48k roundings
    np.testing.assert_allclose(g.temperatures[[0, 1], [1, 0]], 20.0, rtol=1e-12)


def _radau(plant, u_of_segments, f_ext, t_grid):
    y = plant.y0
    out = []
    for (t0, t1, u) in u_of_segments:
        sel = t_grid[(t_grid >= t0) & (t_grid < t1)]
        sol = solve_ivp(plant.rhs, (t0, t1), y, method="Radau", args=(u, f_ext), t_eval=sel,
                        rtol=1e-9, atol=1e-12, max_step=0.01)
        assert sol.success
        out.extend(plant.pin(sol.y[:, j], f_ext) for j in range(sol.y.shape[1]))
        y = sol.y[:, -1] if sol.t[-1] == t1 else solve_ivp(
            plant.rhs, (sel[-1], t1), sol.y[:, -1], method="Radau", args=(u, f_ext),
            rtol=1e-9, atol=1e-12).y[:, -1]
    return np.array(out)


@pytest.mark.slow
def test_kernel_converges_to_radau_reference(forced):
    # Raise, cool, lower under a 50 mN finger: the kernel (exact thermal, implicit Euler on the
    # transformation at mech_fs) against solve_ivp(Radau) of SmaTaxel.rhs.
    v = forced.voltage_for(T_DRIVE)
    segs = [(0.0, 0.6, v), (0.6, 1.2, 0.0), (1.2, 1.8, -v), (1.8, 2.4, 0.0)]
    fs = 48000.0
    t = np.arange(0, int(2.4 * fs), 48) / fs
    ref = _radau(forced, segs, 0.05, t)
    ends = np.searchsorted(t, [0.55, 1.15, 1.75, 2.35])   # settled, 50 ms before each switch
    errs = {}
    for mech in (500.0, 8000.0):
        g = SmaGroup(forced, fs, 1, max_block=960, mech_fs=mech)
        x, _ = run(g, lambda tt: np.where(tt < 0.6, v, 0.0) + np.where((tt >= 1.2) & (tt < 1.8), -v, 0.0),
                   2.4, f_ext=0.05)
        # output sample n is the pin at time (n - lag_samples) / fs
        ref_l = np.interp(t - g.lag_samples / fs, t, ref)
        errs[mech] = np.max(np.abs(x[0, 0, ends] - ref_l[ends]))
    assert np.ptp(ref) > 2.5e-3
    # Measured: 0.37 um at 500 Hz, 0.016 um at 8 kHz (implicit Euler: first order in 1/mech_fs).
    assert errs[8000.0] < 0.05e-6
    assert errs[500.0] > 8 * errs[8000.0]


# ---- the seed's taxel behaviour ----------------------------------------------------------

def _cycle(plant, sign, seconds=4.0, cool=6.0):
    g = SmaGroup(plant, FS, 1, max_block=960)
    v = sign * plant.voltage_for(T_DRIVE)
    hot, _ = run(g, np.array([v]), seconds)
    cold, _ = run(g, np.array([0.0]), cool)
    return g, hot[0, 0, -1], cold[0, 0, -1]


def test_bistable_pin_stays_where_the_heated_spring_left_it(forced):
    # Seed Figs. 5, 6: A (raise spring hot) -> C after cooling, B -> D; C and D are the
    # unpowered positions, "height range of 1.4 mm".
    _, a, c = _cycle(forced, +1.0)
    _, b, d = _cycle(forced, -1.0)
    assert a > c > 0.3e-3 and b < d < -0.3e-3
    assert c - d == pytest.approx(1.4e-3, rel=0.1)
    assert a == pytest.approx(-b, rel=1e-6)   # identical springs: a symmetric taxel


def test_holds_100mN_retracts_under_harder_push_and_rises_again(forced):
    # Seed Figs. 7(b), 9(b), 10: raised, unpowered (martensite) taxel: withstands 100 mN, a
    # 102 mN (measured) / 120 mN (model) push retracts it to surface level (height 0), and it
    # rises again when released.
    g, _, c = _cycle(forced, +1.0)
    x, _ = run(g, np.array([0.0]), 0.2, f_ext=0.100)
    assert x[0, 0, -1] > 0.0
    assert x[0, 2, -1] == 0.100
    x, _ = run(g, np.array([0.0]), 0.2, f_ext=0.120)
    assert x[0, 0, -1] <= 0.0
    x, _ = run(g, np.array([0.0]), 0.2, f_ext=0.0)
    assert x[0, 0, -1] > 0.3e-3 and x[0, 2, -1] == 0.0


@pytest.mark.parametrize("temp,lo,hi", [(85.0, 0.28, 0.34)], ids=["85C"])
def test_austenitic_raise_spring_needs_about_300mN_to_retract(forced, temp, lo, hi):
    # Seed Fig. 7(a) (320 mN, model) and Fig. 9(a) (300 mN, measured): force that pushes the
    # pin from A to height 0 while the raise spring is held austenitic.
    g = SmaGroup(forced, FS, 1, max_block=960)
    v = forced.voltage_for(temp)
    run(g, np.array([v]), 5.0)

    def height(f):
        x, _ = run(g, np.array([v]), 0.05, f_ext=f)
        return x[0, 0, -1]
    assert height(lo) > 0.0 > height(hi)


def test_lower_stop_carries_the_excess_push(forced):
    g = SmaGroup(forced, FS, 1, max_block=960)
    x, _ = run(g, np.array([0.0]), 0.2, f_ext=5.0)
    assert x[0, 0, -1] == -forced.stop_down
    assert 0.0 <= x[0, 2, -1] < 5.0


def _strokes(plant, freqs, seconds):
    g = SmaGroup(plant, FS, len(freqs), max_block=960)
    v = plant.voltage_for(T_DRIVE)
    freqs = np.asarray(freqs)[:, None]
    x, _ = run(g, lambda t: v * np.sign(np.sin(2 * np.pi * freqs * t[None, :]) + 1e-12), seconds)
    t = np.arange(x.shape[2]) * 48 / FS
    return np.array([np.ptp(x[j, 0, t >= seconds - max(2 / f, 10.0)]) for j, f in enumerate(freqs[:, 0])])


@pytest.mark.slow
def test_still_air_saturates_between_027_and_037_hz(still):
    # Seed Fig. 11(a): tracking at 0.27 Hz, saturation soon after (0.37 Hz) without the fan.
    s = _strokes(still, [0.1, 0.27, 0.37, 1.5], 40.0)
    assert s[1] > 0.8 * s[0]
    assert s[2] < 0.5 * s[0] and s[3] < 0.1 * s[0]


@pytest.mark.slow
def test_forced_air_full_stroke_at_1p5_hz(forced):
    # Seed Fig. 11(b): full stroke to 1.5 Hz with the mini-fan; it saturates above (3 Hz).
    s = _strokes(forced, [0.1, 1.0, 1.5, 3.0], 30.0)
    assert s[1] > 0.8 * s[0] and s[2] > 0.8 * s[0]
    assert s[3] < 0.5 * s[0]


def test_thermal_cutoff_holds_a_spring_near_t_cut_and_never_reaches_t_max(still):
    # A drive that settles at 200 degC without a cutoff: with t_cut = 120 the raise spring
    # hovers within one sample's heating of 120 degC and the run never signals over-temperature.
    p = SmaTaxel(cooling="still", t_cut=120.0)
    g = SmaGroup(p, FS, 1, max_block=480)
    v = p.voltage_for(200.0)
    x, st = run(g, np.array([v]), 20.0, block=480)
    assert not st & K.STATUS_OVERTEMP
    step = (200.0 - p.t_ambient) * -math.expm1(-1.0 / (FS * p.heat_capacity / (p.h * p.area)))
    assert 120.0 - 1e-9 <= g.temperatures[0, 0] < 120.0 + 2 * step
    assert x[0, 0, -1] > 0.5e-3               # and the pin is up


# ---- group contract --------------------------------------------------------------------------

def test_overtemperature_and_nonfinite_status(forced):
    g = SmaGroup(forced, FS, 2, max_block=64)
    v = forced.voltage_for(200.0)
    _, st = run(g, np.array([v, 0.0]), 0.5, block=64)
    assert st & K.STATUS_OVERTEMP and g.probe[0].max() > forced.t_max
    assert g.probe[1, 0] == pytest.approx(v * v / forced.resistance)
    g.reset()
    _, st = run(g, np.array([0.0, 0.0]), 0.01, block=64)
    assert st == 0
    _, st = run(g, np.array([np.nan, 0.0]), 0.01, block=64)
    assert st & K.STATUS_NONFINITE
    _, st = run(g, np.array([0.0, 0.0]), 0.01, block=64)
    assert st & K.STATUS_NONFINITE           # sticky until reset
    g.reset()
    _, st = run(g, np.array([0.0, 0.0]), 0.01, block=64)
    assert st == 0


def test_crossbar_row_scan_delivers_one_row_at_a_time(forced):
    # 8x8 at 1 ms slots: each taxel is powered 1/8 of the time, so a sqrt(8) x higher voltage
    # heats like the direct drive (mean power equal; 8 ms scan << 0.45 s thermal time).
    v = forced.voltage_for(90.0)
    direct = SmaGroup(forced, FS, 64, max_block=960)
    xbar = SmaGroup(forced, FS, 64, max_block=960, crossbar=True)
    tr, _ = run(xbar, np.full(64, v * math.sqrt(8)), 1.0, every=1)
    run(direct, np.full(64, v), 1.0)
    # Within the scan ripple: a row heats at 8x the mean power for one 1 ms slot per 8 ms.
    ripple = 8 * (90.0 - 20.0) * 1e-3 / forced.thermal_time_constant
    np.testing.assert_allclose(xbar.temperatures, direct.temperatures, atol=ripple)
    applied = tr[:, 3] != 0.0                    # (64, n): who got power at each sample
    per_sample = applied.reshape(8, 8, -1).any(axis=1).sum(axis=0)
    assert np.all(per_sample == 1)               # exactly one row line at V at any time
    assert applied.mean() == pytest.approx(1 / 8, abs=1e-3)


def test_group_attributes(forced):
    g = SmaGroup(forced, FS, 64, max_block=32)
    assert g.kernel is sma_group_process and g.n_sensed == 0 and g.capacitance == 0.0
    assert g.probe is g.args[9] and g.probe.shape == (2, 32)
    assert [n for n, _ in g.probe_names] == ["spring_temp_max", "power"]
    assert g.temperatures is g.args[4] and g.f_ext is g.args[8]
    np.testing.assert_array_equal(g.state(5), forced.y0)


@pytest.mark.parametrize("kw", [dict(cooling="fan"), dict(a_s=28.0), dict(prestrain=-1.0),
                                dict(stop_down=3e-3), dict(n_shells=1), dict(t_max=10.0)],
                         ids=["cooling", "a_s", "prestrain", "stop", "shells", "t_max"])
def test_bad_parameters_raise_model_error(kw):
    with pytest.raises(ModelError):
        SmaTaxel(**kw)


def test_docstring_examples_run():
    import doctest

    import rtctl.plant.sma as mod
    res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert res.attempted > 0 and res.failed == 0


def test_substeps_sets_the_mechanical_rate_and_the_lag(forced):
    g = SmaGroup(forced, FS, 1, substeps=12)
    assert g.k_mech == 12 and g.lag_samples == 11
    assert SmaGroup(forced, FS, 1, mech_fs=4000.0).k_mech == 12
