"""Plain numpy/loop twins of the render kernels (``rtctl/render/_kernels.py``).

They work on the image-wide maps directly (padding the HIA with background, slicing, np.unique,
np.var), never on summed-area tables or stamps, so they share no code path with the kernels.
"""

import numpy as np


def window(img, r0, c0, h, w, fill):
    """The ``h x w`` window of ``img`` at top-left ``(r0, c0)``, outside pixels = ``fill``."""
    out = np.full((h, w), fill, dtype=float)
    H, W = img.shape
    a, b, c, d = max(r0, 0), min(r0 + h, H), max(c0, 0), min(c0 + w, W)
    if a < b and c < d:
        out[a - r0:b - r0, c - c0:d - c0] = img[a:b, c:d]
    return out


def cells(win, R, C, cell):
    """(R, C, cell, cell) view of a window."""
    return win.reshape(R, cell, C, cell).transpose(0, 2, 1, 3)


def naive_roi(black, r0, c0, R, C, cell):
    """``up`` per pin: more than half of the cell's pixels black (outside = white)."""
    win = window(black, r0, c0, R * cell, C * cell, 0)
    frac = cells(win, R, C, cell).mean(axis=(2, 3))
    return (frac > 0.5).astype(float).ravel()


def naive_frequency(tactile, r0, c0, R, C, cell, f_pmax):
    win = window(tactile, r0, c0, R * cell, C * cell, 0)
    return (f_pmax * cells(win, R, C, cell).mean(axis=(2, 3)) / 255.0).ravel()


def distinct_valid(labels, valid, a, b, c, d):
    u = np.unique(labels[max(a, 0):max(b, 0), max(c, 0):max(d, 0)])
    return int(np.sum(valid[u] != 0))


def naive_beat(gray, labels, valid, elabels, evalid, r0, c0, R, C, cell, unit, params):
    """Per pin ``(freq, beat, carrier, amplitude)`` by slicing, np.unique and np.var."""
    alpha, fl, fh, fpl, fph, a_s, inv_b, inv_e = params
    ur, uc = unit
    out = np.zeros((R, C, 4))
    for ui in range(R // ur):
        for uj in range(C // uc):
            a, b = r0 + ui * ur * cell, r0 + (ui + 1) * ur * cell
            c, d = c0 + uj * uc * cell, c0 + (uj + 1) * uc * cell
            nb = distinct_valid(labels, valid, a, b, c, d)
            ne = distinct_valid(elabels, evalid, a, b, c, d)
            g = gray[max(a, 0):max(b, 0), max(c, 0):max(d, 0)].astype(float)
            var = g.var() if g.size else 0.0
            fb = alpha * (min(nb * inv_b, 1.0) * (fh - fl) + fl)
            fc = alpha * (min(ne * inv_e, 1.0) * (fph - fpl) + fpl)
            amp = 1.0 - 1.0 / (1.0 + a_s * var)
            for i in range(ui * ur, (ui + 1) * ur):
                for j in range(uj * uc, (uj + 1) * uc):
                    if C % 2 == 1 and j == C - 1:
                        f = fc
                    else:
                        f = fc - fb / 2 if j % 2 == 0 else fc + fb / 2
                    out[i, j] = (f, fb, fc, amp)
    return out.reshape(R * C, 4)


def naive_max_window_count(labels, valid, h, w, sr, sc):
    H, W = labels.shape
    best = 0
    for r in range(-(h // 2), H - h // 2 + 1, sr):
        for c in range(-(w // 2), W - w // 2 + 1, sc):
            best = max(best, distinct_valid(labels, valid, r, r + h, c, c + w))
    return best
