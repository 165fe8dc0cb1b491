"""Numba kernels that advance many identical LTI channels at once.

Layout (measured, see ``bench/plant.py``): the channel is the innermost index so that every loop
runs over channels with shared coefficients and vectorizes.

* ``X`` ``(n_states, >= (chunk + 1) * n_channels)``: the state *trajectory* of one chunk;
  sample ``t`` of channel ``ch`` is column ``t * n_channels + ch``. Columns
  ``[0, n_channels)`` (slot 0) hold the persistent state between calls. The recursion writes
  slot ``t + 1`` from slot ``t``.
* ``ut`` ``(>= max_block * n_channels,)``: the inputs of one block, transposed from the house
  block layout ``(n_channels, n)``.
* ``ys`` ``(n_outputs, >= chunk * n_channels)``: outputs of one chunk (same columns as ``X``).

The modal recursion runs two pairs (or two real modes) at a time over all samples of a chunk,
with unit input gains (``ModalForm.unit_input``: no input multiplies). Outputs are computed
after the recursion, for the whole chunk at once: ``ys = C X + D u`` is then a product over
``chunk * n_channels`` columns, long loops that LLVM vectorizes well. It runs as a *plan* of
tiles (:func:`output_plan`): each tile updates up to 3 outputs from up to 8 states, so each
state value loaded serves every output of the tile, and an output reads only the states it
depends on. In a cascade realization (``to_modal(..., blocks=...)``) ``C`` has exact
structural zeros (the tip does not depend on the anti-alias filters, current ``j`` not on
segment ``k``'s filter), which the plan skips: for the bundled bimorph 70 multiply-adds per
channel-sample instead of 96. Loops run over a chunk or a block, not per sample: per-sample
loops over only 48 channels were 2-5x slower (loop set-up and epilogues dominate). The rows of
the house layouts are filled per chunk from ``ys`` (a transpose, bound by memory traffic).

Scratch arrays start on 64-byte boundaries (:func:`aligned_zeros`): with numpy's 16-byte
alignment most vector loads straddle two cache lines (30 % slower recursion, measured).

Kernels take only preallocated arrays: no allocation, no exceptions, no Python objects. Views are
taken inside small kernels with one loop nest, where numba drops their reference counting; the
top-level kernels pass whole arrays and offsets. States are flushed to zero below ``TINY`` in
the recursion: decaying modes after silence otherwise reach subnormal floats, which run ~100x
slower. Non-finite values are detected with ``math.isfinite`` (the house fastmath set keeps
NaN/Inf semantics).
"""

import math

import numpy as np

from rtctl._numba import TINY, kernel

STATUS_OK = 0
STATUS_SATURATED = 1
STATUS_NONFINITE = 2
FORM_MODAL = 0
FORM_DENSE = 1

#: Output tile shapes (rows, states) with a kernel each (see :func:`output_plan`); a plan row is
#: ``(n_rows, row0, row1, row2, width, state0 .. state7)``.
TILE_SHAPES = ((3, 8), (3, 4), (2, 8), (2, 4), (1, 8), (1, 4), (1, 1))
PLAN_COLUMNS = 13


@kernel
def lti_steps_modal(pairs, reals, X, src, dst, steps, ut, uoff, nc):
    """``steps`` samples of the real block-diagonal recursion with unit inputs, subnormal flush.

    Step ``j`` reads the states at columns ``src + j * nc + ch`` and writes ``dst + j * nc +
    ch``; its inputs are ``ut[uoff + j * nc + ch]``. The two column ranges must not overlap
    within a step (in-place steps would run scalar). ``pairs[p] = (sigma, omega)``:
    ``[x1, x2] <- [[sigma, omega], [-omega, sigma]] [x1, x2] + [u, 0]``; then ``reals[r]`` on
    the diagonal after the ``2 n_pairs`` pair states, ``x <- lambda x + u``
    (``ModalForm.unit_input``). The blocks are decoupled, so two pairs (or two reals) at a time
    run over all steps before the next ones: their rows are taken as 1-D views once (LLVM
    vectorizes those loops reliably).
    """
    n_pairs = pairs.shape[0]
    base = 2 * n_pairs
    L = steps * nc
    uu = ut[uoff:uoff + L]
    p = 0
    while p + 2 <= n_pairs:
        sg, om, sh, oh = pairs[p, 0], pairs[p, 1], pairs[p + 1, 0], pairs[p + 1, 1]
        i = 2 * p
        ra, rb = X[i, src:src + L], X[i + 1, src:src + L]
        rc, rd = X[i + 2, src:src + L], X[i + 3, src:src + L]
        wa, wb = X[i, dst:dst + L], X[i + 1, dst:dst + L]
        wc, wd = X[i + 2, dst:dst + L], X[i + 3, dst:dst + L]
        for j in range(steps):
            k0 = j * nc
            for ch in range(nc):
                k = k0 + ch
                u = uu[k]
                x1, x2, x3, x4 = ra[k], rb[k], rc[k], rd[k]
                n1 = sg * x1 + (om * x2 + u)
                n2 = sg * x2 - om * x1
                n3 = sh * x3 + (oh * x4 + u)
                n4 = sh * x4 - oh * x3
                if abs(n1) < TINY:
                    n1 = 0.0
                if abs(n2) < TINY:
                    n2 = 0.0
                if abs(n3) < TINY:
                    n3 = 0.0
                if abs(n4) < TINY:
                    n4 = 0.0
                wa[k] = n1
                wb[k] = n2
                wc[k] = n3
                wd[k] = n4
        p += 2
    if p < n_pairs:
        sg, om = pairs[p, 0], pairs[p, 1]
        i = 2 * p
        ra, rb = X[i, src:src + L], X[i + 1, src:src + L]
        wa, wb = X[i, dst:dst + L], X[i + 1, dst:dst + L]
        for j in range(steps):
            k0 = j * nc
            for ch in range(nc):
                k = k0 + ch
                x1, x2 = ra[k], rb[k]
                n1 = sg * x1 + (om * x2 + uu[k])
                n2 = sg * x2 - om * x1
                if abs(n1) < TINY:
                    n1 = 0.0
                if abs(n2) < TINY:
                    n2 = 0.0
                wa[k] = n1
                wb[k] = n2
    r = 0
    n_real = reals.shape[0]
    while r + 2 <= n_real:
        i = base + r
        l1, l2 = reals[r], reals[r + 1]
        ra, rb = X[i, src:src + L], X[i + 1, src:src + L]
        wa, wb = X[i, dst:dst + L], X[i + 1, dst:dst + L]
        for j in range(steps):
            k0 = j * nc
            for ch in range(nc):
                k = k0 + ch
                u = uu[k]
                v = l1 * ra[k] + u
                w = l2 * rb[k] + u
                if abs(v) < TINY:
                    v = 0.0
                if abs(w) < TINY:
                    w = 0.0
                wa[k] = v
                wb[k] = w
        r += 2
    if r < n_real:
        i = base + r
        lam = reals[r]
        ra = X[i, src:src + L]
        wa = X[i, dst:dst + L]
        for j in range(steps):
            k0 = j * nc
            for ch in range(nc):
                k = k0 + ch
                v = lam * ra[k] + uu[k]
                if abs(v) < TINY:
                    v = 0.0
                wa[k] = v


@kernel
def lti_steps_dense(a, b, X, src, dst, steps, ut, uoff, nc):
    """``steps`` samples of ``x <- a x + b u`` (dense fallback), columns as in
    :func:`lti_steps_modal`, with subnormal flush."""
    n_states = a.shape[0]
    for j in range(steps):
        k0 = src + j * nc
        k1 = dst + j * nc
        uu = ut[uoff + j * nc:uoff + (j + 1) * nc]
        for i in range(n_states):
            yi = X[i, k1:k1 + nc]
            bi = b[i]
            for ch in range(nc):
                yi[ch] = bi * uu[ch]
            for q in range(n_states):
                aiq = a[i, q]
                xq = X[q, k0:k0 + nc]
                for ch in range(nc):
                    yi[ch] += aiq * xq[ch]
            for ch in range(nc):
                if abs(yi[ch]) < TINY:
                    yi[ch] = 0.0


@kernel
def _tile3x8_add(plan, coef, k, X, ys, L):
    """Output rows ``plan[k, 1:4]`` += ``coef[k, :3, :8] @ X[plan[k, 5:13], :L]``."""
    y0 = ys[plan[k, 1], :L]
    y1 = ys[plan[k, 2], :L]
    y2 = ys[plan[k, 3], :L]
    s0, s1, s2, s3 = plan[k, 5], plan[k, 6], plan[k, 7], plan[k, 8]
    s4, s5, s6, s7 = plan[k, 9], plan[k, 10], plan[k, 11], plan[k, 12]
    c00, c01, c02, c03 = coef[k, 0, 0], coef[k, 0, 1], coef[k, 0, 2], coef[k, 0, 3]
    c04, c05, c06, c07 = coef[k, 0, 4], coef[k, 0, 5], coef[k, 0, 6], coef[k, 0, 7]
    c10, c11, c12, c13 = coef[k, 1, 0], coef[k, 1, 1], coef[k, 1, 2], coef[k, 1, 3]
    c14, c15, c16, c17 = coef[k, 1, 4], coef[k, 1, 5], coef[k, 1, 6], coef[k, 1, 7]
    c20, c21, c22, c23 = coef[k, 2, 0], coef[k, 2, 1], coef[k, 2, 2], coef[k, 2, 3]
    c24, c25, c26, c27 = coef[k, 2, 4], coef[k, 2, 5], coef[k, 2, 6], coef[k, 2, 7]
    for i in range(L):
        v0 = X[s0, i]
        v1 = X[s1, i]
        v2 = X[s2, i]
        v3 = X[s3, i]
        v4 = X[s4, i]
        v5 = X[s5, i]
        v6 = X[s6, i]
        v7 = X[s7, i]
        y0[i] += ((c00 * v0 + c01 * v1 + c02 * v2 + c03 * v3)
                  + (c04 * v4 + c05 * v5 + c06 * v6 + c07 * v7))
        y1[i] += ((c10 * v0 + c11 * v1 + c12 * v2 + c13 * v3)
                  + (c14 * v4 + c15 * v5 + c16 * v6 + c17 * v7))
        y2[i] += ((c20 * v0 + c21 * v1 + c22 * v2 + c23 * v3)
                  + (c24 * v4 + c25 * v5 + c26 * v6 + c27 * v7))


@kernel
def _tile3x4_add(plan, coef, k, X, ys, L):
    """Output rows ``plan[k, 1:4]`` += ``coef[k, :3, :4] @ X[plan[k, 5:9], :L]``."""
    y0 = ys[plan[k, 1], :L]
    y1 = ys[plan[k, 2], :L]
    y2 = ys[plan[k, 3], :L]
    s0, s1, s2, s3 = plan[k, 5], plan[k, 6], plan[k, 7], plan[k, 8]
    c00, c01, c02, c03 = coef[k, 0, 0], coef[k, 0, 1], coef[k, 0, 2], coef[k, 0, 3]
    c10, c11, c12, c13 = coef[k, 1, 0], coef[k, 1, 1], coef[k, 1, 2], coef[k, 1, 3]
    c20, c21, c22, c23 = coef[k, 2, 0], coef[k, 2, 1], coef[k, 2, 2], coef[k, 2, 3]
    for i in range(L):
        v0 = X[s0, i]
        v1 = X[s1, i]
        v2 = X[s2, i]
        v3 = X[s3, i]
        y0[i] += c00 * v0 + c01 * v1 + c02 * v2 + c03 * v3
        y1[i] += c10 * v0 + c11 * v1 + c12 * v2 + c13 * v3
        y2[i] += c20 * v0 + c21 * v1 + c22 * v2 + c23 * v3


@kernel
def _tile2x8_add(plan, coef, k, X, ys, L):
    """Output rows ``plan[k, 1:3]`` += ``coef[k, :2, :8] @ X[plan[k, 5:13], :L]``."""
    y0 = ys[plan[k, 1], :L]
    y1 = ys[plan[k, 2], :L]
    s0, s1, s2, s3 = plan[k, 5], plan[k, 6], plan[k, 7], plan[k, 8]
    s4, s5, s6, s7 = plan[k, 9], plan[k, 10], plan[k, 11], plan[k, 12]
    c00, c01, c02, c03 = coef[k, 0, 0], coef[k, 0, 1], coef[k, 0, 2], coef[k, 0, 3]
    c04, c05, c06, c07 = coef[k, 0, 4], coef[k, 0, 5], coef[k, 0, 6], coef[k, 0, 7]
    c10, c11, c12, c13 = coef[k, 1, 0], coef[k, 1, 1], coef[k, 1, 2], coef[k, 1, 3]
    c14, c15, c16, c17 = coef[k, 1, 4], coef[k, 1, 5], coef[k, 1, 6], coef[k, 1, 7]
    for i in range(L):
        v0 = X[s0, i]
        v1 = X[s1, i]
        v2 = X[s2, i]
        v3 = X[s3, i]
        v4 = X[s4, i]
        v5 = X[s5, i]
        v6 = X[s6, i]
        v7 = X[s7, i]
        y0[i] += ((c00 * v0 + c01 * v1 + c02 * v2 + c03 * v3)
                  + (c04 * v4 + c05 * v5 + c06 * v6 + c07 * v7))
        y1[i] += ((c10 * v0 + c11 * v1 + c12 * v2 + c13 * v3)
                  + (c14 * v4 + c15 * v5 + c16 * v6 + c17 * v7))


@kernel
def _tile2x4_add(plan, coef, k, X, ys, L):
    """Output rows ``plan[k, 1:3]`` += ``coef[k, :2, :4] @ X[plan[k, 5:9], :L]``."""
    y0 = ys[plan[k, 1], :L]
    y1 = ys[plan[k, 2], :L]
    s0, s1, s2, s3 = plan[k, 5], plan[k, 6], plan[k, 7], plan[k, 8]
    c00, c01, c02, c03 = coef[k, 0, 0], coef[k, 0, 1], coef[k, 0, 2], coef[k, 0, 3]
    c10, c11, c12, c13 = coef[k, 1, 0], coef[k, 1, 1], coef[k, 1, 2], coef[k, 1, 3]
    for i in range(L):
        v0 = X[s0, i]
        v1 = X[s1, i]
        v2 = X[s2, i]
        v3 = X[s3, i]
        y0[i] += c00 * v0 + c01 * v1 + c02 * v2 + c03 * v3
        y1[i] += c10 * v0 + c11 * v1 + c12 * v2 + c13 * v3


@kernel
def _tile1x8_add(plan, coef, k, X, ys, L):
    """Output row += ``coef[k, :1, :8] @ X[plan[k, 5:13], :L]``."""
    y0 = ys[plan[k, 1], :L]
    s0, s1, s2, s3 = plan[k, 5], plan[k, 6], plan[k, 7], plan[k, 8]
    s4, s5, s6, s7 = plan[k, 9], plan[k, 10], plan[k, 11], plan[k, 12]
    c00, c01, c02, c03 = coef[k, 0, 0], coef[k, 0, 1], coef[k, 0, 2], coef[k, 0, 3]
    c04, c05, c06, c07 = coef[k, 0, 4], coef[k, 0, 5], coef[k, 0, 6], coef[k, 0, 7]
    for i in range(L):
        v0 = X[s0, i]
        v1 = X[s1, i]
        v2 = X[s2, i]
        v3 = X[s3, i]
        v4 = X[s4, i]
        v5 = X[s5, i]
        v6 = X[s6, i]
        v7 = X[s7, i]
        y0[i] += ((c00 * v0 + c01 * v1 + c02 * v2 + c03 * v3)
                  + (c04 * v4 + c05 * v5 + c06 * v6 + c07 * v7))


@kernel
def _tile1x4_add(plan, coef, k, X, ys, L):
    """Output row += ``coef[k, :1, :4] @ X[plan[k, 5:9], :L]``."""
    y0 = ys[plan[k, 1], :L]
    s0, s1, s2, s3 = plan[k, 5], plan[k, 6], plan[k, 7], plan[k, 8]
    c00, c01, c02, c03 = coef[k, 0, 0], coef[k, 0, 1], coef[k, 0, 2], coef[k, 0, 3]
    for i in range(L):
        v0 = X[s0, i]
        v1 = X[s1, i]
        v2 = X[s2, i]
        v3 = X[s3, i]
        y0[i] += c00 * v0 + c01 * v1 + c02 * v2 + c03 * v3


@kernel
def _tile1x1_add(plan, coef, k, X, ys, L):
    """Output row += ``coef[k, :1, :1] @ X[plan[k, 5:6], :L]``."""
    y0 = ys[plan[k, 1], :L]
    s0 = plan[k, 5]
    c00 = coef[k, 0, 0]
    for i in range(L):
        v0 = X[s0, i]
        y0[i] += c00 * v0


@kernel
def _start_rows(ys, d, ut, uoff, L):
    """``ys[o, :L] = d[o] * ut[uoff:uoff + L]`` for every output (the feedthrough, often 0)."""
    uu = ut[uoff:uoff + L]
    for o in range(ys.shape[0]):
        y = ys[o, :L]
        do = d[o]
        for i in range(L):
            y[i] = do * uu[i]


@kernel
def lti_outputs(plan, coef, d, X, ut, uoff, ys, L):
    """``ys[:, :L] = C X[:, :L] + d ut[uoff:uoff + L]``, tile by tile (see :func:`output_plan`).

    Every row starts at its feedthrough ``d[o] u``; tile ``k`` then adds to output rows
    ``plan[k, 1:1 + plan[k, 0]]`` from the states ``plan[k, 5:5 + plan[k, 4]]`` with
    coefficients ``coef[k]``. (Assigning in each row's first tile instead saves ~0.3 ns per
    channel-sample but doubles the tile kernels and their compile time.)
    """
    _start_rows(ys, d, ut, uoff, L)
    for k in range(plan.shape[0]):
        nr = plan[k, 0]
        w = plan[k, 4]
        if nr == 3:
            if w == 8:
                _tile3x8_add(plan, coef, k, X, ys, L)
            else:
                _tile3x4_add(plan, coef, k, X, ys, L)
        elif nr == 2:
            if w == 8:
                _tile2x8_add(plan, coef, k, X, ys, L)
            else:
                _tile2x4_add(plan, coef, k, X, ys, L)
        elif w == 8:
            _tile1x8_add(plan, coef, k, X, ys, L)
        elif w == 4:
            _tile1x4_add(plan, coef, k, X, ys, L)
        else:
            _tile1x1_add(plan, coef, k, X, ys, L)


@kernel
def lti_outputs_live(plan, coef, d, X, ut, uoff, ys, L, tcell, quiet):
    """:func:`lti_outputs`, less every tile whose sources all belong to quiet channels: their
    terms are exact zeros, so the rows come out bitwise the same (a plate's undriven cells).

    ``tcell[k, i]`` is the channel of tile ``k``'s ``i``-th source (-1: of no channel, always
    read); ``quiet[c]`` is nonzero when every source of channel ``c`` is exactly zero over the
    ``L`` samples.
    """
    _start_rows(ys, d, ut, uoff, L)
    for k in range(plan.shape[0]):
        live = False
        for i in range(plan[k, 4]):
            c = tcell[k, i]
            if c < 0 or quiet[c] == 0:
                live = True
                break
        if not live:
            continue
        # (the dispatch of lti_outputs, written out again: called as a function of its own, it
        # made the plate's kernel 40 % slower)
        nr = plan[k, 0]
        w = plan[k, 4]
        if nr == 3:
            if w == 8:
                _tile3x8_add(plan, coef, k, X, ys, L)
            else:
                _tile3x4_add(plan, coef, k, X, ys, L)
        elif nr == 2:
            if w == 8:
                _tile2x8_add(plan, coef, k, X, ys, L)
            else:
                _tile2x4_add(plan, coef, k, X, ys, L)
        elif w == 8:
            _tile1x8_add(plan, coef, k, X, ys, L)
        elif w == 4:
            _tile1x4_add(plan, coef, k, X, ys, L)
        else:
            _tile1x1_add(plan, coef, k, X, ys, L)


@kernel
def copy_slot(X, src, dst, nc):
    """``X[:, dst:dst + nc] = X[:, src:src + nc]``."""
    for s in range(X.shape[0]):
        xs = X[s, src:src + nc]
        xd = X[s, dst:dst + nc]
        for ch in range(nc):
            xd[ch] = xs[ch]


@kernel
def lti_chunk(form, a, reals, b, d, plan, coef, X, ut, uoff, ys, nc, m):
    """Advance all channels over ``m <= chunk`` samples of ``ut[uoff:]``; outputs into
    ``ys[:, :m * nc]``.

    ``form`` is ``FORM_MODAL`` (``a`` holds ``pairs``, shape (n_pairs, 2), inputs with unit
    gain, ``b`` unused) or ``FORM_DENSE`` (``a`` is the full state matrix, shape (n_states,
    n_states)). The outputs need the states before each sample (slots ``0 .. m - 1``); in
    modal form the last sample's update then writes straight into slot 0, otherwise slot ``m``
    is copied there (a one-sample modal chunk too: an in-place step would run the scalar loop,
    and any chunk length must give bitwise the same samples).
    """
    k = m * nc
    if form == FORM_MODAL and m > 1:
        lti_steps_modal(a, reals, X, 0, nc, m - 1, ut, uoff, nc)
        lti_outputs(plan, coef, d, X, ut, uoff, ys, k)
        lti_steps_modal(a, reals, X, k - nc, 0, 1, ut, uoff + k - nc, nc)
        return
    if form == FORM_MODAL:
        lti_steps_modal(a, reals, X, 0, nc, m, ut, uoff, nc)
    else:
        lti_steps_dense(a, b, X, 0, nc, m, ut, uoff, nc)
    lti_outputs(plan, coef, d, X, ut, uoff, ys, k)
    copy_slot(X, k, 0, nc)


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
def rows_out(ys, n_truth, n_seg, truth, sensed, start, m, nc):
    """Copy one chunk of outputs into the house layouts (a transpose).

    ``truth[ch, o, start + t] = ys[o, t * nc + ch]`` for ``o < n_truth``, then
    ``sensed[ch * n_seg + s, start + t] = ys[n_truth + s, t * nc + ch]`` for ``s < n_seg``
    (``sensed`` is not touched when ``n_seg == 0``). Eight samples at a time (then 4, 2, 1):
    eight source rows as views, then each destination row gets 8 consecutive values, channels
    inside; one function for all rows (a call per row cost ~4 % of the plant, measured). A
    loop storing one sample per channel is vectorized as a scatter, which made chunks of 4
    samples 40 % slower: hence the explicit 4, 2, 1 cases.
    """
    for r in range(n_truth + n_seg):
        src = ys[r]
        dst = truth[:, r, start:start + m] if r < n_truth else \
            sensed[r - n_truth::n_seg, start:start + m]
        for tb in range(m // 8):
            t0 = tb * 8
            s0, s1 = src[t0 * nc:(t0 + 1) * nc], src[(t0 + 1) * nc:(t0 + 2) * nc]
            s2, s3 = src[(t0 + 2) * nc:(t0 + 3) * nc], src[(t0 + 3) * nc:(t0 + 4) * nc]
            s4, s5 = src[(t0 + 4) * nc:(t0 + 5) * nc], src[(t0 + 5) * nc:(t0 + 6) * nc]
            s6, s7 = src[(t0 + 6) * nc:(t0 + 7) * nc], src[(t0 + 7) * nc:(t0 + 8) * nc]
            for ch in range(nc):
                row = dst[ch, t0:t0 + 8]
                row[0] = s0[ch]
                row[1] = s1[ch]
                row[2] = s2[ch]
                row[3] = s3[ch]
                row[4] = s4[ch]
                row[5] = s5[ch]
                row[6] = s6[ch]
                row[7] = s7[ch]
        t0 = m - m % 8
        if m - t0 >= 4:
            s0, s1 = src[t0 * nc:(t0 + 1) * nc], src[(t0 + 1) * nc:(t0 + 2) * nc]
            s2, s3 = src[(t0 + 2) * nc:(t0 + 3) * nc], src[(t0 + 3) * nc:(t0 + 4) * nc]
            for ch in range(nc):
                row = dst[ch, t0:t0 + 4]
                row[0] = s0[ch]
                row[1] = s1[ch]
                row[2] = s2[ch]
                row[3] = s3[ch]
            t0 += 4
        if m - t0 >= 2:
            s0, s1 = src[t0 * nc:(t0 + 1) * nc], src[(t0 + 1) * nc:(t0 + 2) * nc]
            for ch in range(nc):
                row = dst[ch, t0:t0 + 2]
                row[0] = s0[ch]
                row[1] = s1[ch]
            t0 += 2
        if m - t0 >= 1:
            s0 = src[t0 * nc:(t0 + 1) * nc]
            for ch in range(nc):
                row = dst[ch, t0:t0 + 1]
                row[0] = s0[ch]


@kernel
def lti_group_process(form, a, reals, b, d, plan, coef, X, ut, ys, u, y):
    """Streaming LTI channel group without a front end (the generic kernel).

    Parameters
    ----------
    form, a, reals, b, d, plan, coef : arrays
        The discrete system as in :func:`lti_chunk` (``plan, coef = output_plan(c)``).
    X, ut, ys : ndarray
        Scratch of exactly ``(n_states, (chunk + 1) * nc)``, ``(max_block * nc,)`` and
        ``(n_outputs, chunk * nc)``: chunk and block lengths are taken from these shapes.
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
    status = 0
    for start in range(0, n, blk):
        nb = min(blk, n - start)
        transpose_in(u, ut, start, nb)
        for c0 in range(0, nb, chunk):
            m = min(chunk, nb - c0)
            lti_chunk(form, a, reals, b, d, plan, coef, X, ut, c0 * nc, ys, nc, m)
            rows_out(ys, ys.shape[0], 0, y, ys, start + c0, m, nc)
        if state_nonfinite(X, nc):
            status |= 2
    return status


@kernel
def adc_block(ys, row0, n_seg, nc, nb, adc, table1, table2, ipos):
    """Noise, quantization and clipping of all sensed streams over one block, in place.

    ``ys[row0 + s, t * nc + ch]`` holds the anti-aliased current (A) of segment ``s`` of
    channel ``ch`` and is overwritten with the ADC reading (A). ``adc = (gain_v_per_a,
    inv_lsb_v, lsb_a, max_code, min_code, noise_scale_v)``. Codes are rounded in floating point
    and clipped to ``[min_code, max_code]``; a NaN reads as ``min_code`` and counts as clipped.

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
                q = np.floor(v * inv_lsb + 0.5)
                inside = (q >= lo) & (q <= hi)       # False for NaN: clipped to lo, counted
                n_sat += not inside
                q = q if q >= lo else lo
                yy[ch] = (q if q <= hi else hi) * lsb_a
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
def sim_group_process(sizes, a, reals, b, d, plan, coef, X, ut, ys, adc, table1, table2, ipos,
                      drive, sensed, truth):
    """Advance a simulated channel group by one block (see ``rtctl.plant.SimGroup``).

    Parameters
    ----------
    sizes : ndarray of int64, shape (5,)
        ``(form, n_truth, n_seg, chunk, max_block)``.
    a, reals, b, d, plan, coef, X, ut, ys : arrays
        Discrete plant (modal or dense), its output plan and scratch, as in :func:`lti_chunk`
        (at least ``(chunk + 1) * nc``, ``max_block * nc`` and ``chunk * nc`` columns; see
        :func:`aligned_zeros`); the output rows are the ``n_truth`` truth signals followed by
        the ``n_seg`` anti-aliased currents.
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
    chunk = sizes[3]
    blk = sizes[4]
    nc, n = drive.shape
    status = 0
    for start in range(0, n, blk):
        nb = min(blk, n - start)
        transpose_in(drive, ut, start, nb)
        for c0 in range(0, nb, chunk):
            m = min(chunk, nb - c0)
            # lti_chunk, written out: one call level less saves ~3 s of cold compile.
            uoff = c0 * nc
            k = m * nc
            if form == FORM_MODAL and m > 1:
                lti_steps_modal(a, reals, X, 0, nc, m - 1, ut, uoff, nc)
                lti_outputs(plan, coef, d, X, ut, uoff, ys, k)
                lti_steps_modal(a, reals, X, k - nc, 0, 1, ut, uoff + k - nc, nc)
            else:
                if form == FORM_MODAL:
                    lti_steps_modal(a, reals, X, 0, nc, m, ut, uoff, nc)
                else:
                    lti_steps_dense(a, b, X, 0, nc, m, ut, uoff, nc)
                lti_outputs(plan, coef, d, X, ut, uoff, ys, k)
                copy_slot(X, k, 0, nc)
            if adc_block(ys, n_truth, n_seg, nc, m, adc, table1, table2, ipos):
                status |= 1
            rows_out(ys, n_truth, n_seg, truth, sensed, start + c0, m, nc)
        if state_nonfinite(X, nc):
            status |= 2
    return status


def aligned_zeros(shape):
    """Zeroed float64 scratch whose data starts on a 64-byte boundary (not a kernel).

    numpy aligns to 16 bytes; a 64-byte vector access that straddles two cache lines made the
    recursion ~30 % slower (2.2 vs 3.1 ns per channel-sample, measured). The last axis is
    padded to a multiple of 8 doubles so that every row starts on a boundary too
    (:func:`sim_group_process` takes its chunk and block lengths from ``sizes``, not from the
    scratch shapes).
    """
    shape = tuple(int(v) for v in shape)
    padded = shape[:-1] + (-(-shape[-1] // 8) * 8,)
    n = int(np.prod(padded))
    buf = np.zeros(n + 8)
    start = (-(buf.ctypes.data // 8)) % 8   # float64 data is 8-byte aligned
    return buf[start:start + n].reshape(padded)


def output_plan(c, slack=0.25):
    """Tiles for :func:`lti_outputs` from the exact zero pattern of ``c`` (not a kernel).

    Outputs are grouped (up to 3, in order) when the union of the states they read is not much
    larger than what they read apart (``slack``: at most that fraction of the tile's
    multiply-adds are zeros); each group runs over the union of its states in tiles of 8, then
    4 (a remainder of 5-7 states is padded to 8, of 2-3 to 4, of 1 to 4 unless the group has a
    single row), padding with a state of the tile and a zero coefficient. States an output does
    not read at all (exact zeros) are skipped.

    Parameters
    ----------
    c : ndarray, shape (n_outputs, n_states)

    Returns
    -------
    plan : ndarray of int64, shape (n_tiles, 13)
        ``(n_rows, row0, row1, row2, width, state0 .. state7)``; unused rows repeat
        ``row0``, unused states repeat ``state0``.
    coef : ndarray, shape (n_tiles, 3, 8)
        Coefficients, zero where unused.
    """
    c = np.asarray(c, dtype=np.float64)
    n_out = c.shape[0]
    sup = [set(np.flatnonzero(c[o]).tolist()) for o in range(n_out)]
    left = list(range(n_out))
    groups = []
    while left:
        g = [left.pop(0)]
        cols = set(sup[g[0]])
        for q in list(left):
            if len(g) == 3:
                break
            union = cols | sup[q]
            work = sum(len(sup[r]) for r in g) + len(sup[q])
            if len(union) * (len(g) + 1) <= (1.0 + slack) * work:
                g.append(q)
                cols = union
                left.remove(q)
        groups.append((g, sorted(cols)))
    plan, coef = [], []
    for g, cols in groups:
        nr = len(g)
        tiles = [cols[i:i + 8] for i in range(0, len(cols) - len(cols) % 8, 8)]
        rest = cols[len(cols) - len(cols) % 8:]
        if rest or not tiles:
            tiles.append(rest if rest else [0])
        for tc in tiles:
            w = 8 if len(tc) > 4 else 4 if (len(tc) > 1 or nr > 1) else 1
            rows = g + [g[0]] * (3 - nr)
            plan.append([nr, *rows, w, *(tc + [tc[0]] * (8 - len(tc)))])
            cf = np.zeros((3, 8))
            for r, o in enumerate(g):
                cf[r, :len(tc)] = c[o, tc]
            coef.append(cf)
    return np.array(plan, dtype=np.int64).reshape(-1, PLAN_COLUMNS), \
        np.array(coef, dtype=np.float64).reshape(-1, 3, 8)
