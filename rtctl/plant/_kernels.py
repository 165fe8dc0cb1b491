"""Numba kernels that advance many identical LTI channels at once.

Layout (measured, see ``bench/plant.py``): the channel is the innermost index so that every loop
runs over channels with shared coefficients and vectorizes.

* ``X`` ``(n_states, (chunk + 1) * n_channels)``: the state *trajectory* of one chunk; sample
  ``t`` of channel ``ch`` is column ``t * n_channels + ch``. Columns ``[0, n_channels)`` hold
  the persistent state between calls. The recursion writes slot ``t + 1`` from slot ``t``.
* ``ut`` ``(chunk * n_channels,)``: the inputs of one chunk, transposed from the house block
  layout ``(n_channels, n)``.
* ``yt`` ``(n_outputs, chunk * n_channels)``: outputs of one chunk.

Outputs are computed after the recursion, for the whole chunk at once: ``yt = C X + D u`` is then
a product over ``chunk * n_channels`` columns, long loops that LLVM vectorizes well, blocked as 3
outputs x 4 states so each state value loaded is used three times. Per-sample loops over only
48 channels were 2-5x slower (loop set-up and epilogues dominate). Chunks of 8 samples keep the
trajectory in L1/L2.

Kernels take only preallocated arrays: no allocation, no exceptions, no Python objects. States are
flushed to zero below ``TINY`` in the recursion: decaying modes after silence otherwise reach
subnormal floats, which run ~100x slower. Non-finite values are detected with ``math.isfinite``
(the house fastmath set keeps NaN/Inf semantics).
"""

import math

import numpy as np

from rtctl._numba import TINY, kernel

STATUS_OK = 0
STATUS_SATURATED = 1
STATUS_NONFINITE = 2
FORM_MODAL = 0
FORM_DENSE = 1


@kernel
def lti_step_modal(pairs, reals, b, X, ut, off, nc, m):
    """``m`` samples of the real block-diagonal recursion, slot t -> t + 1, with subnormal flush.

    ``pairs[p] = (sigma, omega)``: ``[x1, x2] <- [[sigma, omega], [-omega, sigma]] [x1, x2]
    + b u``; then ``reals[r]`` on the diagonal after the ``2 n_pairs`` pair states. Inputs are
    ``ut[off + t * nc + ch]``. The blocks are decoupled, so each block runs over the whole chunk
    before the next: its rows are taken as 1-D views once (LLVM vectorizes those loops
    reliably; a view per sample costs reference counting).
    """
    n_pairs = pairs.shape[0]
    base = 2 * n_pairs
    L = m * nc
    uu = ut[off:off + L]
    for p in range(n_pairs):
        sg = pairs[p, 0]
        om = pairs[p, 1]
        i = 2 * p
        b1 = b[i]
        b2 = b[i + 1]
        xa = X[i]
        xb = X[i + 1]
        for t in range(m):
            k0 = t * nc
            k1 = k0 + nc
            for ch in range(nc):
                u = uu[k0 + ch]
                x1 = xa[k0 + ch]
                x2 = xb[k0 + ch]
                n1 = sg * x1 + om * x2 + b1 * u
                n2 = sg * x2 - om * x1 + b2 * u
                if abs(n1) < TINY:
                    n1 = 0.0
                if abs(n2) < TINY:
                    n2 = 0.0
                xa[k1 + ch] = n1
                xb[k1 + ch] = n2
    for r in range(reals.shape[0]):
        lam = reals[r]
        br = b[base + r]
        xr = X[base + r]
        for t in range(m):
            k0 = t * nc
            k1 = k0 + nc
            for ch in range(nc):
                v = lam * xr[k0 + ch] + br * uu[k0 + ch]
                if abs(v) < TINY:
                    v = 0.0
                xr[k1 + ch] = v


@kernel
def lti_step_dense(a, b, X, ut, off, nc, m):
    """``m`` samples of ``x <- a x + b u`` (dense fallback), slot t -> t + 1, subnormal flush."""
    n_states = a.shape[0]
    for t in range(m):
        k0 = t * nc
        k1 = k0 + nc
        ku = off + k0
        for i in range(n_states):
            bi = b[i]
            for ch in range(nc):
                X[i, k1 + ch] = bi * ut[ku + ch]
            for j in range(n_states):
                aij = a[i, j]
                for ch in range(nc):
                    X[i, k1 + ch] += aij * X[j, k0 + ch]
            for ch in range(nc):
                if abs(X[i, k1 + ch]) < TINY:
                    X[i, k1 + ch] = 0.0


@kernel
def lti_outputs(c, d, X, ut, yt, off, L):
    """``yt[:, off:off+L] = c @ X[:, :L] + d ut[off:off+L]``, blocked 3 outputs x 4 states.

    Row views are taken once per loop (not per element) so that each inner loop sees a few
    distinct 1-D streams: LLVM then vectorizes it behind cheap runtime alias checks, which it
    does not do for the equivalent 2-D indexing with an offset.
    """
    n_out, ns = c.shape
    uu = ut[off:off + L]
    o = 0
    while o + 3 <= n_out:
        y0 = yt[o, off:off + L]
        y1 = yt[o + 1, off:off + L]
        y2 = yt[o + 2, off:off + L]
        d0 = d[o]
        d1 = d[o + 1]
        d2 = d[o + 2]
        for i in range(L):
            u = uu[i]
            y0[i] = d0 * u
            y1[i] = d1 * u
            y2[i] = d2 * u
        s = 0
        while s + 4 <= ns:
            x0 = X[s, :L]
            x1 = X[s + 1, :L]
            x2 = X[s + 2, :L]
            x3 = X[s + 3, :L]
            a0, a1, a2, a3 = c[o, s], c[o, s + 1], c[o, s + 2], c[o, s + 3]
            b0, b1, b2, b3 = c[o + 1, s], c[o + 1, s + 1], c[o + 1, s + 2], c[o + 1, s + 3]
            e0, e1, e2, e3 = c[o + 2, s], c[o + 2, s + 1], c[o + 2, s + 2], c[o + 2, s + 3]
            for i in range(L):
                v0 = x0[i]
                v1 = x1[i]
                v2 = x2[i]
                v3 = x3[i]
                y0[i] += a0 * v0 + a1 * v1 + a2 * v2 + a3 * v3
                y1[i] += b0 * v0 + b1 * v1 + b2 * v2 + b3 * v3
                y2[i] += e0 * v0 + e1 * v1 + e2 * v2 + e3 * v3
            s += 4
        while s < ns:
            xs = X[s, :L]
            a0 = c[o, s]
            b0 = c[o + 1, s]
            e0 = c[o + 2, s]
            for i in range(L):
                v = xs[i]
                y0[i] += a0 * v
                y1[i] += b0 * v
                y2[i] += e0 * v
            s += 1
        o += 3
    while o < n_out:
        yo = yt[o, off:off + L]
        do = d[o]
        for i in range(L):
            yo[i] = do * uu[i]
        for s in range(ns):
            cs = c[o, s]
            xs = X[s, :L]
            for i in range(L):
                yo[i] += cs * xs[i]
        o += 1


@kernel
def lti_chunk(form, a, reals, b, c, d, X, ut, ys, off, nc, m):
    """Advance all channels over ``m <= chunk`` samples of ``ut[off:]``; outputs into
    ``ys[:, off:off + m * nc]``.

    ``form`` is ``FORM_MODAL`` (``a`` holds ``pairs``, shape (n_pairs, 2)) or ``FORM_DENSE``
    (``a`` is the full state matrix, shape (n_states, n_states)). The chunk length is
    ``X.shape[1] // nc - 1``: the trajectory and the chunk's outputs stay in L1/L2.
    """
    if form == 0:
        lti_step_modal(a, reals, b, X, ut, off, nc, m)
    else:
        lti_step_dense(a, b, X, ut, off, nc, m)
    k = m * nc
    lti_outputs(c, d, X, ut, ys, off, k)
    for s in range(X.shape[0]):
        xs = X[s]
        for ch in range(nc):
            xs[ch] = xs[k + ch]


@kernel
def state_nonfinite(X, nc):
    """True if any persistent state (columns ``[0, nc)``) is NaN or infinite."""
    bad = False
    for s in range(X.shape[0]):
        for ch in range(nc):
            if not math.isfinite(X[s, ch]):
                bad = True
    return bad


@kernel
def transpose_in(u, ut, start, nb):
    """``ut[t * nc + ch] = u[ch, start + t]`` for ``t < nb``."""
    nc = u.shape[0]
    for ch in range(nc):
        for t in range(nb):
            ut[t * nc + ch] = u[ch, start + t]


@kernel
def lti_group_process(form, a, reals, b, c, d, X, ut, ys, u, y):
    """Streaming LTI channel group without a front end (the generic kernel).

    Parameters
    ----------
    u : ndarray, shape (n_channels, n)
        Inputs, one per channel.
    y : ndarray, shape (n_channels, n_outputs, n)
        Outputs, written in place.

    Returns
    -------
    int
        ``STATUS_NONFINITE`` if a state became NaN/Inf, else 0.
    """
    nc, n = u.shape
    blk = ut.shape[0] // nc
    chunk = X.shape[1] // nc - 1
    n_out = c.shape[0]
    status = 0
    for start in range(0, n, blk):
        nb = min(blk, n - start)
        transpose_in(u, ut, start, nb)
        for c0 in range(0, nb, chunk):
            lti_chunk(form, a, reals, b, c, d, X, ut, ys, c0 * nc, nc, min(chunk, nb - c0))
        for ch in range(nc):
            for o in range(n_out):
                for t in range(nb):
                    y[ch, o, start + t] = ys[o, t * nc + ch]
        if state_nonfinite(X, nc):
            status |= 2
    return status


@kernel
def adc_block(ys, row0, n_seg, nc, nb, adc, table1, table2, ipos):
    """Noise, quantization and clipping of all sensed streams over one block, in place.

    ``ys[row0 + s, t * nc + ch]`` holds the anti-aliased current (A) of segment ``s`` of
    channel ``ch`` and is overwritten with the ADC reading (A). ``adc = (gain_v_per_a,
    inv_lsb_v, lsb_a, max_code, min_code, noise_scale_v)``.

    Noise: ``noise_scale * (table1[i1 + j] + table2[i2 + j])`` for stream ``j = s * nc + ch``,
    then both positions advance by ``S = n_seg * nc`` per sample and wrap at the prime table
    lengths ``len(table) - S`` (each table carries a copy of its first ``S`` entries at the end,
    so a sample's ``S`` reads are contiguous). Consecutive samples of all streams thus read one
    contiguous stretch of each table (cache- and prefetch-friendly; independent positions per
    stream cost ~5 ns per reading in cache misses).

    Returns
    -------
    bool
        True if any sample clipped.
    """
    gain = adc[0]
    inv_lsb = adc[1]
    lsb_a = adc[2]
    hi = adc[3]
    lo = adc[4]
    scale = adc[5]
    S = n_seg * nc
    n1 = table1.shape[0] - S
    n2 = table2.shape[0] - S
    n_sat = 0
    for s in range(n_seg):
        y = ys[row0 + s]
        i1 = ipos[0] + s * nc
        i2 = ipos[1] + s * nc
        for t in range(nb):
            # 1-D views per sample: measured 5x faster here than offset indexing.
            w1 = table1[i1:i1 + nc]
            w2 = table2[i2:i2 + nc]
            yy = y[t * nc:(t + 1) * nc]
            for ch in range(nc):
                noise = np.float64(w1[ch]) + np.float64(w2[ch])
                v = gain * yy[ch] + scale * noise
                q = math.floor(v * inv_lsb + 0.5)
                n_sat += (q > hi) | (q < lo)
                yy[ch] = min(max(q, lo), hi) * lsb_a
            i1 += S
            i2 += S
            if i1 >= n1 + s * nc:
                i1 -= n1
            if i2 >= n2 + s * nc:
                i2 -= n2
    i1 = ipos[0] + (nb * S) % n1
    i2 = ipos[1] + (nb * S) % n2
    ipos[0] = i1 - n1 if i1 >= n1 else i1
    ipos[1] = i2 - n2 if i2 >= n2 else i2
    return n_sat > 0


@kernel
def sim_group_process(sizes, a, reals, b, c, d, X, ut, ys, adc, table1, table2, ipos,
                      drive, sensed, truth):
    """Advance a simulated channel group by one block (see ``rtctl.plant.SimGroup``).

    Parameters
    ----------
    sizes : ndarray of int64, shape (3,)
        ``(form, n_truth, n_seg)``.
    a, reals, b, c, d, X, ut, ys : arrays
        Discrete plant (modal or dense) and scratch, as in :func:`lti_chunk`; the output rows
        are the ``n_truth`` truth signals followed by the ``n_seg`` anti-aliased currents.
    adc, table1, table2, ipos : arrays
        ADC constants, the two padded noise tables and the two table positions
        (see :func:`adc_block`).
    drive : ndarray, shape (n_channels, n)
        Commanded voltage in V.
    sensed : ndarray, shape (n_channels * n_seg, n)
        ADC readings in A, row ``ch * n_seg + seg`` (written).
    truth : ndarray, shape (n_channels, n_truth, n)
        True signals (written).

    Returns
    -------
    int
        Bit value 1: an ADC clipped in this block; bit value 2: a state is NaN/Inf (it stays so
        until ``reset``).
    """
    form = sizes[0]
    n_truth = sizes[1]
    n_seg = sizes[2]
    nc, n = drive.shape
    blk = ut.shape[0] // nc
    chunk = X.shape[1] // nc - 1
    status = 0
    for start in range(0, n, blk):
        nb = min(blk, n - start)
        transpose_in(drive, ut, start, nb)
        for c0 in range(0, nb, chunk):
            lti_chunk(form, a, reals, b, c, d, X, ut, ys, c0 * nc, nc, min(chunk, nb - c0))
        if adc_block(ys, n_truth, n_seg, nc, nb, adc, table1, table2, ipos):
            status |= 1
        for ch in range(nc):
            for o in range(n_truth):
                for t in range(nb):
                    truth[ch, o, start + t] = ys[o, t * nc + ch]
            for s in range(n_seg):
                for t in range(nb):
                    sensed[ch * n_seg + s, start + t] = ys[n_truth + s, t * nc + ch]
        if state_nonfinite(X, nc):
            status |= 2
    return status
