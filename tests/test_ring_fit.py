"""The amplitude controller's ring fit: a steady phasor and one real mode's decaying ring, read
from the last fresh estimates, against the closed form they were made from; and the loop it
shortens, on a plant whose tip rings after its gain changes."""

from __future__ import annotations

import numpy as np
import pytest

from rtctl.control import AmplitudeController, amplitude_control
from rtctl.control._kernels import (
    CMD,
    ENABLE,
    FSWING,
    HIST,
    N_STATE,
    NH,
    NOISE,
    RING_K,
    RING_NOISE,
    ROT,
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
