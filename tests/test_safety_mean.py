"""The limiter's running-mean bounds (a piezo's DC offset, an SMA spring's duty) against closed
forms and the naive twin (whose ceiling comes from scipy's brentq, not a bisection)."""

import json
import math

import naive_loop
import numpy as np
import pytest

from rtctl.safety import LIMIT_DC, LIMIT_DUTY, Limiter

FS, BLOCK = 48000.0, 32


def piezo(n=1, **kw):
    args = dict(max_voltage=100.0, slew=5e6, current=10.0, capacitance=10e-9, temperature=1e3, ambient=25.0,
                loss_tangent=0.02, thermal_resistance=150.0, thermal_tau=20.0, dc_offset=10.0, dc_tau=0.1)
    args.update(kw)
    args["max_voltage"] = np.broadcast_to(args["max_voltage"], (n,))
    return Limiter(FS, **args)


def sma(**kw):
    # seed 002's spring: R = 1.56 ohm, 2 A; max_voltage 2 V is the tighter bound
    args = dict(max_voltage=[2.0], slew=1e6, current=2.0, capacitance=0.0, resistance=1.56, temperature=1e3,
                ambient=20.0, loss_tangent=0.0, thermal_resistance=5.0, thermal_tau=10.0, duty=0.5, duty_tau=0.05)
    args.update(kw)
    return Limiter(FS, **args)


def run_blocks(lim, x):
    status, means = 0, []
    for i in range(0, x.shape[1], BLOCK):
        status |= lim.process(x[:, i:i + BLOCK])
        means.append(lim.mean.copy())
    return status, np.array(means)


def test_a_dc_request_rises_like_the_one_pole_then_is_held_at_the_bound():
    V, D, tau = 50.0, 10.0, 0.1
    lim = piezo(dc_offset=D, dc_tau=tau)
    n = int(FS * 0.2) // BLOCK * BLOCK
    x = np.full((1, n), V)
    status, m = run_blocks(lim, x)
    assert status & LIMIT_DC
    t_end = np.arange(1, m.shape[0] + 1) * BLOCK / FS
    free = V * -np.expm1(-t_end / tau)  # the one-pole's step response, exact at block ends
    t_star = -tau * math.log(1 - D / V)  # when it reaches the bound: 22.3 ms
    before = t_end < t_star - BLOCK / FS
    np.testing.assert_allclose(m[before, 0, 0], free[before], rtol=1e-12)
    assert np.all(m[:, 0, 0] <= D * (1 + 1e-12))
    k_star = int(t_star * FS)
    assert np.all(x[0, : k_star - BLOCK] == V)   # untouched before
    np.testing.assert_allclose(x[0, k_star + BLOCK:], D, rtol=1e-12)  # then held at the bound
    assert m[-1, 0, 0] == pytest.approx(D, rel=1e-12)
    assert lim.counts[2, 0] == n - np.argmax(x[0] < V)


def test_a_zero_mean_sine_passes_untouched_and_its_mean_follows_the_closed_form():
    # 1 Hz at full voltage through a 10 s mean: m(t) = V (sin wt - wt cos wt + wt e^(-t/tau)) / (1 + (w tau)^2)
    V, f, tau = 100.0, 1.0, 10.0
    lim = piezo(dc_offset=10.0, dc_tau=tau)
    n = int(FS * 3) // BLOCK * BLOCK
    t = np.arange(n) / FS
    x = (V * np.sin(2 * np.pi * f * t))[None, :]
    y = x.copy()
    status, m = run_blocks(lim, y)
    assert not status & LIMIT_DC and lim.counts[2, 0] == 0
    np.testing.assert_array_equal(y, x)
    # the block mean is the one-pole's exact integral over the block (weights flat to T/tau = 3e-5);
    # the samples sit at i/fs, half a sample before the continuous signal they average
    te = np.arange(1, m.shape[0] + 1) * BLOCK / FS - 0.5 / FS
    wt = 2 * np.pi * f * tau
    closed = V * (np.sin(2 * np.pi * f * te) - wt * np.cos(2 * np.pi * f * te) + wt * np.exp(-te / tau)) / (1 + wt**2)
    amp = V * wt / (1 + wt**2)  # 1.6 V
    np.testing.assert_allclose(m[:, 0, 0], closed, atol=2e-3 * amp)


def test_an_offset_sine_is_lowered_until_its_mean_sits_on_the_bound():
    V, off, D = 40.0, 30.0, 5.0
    lim = piezo(dc_offset=D, dc_tau=0.02)
    n = int(FS * 0.5) // BLOCK * BLOCK
    t = np.arange(n) / FS
    x = (off + V * np.sin(2 * np.pi * 200 * t))[None, :]
    status, m = run_blocks(lim, x)
    assert status & LIMIT_DC
    assert np.all(m[:, 0, 0] <= D * (1 + 1e-12))
    last = m[-int(0.1 * FS / BLOCK):, 0, 0]  # blocks of a 200 Hz sine differ: the mean touches the bound
    assert last.max() == pytest.approx(D, rel=1e-9) and last.min() > 0.8 * D
    assert 0.8 * D < x[0, -int(0.1 * FS):].mean() <= D * (1 + 1e-9)
    assert np.all(np.abs(np.diff(x[0])) <= 5e6 / FS * (1 + 1e-12))  # the ceiling never breaks the slew bound


def test_a_held_sma_spring_is_held_at_the_duty_bound_power():
    # full voltage held on one spring: duty (v/Vmax)^2 rises as 1 - e^(-t/tau) to 0.5 at tau ln 2,
    # then the ceiling holds the power at half: v = Vmax / sqrt(2)
    duty, tau = 0.5, 0.05
    lim = sma(duty=duty, duty_tau=tau)
    n = int(FS * 0.3) // BLOCK * BLOCK
    x = np.full((1, n), 2.0)
    status, m = run_blocks(lim, x)
    assert status & LIMIT_DUTY
    assert np.all(m[:, 0, 0] <= duty * (1 + 1e-12)) and np.all(m[:, 1, 0] == 0.0)
    k_star = int(tau * math.log(2) * FS)
    assert np.all(x[0, : k_star - BLOCK] == 2.0)
    np.testing.assert_allclose(x[0, k_star + BLOCK:], 2.0 / math.sqrt(2.0), rtol=1e-9)
    # the other polarity has its own duty: a negative hold now runs at full voltage
    y = np.full((1, 64), -2.0)
    lim.process(y)
    assert np.all(y == -2.0)


def test_a_square_wave_drive_of_half_duty_per_spring_passes_untouched():
    # the sma-8x8 scene's drive: +-1.62 V at 1.5 Hz, each spring on half the time: (1.62/2)^2 / 2 = 0.33
    lim = sma(duty=0.5, duty_tau=2.0)
    n = int(FS * 4) // BLOCK * BLOCK
    t = np.arange(n) / FS
    x = (1.62 * np.sign(np.sin(2 * np.pi * 1.5 * t)))[None, :]
    y = x.copy()
    status, m = run_blocks(lim, y)
    assert not status & LIMIT_DUTY
    np.testing.assert_array_equal(y, x)
    assert 0.25 < m[-1, 0, 0] < 0.45 and 0.25 < m[-1, 1, 0] < 0.45


@pytest.mark.parametrize("smooth", [False, True], ids=["fault-fade", "requested-stop"])
def test_kernel_matches_naive_twin_with_the_mean_bounds_engaged(smooth):
    rng = np.random.default_rng(3)
    kw = dict(max_voltage=[100.0, 100.0, 2.0, 12.0], slew=[2e6, 3e4, 1e6, 1e9], current=[1e-2, 1e-2, 2.0, 1.0],
              capacitance=[1e-8, 1e-8, 0.0, 0.0], resistance=[0.0, 0.0, 1.56, 8.0], temperature=1e3,
              ambient=25.0, loss_tangent=0.02, thermal_resistance=5.0, thermal_tau=1.0,
              dc_offset=[8.0, 3.0, np.inf, np.inf], dc_tau=0.005, duty=[np.inf, np.inf, 0.3, np.inf], duty_tau=0.004)
    lim, ref = Limiter(FS, **kw), Limiter(FS, **kw)
    seen = 0
    for k in range(40):
        x = rng.normal(0, 1, (4, 32)) * [[60], [60], [2.5], [10]] + [[40], [-30], [1.0], [0]]
        if k == 35:
            lim.shutdown(50, smooth), ref.shutdown(50, smooth)
        y = x.copy()
        s1 = lim.process(x)
        s2 = naive_loop.limit_block(y, *ref.args)
        seen |= s1
        assert s1 == s2
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(lim.state, ref.state, rtol=1e-9, atol=1e-9)
    assert seen & LIMIT_DC and seen & LIMIT_DUTY
    np.testing.assert_array_equal(lim.counts, ref.counts)


def test_behind_a_pin_controller_the_duty_bound_counts_commanded_time():
    # a held UP command (the firmware heats at its own full power whatever the level above the
    # threshold): the bound switches whole blocks off so the commanded share settles at the duty
    duty, tau = 0.3, 0.05
    lim = sma(duty=duty, duty_tau=tau)
    lim.commands_only(1.0)
    n = int(FS * 1.0) // BLOCK * BLOCK
    x = np.full((1, n), 2.0)
    status, m = run_blocks(lim, x)
    assert status & LIMIT_DUTY
    assert np.all(m[:, 0, 0] <= duty * (1 + 1e-12))
    on = x[0].reshape(-1, BLOCK)[:, -1] > 1.0  # the command a block sends: its last sample
    assert np.all(on[: int(-tau * math.log(1 - duty) * FS / BLOCK) - 1])  # on until the bound
    assert set(np.unique(x)) <= {0.0, 2.0}                   # commands are on or off, never lowered
    assert on[n // BLOCK // 2:].mean() == pytest.approx(duty, abs=0.01)
    # the naive twin agrees on a random command stream
    a, b = sma(duty=duty, duty_tau=0.004), sma(duty=duty, duty_tau=0.004)
    a.commands_only(1.0), b.commands_only(1.0)
    rng = np.random.default_rng(7)
    for _ in range(30):
        y = rng.choice([-2.0, 0.0, 2.0], size=(1, BLOCK), p=[0.3, 0.2, 0.5])
        z = y.copy()
        assert a.process(y) == naive_loop.limit_block(z, *b.args)
        np.testing.assert_array_equal(y, z)
    np.testing.assert_array_equal(a.counts, b.counts)
    np.testing.assert_allclose(a.state, b.state, rtol=1e-12)
    with pytest.raises(ValueError, match="threshold"):
        sma().commands_only()


def test_mean_bounds_apply_to_their_own_kind_of_channel():
    with pytest.raises(ValueError, match="dc_offset bounds piezo"):
        sma(dc_offset=1.0)
    with pytest.raises(ValueError, match="duty coil"):
        piezo(duty=0.5)
    with pytest.raises(ValueError, match="duty in"):
        sma(duty=1.5)
    with pytest.raises(ValueError, match="dc_tau"):
        piezo(dc_tau=0.0)


def run_json(capsys, tmp_path, scene, *sets):
    from rtctl.cli import main

    args = ["run", scene, "--json", "--no-plot", "--out", str(tmp_path)]
    for s in sets:
        args += ["--set", s]
    assert main(args) == 0
    return json.loads(capsys.readouterr().out)


def test_a_scene_holding_an_sma_spring_runs_at_the_duty_bound(capsys, tmp_path):
    # a 0.1 Hz square holds channel 0's raising spring at 1.62 V ((1.62/2)^2 = 0.66 of full power)
    # (with a 1 s mean the other taxels' 1.5 Hz squares, 0.33 on average, peak at 0.38 < 0.6)
    out = run_json(capsys, tmp_path, "sma-8x8", "timing.duration=4.0", "stimulus.tones.0.freq=0.1",
                   "actuator.sma.limits.duty_tau=1.0")
    assert out["faults"] == [] and any("duty limited" in w for w in out["warnings"])
    limited = [c["limited"] for c in out["channels"]]
    assert limited[0] and not any(limited[1:]) and out["channels"][0]["limited_by"] == ["duty"]
    from rtctl.trace import TraceReader

    drive = TraceReader(tmp_path / "trace").signal("drive", 0)
    # held at 0.6 of full power, 2 V sqrt(0.6), from -tau ln(1 - 0.6 / 0.656) = 2.46 s on
    # (the trace stores float32)
    np.testing.assert_allclose(drive[: int(2.4 * FS)], 1.62, rtol=1e-7)
    np.testing.assert_allclose(drive[int(2.6 * FS):int(3.9 * FS)], 2.0 * math.sqrt(0.6), rtol=1e-7)


def test_a_scene_with_a_dc_drive_on_a_bimorph_is_held_at_the_dc_bound(capsys, tmp_path):
    out = run_json(capsys, tmp_path, "line-bimorph-5", "timing.duration=0.5", "stimulus.tones.0.freq=0.2",
                   "stimulus.tones.0.shape=square", "actuator.lateral.limits.dc_tau=0.05")
    assert out["faults"] == [] and any("DC offset limited" in w for w in out["warnings"])
    assert out["channels"][0]["limited"] and "dc offset" in out["channels"][0]["limited_by"]
