"""Amplitude control: the kernel against its naive twin, and the loop it closes against what a
plant of known gain, seen through a lock-in window and an I/O latency, must do."""

from __future__ import annotations

import numpy as np
import pytest
from naive_control import amplitude_control as naive

from rtctl.control import AmplitudeController, amplitude_control, design
from rtctl.control._kernels import (
    CMD,
    ENABLE,
    HOLD,
    HOLD0,
    HOLDMAX,
    MAX_STEP,
    REF,
    REFV,
    SAT,
    START,
    TARGET,
    TRIES,
    WAIT,
)
from rtctl.dsp._kernels import N_PEND, P_AMP
from rtctl.safety import CONTROL_FROZEN, CONTROL_SATURATED

BLOCK = 32


class Loop:
    """Controllers of ``n`` tones on a plant that is a gain per tone (tip m per V), seen by an
    observer as the mean over ``window`` blocks of the tip ``latency`` blocks earlier."""

    def __init__(self, plant_gain, model_gain, targets, amax=150.0, latency=1, window=6, ring=0):
        n = len(targets)
        self.n, self.latency, self.window = n, latency, window
        self.plant = np.asarray(plant_gain, dtype=float)
        self.ctl = AmplitudeController(np.arange(n), np.zeros(n, int), np.arange(n), np.arange(n),
                                       model_gain, np.full(n, amax), targets, latency, window, BLOCK, ring)
        self.est = np.zeros((n, 1, 9, 2))
        self.pending = np.zeros((N_PEND, n))
        self.lim = np.zeros((3, n), dtype=np.int64)
        self.history = [np.zeros(n)] * (latency + window + 2)  # tip amplitudes, oldest first
        self.drives = [np.zeros(n)] * (latency + window + 2)  # drive amplitudes, oldest first
        self.drive_est = np.zeros((n, 1, 2))
        self.amp = np.zeros(n)
        self.truth, self.status = [], 0
        self.ctl.target[ENABLE] = 1.0

    def block(self, nan=False):
        self.amp = self.pending[P_AMP].copy()  # the oscillator ramps to it over this block
        self.truth.append(self.plant * self.amp)
        self.history = self.history[1:] + [self.truth[-1]]
        self.drives = self.drives[1:] + [self.amp]
        seen = slice(-1 - self.latency - self.window + 1, len(self.history) - self.latency)
        y = np.mean(self.history[seen], axis=0)
        self.est[:, 0, 0, 0] = np.nan if nan else y
        self.drive_est[:, 0, 0] = np.mean(self.drives[seen], axis=0)  # the drive's lock-in, same window
        self.status |= amplitude_control(self.est, self.drive_est, **self.ctl.args, pending=self.pending,
                                         lim_counts=self.lim, ramp=float(BLOCK))

    def run(self, n):
        for _ in range(n):
            self.block()
        return np.array(self.truth)


def test_design_waits_for_window_and_latency():
    assert design(1, 6) == (1.0, 8)
    assert design(2, 300) == (1.0, 303)


@pytest.mark.parametrize("error", [0.1, 0.2, 0.3, 0.5, 0.7, 0.95, 1.0, 1.05, 1.5, 3.0, 6.0, 20.0])
def test_any_model_gain_error_is_removed_without_crossing_the_target(error):
    """A static plant whose gain the model has wrong by ``error``: the first command aims at START
    of the target by the model (or is capped at max_voltage) until the first correction, a wait
    and two stretches of fresh estimates after it; the correction lands exactly on the target
    when the remaining error is within MAX_STEP (each correction moves by at most that), and the
    truth never crosses the target on its way unless the model's gain is more than 1 / START
    too low (feedback adds no overshoot)."""
    gain, target = 2e-7, 12e-6
    loop = Loop([gain], [gain * error], [target])
    every = loop.ctl.warm + 2 * loop.ctl.hold
    truth = loop.run(4 * every)[:, 0]
    first = min(START * target / error, 150.0 * gain)  # the feedforward's tip amplitude
    np.testing.assert_allclose(truth[1:every + 1], first, rtol=1e-12)
    steps = 1 if 1.0 / MAX_STEP <= first / target <= MAX_STEP else 2
    np.testing.assert_allclose(truth[1 + steps * every:], target, rtol=1e-12)
    side = np.sign(np.round(truth[1:] / target - 1.0, 12))
    assert np.all(side[side != 0] == side[0])
    if error >= START:  # a model no more than 1 / START too weak: the tip comes up from below
        assert truth.max() <= target * (1 + 1e-12)


def test_a_plant_change_is_corrected_once_the_window_has_passed_it():
    """The finger presses harder (40 % less tip per volt): while the observer's window slides
    over the change its estimate moves, and the loop waits; the one correction comes once the
    window holds nothing older than the change, and lands exactly on the target from below."""
    loop = Loop([1e-7], [1e-7], [5e-6], window=24)
    loop.run(200)
    np.testing.assert_allclose(loop.truth[-1][0], 5e-6, rtol=1e-12)
    k0 = len(loop.truth)
    loop.plant[0] *= 0.6
    cmds = []
    for _ in range(200):
        loop.block()
        cmds.append(loop.ctl.state[CMD, 0])
    changed = np.flatnonzero(np.diff(cmds)) + 1
    assert changed.size == 1, changed
    assert changed[0] >= loop.latency + loop.window, changed  # not on a window that straddles it
    assert changed[0] <= loop.latency + loop.window + 3 * loop.ctl.hold + 1, changed
    truth = np.array(loop.truth[k0:])[:, 0]
    np.testing.assert_allclose(truth[changed[0] + 1:], 5e-6, rtol=1e-12)
    assert truth.max() <= 5e-6 * (1 + 1e-12)


def test_saturation_holds_max_voltage_without_windup_and_recovers():
    loop = Loop([1e-7], [1e-7], [30e-6], amax=100.0)  # needs 300 V
    loop.run(60)
    assert loop.ctl.state[CMD, 0] == 100.0 and loop.ctl.state[SAT, 0] == 1.0
    assert loop.status & CONTROL_SATURATED
    assert max(loop.pending[P_AMP]) <= 100.0
    loop.ctl.target[TARGET, 0] = 5e-6  # reachable again: from the learned gain, no excess to unwind
    truth = loop.run(3 * loop.ctl.warm)[:, 0]
    np.testing.assert_allclose(truth[-loop.ctl.warm:], 5e-6, rtol=1e-12)
    assert loop.ctl.state[SAT, 0] == 0.0 and truth.max() <= 10e-6 * (1 + 1e-12)


def test_a_bad_estimate_freezes_the_drive_never_raises_it():
    loop = Loop([1e-7], [2e-7], [5e-6])  # the model says half the drive needed
    loop.run(loop.ctl.warm + 1)
    held = loop.ctl.state[CMD, 0]
    for _ in range(50):
        loop.block(nan=True)
    assert loop.ctl.state[CMD, 0] == held and loop.status & CONTROL_FROZEN


def test_while_the_limiter_holds_the_channel_the_command_does_not_grow():
    loop = Loop([1e-7], [2e-7], [5e-6])
    loop.run(2)
    start = loop.ctl.state[CMD, 0]
    for _ in range(100):
        loop.lim[1, 0] += 3  # slew-limited samples in every block
        loop.block()
    assert loop.ctl.state[CMD, 0] == start


def test_disabling_a_tone_ramps_it_to_zero():
    loop = Loop([1e-7], [1e-7], [5e-6])
    loop.run(20)
    loop.ctl.target[ENABLE, 0] = 0.0
    loop.block()
    assert loop.pending[P_AMP, 0] == 0.0 and loop.ctl.state[CMD, 0] == 0.0


@pytest.mark.parametrize("seed", range(4))
def test_kernel_matches_its_naive_twin(seed):
    rng = np.random.default_rng(seed)
    n = 7
    ctl = AmplitudeController(np.arange(n), np.zeros(n, int), rng.permutation(n), rng.integers(0, 3, n),
                              rng.uniform(1e-8, 1e-6, n), rng.uniform(10, 150, n), rng.uniform(1e-7, 5e-5, n),
                              1, 3, BLOCK, ring=(0, 30, 60, 100)[seed], rise=(0, 1, 5, 12)[seed])
    twin = [a.copy() for a in (ctl.index, ctl.target, ctl.state)]
    pend_k, pend_n = np.zeros((N_PEND, n)), np.zeros((N_PEND, n))
    lim = np.zeros((3, 3), dtype=np.int64)
    scale = 0.0  # the largest squared stretch mean so far
    grown = 0  # blocks in which some stretch had grown past its design (the hunting rule acted)
    side, last_cmd = np.ones(n), ctl.state[CMD].copy()
    for k in range(900):
        est = np.zeros((n, 1, 9, 2))
        est[:, 0, 0] = rng.normal(0, 2e-5, (n, 2))
        # after the first 300 blocks estimates 8 % off the target, over and under by turns
        # of the commands (each correction overshoots: hunting, so that the stretches grow)
        side[ctl.state[CMD] != last_cmd] *= -1.0
        last_cmd = ctl.state[CMD].copy()
        near = np.full(n, k >= 300)
        est[near, 0, 0, 0] = (ctl.target[TARGET] * (1.0 + 0.08 * side) * rng.uniform(0.995, 1.005, n))[near]
        est[near, 0, 0, 1] = 0.0
        drive_est = np.zeros((n, 1, 2))
        drive_est[:, 0, 0] = rng.uniform(0, 150, n) * (rng.uniform(size=n) < 0.8)
        if k % 13 == 0 and k < 300:
            ctl.target[TARGET, k % n] = twin[1][TARGET, k % n] = rng.uniform(1e-7, 5e-5)  # a moving target
        if k % 37 == 5:
            est[rng.integers(n), 0, 0, 0] = np.nan
        if k % 11 == 0:
            lim[rng.integers(3), rng.integers(3)] += 1
        if k % 23 == 0 and k < 300:
            j = rng.integers(n)
            ctl.target[ENABLE, j] = twin[1][ENABLE, j] = float(rng.integers(2))
            ctl.target[TARGET, j] = twin[1][TARGET, j] = rng.uniform(1e-7, 5e-5)
        sk = amplitude_control(est, drive_est, ctl.index, ctl.target, ctl.state, pend_k, lim, float(BLOCK))
        sn = naive(est, drive_est, twin[0], twin[1], twin[2], pend_n, lim, float(BLOCK))
        assert sk == sn
        rows = np.arange(ctl.state.shape[0]) != REFV
        np.testing.assert_allclose(ctl.state[rows], twin[2][rows], rtol=1e-12, atol=0)
        # a variance by subtraction (mean square less squared mean) is good to rounding of the
        # squares, not of itself
        scale = max(scale, np.max(twin[2][REF]) ** 2)
        np.testing.assert_allclose(ctl.state[REFV], twin[2][REFV], rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(pend_k, pend_n, rtol=1e-12, atol=0)
        grown += bool(np.any(ctl.state[HOLD] > ctl.state[HOLD0]))
    assert grown > 0 or seed == 0  # seed 0 has no ring: its stretches cannot grow


def test_a_ripple_is_averaged_out_not_chased():
    """A plant whose gain ripples by +-30 % (a loaded mode beating with the tone, period 4
    blocks) around the true gain; the window (6 blocks) leaves +-10 % of it in the estimate.
    Each stretch (an eighth of the ring time, 4 blocks here) holds whole ripple periods, so the
    loop corrects once, on the true gain, and then leaves the command alone."""
    loop = Loop([1e-7], [2e-7], [5e-6], ring=32)
    assert loop.ctl.hold == 4
    cmds = []
    for k in range(400):
        loop.plant[0] = 1e-7 * (1.0 + 0.3 * np.sin(2 * np.pi * k / 4.0))
        loop.block()
        cmds.append(loop.ctl.state[CMD, 0])
    assert np.count_nonzero(np.diff(cmds)) == 1
    np.testing.assert_allclose(cmds[-1] * 1e-7, 5e-6, rtol=1e-3)


def _ringing_loop(rule: bool, period: int, tau: float, swing: float, n: int = 1200):
    """A plant whose every command step rings a loaded mode that beats with the tone (gain
    ``1 + a exp(-t / tau) sin(2 pi t / period)``, ``t`` blocks since the step, ``a`` up to
    ``swing`` in proportion to the step, full from a 10 % step on), ring time ``tau``; with
    ``rule`` False the stretch may not grow. Returns the commands."""
    loop = Loop([1e-7], [1e-7], [5e-6], window=3, ring=int(tau))
    if not rule:
        loop.ctl.state[HOLDMAX] = loop.ctl.state[HOLD0]
    cmds, k0, last, a = [], 0, None, 0.0
    for k in range(n):
        c = loop.ctl.state[CMD, 0]
        if c != last:
            if last:
                a = swing * min(1.0, abs(np.log(c / last)) / np.log(1.1))
            k0, last = k, c
        loop.plant[0] = 1e-7 * (1.0 + a * np.exp(-(k - k0) / tau) * np.sin(2 * np.pi * (k - k0) / period))
        loop.block()
        cmds.append(loop.ctl.state[CMD, 0])
    return np.array(cmds)


@pytest.mark.parametrize("period, tau, swing", [(22, 20.0, 0.25), (22, 30.0, 0.25), (30, 30.0, 0.25)])
def test_hunting_beside_a_loaded_mode_stops(period, tau, swing):
    """Stretches of 3-4 blocks against a beat of 22-30: two stretches agree on an extreme of the
    beat, the correction rings the mode again, and the loop hunts for as long as it runs (the
    drive swings by 9-13 % in the second half, corrected 40-55 times). With the stretch doubled
    at each reversing correction by 5-30 % from the second on, what is left in the second half is
    fine tuning: the drive within 1.5 % (0.6-1.0 % measured), on the target's drive."""
    n = 1200
    cmds = _ringing_loop(False, period, tau, swing, n)
    late = np.count_nonzero(np.diff(cmds[n // 2:]))
    assert late > 20 and np.ptp(cmds[n // 2:]) / cmds[-1] > 0.08  # the loop hunts without the rule
    cmds = _ringing_loop(True, period, tau, swing, n)
    assert np.ptp(cmds[n // 2:]) / cmds[-1] < 0.015
    np.testing.assert_allclose(cmds[-1] * 1e-7, 5e-6, rtol=0.015)


def test_a_drifting_plant_is_followed_at_half_strength():
    """Estimates that never settle (the gain drifts up by 6 % per stretch): after PATIENCE times
    (wait + 2 stretches) without two agreeing stretches the loop corrects anyway, at half
    strength, so the drive follows the drift instead of freezing; once the drift stops the loop
    lands on the target."""
    from rtctl.control._kernels import PATIENCE

    loop = Loop([1e-7], [1e-7], [5e-6])
    k_patience = loop.ctl.warm + PATIENCE * (loop.ctl.warm + 2 * loop.ctl.hold)
    cmds, ests = [], []
    for k in range(2 * k_patience):
        loop.plant[0] = 1e-7 * 1.06 ** (k / loop.ctl.hold)
        loop.block()
        ests.append(loop.est[0, 0, 0, 0])  # what the controller read in this block
        cmds.append(loop.ctl.state[CMD, 0])
    changed = np.flatnonzero(np.diff(cmds)) + 1
    assert changed.size >= 1 and changed[0] == k_patience, (changed, k_patience)
    k = changed[0]  # half strength, on the mean of the last stretch
    mean = np.mean(ests[k - loop.ctl.hold + 1:k + 1])
    np.testing.assert_allclose(cmds[k] / cmds[k - 1], (5e-6 / mean) ** 0.5, rtol=1e-12)
    assert cmds[k] < cmds[k - 1]  # the tip per volt grew: the drive comes down
    loop.run(6 * k_patience)
    np.testing.assert_allclose(loop.truth[-1][0], 5e-6, rtol=1e-12)


def test_a_target_that_moves_every_block_is_driven_at_the_plants_tip_per_volt():
    """A target that changes every block (a swell) never leaves a window of one command to correct
    on. The drive for each new target comes from the tip per volt of the windows (tip over the
    window's own drive), taken once two stretches of them agree: from then on the tip follows the
    target at the plant's own gain, not at START of a model that is 2x wrong (0.35 of the
    target)."""
    loop = Loop([1e-7], [2e-7], [1e-6])
    targets = 1e-6 * (1.0 + np.arange(300) / 100.0)  # 1 um to 4 um over 300 blocks
    for r in targets:
        loop.ctl.target[TARGET, 0] = r
        loop.block()
    tip = np.array(loop.truth)[:, 0]
    # block k plays the command set after block k-1 for that block's target
    assert tip[2] == pytest.approx(START * 0.5 * targets[1], rel=1e-12)  # the model's, aimed low
    # two stretches of windows that hold drive (the first stretch from the window's first block)
    learned = 2 + loop.latency + 2 * loop.ctl.hold
    np.testing.assert_allclose(tip[2:learned], START * 0.5 * targets[1:learned - 1], rtol=1e-12)
    settled = loop.latency + loop.window + 2 * loop.ctl.hold + 1
    np.testing.assert_allclose(tip[settled:], targets[settled - 1:-1], rtol=1e-9)


@pytest.mark.parametrize("rise", [1, 2, 7, 30])
def test_a_start_rises_along_a_raised_cosine_then_waits_a_window(rise):
    # the drive of block k of the rise is the command times (1 - cos(pi k / R)) / 2, k = 1 .. R
    # (R = 1: the whole command in the first block, as without a rise); the first correction
    # comes a latency and a window after the rise has reached the command, never before
    latency, window = 1, 6
    loop = Loop([5e-8], [1e-7], [5e-6], latency=latency, window=window)
    loop.ctl.rise = rise
    loop.ctl.reset()
    loop.ctl.target[ENABLE] = 1.0
    drives = []
    for _ in range(rise + latency + window + 40):
        loop.block()
        drives.append(loop.pending[P_AMP, 0])
    first = START * 5e-6 / 1e-7
    k = np.arange(1, rise + 1)
    np.testing.assert_allclose(drives[:rise], first * (1 - np.cos(np.pi * k / rise)) / 2, rtol=1e-15)
    wait = design(latency, window)[1]  # from the rise's last block to an estimate of it alone
    assert np.all(np.array(drives[rise - 1:rise + wait]) == first)
    # the plant is half the model: feedback brings the drive to the target's without crossing it
    assert drives[-1] == pytest.approx(5e-6 / 5e-8, rel=1e-3)
    assert max(loop.truth[-1]) == pytest.approx(5e-6, rel=1e-3) and np.max(loop.truth) <= 5e-6 * (1 + 1e-9)


def test_a_big_correction_rises_from_the_present_drive_a_small_one_steps():
    # a plant 20x weaker than the model: the first correction is the largest allowed (x MAX_STEP),
    # more than BIG_STEP, so it rises from the present drive along the same raised cosine as a
    # start and the next estimate waits for the rise's end; the last one (20 / 0.7 / 16 = x1.79)
    # goes in one block
    from rtctl.control._kernels import BIG_STEP

    rise, latency, window, target = 9, 1, 6, 5e-7
    loop = Loop([5e-9], [1e-7], [target], latency=latency, window=window)
    loop.ctl.rise = rise
    loop.ctl.reset()
    loop.ctl.target[ENABLE] = 1.0
    d = []
    for _ in range(200):
        loop.block()
        d.append(loop.pending[P_AMP, 0])
    d = np.array(d)
    changes = np.flatnonzero(np.diff(d[rise - 1:]) != 0) + rise  # first block of each new command
    k0 = changes[0]
    a0, a1 = d[k0 - 1], d[k0 + rise - 1]
    assert a0 == START * target / 1e-7 and a1 / a0 == pytest.approx(MAX_STEP, rel=1e-12) and MAX_STEP > BIG_STEP
    k = np.arange(1, rise + 1)
    np.testing.assert_allclose(d[k0:k0 + rise], a0 + (a1 - a0) * (1 - np.cos(np.pi * k / rise)) / 2, rtol=1e-14)
    assert np.all(d[k0 + rise - 1:k0 + rise + design(latency, window)[1]] == a1)
    k1 = [c for c in changes if c >= k0 + rise][0]
    assert d[k1] / d[k1 - 1] == pytest.approx(20 / START / MAX_STEP, rel=1e-9) and 20 / START / MAX_STEP < BIG_STEP
    assert np.all(d[k1:] == d[k1]) and d[k1] == pytest.approx(target / 5e-9, rel=1e-9)
    assert np.max(loop.truth) <= target * (1 + 1e-9)


def _fed(stretches, target=1e-6, window=6, ring=48):
    """One tone whose estimates are given: a filler until the controller reads its first fresh
    estimate, then ``stretches`` (lists of HOLD estimates, m) one after the other. Returns the
    controller and the commands: before the first given estimate and after each."""
    ctl = AmplitudeController([0], [0], [0], [0], [1e-7], [150.0], [target], 1, window, BLOCK, ring)
    ctl.target[ENABLE] = 1.0
    est, drive_est = np.zeros((1, 1, 9, 2)), np.zeros((1, 1, 2))
    pending, lim = np.zeros((N_PEND, 1)), np.zeros((3, 1), dtype=np.int64)

    def call(y):
        est[0, 0, 0, 0] = y
        amplitude_control(est, drive_est, **ctl.args, pending=pending, lim_counts=lim, ramp=float(BLOCK))

    call(0.5 * target)  # the start
    while ctl.state[WAIT, 0] > 0.0:  # its wait: estimates not read
        call(0.5 * target)
    cmds = [ctl.state[CMD, 0]]  # the next call reads the first estimate of the first stretch
    for y in (y for s in stretches for y in s):
        call(y)
        cmds.append(ctl.state[CMD, 0])
    assert ctl.state[TRIES, 0] > 0 or np.any(np.diff(cmds))  # every estimate was read
    return ctl, np.array(cmds)


def _scatter(mean, rel, n):
    """``n`` estimates (n even) of ``mean`` scattered by +-``rel``: their population variance is
    (mean rel)^2."""
    return [mean * (1.0 + rel * (-1) ** k) for k in range(n)]


def _z(a, b):
    """How many standard errors of their difference the means of two stretches lie apart (numpy's
    variance of each, as if the estimates were independent)."""
    return abs(np.mean(a) - np.mean(b)) / np.sqrt(np.var(a) / len(a) + np.var(b) / len(b))


@pytest.mark.parametrize("far, window", [(0.5, 6), (0.13, 6), (0.5, 30)])
def test_far_from_the_target_two_stretches_agree_within_their_scatter(far, window):
    """A finger that landed: the tip far below the target (more than FAR, 10 %), its estimates
    scattered (a tenth of the amplitude is read through the same current noise). Two stretches
    whose means differ by more than AGREE but by less than NOISE_Z (2) standard errors agree; 2.5
    standard errors do not: the correction comes at the end of the third stretch, on its mean.
    Only where a stretch spans a whole window (6 blocks, a stretch of 6): with a window of 30
    (stretch 8) the estimates of a stretch overlap, their spread is not their noise, and the loop
    waits for AGREE or PATIENCE."""
    from rtctl.control._kernels import AGREE, HOLD, PATIENCE, WARM

    r = 1e-6
    ctl0 = AmplitudeController([0], [0], [0], [0], [1e-7], [150.0], [r], 1, window, BLOCK, 48)
    h = int(ctl0.state[HOLD, 0])
    assert h % 2 == 0 and (h >= window) == (window == 6)
    m3 = r / (1.0 + far)
    err = 0.1 * m3 * np.sqrt(2.0 / h)  # the standard error of two stretches' difference at 10 % scatter
    s3 = _scatter(m3, 0.1, h)
    s2 = _scatter(m3 - 1.5 * err, 0.1 * m3 / (m3 - 1.5 * err), h)
    s1 = _scatter(m3 + 1.0 * err, 0.1 * m3 / (m3 + 1.0 * err), h)
    assert abs(np.mean(s2) / np.mean(s1) - 1.0) > AGREE and abs(np.mean(s3) / np.mean(s2) - 1.0) > AGREE
    assert _z(s1, s2) == pytest.approx(2.5) and _z(s2, s3) == pytest.approx(1.5)
    ctl, cmds = _fed([s1, s2, s3, _scatter(m3, 0.1, h)], target=r, window=window)
    changed = np.flatnonzero(np.diff(cmds)) + 1
    if window > h:  # not on the third stretch: on the fourth, equal to it (AGREE), before PATIENCE
        assert changed[0] == 4 * h < PATIENCE * (ctl0.state[WARM, 0] + 2 * h), changed
        return
    assert changed[0] == 3 * h, changed  # the last estimate of the third stretch
    np.testing.assert_allclose(cmds[3 * h] / cmds[0], r / np.mean(s3), rtol=1e-9)


def test_near_the_target_only_agree_counts():
    """Within FAR (10 %) of the target, stretches that agree only within their scatter are not
    corrected on (a correction on noise blinds the loop for a window): the command holds."""
    from rtctl.control._kernels import HOLD

    r = 1e-6
    h = int(AmplitudeController([0], [0], [0], [0], [1e-7], [150.0], [r], 1, 6, BLOCK, 48).state[HOLD, 0])
    m = r / 1.07
    stretches = [_scatter(m * (1.0 + 0.06 * (k % 2)), 0.3, h) for k in range(6)]  # 6 % apart, < 1 error
    assert all(_z(a, b) < 1.0 for a, b in zip(stretches, stretches[1:]))
    _, cmds = _fed(stretches, target=r)
    assert np.all(cmds == cmds[0])


def test_a_window_sliding_over_a_change_never_agrees_within_its_scatter():
    """Far below the target, estimates that fall along a ramp (a window sliding over a finger's
    landing) spread within each stretch, but the stretches' means move by several standard errors
    (sqrt(6 n) for n estimates): no correction until two stretches of the settled value agree,
    then one on that value."""
    from rtctl.control._kernels import HOLD

    r = 1e-6
    h = int(AmplitudeController([0], [0], [0], [0], [1e-7], [150.0], [r], 1, 6, BLOCK, 48).state[HOLD, 0])
    ramp = list(np.linspace(0.6 * r, 0.1 * r, 4 * h))
    flat = [0.1 * r] * (3 * h)
    _, cmds = _fed([ramp[k * h:(k + 1) * h] for k in range(4)] + [flat], target=r)
    changed = np.flatnonzero(np.diff(cmds)) + 1
    assert changed[0] == 6 * h, changed  # the second stretch of the settled value
    np.testing.assert_allclose(cmds[6 * h] / cmds[0], 10.0, rtol=1e-12)  # 10x, on the settled value
