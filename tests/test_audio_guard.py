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


def test_the_block_that_ends_a_stop_fade_is_marked_when_the_limiter_is_done():
    """``ctl[FADE_END]`` = the blocks counted once ``Limiter.done`` turned true in a block, for a
    requested stop's raised cosine over several blocks and for a fault's one-block fade; never
    before, never without a stop, and not moved by later blocks."""
    rng = np.random.default_rng(5)
    sensed = np.full((1, BLOCK), 1e-6)
    for smooth, fade_blocks in ((True, 3.5), (False, 1)):
        ctl, lim = setup()
        for k in range(40):
            x = rng.uniform(-80, 80, (2, BLOCK))
            if k == 10:
                ctl[K.STOP_BEGUN] = 1  # what the callback does on a stop request
                K.limiter_shutdown(*lim.args[:3], int(fade_blocks * BLOCK), smooth)
            was_done = lim.done
            lim.process(x)
            guard(ctl, lim, sensed, x)
            if lim.done and not was_done:
                want = k + 1
            assert ctl[K.FADE_END] == (want if lim.done else 0), (smooth, k)
            ctl[K.DONE] += 1  # the callback counts the block after the guard
        assert ctl[K.FADE_END] == 10 + int(np.ceil(fade_blocks)), smooth
    ctl, lim = setup()  # a limiter whose fade is done but no stop began in the device thread
    lim.shutdown(BLOCK)
    lim.process(np.zeros((2, BLOCK)))
    assert lim.done and guard(ctl, lim, sensed, np.zeros((2, BLOCK))) == 0 and ctl[K.FADE_END] == 0


def test_fade_done_kernel_is_the_limiters():
    ctl, lim = setup()
    rng = np.random.default_rng(6)
    for _ in range(300):
        lim.fade[:] = rng.integers(0, 4), rng.integers(0, 4), 1
        lim.state[0] = rng.choice([0.0, -0.0, 1e-300, -3.0, np.nan], 2, p=[0.4, 0.3, 0.1, 0.1, 0.1])
        assert K.fade_done(lim.state, lim.fade) == lim.done
