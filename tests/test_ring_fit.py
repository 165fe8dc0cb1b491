"""The amplitude controller's ring fit: a steady phasor and one real mode's decaying ring, read
from the last fresh estimates, against the closed form they were made from; the loop it
shortens, on a plant whose tip rings after its gain changes; and the pulse of drive that cancels
such a ring once the drive is on target, against the ring's free decay and the naive twin."""

from __future__ import annotations

import numpy as np
import pytest
from naive_control import amplitude_control as naive

from rtctl.control import AmplitudeController, amplitude_control
from rtctl.control._kernels import (
    CMD,
    DEADBAND,
    ENABLE,
    FSWING,
    HIST,
    N_STATE,
    NH,
    NOISE,
    P1V,
    PULSE_MIN,
    PULSE_NEAR,
    PULSES,
    REFV,
    RING_K,
    RING_NOISE,
    RMR,
    ROT,
    RPR,
    RSR,
    _ring_fit,
)
from rtctl.dsp._kernels import N_PEND, P_AMP

BLOCK = 32


def ringing(steady, z, rho, theta, rot, n, image=0.3):
    """Phasor estimates of a tone whose tip rings in one real mode: the steady phasor, the mode
    at ``theta`` rad per block from the tone and its other half at ``-(theta + 2 rot)`` (the real
    signal's negative frequency, seen through the tone's lock-in), both decaying by ``rho``."""
    k = np.arange(n)
    return (steady + z * (rho * np.exp(1j * theta)) ** k
            + image * np.conj(z) * (rho * np.exp(-1j * (theta + 2 * rot))) ** k)


def fit(w, rot, start=0, noise=0.0):
    """``_ring_fit`` on the phasors ``w`` (oldest first), pushed into a state column as the
    controller does (``start`` pushes before them, so the circular buffer wraps), for an
    estimate of rms noise ``noise``."""
    state = np.zeros((N_STATE, 1))
    state[ROT, 0], state[NOISE, 0] = rot, noise
    for x in np.r_[np.zeros(start), w]:
        k = int(state[NH, 0]) % RING_K
        state[HIST + 2 * k, 0], state[HIST + 2 * k + 1, 0] = x.real, x.imag
        state[NH, 0] += 1
    return _ring_fit(state, 0), state[FSWING, 0]


@pytest.mark.parametrize("theta, rho, rot, image, start", [
    (0.40, 0.977, 2 * np.pi / 3, 0.3, 0),   # 500 Hz at block 32, a loaded mode 95 Hz away
    (0.87, 0.951, 4 * np.pi / 3, 0.0, 3),   # 1 kHz, no image left by the window
    (-1.3, 0.90, 0.52, 1.0, 7),             # a mode below the tone, its image as large
    (1.05, 0.975, 2 * np.pi / 3, 0.5, 12),  # both halves on one turn per block (a 750 Hz mode)
])
def test_a_ring_is_fitted_to_its_steady_phasor(theta, rho, rot, image, start):
    steady = 11.16e-6 * np.exp(-2.2j)
    w = ringing(steady, 3e-6 * np.exp(0.7j), rho, theta, rot, RING_K, image)
    y, swing = fit(w, rot, start)
    np.testing.assert_allclose(y, abs(steady), rtol=1e-9)
    np.testing.assert_allclose(swing, np.abs(w - steady).max(), rtol=1e-6)


def test_what_is_no_ring_is_not_fitted():
    rng = np.random.default_rng(1)
    rot, steady = 2 * np.pi / 3, 10e-6 * np.exp(0.3j)
    k = np.arange(RING_K)
    cases = {
        "a window sliding over a change (a line)": steady * (1 + 0.02 * k),
        "noise": steady + 0.3e-6 * (rng.normal(size=RING_K) + 1j * rng.normal(size=RING_K)),
        "a growing ring": ringing(steady, 3e-6, 1.02, 0.4, rot, RING_K),
        "a ring that does not decay": ringing(steady, 3e-6, 1.0, 0.4, rot, RING_K),
        "two modes": ringing(steady, 3e-6, 0.97, 0.4, rot, RING_K) + ringing(0, 2e-6, 0.9, -1.5, rot, RING_K),
        "a ring within STILL of the steady amplitude": ringing(steady, 0.05e-6, 0.97, 0.4, rot, RING_K),
        "a mode that is not real (its other half on the wrong turn)":
            steady + 3e-6 * (0.97 * np.exp(0.4j)) ** k + 1.5e-6 * (0.97 * np.exp(-1.9j)) ** k,
    }
    for what, w in cases.items():
        assert fit(w, rot)[0] == -1.0, what
    ring = ringing(steady, 3e-6, 0.97, 0.4, rot, RING_K)
    assert fit(ring, rot)[0] > 0  # (the same ring, fitted)
    # a ring whose estimates move by no more than RING_NOISE times their noise is left alone
    spread = np.abs(ring - ring[-1]).max()
    assert fit(ring, rot, noise=1.01 * spread / RING_NOISE)[0] == -1.0
    assert fit(ring, rot, noise=0.99 * spread / RING_NOISE)[0] > 0


def test_the_fit_is_for_short_windows_and_needs_a_turn_and_a_noise():
    """A window longer than RING_K - 4 blocks, read within RING_K estimates, could slide over a
    change and pass for a ring: no fit there; a turn or a noise that is not finite and >= 0 is
    refused."""
    def rot(window, turn):
        return AmplitudeController([0], [0], [0], [0], [1e-7], [150.0], [5e-6], 1, window, BLOCK,
                                   turn=turn).state[ROT, 0]
    assert rot(RING_K - 4, 1.25) == pytest.approx(2 * np.pi * 0.25)
    assert rot(RING_K - 3, 1.25) == -1.0 and rot(3, None) == -1.0
    for bad in (-0.1, np.nan, np.inf):
        with pytest.raises(ValueError, match="turn"):
            rot(3, bad)
        with pytest.raises(ValueError, match="noise"):
            AmplitudeController([0], [0], [0], [0], [1e-7], [150.0], [5e-6], 1, 3, BLOCK, noise=bad)
    # the windows a pulse reads its ring through: samples, at least 1 (default the window's blocks)
    ctl = AmplitudeController([0], [0], [0], [0], [1e-7], [150.0], [5e-6], 1, 3, BLOCK)
    assert ctl.window_samples.tolist() == ctl.amplitude_window.tolist() == [3 * BLOCK]
    for bad in (0.5, np.nan, np.inf):
        for name in ("window_samples", "amplitude_window"):
            with pytest.raises(ValueError, match=name):
                AmplitudeController([0], [0], [0], [0], [1e-7], [150.0], [5e-6], 1, 3, BLOCK, **{name: [bad]})


def loop(turn, blocks=400, event=150, window=3, latency=1, gain=1e-7, target=5e-6):
    """A tone on a plant of tip per volt ``gain`` (the model's), seen by an observer as the mean
    over ``window`` blocks of the tip phasor ``latency`` blocks earlier (the model's ring time
    48 blocks, which sets the stretch). At ``event`` the gain
    drops by 10 % and the tip rings in a real mode beside the tone, as after a finger presses:
    +-30 % of the target, decaying by 0.977 per block, at 95 Hz from a 500 Hz tone. Returns
    the command after each block."""
    rot = 2 * np.pi * (turn or 0.0)
    ctl = AmplitudeController([0], [0], [0], [0], [gain], [150.0], [target], latency, window, BLOCK,
                              ring=48, turn=turn)
    ctl.target[ENABLE] = 1.0
    est, drive_est = np.zeros((1, 1, 9, 2)), np.zeros((1, 1, 2))
    pending, lim = np.zeros((N_PEND, 1)), np.zeros((3, 1), dtype=np.int64)
    ring = ringing(0.0, 0.3 * target, 0.977, 0.4, 2 * np.pi / 3, blocks - event)
    tips, cmds = [], []
    for k in range(blocks):
        g = gain * (0.9 if k >= event else 1.0)
        tips.append(g * pending[P_AMP, 0] + (ring[k - event] if k >= event else 0.0))
        seen = tips[max(0, len(tips) - latency - window):len(tips) - latency] or [0j]
        y = np.mean(seen)
        est[0, 0, 0] = y.real, y.imag
        drive_est[0, 0, 0] = pending[P_AMP, 0]
        amplitude_control(est, drive_est, **ctl.args, pending=pending, lim_counts=lim, ramp=float(BLOCK))
        cmds.append(ctl.state[CMD, 0])
    assert ctl.state[ROT, 0] == (rot if turn is not None else -1.0)
    return np.array(cmds)


def test_a_ring_after_a_plant_change_is_corrected_on_its_end():
    """With the tone's turn given the loop fits the ring and corrects once, to the exact drive
    for the new gain, RING_K fresh estimates after the window holds nothing of the old plant;
    on stretch means alone it corrects on points of the ring, later and more than once."""
    event, need = 150, 5e-6 / 0.9e-7  # the target over the new tip per volt
    cmds = loop(1 / 3, event=event)
    moved = np.flatnonzero(np.diff(cmds[event - 1:])) + 1
    assert moved.size == 1, moved
    clean = 1 + 3 + 1  # the window holds nothing older than the change: latency, window, a block
    assert moved[0] <= clean + RING_K + 1, moved
    np.testing.assert_allclose(cmds[-1], need, rtol=1e-9)
    old = loop(None, event=event)
    moved_old = np.flatnonzero(np.diff(old[event - 1:])) + 1
    assert moved_old[0] > moved[0] and (moved_old.size > 1 or abs(old[-1] / need - 1) > 1e-9), moved_old


def pulse_loop(theta, rho, blocks=300, event=100, window=3, latency=1, gain=1e-7, target=5e-6, limit_from=None):
    """A tone's tip phasor sample by sample on a plant with one mode beside it, turning by ``theta``
    and decaying by ``rho`` per block: a step of drive leaves a ring of minus the step it makes in
    the steady phasor (the tip cannot jump), each sample of a ramp its share; at ``event`` the
    gain drops by 10 % and the tip, continuous, rings by the difference. The observer's estimate
    is the mean of the tip phasor over ``window`` blocks ``latency`` blocks before; from block
    ``limit_from`` on the limiter acts on the channel in every block. Returns the
    controller, the ring at the end of each block, and the drive sent and the command in each block."""
    B = BLOCK
    step = (rho * np.exp(1j * theta)) ** (1.0 / B)
    ctl = AmplitudeController([0], [0], [0], [0], [gain], [150.0], [target], latency, window, B, ring=48,
                              turn=1 / 3)
    ctl.target[ENABLE] = 1.0
    twin = [a.copy() for a in (ctl.index, ctl.target, ctl.state)]
    est, drive_est = np.zeros((1, 1, 9, 2)), np.zeros((1, 1, 2))
    pending, lim = np.zeros((N_PEND, 1)), np.zeros((3, 1), dtype=np.int64)
    pend_n = pending.copy()
    tip = np.zeros(blocks * B, complex)
    rings, drives, cmds = np.zeros(blocks, complex), np.zeros(blocks), np.zeros(blocks)
    ring, u, g = 0j, 0.0, gain
    for k in range(blocks):
        end = (k + 1 - latency) * B
        seen = tip[max(0, end - window * B):end] if end > 0 else np.zeros(1)
        y = seen.mean()
        est[0, 0, 0] = y.real, y.imag
        drive_est[0, 0, 0] = u
        if limit_from is not None and k >= limit_from:
            lim[1, 0] += 1
        sk = amplitude_control(est, drive_est, **ctl.args, pending=pending, lim_counts=lim, ramp=float(B))
        # the naive twin on the same estimates: the same decisions, the same state
        assert naive(est, drive_est, *twin, pend_n, lim, float(B)) == sk
        fin = np.where(np.isfinite(ctl.state), np.abs(ctl.state), 0.0)
        for re in (RMR, RPR, RSR):  # a phasor's parts to rounding of the phasor
            fin[re] = fin[re + 1] = np.hypot(fin[re], fin[re + 1])
        fin[[REFV, P1V]] = target ** 2  # variances by subtraction: to rounding of the squares
        with np.errstate(invalid="ignore"):
            off = ~((twin[2] == ctl.state) | (np.abs(twin[2] - ctl.state) <= 1e-9 * fin))
        assert not off.any(), (k, np.flatnonzero(off.any(axis=1)))
        np.testing.assert_allclose(pend_n, pending, rtol=1e-12, atol=0)
        if k == event:
            ring += (g - 0.9 * g) * u
            g *= 0.9
        u0, u1 = u, pending[P_AMP, 0]
        for s in range(B):  # the oscillator's ramp over the block, its last sample at the command
            un = u0 + (u1 - u0) * (s + 1) / B
            ring = ring * step - g * (un - u)
            u = un
            tip[k * B + s] = g * u + ring
        rings[k], drives[k], cmds[k] = ring, u, ctl.state[CMD, 0]
    return ctl, rings, drives, cmds


@pytest.mark.parametrize("theta, rho", [(0.285, 0.975), (-0.25, 0.97), (0.2, 0.99), (0.9, 0.95)])
def test_a_ring_on_target_is_cancelled_by_a_pulse(theta, rho):
    """After the fit's correction puts the tone on target, the ring left is cancelled by pulses of
    drive (a step and back, the command unchanged): each leaves at most a third of what the ring's
    free decay would, and once the ring is under PULSE_MIN no pulse comes. A ring further from
    the tone than PULSE_NEAR of its frequency (0.9 rad per block at 500 Hz: 215 Hz off) is left to
    decay."""
    event, target = 100, 5e-6
    ctl, rings, drives, cmds = pulse_loop(theta, rho, event=event, target=target)
    np.testing.assert_allclose(cmds[-1], target / 0.9e-7, rtol=DEADBAND)  # on target
    pulsed = np.flatnonzero(drives != cmds)
    pulsed = pulsed[pulsed > event]
    near = abs(theta) <= 2 * np.pi * PULSE_NEAR / 3
    assert (pulsed.size > 0) == near, pulsed
    if not near:
        return
    starts = pulsed[np.r_[True, np.diff(pulsed) > 1]]
    ends = pulsed[np.r_[np.diff(pulsed) > 1, True]] + 1  # the block that ramps back
    assert len(starts) <= PULSES
    for k0, k1 in zip(starts, ends):
        assert np.all(cmds[k0 - 1:k1 + 1] == cmds[k0 - 1])  # the command stays
        free = np.abs(rings[k0 - 1]) * rho ** (np.arange(k1 + 1, k1 + 21) - (k0 - 1))
        assert np.all(np.abs(rings[k1 + 1:k1 + 21]) <= free / 3), (k0, k1)
    assert np.abs(rings[ends[-1] + 1]) <= PULSE_MIN * target
    assert np.all(drives[ends[-1] + 1:] == cmds[ends[-1] + 1:])  # (later corrections fine-tune)


def test_no_pulse_up_while_the_limiter_holds_the_channel():
    """A pulse that would raise the drive waits while the limiter acts on the channel (as a
    correction upwards does: no windup); the same ring without the limiter gets it."""
    ctl, rings, drives, cmds = pulse_loop(-0.25, 0.97)
    up = np.flatnonzero(drives > cmds)
    k0 = up[up > 100][0]  # the first pulse upwards after the plant changed
    assert drives[k0 - 1] == cmds[k0 - 1]
    ctl, rings, drives, cmds = pulse_loop(-0.25, 0.97, limit_from=k0 - 1)
    assert np.all(drives[k0 - 1:] <= cmds[k0 - 1:])
