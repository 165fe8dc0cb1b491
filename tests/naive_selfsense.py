"""Plain numpy twins of the self-sensing kernels and series (stumpy's tests/naive.py)."""

import numpy as np
import scipy.linalg


def piece_matrix(lam, EI, x):
    """Field matrix of a uniform beam piece by ``expm`` of the state ODE
    ``w' = psi, psi' = M / EI, M' = Q, Q' = lam EI w``."""
    A = np.zeros((4, 4), dtype=complex)
    A[0, 1] = 1.0
    A[1, 2] = 1.0 / EI
    A[2, 3] = 1.0
    A[3, 0] = lam * EI
    return scipy.linalg.expm(A * x)


def observer_block(H, drive, sensed, freqs, fs, n_seg, start=0, K=None, before=None):
    """Estimates from one full window starting at sample ``start`` of the references (phase 0 at
    sample 0): direct sums, then ``H``; with ``K``, less ``K`` times a drive step's boundary term.

    drive: (n_ch, W); sensed: (n_ch * n_seg, W); freqs: (n_ch, n_t); H complex
    (n_ch, n_t, n_est, 1 + n_seg). K complex (n_ch, n_t, n_est): what the boundary term puts in
    each estimate (``steps_K``); before (n_ch,): the drive sample just before the window (default
    0, as before a first window). The term is the phasor of the drive's first difference over
    ``1 - exp(-j w / fs)`` (a steady tone's), less the drive's phasor. Returns est (n_ch, n_t,
    n_est) complex; the rebuilt tip waveform over the window's last ``block`` samples is left to
    the caller.
    """
    n_ch, W = drive.shape
    n = start + np.arange(W)
    est = np.zeros(H.shape[:3], dtype=complex)
    b = np.zeros(n_ch) if before is None else np.asarray(before, dtype=float)
    dx = np.diff(np.concatenate([b[:, None], drive], axis=1), axis=1)
    for c in range(n_ch):
        for k in range(freqs.shape[1]):
            ref = np.exp(-2j * np.pi * freqs[c, k] * n / fs)
            x = [2.0 / W * np.sum(drive[c] * ref)]
            x += [2.0 / W * np.sum(sensed[c * n_seg + j] * ref) for j in range(n_seg)]
            est[c, k] = H[c, k] @ np.array(x)
            if K is not None and freqs[c, k] > 0:
                d = 2.0 / W * np.sum(dx[c] * ref)
                est[c, k] -= K[c, k] * (d / (1.0 - np.exp(-2j * np.pi * freqs[c, k] / fs)) - x[0])
    return est


def steps_K(obs):
    """An observer's drive step correction at each channel's image load in use, complex (n_ch,
    n_t, n_est)."""
    k = obs.Kc[np.arange(obs.Kc.shape[0]), :, obs.pick]
    return k[..., 0] + 1j * k[..., 1]


def rebuild(est_tip, freqs, fs, start, n):
    """Tip waveform ``sum_k Re(X_k exp(2 pi i f_k t))`` on samples start..start+n-1."""
    t = (start + np.arange(n)) / fs
    return np.sum((est_tip[..., None] * np.exp(2j * np.pi * freqs[..., None] * t)).real, axis=1)
