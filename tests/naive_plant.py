"""Plain numpy/loop twins of the kernels in ``rtctl.plant._kernels`` (as stumpy's tests/naive.py).

They use the plain state-space form ``x[k+1] = A x[k] + b u[k]``, ``y = C x + d u`` per channel,
with the same subnormal flush, and the same ADC arithmetic written the obvious way. The modal
kernels run with unit input gains (``ModalForm.unit_input``): their twins take ``b = unit_b``.
"""

import numpy as np

from rtctl._numba import TINY


def modal_matrix(pairs, reals):
    """Dense block-diagonal matrix of the modal kernel's coefficients."""
    n_pairs = pairs.shape[0]
    n = 2 * n_pairs + reals.size
    A = np.zeros((n, n))
    for p, (sg, om) in enumerate(pairs):
        i = 2 * p
        A[i, i] = A[i + 1, i + 1] = sg
        A[i, i + 1] = om
        A[i + 1, i] = -om
    A[2 * n_pairs:, 2 * n_pairs:] = np.diag(reals)
    return A


def unit_b(n_pairs, n_real):
    """Input vector of a modal form with unit input gains: ``(1, 0)`` per pair, 1 per real."""
    b = np.zeros(2 * n_pairs + n_real)
    b[0:2 * n_pairs:2] = 1.0
    b[2 * n_pairs:] = 1.0
    return b


def modal_steps(pairs, reals, X, src, dst, steps, ut, uoff, nc):
    """Twin of ``lti_steps_modal``: ``steps`` samples, slot ``src + j nc`` -> ``dst + j nc``."""
    n_pairs = pairs.shape[0]
    for j in range(steps):
        for ch in range(nc):
            k0, k1 = src + j * nc + ch, dst + j * nc + ch
            u = ut[uoff + j * nc + ch]
            x = X[:, k0].copy()
            new = np.empty_like(x)
            for p, (sg, om) in enumerate(pairs):
                x1, x2 = x[2 * p], x[2 * p + 1]
                new[2 * p] = sg * x1 + om * x2 + u
                new[2 * p + 1] = sg * x2 - om * x1
            for r, lam in enumerate(reals):
                new[2 * n_pairs + r] = lam * x[2 * n_pairs + r] + u
            new[np.abs(new) < TINY] = 0.0
            X[:, k1] = new


def outputs(c, d, X, ut, uoff, L):
    """Twin of ``lti_outputs`` (whatever the plan): ``c @ X[:, :L] + d u``, shape (n_out, L)."""
    return c @ X[:, :L] + np.outer(d, ut[uoff:uoff + L])


def rows(ys, n_truth, n_seg, truth, sensed, start, m, nc):
    """Twin of ``rows_out``: the chunk ``ys[:, :m nc]`` (sample-major) into the house layouts."""
    for r in range(n_truth + n_seg):
        block = ys[r, :m * nc].reshape(m, nc).T          # (nc, m)
        if r < n_truth:
            truth[:, r, start:start + m] = block
        else:
            sensed[r - n_truth::n_seg, start:start + m] = block


def lti_process(A, b, c, d, x, u):
    """Twin of ``lti_group_process``: x (n_states, n_channels) updated in place.

    Returns
    -------
    y : ndarray, shape (n_channels, n_outputs, n)
    status : int
    """
    nc, n = u.shape
    y = np.empty((nc, c.shape[0], n))
    for t in range(n):
        y[:, :, t] = (c @ x + np.outer(d, u[:, t])).T
        x[:] = A @ x + np.outer(b, u[:, t])
        x[np.abs(x) < TINY] = 0.0
    status = 2 if not np.all(np.isfinite(x)) else 0
    return y, status


def noise(table1, table2, ipos, n_streams, n):
    """Unscaled noise of stream ``j`` at sample ``t``: ``table1[p1 + tS + j] + table2[...]``.

    ``table1/2`` unpadded; returns shape (n_streams, n).
    """
    t = np.arange(n)[None, :] * n_streams + np.arange(n_streams)[:, None]
    i1 = (ipos[0] + t) % table1.size
    i2 = (ipos[1] + t) % table2.size
    return table1[i1].astype(np.float64) + table2[i2].astype(np.float64)


def adc(current, noise_v, gain, lsb_v, lo, hi):
    """ADC reading in A of currents (A) with added noise (V); returns (reading, saturated)."""
    code = np.floor((gain * current + noise_v) / lsb_v + 0.5)
    sat = bool(np.any((code > hi) | (code < lo)))
    return np.clip(code, lo, hi) * lsb_v / gain, sat


def sim_group(A, b, c, d, x, drive, n_truth, n_seg, gain, lsb_v, lo, hi, scale, table1, table2,
              ipos):
    """Twin of ``sim_group_process`` (tables unpadded); returns (sensed, truth, status)."""
    nc, n = drive.shape
    y, status = lti_process(A, b, c, d, x, drive)
    truth = y[:, :n_truth].copy()
    nz = scale * noise(table1, table2, ipos, n_seg * nc, n)       # stream j = seg * nc + ch
    sensed = np.empty((nc * n_seg, n))
    sat = False
    for ch in range(nc):
        for s in range(n_seg):
            r, st = adc(y[ch, n_truth + s], nz[s * nc + ch], gain, lsb_v, lo, hi)
            sensed[ch * n_seg + s] = r
            sat |= st
    return sensed, truth, status | (1 if sat else 0)
