"""Real-time kernel of the self-sensing observer: lock-in, observer matrices, tip waveform.

Allocates nothing, raises nothing; the wrapper is :class:`rtctl.selfsense.rt.Observer`.
"""

import numpy as np

from rtctl._numba import kernel
from rtctl.dsp import _kernels as _dk

# Status bit: an estimate is NaN/Inf (a poisoned reading or state); the sim uses 1 and 2.
STATUS_NONFINITE = 4

_ZR, _ZI, _WR, _WI = _dk.ZR, _dk.ZI, _dk.WR, _dk.WI
_XR, _XI = _dk.X_R, _dk.X_I  # the window sums the lock-ins' estimates are made of
_lockin = _dk.lockin_process


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
    _lockin(u_ref, u_pend, u_chan, u_acc, u_ring, u_solve, drive, u_out)
    _lockin(i_ref, i_pend, i_chan, i_acc, i_ring, i_solve, sensed, i_out)
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
