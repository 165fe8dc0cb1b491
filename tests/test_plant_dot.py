"""Latching Dot Braille pin (rtctl.plant.dot): latch, transitions, pulses, finger, numerics."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from naive_em import dot_simulate
from scipy.integrate import solve_ivp

from rtctl.errors import ModelError
from rtctl.plant.dot import DotGroup, DotPin

FS = 48000.0


def run(group, drive, block=32):
    """Drive a group block by block as the loop does; returns (status, truth, up_share)."""
    nc, n = drive.shape
    truth = np.empty((nc, 4, n))
    share = np.empty(n)
    status = 0
    for a in range(0, n, block):
        b = min(n, a + block)
        t = np.empty((nc, 4, b - a))
        status |= group.process(np.ascontiguousarray(drive[:, a:b]), np.empty((0, b - a)), t)
        truth[:, :, a:b] = t
        share[a:b] = group.probe[0, :b - a]
    return status, truth, share


def pulse(n, start, length, volts=5.0):
    d = np.zeros(n)
    d[int(round(start * FS)):int(round((start + length) * FS))] = volts
    return d


@pytest.fixture(scope="module")
def pin():
    return DotPin()


def test_latch_holds_without_power(pin):
    # Pins latched up and down, then 0.5 s of no drive and of commands inside the dead band
    # (|u| < V_s / 2: the bridge does not conduct): nothing moves, the coil carries no current.
    group = DotGroup(pin, FS, n_channels=4, up=[True, False, True, False])
    n = int(0.5 * FS)
    drive = np.zeros((4, n))
    drive[2:] = 2.4 * np.sign(np.sin(2 * np.pi * 7.0 * np.arange(n) / FS))
    status, truth, _ = run(group, drive)
    assert status == 0
    h = truth[:, 0]
    np.testing.assert_allclose(h[[0, 2]], 0.5e-3, atol=1e-7)   # up, on the top stop
    np.testing.assert_allclose(h[[1, 3]], 0.0, atol=1e-7)      # down, on the bottom stop
    assert np.all(truth[:, 3] == 0.0)                          # no coil voltage
    assert np.max(np.abs(group.state[:, 0])) < 1e-12           # no current


def test_motion_starts_when_the_coil_current_beats_the_latch(pin):
    # Until the pin moves, the coil is an R-L circuit: i = V/R (1 - exp(-t R / L)). The pin
    # leaves the bottom stop when K i = F_h + F_c (latch and the finger's rest force). The
    # crossing is interpolated between samples on a curve that turns from creeping (the stop's
    # 43 nm compression) to accelerating, so it is good to one sample.
    group = DotGroup(pin, FS, n_channels=1)
    n = int(0.004 * FS)
    status, truth, _ = run(group, pulse(n, 0.0, 1.0)[None, :])
    assert status == 0
    f_c0 = pin.skin.rest_force(pin.preload, 0.0)
    tau = 10e-3 / 8.0
    t_start = -tau * math.log(1.0 - (0.4 + f_c0) * 8.0 / (2.0 * 5.0))
    h = truth[0, 0]
    k = int(np.flatnonzero(h > 0.0)[0])
    t_cross = (k - 1 + (-h[k - 1]) / (h[k] - h[k - 1])) / FS   # linear interpolation
    assert abs(t_cross - t_start) < 1.0 / FS, (t_cross, t_start)


def test_up_and_down_transition_times(pin):
    # Stated in docs/plants/dot.md: up 10-90 % in 1.08-2.15 ms after the command under the
    # default finger, 1.58 ms down; finite (> 1 ms: L/R = 1.25 ms) and short against a Braille
    # refresh (< 3 ms).
    group = DotGroup(pin, FS, n_channels=2, up=[False, True])
    n = int(0.02 * FS)
    drive = np.stack([pulse(n, 0.0, 0.01), pulse(n, 0.0, 0.01, -5.0)])
    status, truth, _ = run(group, drive)
    assert status == 0
    up, down = truth[0, 0], truth[1, 0]
    t90_up = np.argmax(up > 0.45e-3) / FS
    t10_up = np.argmax(up > 0.05e-3) / FS
    t90_down = np.argmax(down < 0.05e-3) / FS
    assert 1e-3 < t90_up < 3e-3 and 1e-3 < t90_down < 3e-3
    assert abs(t90_up - 2.15e-3) < 0.1e-3 and abs(t10_up - 1.08e-3) < 0.1e-3
    assert abs(t90_down - 1.58e-3) < 0.1e-3
    assert abs(up[-1] - 0.5e-3) < 1e-7 and abs(down[-1]) < 1e-7


def test_short_pulse_does_not_switch_the_pin(pin):
    # A pulse cut before the pin passes mid-travel leaves it to the latch, which pulls it back
    # (documented: minimum up pulse 1.6 ms under the default finger, 1.3 ms without).
    lengths = [0.5e-3, 1.2e-3, 1.5e-3, 1.7e-3, 3e-3]
    group = DotGroup(pin, FS, n_channels=len(lengths))
    n = int(0.03 * FS)
    status, truth, share = run(group, np.stack([pulse(n, 0.0, L) for L in lengths]))
    assert status == 0
    final = truth[:, 0, -1]
    np.testing.assert_allclose(final[:3], 0.0, atol=1e-7)
    np.testing.assert_allclose(final[3:], 0.5e-3, atol=1e-7)
    assert truth[2, 0].max() > 0.1e-3          # the 1.5 ms pulse moved it, then it fell back
    free = DotGroup(DotPin(finger=None, preload=0.0), FS, n_channels=2)
    _, truth, _ = run(free, np.stack([pulse(n, 0.0, 1.2e-3), pulse(n, 0.0, 1.4e-3)]))
    assert abs(truth[0, 0, -1]) < 1e-7 and abs(truth[1, 0, -1] - 0.5e-3) < 1e-7


def test_finger_force_is_never_negative_and_contact_can_be_lost():
    # Random up/down/idle commands; without preload a fast down stroke outruns the skin.
    rng = np.random.default_rng(3)
    n = int(0.2 * FS)
    cmds = rng.choice([-5.0, 0.0, 5.0], size=(3, 40))
    drive = np.ascontiguousarray(np.repeat(cmds, n // 40, axis=1))
    for preload in (0.0, 0.03):
        pin = DotPin(preload=preload)
        group = DotGroup(pin, FS, n_channels=3)
        share = []
        truth = np.empty((3, 4, n))
        for a in range(0, n, 32):
            t = np.empty((3, 4, 32))
            assert group.process(np.ascontiguousarray(drive[:, a:a + 32]),
                                 np.empty((0, 32)), t) == 0
            truth[:, :, a:a + 32] = t
            share.append(group.probe[1, :32].copy())
        assert truth[:, 2].min() >= 0.0
        if preload == 0.0:
            assert np.concatenate(share).min() < 1.0


def test_a_finger_stronger_than_the_latch_pushes_the_pin_down_and_it_stays_down(pin):
    # Up pins under 0.03 N (normal), 0.30 N and 0.35 N preload. The finger's force on an up pin
    # is F_p + k0 x: the pin leaves its top stop when that exceeds F_h (F_p > 0.25 N), rests
    # where it equals F_h, and flips down when that point is below mid-travel (F_p > 0.325 N).
    group = DotGroup(pin, FS, n_channels=3, up=True)
    n = int(0.3 * FS)
    status, truth, _ = run(group, np.zeros((3, n)))
    assert status == 0 and np.all(np.abs(truth[:, 0, -1] - 0.5e-3) < 1e-7)
    group.params[1:, 0] = [0.30, 0.35]
    status, truth, share = run(group, np.zeros((3, 2 * n)))
    assert status == 0
    h = truth[:, 0, -1]
    assert abs(h[0] - 0.5e-3) < 1e-7                    # normal pressure: holds
    # gives way toward (F_h - F_p) / k0 = 0.333 mm as the tissue relaxes (tau up to 1.4 s)
    assert 0.3334e-3 < h[1] < 0.49e-3 and abs(truth[1, 2, -1] - 0.4) < 1e-3
    assert abs(h[2]) < 1e-7                             # too strong: flipped down
    assert abs(share[-1] - 2 / 3) < 1e-12
    # ... and stays down when the finger lets go again, until an up command
    group.params[1:, 0] = 0.03
    _, truth, _ = run(group, np.zeros((3, int(0.05 * FS))))
    assert abs(truth[2, 0, -1]) < 1e-7
    for preload in (0.26, 0.35):
        with pytest.raises(ModelError, match="cannot hold the pin up"):
            DotPin(preload=preload)


@settings(max_examples=10, deadline=None)
@given(st.lists(st.integers(1, 200), min_size=1, max_size=12))
def test_chunk_invariance(splits):
    n = 1600
    drive = np.ascontiguousarray(np.stack([pulse(n, 0.0, 4e-3) - pulse(n, 0.02, 4e-3),
                                           -pulse(n, 0.005, 3e-3)]))
    pin = DotPin(preload=0.0)
    one = DotGroup(pin, FS, n_channels=2, up=[False, True])
    t1 = np.empty((2, 4, n))
    assert one.process(drive, np.empty((0, n)), t1) == 0
    many = DotGroup(pin, FS, n_channels=2, up=[False, True])
    t2 = np.empty((2, 4, n))
    cuts = [0] + [int(c) for c in np.cumsum(splits) if c < n] + [n]
    for a, b in zip(cuts[:-1], cuts[1:]):
        t = np.empty((2, 4, b - a))
        assert many.process(np.ascontiguousarray(drive[:, a:b]), np.empty((0, b - a)), t) == 0
        t2[:, :, a:b] = t
    np.testing.assert_array_equal(t1, t2)


def test_kernel_matches_the_naive_twin(pin):
    # levels=0 (switches at substep boundaries, as the twin); the twin writes the H-bridge,
    # latch, stops and contact out by hand and steps each mode with scipy.linalg.expm.
    n = int(0.012 * FS)
    drive = pulse(n, 0.0, 3e-3) - pulse(n, 0.006, 3e-3)
    group = DotGroup(pin, FS, n_channels=1, substeps=2, levels=0)
    status, truth, _ = run(group, drive[None, :])
    ref = dot_simulate(pin, FS, drive, preload=pin.preload, x0=pin.y0)
    assert status == 0
    assert ref[0].max() > 0.49e-3                     # it did go up and come back
    for row in range(4):
        scale = np.max(np.abs(ref[row]))
        np.testing.assert_allclose(truth[0, row], ref[row], atol=1e-7 * scale, rtol=0)


@pytest.mark.slow
def test_radau_agrees_through_an_up_transition(pin):
    # The command is a sample-aligned 5 V step, so the DAC staircase is the continuous input.
    n = int(0.006 * FS)
    t = np.arange(n) / FS

    def u(tt):
        return 5.0 if tt < 4e-3 else 0.0

    sol = solve_ivp(lambda tt, y: pin.rhs(tt, y, u(tt)), (0.0, t[-1]), pin.y0, method="Radau",
                    t_eval=t, rtol=1e-8, atol=1e-12, max_step=2e-5)
    assert sol.success
    ref = np.array([pin.outputs(y, u(tt)) for tt, y in zip(sol.t, sol.y.T)]).T
    group = DotGroup(pin, FS, n_channels=1)                  # default substeps and levels
    status, truth, _ = run(group, np.array([[u(tt) for tt in t]]))
    assert status == 0
    # measured (max / peak): height 1.6e-6, velocity 3.2e-4, force 3.5e-4 (at the top stop)
    for row, tol in ((0, 1e-5), (1, 1e-3), (2, 1e-3)):
        err = np.max(np.abs(truth[0, row] - ref[row])) / np.max(np.abs(ref[row]))
        assert err < tol, (row, err)


def test_group_contract(pin):
    g = DotGroup(pin, FS)
    assert g.n_channels == 16 and g.n_sensed == 0 and g.sensed_labels == ()
    assert g.capacitance == 0.0 and g.resistance == 8.0
    assert g.probe_names == (("up_share", ""), ("contact_share", ""))
    assert g.params.shape == (16, 1)
    from rtctl.plant import dot
    assert (dot.PITCH, dot.GRID) == (2.6e-3, (4, 4))
    drive = np.full((16, 8), np.nan)
    truth = np.empty((16, 4, 8))
    assert g.process(drive, np.empty((0, 8)), truth) & 2
    g.reset()
    assert g.process(np.zeros((16, 8)), np.empty((0, 8)), truth) == 0
    with pytest.raises(ModelError, match="cannot beat the latch"):
        DotPin(latch_force=2.0)
