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


def observer_block(H, drive, sensed, freqs, fs, n_seg, start=0):
    """Estimates from one full window starting at sample ``start`` of the references (phase 0 at
    sample 0): direct sums, then ``H``.

    drive: (n_ch, W); sensed: (n_ch * n_seg, W); freqs: (n_ch, n_t); H complex
    (n_ch, n_t, n_est, 1 + n_seg). Returns est (n_ch, n_t, n_est) complex and the rebuilt
    tip waveform over the window's last ``block`` samples is left to the caller.
    """
    n_ch, W = drive.shape
    n = start + np.arange(W)
    est = np.zeros(H.shape[:3], dtype=complex)
    for c in range(n_ch):
        for k in range(freqs.shape[1]):
            ref = np.exp(-2j * np.pi * freqs[c, k] * n / fs)
            x = [2.0 / W * np.sum(drive[c] * ref)]
            x += [2.0 / W * np.sum(sensed[c * n_seg + j] * ref) for j in range(n_seg)]
            est[c, k] = H[c, k] @ np.array(x)
    return est


def rebuild(est_tip, freqs, fs, start, n):
    """Tip waveform ``sum_k Re(X_k exp(2 pi i f_k t))`` on samples start..start+n-1."""
    t = (start + np.arange(n)) / fs
    return np.sum((est_tip[..., None] * np.exp(2j * np.pi * freqs[..., None] * t)).real, axis=1)
