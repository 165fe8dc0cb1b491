"""The figures of a sweep: each headline metric against every varied key, and with exactly two
varied keys, a heat map of the metric over both (``plot_<metric>.png``).

Headline metrics, by ``--what``: the first loaded resonance, deflection per volt and blocked
force (model); each receptor's margin over its threshold, with the threshold at 0 dB (reach);
the observer's amplitude error (selfsense); each channel's error against its target (run).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

HEADLINES = {
    "model": (".f1_loaded_hz", ".deflection_per_volt_m", ".blocked_force_per_volt_n"),
    "reach": (".margin_db",),
    "selfsense": (".amp_err_pct",),
    "run": (".error_pct",),
}
#: Beyond this many combinations of the other keys a line panel shows points, not one line each.
MAX_LINES = 8
#: Heat map cells get their value written in them up to this many cells.
MAX_ANNOTATED = 144


def headline_columns(rows: list[dict], whats) -> list[str]:
    cols = list(rows[0]) if rows else []
    out = []
    for w in whats:
        for suffix in HEADLINES[w]:
            out += [c for c in cols if c.endswith(suffix) and c not in out and _numeric(rows, c)]
    return out


def _numeric(rows, col) -> bool:
    vals = [r[col] for r in rows if r[col] is not None]
    return bool(vals) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals)


def _finite(v) -> float:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else math.nan


def _label(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def plot(rows: list[dict], varies, whats, out_dir) -> list[Path]:
    """Write the figures into ``out_dir``; returns their paths (none when no key varies)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [v for v in varies if len(v.values) > 1]
    if not keys or not rows:
        return []
    paths = []
    for col in headline_columns(rows, whats):
        heat = len(keys) == 2
        n = len(keys) + heat
        fig, axes = plt.subplots(1, n, figsize=(5.2 * n, 4.2), squeeze=False)
        axes = list(axes[0])
        if heat:
            _heat(axes.pop(0), rows, keys, col)
        for ax, key in zip(axes, keys):
            _lines(ax, rows, keys, key, col)
        fig.suptitle(col)
        fig.tight_layout()
        path = Path(out_dir) / f"plot_{re.sub(r'[^A-Za-z0-9_.-]+', '_', col)}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def _axis(ax, key, axis="x"):
    """Numbers on their own scale (log for a log SPEC); anything else as categories."""
    numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in key.values)
    if numeric:
        if key.log:  # ticks at the values swept: log axes' own labels crowd a short decade
            (ax.set_xscale if axis == "x" else ax.set_yscale)("log")
            ax.minorticks_off()
            (ax.set_xticks if axis == "x" else ax.set_yticks)(
                [float(v) for v in key.values], [_label(v) for v in key.values], fontsize=7,
                rotation=45 if axis == "x" else 0)
        return lambda v: float(v)
    ticks = list(range(len(key.values)))
    (ax.set_xticks if axis == "x" else ax.set_yticks)(ticks, [_label(v) for v in key.values])
    index = {repr(v): i for i, v in enumerate(key.values)}
    return lambda v: index[repr(v)]


def _lines(ax, rows, keys, key, col):
    pos = _axis(ax, key)
    others = [k for k in keys if k is not key]
    groups: dict = {}
    for r in rows:
        groups.setdefault(tuple(repr(r[k.name]) for k in others), []).append(r)
    if len(groups) <= MAX_LINES:
        for g in groups.values():
            g = sorted(g, key=lambda r: pos(r[key.name]))
            label = ", ".join(f"{k.short}={_label(g[0][k.name])}" for k in others) or None
            ax.plot([pos(r[key.name]) for r in g], [_finite(r[col]) for r in g], "o-", ms=3, label=label)
        if others:
            ax.legend(fontsize=7)
    else:  # every point, and the largest value at each of this key's values
        ax.plot([pos(r[key.name]) for r in rows], [_finite(r[col]) for r in rows], ".", alpha=0.4)
        best: dict = {}
        for r in rows:
            v = _finite(r[col])
            if math.isfinite(v):
                x = pos(r[key.name])
                best[x] = max(best.get(x, -math.inf), v)
        xs = sorted(best)
        ax.plot(xs, [best[x] for x in xs], "-", color="k", lw=1, label="max over the other keys")
        ax.legend(fontsize=7)
    if col.endswith(".margin_db"):
        ax.axhline(0.0, color="k", lw=0.8, ls="--")
        ax.text(ax.get_xlim()[0], 0.0, " threshold", va="bottom", fontsize=7)
    ax.set_xlabel(key.short)
    ax.set_ylabel(col)
    ax.grid(True, alpha=0.3)


def _heat(ax, rows, keys, col):
    import numpy as np

    kx, ky = keys[1], keys[0]  # the first --vary down the side, the second across
    ix = {repr(v): i for i, v in enumerate(kx.values)}
    iy = {repr(v): i for i, v in enumerate(ky.values)}
    z = np.full((len(ky.values), len(kx.values)), np.nan)
    for r in rows:
        z[iy[repr(r[ky.name])], ix[repr(r[kx.name])]] = _finite(r[col])
    margin = col.endswith(".margin_db")
    kw = {}
    if margin and np.isfinite(z).any():  # red short of the threshold, blue beyond it
        lim = max(1.0, float(np.nanmax(np.abs(z))))
        kw = {"cmap": "RdBu", "vmin": -lim, "vmax": lim}
    im = ax.imshow(z, origin="lower", aspect="auto", **kw)
    ax.figure.colorbar(im, ax=ax, label=col)
    ax.set_xticks(range(len(kx.values)), [_label(v) for v in kx.values], rotation=45, fontsize=7)
    ax.set_yticks(range(len(ky.values)), [_label(v) for v in ky.values], fontsize=7)
    ax.set_xlabel(kx.short)
    ax.set_ylabel(ky.short)
    if z.size <= MAX_ANNOTATED:
        for (i, j), v in np.ndenumerate(z):
            # white on dark cells (luminance of the cell's colour), black on light ones
            r, g, b, _ = im.cmap(im.norm(v)) if np.isfinite(v) else (1.0, 1.0, 1.0, 1.0)
            ax.text(j, i, "x" if not np.isfinite(v) else f"{v:.3g}", ha="center", va="center", fontsize=6,
                    color="w" if 0.299 * r + 0.587 * g + 0.114 * b < 0.5 else "k",
                    fontweight="bold" if margin and v >= 0 else "normal")
    if margin and np.nanmin(z) < 0 < np.nanmax(z):
        ax.contour(z, levels=[0.0], colors="k", linewidths=1.2)
