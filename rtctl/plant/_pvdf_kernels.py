"""Real-time kernel of the PVDF-cells-on-a-plate group (see :mod:`rtctl.plant.pvdf`).

One call advances all cells of one plate. The plate's modes are shared by every cell, so the
group is one MIMO system; per sample and per modal block ``b`` (2 states for a complex pair,
1 for a real mode, padded to 2 with a dummy state and zero coefficients)::

    p      = Q u                                  dense projections of the 48 drives
    z_b   <- L_b z_b + Gg_b g_b + Gp_b p_b        exact ZOH of amplifier -> mode, per block
    g     <- alpha g + (1 - alpha) p              amplifier lag on each projection
    (v, y, y') <- R (v, y, y') + r u               per cell: amplifier, residual mode
    y      = C [z; g] + Rd [y; y']                 modes + residual of the truncated ones

The projections are formed and the outputs evaluated for a whole chunk at a time; only the
small recursions run sample by sample. Both products are one matrix each over the chunk's
*sources* ``X`` (rows: ``e = [z; g]`` before each sample, then per cell ``v``, ``y'``, ``u - v``,
``v - y`` and ``u``), run as tiles of up to 3 rows by 8 sources with time innermost
(:func:`rtctl.plant._kernels.lti_outputs`): each source value loaded serves 3 rows, where a
row-by-row ``out += w * x`` loads and stores its row once per multiply-add. The dense
``Rd [y; y']`` (48 x 48, the same matrix on ``y`` and on ``y'``) is one product over ``[y | y']``,
twice the samples: half the tiles, each of twice the length (a tile's fixed cost is most of its
time at 32 samples). The differences
``u - v`` and ``v - y`` are sources of their own so that the cell current's ``C_f w_a (u - v)``
and the residual acceleration ``w_r^2 (v - y)`` are not formed from two large products that
cancel. A cell at rest (its state exactly 0) and undriven over a chunk is not stepped, and every
tile that reads nothing but such cells is left out: exact zeros, bitwise the same outputs (a
plate with 2 of its 48 cells driven spent nearly half its time on the other 46).
"""

from __future__ import annotations

import math

from rtctl._numba import TINY, kernel
from rtctl.plant._kernels import lti_outputs_live

STATUS_OK = 0
STATUS_NONFINITE = 2


@kernel
def _recurse(zi, pi, L, Gg, Gp, alpha, Z, G, P, E, nb):
    """Block recursion over ``nb`` samples; ``E[:n_z + n_p, t]`` gets the states ``[z; g]``
    *before* sample t (``n_z``, ``n_p``: the lengths of ``Z`` and ``G`` less their dummies)."""
    n_z = Z.shape[0] - 1
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
def pvdf_group_process(sizes, zi, pi, L, Gg, Gp, consts, Z, G, V, qplan, qcoef, oplan, ocoef,
                       rplan, rcoef, qcell, ocell, rcell, quiet, zeros, P, X, ys, Y2, ys2, probe,
                       drive, sensed, truth):
    """Advance one plate with all its PVDF cells by one block (``PvdfGroup``'s kernel).

    Parameters
    ----------
    sizes : ndarray of int64, shape (6,)
        ``(max_block, finger_channel (-1: none), n_sensed (0 or 1), n_probe, residual (0/1: the
        truncated modes' terms are in the tiles or not; not read here), n_e)``.
    zi, pi : ndarray of int64, shape (n_blocks, 2)
        State and projection indices of each modal block (dummy ``n_z`` / ``n_p`` pads).
    L, Gg, Gp : ndarray, shape (n_blocks, 2, 2)
        Discrete block coefficients (state, amplifier-state and held-input parts).
    consts : ndarray, shape (17,)
        ``(alpha, preload_n, cf_wa, w_r^2, 2 zeta_r w_r, R[3, 3] row-major, r[3])``: amplifier
        pole per sample, static finger force, film capacitance times the amplifier corner
        (A per V of ``u - v``), the residual mode's coefficients, and the exact ZOH recursion
        of each cell's ``(v, y, y')`` (amplifier, then residual mode): ``x <- R x + r u``.
    Z, G, V : ndarray, shapes (n_z + 1,), (n_p + 1,), (n_channels, 3)
        States: modal, amplified projections (last entries of Z, G: dummies), and per cell
        ``(v, y, y')``: voltage and residual mode.
    qplan, qcoef, oplan, ocoef, rplan, rcoef : ndarray
        Tiles (:func:`rtctl.plant._kernels.output_plan`) of the input projections ``P = Q u``,
        of every output row over the sources ``X`` (``ys``: cell displacement, velocity and
        current, force on the finger, probes; ``PvdfGroup.Q`` and ``PvdfGroup.W``), and of the
        truncated modes' static displacement ``Rd`` over ``Y2 = [y | y']`` (``ys2``: the
        displacement terms in its first ``nb`` columns, the velocity terms in the next ``nb``;
        one product over twice the samples, added to ``ys``'s rows when they are copied out).
    qcell, ocell, rcell : ndarray of int64, shape (n_tiles, 8)
        The cell of each source of each tile of the three plans (-1: the modes and amplified
        projections, read always).
    quiet : ndarray of int64, shape (n_channels,)
        1 where the cell's rows of ``X`` and ``Y2`` hold zeros: a cell at rest (state exactly 0)
        and undriven over a chunk is not stepped, and the tiles that read nothing but such cells
        are left out (:func:`~rtctl.plant._kernels.lti_outputs_live`), bitwise the same outputs.
        A plate of 48 cells with two driven spends most of its product on the other 46.
    zeros : ndarray
        At least ``max(3 n_channels + 1 + n_probe, n_p + 1, 2 max_block)`` zeros (the tiles'
        feedthrough and its input).
    P, X, ys, Y2, ys2 : ndarray
        Scratch, shapes ``(n_p + 1, >= max_block)``, ``(n_e + 5 n_channels, >= max_block)``,
        ``(3 n_channels + 1 + n_probe, >= max_block)``, ``(n_channels, >= 2 max_block)``,
        ``(n_channels + 1, >= 2 max_block)``.
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
    n_e = sizes[5]
    nc, n = drive.shape
    alpha = consts[0]
    preload = consts[1]
    r00, r01, r02 = consts[5], consts[6], consts[7]
    r10, r11, r12 = consts[8], consts[9], consts[10]
    r20, r21, r22 = consts[11], consts[12], consts[13]
    b0, b1, b2 = consts[14], consts[15], consts[16]
    x_v = n_e
    x_yd = n_e + nc
    x_uv = n_e + 2 * nc
    x_vy = n_e + 3 * nc
    x_u = n_e + 4 * nc
    for start in range(0, n, blk):
        nb = min(blk, n - start)
        for j in range(nc):
            rest = V[j, 0] == 0.0 and V[j, 1] == 0.0 and V[j, 2] == 0.0
            for t in range(nb):
                if drive[j, start + t] != 0.0:  # (NaN too)
                    rest = False
                    break
            if rest:
                if quiet[j] == 0:  # its rows still hold its last samples
                    for r in range(5):
                        for t in range(blk):
                            X[n_e + r * nc + j, t] = 0.0
                    for t in range(2 * blk):
                        Y2[j, t] = 0.0
                    quiet[j] = 1
            else:
                quiet[j] = 0
                _copy(drive, j, start, X, x_u + j, 0, nb)
        lti_outputs_live(qplan, qcoef, zeros, X, zeros, 0, P, nb, qcell, quiet)
        _recurse(zi, pi, L, Gg, Gp, alpha, Z, G, P, X, nb)
        for j in range(nc):
            if quiet[j] != 0:
                continue  # at rest, undriven: stays exactly 0 (R 0 + r 0)
            v = V[j, 0]
            y = V[j, 1]
            w = V[j, 2]
            for t in range(nb):
                ut = X[x_u + j, t]
                X[x_v + j, t] = v
                X[x_yd + j, t] = w
                Y2[j, t] = y
                Y2[j, nb + t] = w
                X[x_uv + j, t] = ut - v
                X[x_vy + j, t] = v - y
                nv = r00 * v + r01 * y + r02 * w + b0 * ut
                ny = r10 * v + r11 * y + r12 * w + b1 * ut
                nw = r20 * v + r21 * y + r22 * w + b2 * ut
                v = nv
                y = ny
                w = nw
            V[j, 0] = v if abs(v) >= TINY else 0.0
            V[j, 1] = y if abs(y) >= TINY else 0.0
            V[j, 2] = w if abs(w) >= TINY else 0.0
        lti_outputs_live(oplan, ocoef, zeros, X, zeros, 0, ys, nb, ocell, quiet)
        lti_outputs_live(rplan, rcoef, zeros, Y2, zeros, 0, ys2, 2 * nb, rcell, quiet)
        for j in range(nc):
            for t in range(nb):
                truth[j, 0, start + t] = ys[j, t] + ys2[j, t]
            for t in range(nb):
                truth[j, 1, start + t] = ys[nc + j, t] + ys2[j, nb + t]
            if j == fch:
                for t in range(nb):
                    truth[j, 2, start + t] = ys[3 * nc, t] + preload
            else:
                for t in range(nb):
                    truth[j, 2, start + t] = 0.0
            for t in range(nb):
                truth[j, 3, start + t] = X[x_v + j, t]
            if n_sensed == 1:
                _copy(ys, 2 * nc + j, 0, sensed, j, start, nb)
        for i in range(n_probe):
            _copy(ys, 3 * nc + 1 + i, 0, probe, i, 0, nb)
        for t in range(nb):  # the probe's displacement and velocity: rows 0 and 1
            probe[0, t] += ys2[nc, t]
            probe[1, t] += ys2[nc, nb + t]
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


@kernel
def _copy(src, row, s0, dst, drow, d0, nb):
    """``dst[drow, d0:d0 + nb] = src[row, s0:s0 + nb]``."""
    for t in range(nb):
        dst[drow, d0 + t] = src[row, s0 + t]
