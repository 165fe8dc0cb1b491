"""Plain numpy loop twin of ``rtctl.plant._pvdf_kernels.pvdf_group_process``.

Same arguments, written the obvious way: one sample at a time, matrix products with ``@``,
no column ranges, no chunking. Works on copies of the states and returns them.
"""

import numpy as np

from rtctl._numba import TINY


def pvdf_group(group, drive, n_sensed):
    """Run the PVDF group's recursion over ``drive`` (n_channels, n), from the group's model
    matrices (``Q``, ``C``, ``Rd``, ``Rq``) and its discrete blocks, states and constants.

    Returns
    -------
    truth : ndarray, shape (n_channels, 4, n)
    sensed : ndarray, shape (n_channels * n_sensed, n)
    probe : ndarray, shape (3, n)
    states : tuple of ndarray
        Final ``Z, G, V``.
    """
    sizes, zi, pi, L, Gg, Gp, consts, Z, G, V = group.args[:10]
    Q, C, Rd, Rq = group.Q, group.C, group.Rd, group.Rq
    Z, G, V = Z.copy(), G.copy(), V.copy()
    nc, n = drive.shape
    fch = int(sizes[1])
    residual = bool(sizes[4])
    alpha, preload, cf_wa, wr2, cr = consts[:5]
    R = consts[5:14].reshape(3, 3)
    r = consts[14:17]
    n_z, n_p = Z.size - 1, G.size - 1
    truth = np.zeros((nc, 4, n))
    sensed = np.zeros((nc * n_sensed, n))
    probe = np.zeros((3, n))
    for t in range(n):
        u = drive[:, t]
        p = np.append(Q @ u, 0.0)
        e = np.concatenate([Z[:n_z], G[:n_p]])
        y = C @ e
        v, yr, yd = V[:, 0].copy(), V[:, 1].copy(), V[:, 2].copy()
        disp, vel = y[:nc], y[nc:2 * nc]
        cur = y[2 * nc:3 * nc] + cf_wa * (u - v)
        pr = y[3 * nc + 1:3 * nc + 4].copy()
        if residual:
            disp = disp + Rd[:nc] @ yr
            vel = vel + Rd[:nc] @ yd
            cur = cur + Rq @ yd
            pr[0] += Rd[nc] @ yr
            pr[1] += Rd[nc] @ yd
            pr[2] += Rd[nc] @ (wr2 * (v - yr) - cr * yd)
        truth[:, 0, t] = disp
        truth[:, 1, t] = vel
        if fch >= 0:
            truth[fch, 2, t] = preload + y[3 * nc]
        truth[:, 3, t] = v
        if n_sensed:
            sensed[:, t] = cur
        probe[:, t] = pr
        newZ = Z.copy()
        for b in range(zi.shape[0]):
            zz = Z[zi[b]]
            new = L[b] @ zz + Gg[b] @ G[pi[b]] + Gp[b] @ p[pi[b]]
            new[np.abs(new) < TINY] = 0.0
            newZ[zi[b]] = new
        newZ[n_z] = 0.0
        G[:n_p] = alpha * G[:n_p] + (1.0 - alpha) * p[:n_p]
        G[np.abs(G) < TINY] = 0.0
        Z = newZ
        V = V @ R.T + np.outer(u, r)
    V[np.abs(V) < TINY] = 0.0
    return truth, sensed, probe, (Z, G, V)
