"""The final limiter against closed forms and its naive twin."""

import naive_loop
import numpy as np
import pytest

from rtctl import safety
from rtctl.safety import LIMIT_SLEW, LIMIT_VOLTAGE, NONFINITE, OVERTEMP, Limiter


def make(n=3, fs=48000.0, **kw):
    args = dict(max_voltage=100.0, slew=1e6, current=0.05, capacitance=10e-9, temperature=80.0,
                ambient=25.0, loss_tangent=0.02, thermal_resistance=150.0, thermal_tau=20.0)
    args.update(kw)
    args["max_voltage"] = np.broadcast_to(args["max_voltage"], (n,))
    return Limiter(fs, **args)


@pytest.mark.parametrize("smooth", [False, True], ids=["fault-fade", "requested-stop"])
def test_kernel_matches_naive_twin_on_random_requests(smooth):
    rng = np.random.default_rng(0)
    lim, ref = make(4, slew=2e6, current=1e-2), make(4, slew=2e6, current=1e-2)
    for k in range(20):
        x = rng.normal(0, 80, (4, 37))
        x[rng.random(x.shape) < 0.01] = np.nan
        if k == 15:
            lim.shutdown(50, smooth), ref.shutdown(50, smooth)
        y = x.copy()
        s1 = lim.process(x)
        s2 = naive_loop.limit_block(y, *ref.args)
        assert s1 == s2
        np.testing.assert_allclose(x, y, rtol=1e-13, atol=1e-12)
    np.testing.assert_array_equal(lim.counts, ref.counts)
    np.testing.assert_allclose(lim.state, ref.state, rtol=1e-12)


def test_kernel_matches_naive_twin_with_time_constants_differing_between_channels():
    """The kernel reuses a one-pole factor while the next channel's time constant is the same:
    channels whose thermal and DC-mean time constants alternate, repeat and differ, with a DC
    bound that the offset requests reach, against the twin that computes every factor."""
    rng = np.random.default_rng(3)
    kw = dict(slew=2e6, current=1e-2, thermal_tau=[20.0, 20.0, 5.0, 20.0, 5.0, 5.0, 1.0],
              dc_offset=[4.0, 4.0, 4.0, np.inf, 6.0, 4.0, 4.0], dc_tau=[0.01, 0.02, 0.02, 0.01, 0.01, 0.01, 0.05])
    lim, ref = make(7, **kw), make(7, **kw)
    for k in range(30):
        x = rng.normal(20.0 if k < 20 else -20.0, 40, (7, 33))
        y = x.copy()
        assert lim.process(x) == naive_loop.limit_block(y, *ref.args)
        np.testing.assert_allclose(x, y, rtol=1e-13, atol=1e-12)
    np.testing.assert_array_equal(lim.counts, ref.counts)
    assert lim.counts[2].sum() > 0  # the DC bound acted
    np.testing.assert_allclose(lim.state, ref.state, rtol=1e-12)


@pytest.mark.parametrize("seed", range(6))
def test_kernel_matches_naive_twin_through_stops_fades_and_silent_blocks(seed):
    """Runs that stop: a requested stop's raised cosine or a fault's linear fade begun at a
    random block, its length no multiple of the block (it ends mid-block), a fault cutting a
    raised cosine short, all-zero blocks before, during and after the fade, NaN/Inf requests
    and DC offsets the bound acts on; time constants shared by neighbours or not. Every block:
    status, samples, the fade's progress and ``done`` against the twin, which computes every
    one-pole factor and sum per channel and clamps sample by sample."""
    rng = np.random.default_rng(100 + seed)
    n_ch, block = 6, (1, 5, 32, 33, 32, 64)[seed]
    kw = dict(slew=rng.choice([3e4, 2e6], n_ch), current=1e-2, thermal_tau=rng.choice([1.0, 20.0], n_ch),
              dc_offset=[3.0, 8.0, np.inf, 3.0, 8.0, 3.0], dc_tau=rng.choice([0.002, 0.01], n_ch))
    lim, ref = make(n_ch, **kw), make(n_ch, **kw)
    n_blocks = max(24, 1200 // block)
    stop_at = int(rng.integers(n_blocks // 2, 3 * n_blocks // 4))
    cut_at = stop_at + 2 if seed % 3 == 2 else -1  # a fault during the raised cosine
    smooth = seed % 2 == 0 or cut_at > 0
    offset = np.array([40.0, -40.0, 40.0, 40.0, -40.0, 0.0])  # held: the running means climb to their bounds
    seen_done = False
    for k in range(n_blocks):
        kind = rng.integers(4)
        if kind == 0:
            x = np.zeros((n_ch, block))
        else:
            x = rng.normal(offset[:, None], 60.0, (n_ch, block))
            if kind == 1:
                x[rng.random(x.shape) < 0.05] = rng.choice([np.nan, np.inf, -np.inf])
            if kind == 2:
                x[rng.integers(n_ch)] = 0.0  # one silent channel among driven ones
        if k == stop_at:
            length = int(rng.integers(1, 4 * block + 2))
            assert lim.shutdown(length, smooth) == ref.shutdown(length, smooth)
        if k == cut_at:
            assert lim.shutdown(block, False) == ref.shutdown(block, False)
        y = x.copy()
        assert lim.process(x) == naive_loop.limit_block(y, *ref.args), k
        # where the DC bound lowers a block, the ceiling's root search stops within 1e-13 vmax
        # (1e-11 V) and the twin's brentq elsewhere: the tolerances of the mean bounds' twin test
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-9, err_msg=str(k))
        np.testing.assert_array_equal(lim.fade, ref.fade)
        np.testing.assert_array_equal(lim.counts, ref.counts)
        np.testing.assert_allclose(lim.state, ref.state, rtol=1e-9, atol=1e-9, err_msg=str(k))
        assert lim.done == ref.done, k
        seen_done |= lim.done
        if lim.done:
            assert not np.any(x[:, -1])
    assert seen_done and lim.counts[2].sum() > 0  # the fade ended and the DC bound acted


def test_nan_and_inf_become_zero_and_raise_the_fault_bit():
    lim = make(1)
    x = np.array([[np.nan, np.inf, -np.inf]])
    s = lim.process(x)
    assert s & NONFINITE and s & safety.FAULTS
    assert np.all(x == 0.0)


def test_voltage_is_clipped_and_counted():
    lim = make(1, max_voltage=10.0, slew=1e12, current=1e6)
    x = np.array([[5.0, 20.0, -30.0, 9.0]])
    assert lim.process(x) == LIMIT_VOLTAGE
    assert x.tolist() == [[5.0, 10.0, -10.0, 9.0]]
    assert lim.counts[0, 0] == 2


def test_current_limit_is_a_slope_limit_on_the_capacitor():
    # I = C dV/dt (a piezo is a capacitor): a step request must never draw more than I_max.
    fs, C, imax = 48000.0, 100e-9, 0.02
    lim = make(1, fs=fs, capacitance=C, current=imax, slew=1e9)
    x = np.full((1, 400), 100.0)
    assert lim.process(x) & LIMIT_SLEW
    i = C * np.diff(np.r_[0.0, x[0]]) * fs
    assert i.max() == pytest.approx(imax, rel=1e-12)
    # the closed form of a rate-limited step: a straight line until it reaches the request
    n_ramp = int(np.ceil(100.0 / (imax / C / fs)))
    np.testing.assert_allclose(x[0, : n_ramp - 1], (imax / C / fs) * np.arange(1, n_ramp), rtol=1e-12)
    assert x[0, -1] == 100.0


def test_dielectric_heating_reaches_the_closed_form_steady_state():
    # Sine of amplitude V at f: P = tan(d) w C V^2 / 2; T_ss = T_amb + R_th P.
    fs, f, V, C, tand, rth, tau = 48000.0, 500.0, 100.0, 200e-9, 0.02, 150.0, 0.05
    lim = make(1, fs=fs, capacitance=C, loss_tangent=tand, thermal_resistance=rth, thermal_tau=tau,
               temperature=1000.0, slew=1e9, current=10.0, max_voltage=200.0)
    n = int(fs * 20 * tau)  # 20 time constants
    t = np.arange(n) / fs
    x = (V * np.sin(2 * np.pi * f * t))[None, :].copy()
    for i in range(0, n, 480):
        lim.process(x[:, i:i + 480])
    p = tand * 2 * np.pi * f * C * V**2 / 2
    assert lim.temperature[0] == pytest.approx(25.0 + rth * p, rel=2e-3)


def test_overtemperature_is_a_fault():
    lim = make(1, temperature=25.5, loss_tangent=0.5, thermal_tau=1e-3, thermal_resistance=1e4,
               capacitance=1e-6, current=10.0, slew=1e9)
    t = np.arange(4800) / 48000.0
    x = (100 * np.sin(2 * np.pi * 300 * t))[None, :].copy()
    assert lim.process(x) & OVERTEMP & safety.FAULTS


def test_shutdown_fades_to_zero_in_the_given_samples_and_ignores_requests():
    lim = make(2, slew=1e9, current=10.0)
    x = np.full((2, 32), 50.0)
    x[1] = -40.0
    lim.process(x)
    lim.shutdown(32)
    y = np.full((2, 40), np.nan)  # a controller gone wrong
    lim.process(y)
    np.testing.assert_allclose(y[:, :32], np.outer([50.0, -40.0], 1 - np.arange(1, 33) / 32), atol=1e-12)
    assert np.all(y[:, 31:] == 0.0) and lim.done
    z = np.full((2, 8), 1e3)
    lim.process(z)
    assert np.all(z == 0.0)


def test_rejects_unsafe_parameters():
    with pytest.raises(ValueError, match="max_voltage"):
        make(1, max_voltage=np.inf)
    with pytest.raises(ValueError, match="capacitance"):
        make(1, capacitance=0.0)


def test_describe_names_bits():
    assert safety.describe(NONFINITE | LIMIT_VOLTAGE) == ["voltage limited",
                                                          "non-finite drive request (NaN/Inf) replaced by 0 V"]


def test_shutdown_lengthens_the_fade_when_the_slew_limit_needs_it():
    fs, slew = 48000.0, 1e5  # 2.08 V per sample: a 100 V output needs 48 samples to reach 0
    lim = make(1, fs=fs, slew=slew, current=10.0, max_voltage=200.0)
    x = np.full((1, 200), 100.0)
    lim.process(x)
    assert lim.last[0] == 100.0
    n = lim.shutdown(32)
    assert n == int(np.floor(100.0 / (slew / fs))) + 1
    y = np.zeros((1, 32))
    assert not (lim.process(y) & LIMIT_SLEW)  # the fade itself never needs clamping
    assert not lim.done and y[0, -1] > 0.0
    z = np.zeros((1, 32))
    assert not (lim.process(z) & LIMIT_SLEW)
    assert lim.done and z[0, -1] == 0.0


def test_coil_channel_bounds_steady_current_and_heats_by_joule_loss():
    # A coil (capacitance 0, resistance R): |V| <= I_max R, slope only by the slew bound, and
    # the thermal model settles at T_amb + R_th V^2 / R for a held DC voltage.
    R, imax, rth = 8.0, 0.5, 20.0
    lim = make(1, capacitance=0.0, resistance=R, current=imax, max_voltage=12.0, slew=1e9,
               thermal_resistance=rth, thermal_tau=1e-3)
    x = np.full((1, 48000), 12.0)
    assert lim.process(x) & LIMIT_VOLTAGE
    assert x.max() == pytest.approx(imax * R)           # 4 V, not 12 V
    assert lim.temperature[0] == pytest.approx(25.0 + rth * (imax * R) ** 2 / R, rel=1e-9)
    # a piezo channel next to a coil keeps its slope limit; the naive twin agrees
    lim2 = Limiter(48000.0, max_voltage=[12.0, 100.0], slew=1e9, current=[imax, 0.02],
                   capacitance=[0.0, 100e-9], resistance=[R, 0.0], temperature=80.0, ambient=25.0,
                   loss_tangent=0.02, thermal_resistance=rth, thermal_tau=1e-3)
    ref = Limiter(48000.0, max_voltage=[12.0, 100.0], slew=1e9, current=[imax, 0.02],
                  capacitance=[0.0, 100e-9], resistance=[R, 0.0], temperature=80.0, ambient=25.0,
                  loss_tangent=0.02, thermal_resistance=rth, thermal_tau=1e-3)
    x = np.random.default_rng(1).normal(0, 30, (2, 64))
    y = x.copy()
    assert lim2.process(x) == naive_loop.limit_block(y, *ref.args)
    np.testing.assert_allclose(x, y, rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(lim2.state, ref.state, rtol=1e-12)


def test_a_channel_with_neither_capacitance_nor_resistance_is_refused():
    with pytest.raises(ValueError, match="resistance"):
        make(1, capacitance=0.0)


def test_pin_commands_keep_the_voltage_bound_but_do_not_heat():
    # Behind a serial pin controller a held level is a command, the firmware pulses the coil:
    # same voltage bound as the coil (|V| <= I_max R), no Joule heating from holding it.
    R, imax = 8.0, 0.5
    lim = make(1, capacitance=0.0, resistance=R, current=imax, max_voltage=12.0, slew=1e9,
               thermal_resistance=20.0, thermal_tau=1e-3)
    lim.commands_only()
    x = np.full((1, 48000), 12.0)
    assert lim.process(x) & LIMIT_VOLTAGE
    assert x.max() == pytest.approx(imax * R)
    assert lim.temperature[0] == pytest.approx(25.0, abs=1e-12)


def test_a_requested_stop_releases_the_request_under_a_raised_cosine():
    fs, n = 48000.0, 1440  # a 30 ms release
    lim = make(1, fs=fs, slew=1e9, current=10.0)
    t = np.arange(4 * n) / fs
    tone = 90.0 * np.sin(2 * np.pi * 250.0 * t)
    x = tone[:64].reshape(1, -1).copy()
    lim.process(x)
    assert lim.shutdown(n, smooth=True) == n and lim.smooth_stop
    y = tone[64:64 + 2 * n].reshape(1, -1).copy()
    for b in range(0, y.shape[1], 32):  # block by block, as the loop runs it
        lim.process(y[:, b:b + 32])
    k = np.arange(1, 2 * n + 1)
    window = np.where(k < n, 0.5 * (1 + np.cos(np.pi * k / n)), 0.0)  # Hann's falling half
    np.testing.assert_allclose(y[0], tone[64:64 + 2 * n] * window, atol=1e-12)
    assert lim.done and np.all(y[0, n - 1:] == 0.0)
    # the release is smooth: no step larger than the tone's own (a fault's fade: 90 V in one block)
    assert np.abs(np.diff(y[0])).max() <= 2 * np.pi * 250.0 * 90.0 / fs
    # a fault during a release cuts it to a linear fade from where the output is
    lim2 = make(1, fs=fs, slew=1e9, current=10.0)
    lim2.process(tone[:64].reshape(1, -1).copy())
    lim2.shutdown(n, smooth=True)
    z = tone[64:64 + 320].reshape(1, -1).copy()
    lim2.process(z)
    v = lim2.last[0]
    lim2.shutdown(32)
    assert not lim2.smooth_stop
    w = np.full((1, 32), np.nan)
    lim2.process(w)
    np.testing.assert_allclose(w[0], v * (1 - np.arange(1, 33) / 32), atol=1e-12)
    assert lim2.done
