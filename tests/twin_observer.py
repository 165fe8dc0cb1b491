"""The observer's block step as it was before its kernels were restructured (channel-innermost
tip waveform, currents demodulated without amplitude and phase, ...): a reference twin that the
tests compare the new kernels against bitwise, and that bench/observer.py times in the same
process. A verbatim copy of the lock-in section of ``rtctl/dsp/_kernels.py`` and of
``observer_process`` / ``observe_stage`` at that point; only the oscillator helpers, which did not
change, are the package's."""

import math

import numpy as np

from rtctl._numba import kernel
from rtctl.dsp._kernels import (
    CLOCK,
    DI,
    DR,
    INC1,
    P_FLAG,
    P_FREQ,
    WI,
    WR,
    ZI,
    ZR,
    Y,
    _flush,
    _osc_advance,
    _osc_chunk,
    _osc_start_ramps,
)
from rtctl.safety import ESTIMATE_NONFINITE

STATUS_NONFINITE = 4

ACC_R, ACC_I = 0, 1
S_R, S_I = 2, 3
F_R, F_I = 4, 5
EST_A, EST_P = 6, 7
HOP = 8
NHOP = 9
Z_R, Z_I = 10, 11
X_R, X_I = 12, 13
LSQ = 14
_ZR, _ZI, _WR, _WI = ZR, ZI, WR, WI
_XR, _XI = X_R, X_I


@kernel
def _lockin_demod(ref, chan, acc, x, j0, m, ramping):
    zr = ref[ZR]
    zi = ref[ZI]
    wr = ref[WR]
    wi = ref[WI]
    dr = ref[DR]
    di = ref[DI]
    xs = ref[Y]
    ar = acc[ACC_R]
    ai = acc[ACC_I]
    ns = zr.shape[0]
    for j in range(j0, j0 + m):
        for s in range(ns):
            xs[s] = x[chan[s], j]
        for s in range(ns):
            v = xs[s]
            ar[s] += v * zr[s]
            ai[s] -= v * zi[s]
            r = zr[s] * wr[s] - zi[s] * wi[s]
            zi[s] = zr[s] * wi[s] + zi[s] * wr[s]
            zr[s] = r
        if ramping:
            for s in range(ns):
                r = wr[s] * dr[s] - wi[s] * di[s]
                wi[s] = wr[s] * di[s] + wi[s] * dr[s]
                wr[s] = r


@kernel
def _run_end(acc, s0):
    """One past the last slot of the run from ``s0`` whose windows are ``s0``'s."""
    s1 = s0 + 1
    while s1 < acc.shape[1] and acc[NHOP, s1] == acc[NHOP, s0]:
        s1 += 1
    return s1


@kernel
def _lockin_hop(ref, acc, ring, hop_index):
    """Close hop ``hop_index`` (count since reset, 0-based): move its partial sums into the window.

    Each slot's window holds its own ``NHOP`` hops (ring rows ``0 .. NHOP - 1``). Slots are taken
    in runs of equal ``NHOP`` (a group-wide window is one run; per-channel windows a run per
    channel), so the ring row is one per run and the inner loop stays a contiguous sweep.
    """
    ns = acc.shape[1]
    s0 = 0
    while s0 < ns:
        nh = acc[NHOP, s0]
        s1 = _run_end(acc, s0)
        n_hops = max(1, int(nh))  # >= 1 from LockIn; guarded so a zeroed acc cannot raise
        idx = hop_index % n_hops
        wrap = idx == n_hops - 1
        for s in range(s0, s1):
            pr = _flush(acc[ACC_R, s])
            pi = _flush(acc[ACC_I, s])
            acc[S_R, s] += pr - ring[idx, 0, s]
            acc[S_I, s] += pi - ring[idx, 1, s]
            acc[F_R, s] += pr
            acc[F_I, s] += pi
            ring[idx, 0, s] = pr
            ring[idx, 1, s] = pi
            acc[ACC_R, s] = 0.0
            acc[ACC_I, s] = 0.0
            acc[Z_R, s] = ref[ZR, s]
            acc[Z_I, s] = ref[ZI, s]
            if wrap:
                # the ring now holds exactly the hops added to F since the last wrap: replace the
                # add-and-subtract running sum by this fresh one, so round-off cannot drift
                acc[S_R, s] = acc[F_R, s]
                acc[S_I, s] = acc[F_I, s]
                acc[F_R, s] = 0.0
                acc[F_I, s] = 0.0
            acc[S_R, s] = _flush(acc[S_R, s])
            acc[S_I, s] = _flush(acc[S_I, s])
            acc[F_R, s] = _flush(acc[F_R, s])
            acc[F_I, s] = _flush(acc[F_I, s])
        s0 = s1


@kernel
def _lockin_solve(acc, solve, s):
    """Slot ``s``'s window sum with its row's other tones and every mirror removed (see LockIn,
    "Least squares"): with ``T_l = S_l z_l`` (``z_l`` the reference after the window) over the
    row's slots ``l``, ``Y = solve[s] T`` (real, imaginary interleaved) and ``X = Y conj(z_s)``."""
    n_freq = solve.shape[2] // 2
    b = s - s % n_freq
    yr = 0.0
    yi = 0.0
    for j in range(n_freq):
        lr = acc[S_R, b + j]
        li = acc[S_I, b + j]
        zr = acc[Z_R, b + j]
        zi = acc[Z_I, b + j]
        tr = lr * zr - li * zi
        ti = lr * zi + li * zr
        yr += solve[s, 0, 2 * j] * tr + solve[s, 0, 2 * j + 1] * ti
        yi += solve[s, 1, 2 * j] * tr + solve[s, 1, 2 * j + 1] * ti
    zr = acc[Z_R, s]
    zi = acc[Z_I, s]
    acc[X_R, s] = yr * zr + yi * zi
    acc[X_I, s] = yi * zr - yr * zi


@kernel
def _lockin_estimate(ref, acc, solve):
    """Amplitude and phase of every slot from its window sum (once per call, not per hop); the
    scale is one per run of slots with equal windows, as in :func:`_lockin_hop`. A slot whose
    row is solved by least squares (``LSQ``) reads its solved sum, every other its plain one."""
    ns = acc.shape[1]
    for s in range(ns):
        if acc[LSQ, s] != 0.0:
            _lockin_solve(acc, solve, s)
        else:
            acc[X_R, s] = acc[S_R, s]
            acc[X_I, s] = acc[S_I, s]
    s0 = 0
    while s0 < ns:
        nh = acc[NHOP, s0]
        s1 = _run_end(acc, s0)
        scale = 2.0 / (nh * acc[HOP, 0])
        for s in range(s0, s1):
            if ref[INC1, s] > 0.0:
                acc[EST_A, s] = scale * math.hypot(acc[X_R, s], acc[X_I, s])
                acc[EST_P, s] = math.atan2(acc[X_I, s], acc[X_R, s])
            else:
                acc[EST_A, s] = np.nan
                acc[EST_P, s] = np.nan
        s0 = s1


@kernel
def lockin_process(ref, pending, chan, acc, ring, solve, x, out):
    """Demodulate ``x`` at every slot's reference frequency over a sliding window (see LockIn).

    Parameters
    ----------
    ref : ndarray, shape (N_OSC, n_slots), float64
        Reference oscillators (same layout as the oscillator bank), updated in place.
    pending : ndarray, shape (N_PEND, n_slots), float64
        Reference frequency targets as for the bank (``P_FREQ`` <= 0 or NaN: slot unused).
    chan : ndarray, shape (n_slots,), int64
        Input row of each slot (``slot // n_freq``).
    acc : ndarray, shape (N_ACC, n_slots), float64
        Hop, window and fresh sums and the latest estimates, updated in place; ``acc[NHOP]``
        the hops in each slot's window (equal everywhere for a window shared by all slots).
    ring : ndarray, shape (n_hops, 2, n_slots), float64
        Partial sums of the hops in the window (real, imaginary); ``n_hops`` the longest
        slot's (a slot uses rows ``0 .. acc[NHOP, s] - 1``).
    solve : ndarray, shape (n_slots, 2, 2 * n_freq), float64
        Per slot whose ``acc[LSQ]`` is set: its rows (real, imaginary) of the least-squares
        inverse over its row's slots (see LockIn); unread for the others.
    x : ndarray, shape (n_channels, n), float64, C-contiguous
        Input block.
    out : ndarray, shape (n_channels, n_freq, 2), float64
        Amplitude (peak) and phase (rad) at the last complete hop; NaN for unused slots.
    """
    ns = ref.shape[1]
    if ns == 0:
        return
    for s in range(ns):
        if pending[P_FLAG, s] != 0.0 and not (pending[P_FREQ, s] > 0.0):
            pending[P_FREQ, s] = 0.0  # unused: a still reference costs nothing and reads NaN
    _osc_start_ramps(ref, pending)
    hop = int(acc[HOP, 0])
    n = x.shape[1]
    t = 0
    closed = False
    while t < n:
        clock = int(ref[CLOCK, 0])
        m, mode = _osc_chunk(ref, n - t)
        m = min(m, hop - clock % hop)
        _lockin_demod(ref, chan, acc, x, t, m, mode == 2)
        _osc_advance(ref, m)
        if (clock + m) % hop == 0:
            _lockin_hop(ref, acc, ring, (clock + m) // hop - 1)
            closed = True
        t += m
    if closed:
        _lockin_estimate(ref, acc, solve)
    n_freq = out.shape[1]
    for s in range(ns):
        out[s // n_freq, s % n_freq, 0] = acc[EST_A, s]
        out[s // n_freq, s % n_freq, 1] = acc[EST_P, s]


@kernel
def observer_process(u_ref, u_pend, u_chan, u_acc, u_ring, u_solve, i_ref, i_pend, i_chan, i_acc, i_ring,
                     i_solve, u_out, i_out, H, scale, est, wave, drive, sensed):
    """One block: demodulate drive and currents, apply the observer, rebuild the tip waveform.

    Parameters
    ----------
    u_ref, u_pend, u_chan, u_acc, u_ring, u_solve : ndarray
        Lock-in of the drive (``LockIn.args``), slots ``(n_ch, n_tones)``.
    i_ref, i_pend, i_chan, i_acc, i_ring, i_solve : ndarray
        Lock-in of the sensed currents, rows ``ch * n_seg + seg``, slots ``(n_ch * n_seg, n_tones)``;
        each row's window that of its channel in the drive's lock-in.
    u_out, i_out : ndarray, shapes (n_ch, n_tones, 2) and (n_ch * n_seg, n_tones, 2)
        Scratch for the lock-ins' amplitude/phase outputs.
    H : ndarray, shape (n_ch, n_tones, n_est, 1 + n_seg, 2)
        Observer matrices (real, imaginary); all zero for an unused tone slot.
    scale : ndarray, shape (n_ch,)
        ``2 / window`` of each channel: lock-in sum to phasor.
    est : ndarray, shape (n_ch, n_tones, n_est, 2)
        Written: estimate phasors (real, imaginary) over the last complete window.
    wave : ndarray, shape (n_ch, n)
        Written: tip deflection rebuilt from the row-0 estimates on this block's samples, m.
    drive : ndarray, shape (n_ch, n)
        Drive volts written to the DAC for this block.
    sensed : ndarray, shape (n_ch * n_seg, n)
        ADC current readings of this block, A.

    Returns
    -------
    int
        0, or ``STATUS_NONFINITE`` if any estimate is NaN/Inf.
    """
    lockin_process(u_ref, u_pend, u_chan, u_acc, u_ring, u_solve, drive, u_out)
    lockin_process(i_ref, i_pend, i_chan, i_acc, i_ring, i_solve, sensed, i_out)
    n_ch, n_t, n_est = est.shape[0], est.shape[1], est.shape[2]
    n_seg = H.shape[3] - 1
    n = drive.shape[1]
    status = 0
    for c in range(n_ch):
        sc = scale[c]
        for s in range(n):
            wave[c, s] = 0.0
        for k in range(n_t):
            us = c * n_t + k
            dr = sc * u_acc[_XR, us]
            di = sc * u_acc[_XI, us]
            for e in range(n_est):
                hr = H[c, k, e, 0, 0]
                hi = H[c, k, e, 0, 1]
                zr = hr * dr - hi * di
                zi = hr * di + hi * dr
                for j in range(n_seg):
                    js = (c * n_seg + j) * n_t + k
                    sr = sc * i_acc[_XR, js]
                    si = sc * i_acc[_XI, js]
                    hr = H[c, k, e, 1 + j, 0]
                    hi = H[c, k, e, 1 + j, 1]
                    zr += hr * sr - hi * si
                    zi += hr * si + hi * sr
                est[c, k, e, 0] = zr
                est[c, k, e, 1] = zi
                if not (np.isfinite(zr) and np.isfinite(zi)):
                    status |= STATUS_NONFINITE
            # Rebuild: x[m] = Re(X z[m]); z of the next sample is the reference's (ZR, ZI),
            # earlier samples step back by the conjugate per-sample rotation (steady tones).
            xr, xi = est[c, k, 0, 0], est[c, k, 0, 1]
            if xr == 0.0 and xi == 0.0:
                continue
            zr, zi = u_ref[_ZR, us], u_ref[_ZI, us]
            wr, wi = u_ref[_WR, us], -u_ref[_WI, us]
            for s in range(n - 1, -1, -1):
                t = zr * wr - zi * wi
                zi = zr * wi + zi * wr
                zr = t
                wave[c, s] += xr * zr - xi * zi
    return status


@kernel
def observe_stage(u_ref, u_pend, u_chan, u_acc, u_ring, u_solve, i_ref, i_pend, i_chan, i_acc, i_ring, i_solve,
                  u_out, i_out, H, scale, est, wave, delay, head, out, sensed, amp):
    """Observe one block and push this block's drive into the delay ring.

    Parameters
    ----------
    u_ref ... wave
        ``Observer.args`` (see :func:`rtctl.selfsense.rt.observer_process`).
    delay : ndarray, shape (L, n_ch, block)
        The drive of the last ``L`` blocks; ``delay[head[0]]`` is the oldest, the one the
        currents in ``sensed`` answer.
    head : ndarray int64, shape (1,)
    out : ndarray, shape (n_ch, block)
        This block's drive (after the limiter).
    sensed : ndarray, shape (n_ch * n_seg, block)
        The currents the backend delivered at the start of this block, A.
    amp : ndarray, shape (n_ch,)
        Written: estimated tip amplitude per channel, m: the sum over its tones (the envelope
        peak of a beat pair).

    Returns
    -------
    int
        0 or ``ESTIMATE_NONFINITE``.
    """
    k = head[0]
    s = observer_process(u_ref, u_pend, u_chan, u_acc, u_ring, u_solve, i_ref, i_pend, i_chan, i_acc, i_ring, i_solve,
                         u_out, i_out, H, scale, est, wave, delay[k], sensed)
    delay[k, :, :] = out
    head[0] = (k + 1) % delay.shape[0]
    for c in range(est.shape[0]):
        a = 0.0
        for j in range(est.shape[1]):
            a += np.hypot(est[c, j, 0, 0], est[c, j, 0, 1])
        amp[c] = a
    return ESTIMATE_NONFINITE if s != 0 else 0
