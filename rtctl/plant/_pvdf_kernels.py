"""Real-time kernel of the PVDF-cells-on-a-plate group (see :mod:`rtctl.plant.pvdf`).

One call advances all cells of one plate. The plate's modes are shared by every cell, so the
group is one MIMO system; per sample and per modal block ``b`` (2 states for a complex pair,
1 for a real mode, padded to 2 with a dummy state and zero coefficients)::

    p      = Q u                                  dense projections of the 48 drives
    z_b   <- L_b z_b + Gg_b g_b + Gp_b p_b        exact ZOH of amplifier -> mode, per block
    g     <- alpha g + (1 - alpha) p              amplifier lag on each projection
    (v, y, y') <- R (v, y, y') + r u               per cell: amplifier, residual mode
    y      = C [z; g] + Rd [y; y']                 modes + residual of the truncated ones

The projections are formed and the outputs evaluated for a whole chunk at a time (loops over
time innermost: contiguous, vectorized); only the small block recursion runs sample by sample.
Inner loops index their arrays rather than slicing them: every slice is a view whose reference
count numba raises and drops atomically, and one per (row, column) pair cost more than the
products (the residual pair: 118 -> 76 us per 48-cell block, bitwise the same samples).
"""

from __future__ import annotations

import math

from rtctl._numba import TINY, kernel

STATUS_OK = 0
STATUS_NONFINITE = 2

# Column ranges of C (``ranges`` rows): which states each output group reads. Outside a
# range the coefficients are exact zeros, so the loops skip them.
R_DISP, R_VEL, R_CUR, R_FORCE, R_PROBE = 0, 1, 2, 3, 4


@kernel
def _project(Q, drive, start, nb, P):
    """``P[i, :nb] = sum_j Q[i, j] drive[j, start:start + nb]`` (time innermost)."""
    n_p, n_ch = Q.shape
    for i in range(n_p):
        for t in range(nb):
            P[i, t] = 0.0
        for j in range(n_ch):
            q = Q[i, j]
            if q != 0.0:
                for t in range(nb):
                    P[i, t] += q * drive[j, start + t]


@kernel
def _recurse(zi, pi, L, Gg, Gp, alpha, Z, G, P, E, nb):
    """Block recursion over ``nb`` samples; ``E[:, t]`` gets the states *before* sample t."""
    n_z = E.shape[0] - (G.shape[0] - 1)
    n_p = G.shape[0] - 1
    n_blocks = zi.shape[0]
    beta = 1.0 - alpha
    for t in range(nb):
        for c in range(n_z):
            E[c, t] = Z[c]
        for i in range(n_p):
            E[n_z + i, t] = G[i]
        for b in range(n_blocks):
            i0 = zi[b, 0]
            i1 = zi[b, 1]
            p0 = pi[b, 0]
            p1 = pi[b, 1]
            z0 = Z[i0]
            z1 = Z[i1]
            g0 = G[p0]
            g1 = G[p1]
            q0 = P[p0, t]
            q1 = P[p1, t]
            n0 = (L[b, 0, 0] * z0 + L[b, 0, 1] * z1 + Gg[b, 0, 0] * g0 + Gg[b, 0, 1] * g1
                  + Gp[b, 0, 0] * q0 + Gp[b, 0, 1] * q1)
            n1 = (L[b, 1, 0] * z0 + L[b, 1, 1] * z1 + Gg[b, 1, 0] * g0 + Gg[b, 1, 1] * g1
                  + Gp[b, 1, 0] * q0 + Gp[b, 1, 1] * q1)
            # Subnormals after a silence would slow every later sample ~100x (docs/physics.md, Sec. 5.6).
            if abs(n0) < TINY:
                n0 = 0.0
            if abs(n1) < TINY:
                n1 = 0.0
            Z[i0] = n0
            Z[i1] = n1
        for i in range(n_p):
            g = alpha * G[i] + beta * P[i, t]
            if abs(g) < TINY:
                g = 0.0
            G[i] = g
    # Padded blocks wrote zeros into the dummy slots; keep them exactly zero whatever happens.
    Z[n_z] = 0.0
    G[n_p] = 0.0


@kernel
def _rows(C, r0, c0, c1, E, nb, out):
    """``out[:nb] = C[r0, c0:c1] @ E[c0:c1, :nb]`` (a row of outputs over a chunk)."""
    for t in range(nb):
        out[t] = 0.0
    for c in range(c0, c1):
        w = C[r0, c]
        if w != 0.0:
            for t in range(nb):
                out[t] += w * E[c, t]


@kernel
def _rows_add(R, r0, X, nb, out):
    """``out[:nb] += R[r0] @ X[:, :nb]`` (residual terms; time innermost)."""
    for c in range(R.shape[1]):
        w = R[r0, c]
        if w != 0.0:
            for t in range(nb):
                out[t] += w * X[c, t]


@kernel
def _rows_add_pair(R, r0, X1, X2, nb, out1, out2):
    """``out1[:nb] += R[r0] @ X1[:, :nb]`` and ``out2[:nb] += R[r0] @ X2[:, :nb]`` (the residual
    displacement and velocity share their weights; sums in the order of :func:`_rows_add`).

    The sources are indexed, not sliced: a slice is an array view whose reference count is
    raised and dropped (atomically) each time, and 48 x 48 views per block cost more than the
    arithmetic they serve.
    """
    for c in range(R.shape[1]):
        w = R[r0, c]
        if w != 0.0:
            for t in range(nb):
                out1[t] += w * X1[c, t]
                out2[t] += w * X2[c, t]


@kernel
def pvdf_group_process(sizes, zi, pi, L, Gg, Gp, Q, C, ranges, consts, Rd, Rq, Z, G, V, P, E,
                       VV, YY, YD, probe, drive, sensed, truth):
    """Advance one plate with all its PVDF cells by one block (``PvdfGroup``'s kernel).

    Parameters
    ----------
    sizes : ndarray of int64, shape (5,)
        ``(max_block, finger_channel (-1: none), n_sensed (0 or 1), n_probe, residual (0/1))``.
    zi, pi : ndarray of int64, shape (n_blocks, 2)
        State and projection indices of each modal block (dummy ``n_z`` / ``n_p`` pads).
    L, Gg, Gp : ndarray, shape (n_blocks, 2, 2)
        Discrete block coefficients (state, amplifier-state and held-input parts).
    Q : ndarray, shape (n_p, n_channels)
        Input projections, per volt.
    C : ndarray, shape (3 n_channels + 1 + n_probe, n_z + n_p)
        Output rows: cell displacement (m), cell velocity (m/s), cell current from the plate's
        motion (A), tissue force at the finger (N), probes (displacement, velocity,
        acceleration).
    ranges : ndarray of int64, shape (5, 2)
        Column range read by each row group (``R_DISP .. R_PROBE``).
    consts : ndarray, shape (17,)
        ``(alpha, preload_n, cf_wa, w_r^2, 2 zeta_r w_r, R[3, 3] row-major, r[3])``: amplifier
        pole per sample, static finger force, film capacitance times the amplifier corner
        (A per V of ``u - v``), the residual mode's coefficients, and the exact ZOH recursion
        of each cell's ``(v, y, y')`` (amplifier, then residual mode): ``x <- R x + r u``.
    Rd : ndarray, shape (n_channels + 1, n_channels)
        Static displacement of the truncated modes at the cell centres and at the probe per
        cell volt (m/V), applied to the residual-mode outputs ``y, y', y''``.
    Rq : ndarray, shape (n_channels, n_channels)
        Truncated modes' share of the cell capacitances (F); currents get ``Rq y'``.
    Z, G, V : ndarray, shapes (n_z + 1,), (n_p + 1,), (n_channels, 3)
        States: modal, amplified projections (last entries of Z, G: dummies), and per cell
        ``(v, y, y')``: voltage and residual mode.
    P, E, VV, YY, YD : ndarray
        Scratch, shapes (n_p + 1, max_block) (last row must stay zero), (n_z + n_p,
        max_block), (n_channels, max_block) three times (trajectories of v, y, y').
    probe : ndarray, shape (n_probe, max_block)
        Written: the probe signals of the last chunk (``probe[:, :nb]``).
    drive : ndarray, shape (n_channels, n)
        Commanded cell voltages, V (amplifier input referred to its output).
    sensed : ndarray, shape (n_channels * n_sensed, n)
        Written when ``n_sensed == 1``: cell currents, A.
    truth : ndarray, shape (n_channels, 4, n)
        Written: displacement (m), velocity (m/s), force on the finger (N), cell voltage (V).

    Returns
    -------
    int
        ``STATUS_NONFINITE`` (2) if a state is NaN/Inf (stays so until reset), else 0.
    """
    blk = sizes[0]
    fch = sizes[1]
    n_sensed = sizes[2]
    n_probe = sizes[3]
    residual = sizes[4]
    nc, n = drive.shape
    alpha = consts[0]
    preload = consts[1]
    cf_wa = consts[2]
    wr2 = consts[3]
    cr = consts[4]
    r00, r01, r02 = consts[5], consts[6], consts[7]
    r10, r11, r12 = consts[8], consts[9], consts[10]
    r20, r21, r22 = consts[11], consts[12], consts[13]
    b0, b1, b2 = consts[14], consts[15], consts[16]
    for start in range(0, n, blk):
        nb = min(blk, n - start)
        _project(Q, drive, start, nb, P)
        _recurse(zi, pi, L, Gg, Gp, alpha, Z, G, P, E, nb)
        for j in range(nc):
            u = drive[j, start:start + nb]
            vv = VV[j, :nb]
            yy = YY[j, :nb]
            yd = YD[j, :nb]
            v = V[j, 0]
            y = V[j, 1]
            w = V[j, 2]
            for t in range(nb):
                vv[t] = v
                yy[t] = y
                yd[t] = w
                ut = u[t]
                nv = r00 * v + r01 * y + r02 * w + b0 * ut
                ny = r10 * v + r11 * y + r12 * w + b1 * ut
                nw = r20 * v + r21 * y + r22 * w + b2 * ut
                v = nv
                y = ny
                w = nw
            V[j, 0] = v if abs(v) >= TINY else 0.0
            V[j, 1] = y if abs(y) >= TINY else 0.0
            V[j, 2] = w if abs(w) >= TINY else 0.0
        for j in range(nc):
            disp = truth[j, 0, start:start + nb]
            vel = truth[j, 1, start:start + nb]
            _rows(C, j, ranges[R_DISP, 0], ranges[R_DISP, 1], E, nb, disp)
            _rows(C, nc + j, ranges[R_VEL, 0], ranges[R_VEL, 1], E, nb, vel)
            if residual:
                _rows_add_pair(Rd, j, YY, YD, nb, disp, vel)
            force = truth[j, 2, start:start + nb]
            if j == fch:
                _rows(C, 3 * nc, ranges[R_FORCE, 0], ranges[R_FORCE, 1], E, nb, force)
                for t in range(nb):
                    force[t] += preload
            else:
                for t in range(nb):
                    force[t] = 0.0
            volt = truth[j, 3, start:start + nb]
            vv = VV[j, :nb]
            for t in range(nb):
                volt[t] = vv[t]
            if n_sensed == 1:
                cur = sensed[j, start:start + nb]
                _rows(C, 2 * nc + j, ranges[R_CUR, 0], ranges[R_CUR, 1], E, nb, cur)
                u = drive[j, start:start + nb]
                for t in range(nb):
                    cur[t] += cf_wa * (u[t] - vv[t])
                if residual:
                    _rows_add(Rq, j, YD, nb, cur)
        for i in range(n_probe):
            _rows(C, 3 * nc + 1 + i, ranges[R_PROBE, 0], ranges[R_PROBE, 1], E, nb,
                  probe[i, :nb])
        if residual:
            _rows_add_pair(Rd, nc, YY, YD, nb, probe[0, :nb], probe[1, :nb])
            acc = probe[2, :nb]
            for c in range(nc):
                w = Rd[nc, c]
                vv = VV[c, :nb]
                yy = YY[c, :nb]
                yd = YD[c, :nb]
                for t in range(nb):
                    acc[t] += w * (wr2 * (vv[t] - yy[t]) - cr * yd[t])
    bad = False
    for c in range(Z.shape[0]):
        if not math.isfinite(Z[c]):
            bad = True
    for c in range(G.shape[0]):
        if not math.isfinite(G[c]):
            bad = True
    for j in range(nc):
        for c in range(3):
            if not math.isfinite(V[j, c]):
                bad = True
    return STATUS_NONFINITE if bad else STATUS_OK
