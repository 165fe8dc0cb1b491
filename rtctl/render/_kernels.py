"""Numba kernels of one HIA update: work proportional to the HIA, never to the image.

Image-wide work is done once in ``prepare`` (see :mod:`rtctl.render.hia`): summed-area tables
``S`` of shape ``(H + 1, W + 1)`` (``cv2.integral``, float64, so sums up to 2**53 are exact) give
any rectangle's sum in four reads; blob label maps ``(H, W)`` int32 with a per-label validity
flag give the blobs, turned into *validity maps* (the label where the blob is valid, else 0).
An update then reads four table entries per pin, and for blob counts scans the HIA's pixels
once, marking labels seen with a *stamp* (``stamp[label] == tick``) instead of clearing a set:
no allocation, and the stamp array is sized once for every label in the image.

Geometry shared by all kernels: the HIA's top-left pixel is ``(r0, c0)`` (may lie outside the
image), it holds ``R x C`` square cells of ``cell`` px; pin ``p = i * C + j`` covers rows
``[r0 + i cell, r0 + (i + 1) cell)`` and columns likewise, clipped to the image. Pixels outside
the image count as background: white for ROI (not black), 0 in a tactile image, no blob; the
gray variance uses only the pixels inside.

Every update kernel writes ``out[p, field]`` (fields in :data:`FIELDS` order) for all pins and
returns a status: :data:`STATUS_OK`, or :data:`STATUS_OUTSIDE` when the HIA lies wholly outside
the image (all pins then get their background values).
"""

import numpy as np

from rtctl._numba import kernel

STATUS_OK = 0
STATUS_OUTSIDE = 1

#: Per-pin parameter columns of every ``out`` array.
FIELDS = ("up", "freq_hz", "beat_hz", "carrier_hz", "amplitude")
UP, FREQ, BEAT, CARRIER, AMP = range(5)
N_FIELDS = len(FIELDS)

#: ``params`` of :func:`beat_update`: alpha, f_l, f_h, f_pl, f_ph, amp_scale, 1/n_max_binary,
#: 1/n_max_edge (Hz; amp_scale per gray level squared; 0 when no valid blob exists anywhere).
BEAT_PARAMS = ("alpha", "f_l", "f_h", "f_pl", "f_ph", "amp_scale", "inv_max_binary", "inv_max_edge")


@kernel
def _clip(v, hi):
    if v < 0:
        return 0
    if v > hi:
        return hi
    return v


@kernel
def _rect_sum(S, a, b, c, d):
    """Sum over rows [a, b), columns [c, d) (already clipped) from a summed-area table."""
    return S[b, d] - S[a, d] - S[b, c] + S[a, c]


@kernel
def _outside(S, r0, c0, h, w):
    H = S.shape[0] - 1
    W = S.shape[1] - 1
    return r0 >= H or c0 >= W or r0 + h <= 0 or c0 + w <= 0


@kernel
def roi_update(S_black, r0, c0, R, C, cell, out):
    """``up = 1`` where more than half of a cell's ``cell**2`` pixels are black, else 0.

    ``S_black`` is the summed-area table of the 0/1 black mask. Pixels outside the image are
    white. ``2 * black > area`` compares exact integers, so exactly 50 % black is down.
    """
    H = S_black.shape[0] - 1
    W = S_black.shape[1] - 1
    area = float(cell * cell)
    for i in range(R):
        a = _clip(r0 + i * cell, H)
        b = _clip(r0 + (i + 1) * cell, H)
        for j in range(C):
            c = _clip(c0 + j * cell, W)
            d = _clip(c0 + (j + 1) * cell, W)
            p = i * C + j
            for f in range(out.shape[1]):
                out[p, f] = 0.0
            if 2.0 * _rect_sum(S_black, a, b, c, d) > area:
                out[p, UP] = 1.0
    if _outside(S_black, r0, c0, R * cell, C * cell):
        return STATUS_OUTSIDE
    return STATUS_OK


@kernel
def frequency_update(S_tactile, r0, c0, R, C, cell, f_pmax, out):
    """``freq = f_pmax * g / 255`` with ``g`` the mean tactile gray of the cell (seed 003, Eq. 1).

    The mean is over the full ``cell**2`` pixels, outside ones being 0 (no height change).
    """
    H = S_tactile.shape[0] - 1
    W = S_tactile.shape[1] - 1
    k = f_pmax / (255.0 * cell * cell)
    for i in range(R):
        a = _clip(r0 + i * cell, H)
        b = _clip(r0 + (i + 1) * cell, H)
        for j in range(C):
            c = _clip(c0 + j * cell, W)
            d = _clip(c0 + (j + 1) * cell, W)
            p = i * C + j
            for f in range(out.shape[1]):
                out[p, f] = 0.0
            out[p, FREQ] = k * _rect_sum(S_tactile, a, b, c, d)
    if _outside(S_tactile, r0, c0, R * cell, C * cell):
        return STATUS_OUTSIDE
    return STATUS_OK


@kernel
def count_blobs(vlab, stamp, tick, a, b, c, d):
    """Number of distinct nonzero labels in rows [a, b), columns [c, d) of ``vlab``.

    ``vlab`` is a validity map: blob labels with the invalid blobs (and the background) set to
    0. ``stamp`` (int64, one entry per label) must hold no entry equal to ``tick``; the labels
    counted are left stamped with ``tick``. A label equal to its left neighbour's is skipped
    without a lookup: blobs are runs along a row, so most pixels cost one compare.
    """
    n = 0
    for r in range(a, b):
        row = vlab[r]
        prev = 0
        for q in range(c, d):
            lab = row[q]
            if lab != prev:
                prev = lab
                if lab != 0 and stamp[lab] != tick:
                    stamp[lab] = tick
                    n += 1
    return n


@kernel
def beat_update(S_gray, S_gray2, vlab_b, vlab_e, stamp_b, stamp_e, tick,
                r0, c0, R, C, cell, ur, uc, params, out):
    """Beat rendering (seed 004, Eqs. 1-3) per unit of ``ur x uc`` cells.

    ``vlab_b``, ``vlab_e``: validity maps (see :func:`count_blobs`) of the binary and edge blobs.
    For each unit: ``n_b`` valid binary blobs and ``n_e`` valid edge blobs touching it, the gray
    variance ``var`` of its pixels inside the image; then ``f_b = alpha (min(n_b / n_max_b, 1)
    (f_h - f_l) + f_l)``, ``f_c = alpha (min(n_e / n_max_e, 1) (f_ph - f_pl) + f_pl)``,
    ``A_c = 1 - 1 / (1 + amp_scale var)``. Every cell of the unit gets ``beat_hz = f_b``,
    ``carrier_hz = f_c``, ``amplitude = A_c``, ``up = 1``, and its drive frequency
    ``freq_hz = f_c - f_b / 2`` in even columns, ``f_c + f_b / 2`` in odd ones (the pair of
    neighbouring cells beats at ``f_b``); a last unpaired column (odd ``C``) gets ``f_c``.

    ``tick`` is a one-element int64 array advanced once per count (stamps never need clearing).
    ``ur`` must divide ``R`` and ``uc`` divide ``C``.
    """
    H = S_gray.shape[0] - 1
    W = S_gray.shape[1] - 1
    alpha, f_l, f_h, f_pl, f_ph = params[0], params[1], params[2], params[3], params[4]
    amp_scale, inv_b, inv_e = params[5], params[6], params[7]
    for ui in range(R // ur):
        a = _clip(r0 + ui * ur * cell, H)
        b = _clip(r0 + (ui + 1) * ur * cell, H)
        for uj in range(C // uc):
            c = _clip(c0 + uj * uc * cell, W)
            d = _clip(c0 + (uj + 1) * uc * cell, W)
            tick[0] += 1
            nb = count_blobs(vlab_b, stamp_b, tick[0], a, b, c, d)
            ne = count_blobs(vlab_e, stamp_e, tick[0], a, b, c, d)
            n = float((b - a) * (d - c))
            var = 0.0
            if n > 0.0:
                m = _rect_sum(S_gray, a, b, c, d) / n
                var = _rect_sum(S_gray2, a, b, c, d) / n - m * m
                if var < 0.0:  # rounding of E[g^2] - E[g]^2 on flat regions
                    var = 0.0
            fbb = min(nb * inv_b, 1.0)
            feb = min(ne * inv_e, 1.0)
            fb = alpha * (fbb * (f_h - f_l) + f_l)
            fc = alpha * (feb * (f_ph - f_pl) + f_pl)
            amp = 1.0 - 1.0 / (1.0 + amp_scale * var)
            for i in range(ui * ur, (ui + 1) * ur):
                for j in range(uj * uc, (uj + 1) * uc):
                    p = i * C + j
                    for f in range(out.shape[1]):
                        out[p, f] = 0.0
                    out[p, UP] = 1.0
                    out[p, BEAT] = fb
                    out[p, CARRIER] = fc
                    out[p, AMP] = amp
                    if C % 2 == 1 and j == C - 1:
                        out[p, FREQ] = fc
                    elif j % 2 == 0:
                        out[p, FREQ] = fc - 0.5 * fb
                    else:
                        out[p, FREQ] = fc + 0.5 * fb
    if _outside(S_gray, r0, c0, R * cell, C * cell):
        return STATUS_OUTSIDE
    return STATUS_OK


@kernel
def max_window_count(vlab, stamp, h, w, stride_r, stride_c):
    """Largest number of valid blobs in any ``h x w`` window whose top-left corner lies on the
    grid ``(-h // 2 + k stride_r, -w // 2 + l stride_c)`` covering every HIA centre in the image.

    Prepare-time (scans ``(H / stride_r) (W / stride_c) h w`` pixels). Resets ``stamp`` to -1.
    """
    H, W = vlab.shape
    for k in range(stamp.shape[0]):
        stamp[k] = -1
    best = 0
    tick = 0
    r = -(h // 2)
    while r <= H - h // 2:
        a = _clip(r, H)
        b = _clip(r + h, H)
        c0 = -(w // 2)
        while c0 <= W - w // 2:
            c = _clip(c0, W)
            d = _clip(c0 + w, W)
            n = count_blobs(vlab, stamp, tick, a, b, c, d)
            if n > best:
                best = n
            tick += 1
            c0 += stride_c
        r += stride_r
    return best


def stamp_array(n_labels: int) -> np.ndarray:
    """A fresh stamp array for ``n_labels`` labels (no entry equals any tick >= 0)."""
    return np.full(max(int(n_labels), 1), -1, dtype=np.int64)


__all__ = ["FIELDS", "N_FIELDS", "UP", "FREQ", "BEAT", "CARRIER", "AMP", "STATUS_OK", "STATUS_OUTSIDE",
           "BEAT_PARAMS", "roi_update", "frequency_update", "beat_update", "count_blobs", "max_window_count",
           "stamp_array"]
