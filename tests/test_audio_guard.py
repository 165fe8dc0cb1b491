"""The audio device thread's own guards (rtctl.io._audio_kernels.io_guard): silent inputs after
they were live, and xrun bursts; either starts the limiter's fade in the device thread."""

import numpy as np

from rtctl.io import _audio_kernels as K
from rtctl.safety import DEVICE_LOST, IO_XRUN, XRUN_BURST, Limiter

BLOCK = 32


def setup(silent_blocks=0, window=0, allowed=0):
    ctl = np.zeros(K.N_CTL, dtype=np.int64)
    ctl[K.SILENT_LIMIT] = silent_blocks
    if allowed:
        ctl[K.XRUN_ADD], ctl[K.XRUN_LEAK], ctl[K.XRUN_CAP] = window, allowed, allowed * window
    lim = Limiter(48000.0, max_voltage=[100.0, 100.0], slew=1e9, current=10.0, capacitance=1e-8, temperature=80.0,
                  ambient=25.0, loss_tangent=0.02, thermal_resistance=100.0, thermal_tau=10.0)
    return ctl, lim


def guard(ctl, lim, sensed, out, xrun=0):
    return K.io_guard(ctl, sensed, out, xrun, *lim.args[:3], BLOCK)


def test_silent_inputs_count_only_after_being_live_and_only_while_driving():
    ctl, lim = setup(silent_blocks=3)
    zero, live = np.zeros((4, BLOCK)), np.full((4, BLOCK), 1e-7)
    drive, idle = np.full((2, BLOCK), 5.0), np.zeros((2, BLOCK))
    for _ in range(10):  # before the plant is connected: silent, but never live yet
        assert guard(ctl, lim, zero, drive) == 0
    assert guard(ctl, lim, live, drive) == 0 and ctl[K.LIVE] == 1
    assert guard(ctl, lim, zero, idle) == 0            # not driving: nothing to hear, not counted
    assert guard(ctl, lim, zero, drive) == 0
    assert guard(ctl, lim, zero, drive) == 0
    assert lim.fade[1] == 0
    assert guard(ctl, lim, zero, drive) == DEVICE_LOST  # the third silent block while driving
    assert ctl[K.GUARD] == K.GUARD_SILENT and ctl[K.STOP_BEGUN] == 1
    assert lim.fade[1] >= BLOCK                          # the fade starts with the next block
    one = zero.copy()
    one[3, 17] = -2e-9
    ctl2, lim2 = setup(silent_blocks=3)
    guard(ctl2, lim2, live, drive)
    for _ in range(10):  # one nonzero sample anywhere is a live input
        assert guard(ctl2, lim2, one, drive) == 0


def test_a_burst_of_xruns_ends_the_run_and_a_steady_trickle_does_not():
    # the leaky bucket fires at the k-th consecutive xrun with k (W - N) > N W: N = 5, W = 100 -> k = 6
    ctl, lim = setup(window=100, allowed=5)
    out, sensed = np.full((2, BLOCK), 1.0), np.zeros((0, BLOCK))
    fired = [bool(guard(ctl, lim, sensed, out, IO_XRUN) & XRUN_BURST) for _ in range(8)]
    assert fired.index(True) == 5 and ctl[K.GUARD] == K.GUARD_XRUNS and lim.fade[1] > 0
    # one xrun every 40 blocks (2.5 per window of 100, half the allowance), for 20000 blocks
    ctl, lim = setup(window=100, allowed=5)
    hits = sum(bool(guard(ctl, lim, sensed, out, IO_XRUN if k % 40 == 0 else 0) & XRUN_BURST) for k in range(20000))
    assert hits == 0 and lim.fade[1] == 0
    # against a sliding window, on random streams: while no window of W blocks holds more than N
    # xruns the bucket stays at or below N W (W per xrun, N out per block), so it never fires
    quiet = loud = 0
    for seed in range(40):
        rate = (0.01, 0.04)[seed % 2]  # 1 or 4 per window on average
        flags = np.random.default_rng(seed).random(3000) < rate
        most = np.convolve(flags, np.ones(100, dtype=int)).max()  # every window, partial ones too
        ctl, lim = setup(window=100, allowed=5)
        fired = any(guard(ctl, lim, sensed, out, IO_XRUN if f else 0) & XRUN_BURST for f in flags)
        if most <= 5:
            assert not fired, seed
            quiet += 1
        loud += fired
    assert quiet >= 5 and loud >= 5, (quiet, loud)  # both kinds of stream were seen


def test_a_fault_from_the_block_step_starts_the_fade_in_the_device_thread():
    ctl, lim = setup()
    from rtctl.safety import NONFINITE

    assert guard(ctl, lim, np.zeros((1, BLOCK)), np.zeros((2, BLOCK)), NONFINITE) == 0
    assert ctl[K.STOP_BEGUN] == 1 and lim.fade[1] > 0
