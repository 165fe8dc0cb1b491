"""``rtctl bench render``: HIA update time per method for a 48-pin display on a 2048 x 2048 image.

The image is a real photograph (matplotlib's ``grace_hopper.jpg``) scaled to the size asked for.
For each method: ``preprocess_ms`` (``prepare``, kernels already compiled), then ``n`` updates at
random HIA centres over the image, each timed alone through the public ``update`` (what the
loop calls, Python wrapper included): median and p99 in microseconds. A numpy baseline in the
same process (the same statistics by slicing the image, ``np.unique`` for blob counts) gives a
ratio that survives a noisy machine. Budget: median <= 100 us.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

__all__ = ["main_bench", "bench_method"]

GRID = (6, 8)
HIA = {"roi": 88, "canny": 88, "frequency": 88, "beat": 96}


def _image(size):
    import cv2
    from matplotlib import cbook

    from rtctl.render.image import load_image

    img = load_image(cbook.get_sample_data("grace_hopper.jpg", asfileobj=False))
    return cv2.resize(img, (size, size), interpolation=cv2.INTER_CUBIC)


def _baseline(r, x, y):
    """numpy twin of one update (slices of the image-wide maps; no summed-area tables)."""
    r0, c0 = r.origin(x, y)
    h, w = r.shape
    a, b, c, d = max(r0, 0), max(r0 + h, 0), max(c0, 0), max(c0 + w, 0)
    if r.method == "beat":
        lab = r.labels[a:b, c:d]
        u = np.unique(lab)
        nb = int(r.valid[u].sum())
        g = r.gray[a:b, c:d]
        return nb, g.var()
    src = r.black if r.method in ("roi", "canny") else r.tactile
    win = np.zeros((h, w))
    blk = src[a:b, c:d]
    win[a - r0:a - r0 + blk.shape[0], c - c0:c - c0 + blk.shape[1]] = blk
    R, C = r.grid
    return win.reshape(R, r.cell, C, r.cell).mean(axis=(1, 3))


def _times(fn, xs, ys):
    t = np.empty(xs.size)
    for k in range(xs.size):
        t0 = time.perf_counter_ns()
        fn(xs[k], ys[k])
        t[k] = time.perf_counter_ns() - t0
    return t * 1e-3


def bench_method(method, image, n=2000, seed=0) -> dict:
    """Timings of one method (see the module docstring); dict of floats."""
    from rtctl.render.factory import make_renderer

    r = make_renderer(method, grid=GRID, hia=HIA[method])
    r.prepare(image[:64, :64])  # compile (or load) the kernels outside the timings
    out = r.empty()
    r.update(32, 32, out)
    t0 = time.perf_counter()
    r.prepare(image)
    prep = (time.perf_counter() - t0) * 1e3
    rng = np.random.default_rng(seed)
    H, W = image.shape[:2]
    xs, ys = rng.uniform(0, W - 1, n), rng.uniform(0, H - 1, n)
    t = _times(lambda x, y: r.update(x, y, out), xs, ys)
    tb = _times(lambda x, y: _baseline(r, x, y), xs[: n // 4], ys[: n // 4])
    return {"hia_update_us_median": float(np.median(t)), "hia_update_us_p99": float(np.percentile(t, 99)),
            "preprocess_ms": prep, "numpy_baseline_us_median": float(np.median(tb)),
            "speedup_vs_numpy": float(np.median(tb) / np.median(t)), "pins": r.n_pins, "hia_px": list(r.shape)}


def main_bench(argv=None) -> int:
    """``rtctl bench render [--json] [--size PX] [--n N]``: prints JSON or a table; returns 0."""
    p = argparse.ArgumentParser(prog="rtctl bench render", description=__doc__.splitlines()[0])
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--size", type=int, default=2048, metavar="PX", help="image side (default 2048)")
    p.add_argument("--n", type=int, default=2000, help="updates timed per method (default 2000)")
    p.add_argument("--methods", default="roi,canny,frequency,beat", help="comma-separated methods")
    args = p.parse_args(argv)
    from rtctl.errors import SceneError
    from rtctl.render.image import MAX_SIDE, MIN_SIDE

    # the image side within what load_image accepts (0 or a billion crashed OpenCV); at least one
    # timed baseline update per method (a quarter of --n), at most a million (minutes)
    if not MIN_SIDE <= args.size <= MAX_SIDE:
        raise SceneError(f"--size {args.size}: must be in [{MIN_SIDE}, {MAX_SIDE}] px")
    if not 4 <= args.n <= 10**6:
        raise SceneError(f"--n {args.n}: must be in [4, 1000000] updates")
    unknown = [m for m in args.methods.split(",") if m not in HIA]
    if unknown:
        raise SceneError(f"--methods: {', '.join(map(repr, unknown))} not among {', '.join(HIA)}")
    image = _image(args.size)
    res = {"image_px": [args.size, args.size], "grid": list(GRID), "budget_us": 100.0, "methods": {}}
    for m in args.methods.split(","):
        res["methods"][m] = bench_method(m, image, args.n)
    if args.json:
        print(json.dumps(res))
    else:
        print(f"render: {GRID[0] * GRID[1]} pins, {args.size}x{args.size} px image, {args.n} updates per method")
        print(f"{'method':>10} {'median us':>10} {'p99 us':>8} {'prepare ms':>11} {'numpy us':>9} {'x':>6}")
        for m, d in res["methods"].items():
            print(f"{m:>10} {d['hia_update_us_median']:10.1f} {d['hia_update_us_p99']:8.1f} {d['preprocess_ms']:11.1f} "
                  f"{d['numpy_baseline_us_median']:9.1f} {d['speedup_vs_numpy']:6.1f}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main_bench())
