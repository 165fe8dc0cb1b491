"""Benchmark of the final limiter (rtctl.safety.limit_block) at the loop's block size: what the
running-mean bounds (a piezo's DC offset, an SMA spring's duty) cost, against the same limiter
without them, in the same process.

Cases, 48 channels x 32 samples at 48 kHz, a 1.5 kHz sine request of 100 V (a whole period per
block, so its block means are 0; the bench repeats one block):
no mean bound; the DC bound far from its limit (the fast path: one sum per channel and block);
the DC bound engaged every block (a 30 V offset request: the ceiling's bisection every block);
the SMA duty bound far from its limit; engaged. Times are medians over repeats of an ``@njit``
driver running many blocks (no Python call per block).

``--against REV``: the same cases for ``rtctl/safety.py`` as it was at git revision REV too,
loaded beside the current one in this process, the two timed in alternation (a loaded machine
slows both alike); prints both and their ratio. Also ``--block`` and ``--channels``.

    python bench/limiter.py [--json] [--blocks N] [--against REV] [--block B] [--channels C]
"""

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import numpy as np  # noqa: E402
from numba import njit  # noqa: E402

from rtctl.safety import Limiter, limit_block  # noqa: E402

FS, BLOCK, N_CH = 48000.0, 32, 48


def driver(limit):
    """A compiled loop over ``limit`` (a ``limit_block``), so no Python call per block."""

    @njit(nogil=True)
    def drive(req, state, params, fade, counts, n_blocks):
        """Run ``n_blocks`` blocks of the request (refilled each block, as synthesis would)."""
        x = np.empty((req.shape[0], req.shape[1]))
        s = 0
        for _ in range(n_blocks):
            x[:] = req
            s |= limit(x, state, params, fade, counts)
        return s

    return drive


drive = driver(limit_block)


def safety_at(rev: str):
    """``rtctl/safety.py`` at git revision ``rev``, as a module of the package beside the current
    one (its relative imports resolve to the current package)."""
    root = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
    src = subprocess.run(["git", "-C", root, "show", f"{rev}:rtctl/safety.py"], check=True, capture_output=True,
                         text=True).stdout
    path = os.path.join(tempfile.mkdtemp(prefix="rtctl-bench-"), "safety_at_rev.py")
    with open(path, "w") as f:
        f.write(src)
    spec = importlib.util.spec_from_file_location("rtctl._safety_at_rev", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def limiter(kind: str, cls=Limiter) -> Limiter:
    common = dict(temperature=1e3, ambient=25.0, thermal_resistance=150.0, thermal_tau=20.0)
    if kind.startswith("sma"):
        return cls(FS, max_voltage=np.full(N_CH, 2.0), slew=1e6, current=2.0, capacitance=0.0, resistance=1.56,
                       loss_tangent=0.0, duty=np.inf if kind == "sma off" else 0.5, duty_tau=2.0, **common)
    dc = {"none": np.inf, "dc fast": 10.0, "dc engaged": 10.0}[kind]
    return cls(FS, max_voltage=np.full(N_CH, 150.0), slew=5e6, current=0.05, capacitance=2.19e-9,
                   loss_tangent=0.02, dc_offset=dc, dc_tau=10.0, **common)


def request(kind: str) -> np.ndarray:
    t = np.arange(BLOCK) / FS
    phase = np.arange(N_CH)[:, None] * 0.1
    if kind.startswith("sma"):
        return np.where(kind == "sma engaged", 1.8, np.sign(np.sin(2 * np.pi * 1500.0 * t + phase)) * 1.4)
    return 100.0 * np.sin(2 * np.pi * 1500.0 * t + phase) + (30.0 if kind == "dc engaged" else 0.0)


def time_case(kind: str, n_blocks: int, repeats: int, variants=((Limiter, drive),)) -> list[float]:
    """Median us per block for each (Limiter class, driver), timed in alternation."""
    runs = []
    for cls, drv in variants:
        lim, req = limiter(kind, cls), request(kind)
        if kind.endswith("engaged"):  # start on the bound, so every timed block takes the slow path
            drv(req, *lim.args, int(30 * FS / BLOCK))
        drv(req, *lim.args, 1)
        runs.append((drv, req, lim.args))
    times = [[] for _ in runs]
    for _ in range(repeats):
        for j, (drv, req, a) in enumerate(runs):
            t = time.perf_counter()
            drv(req, *a, n_blocks)
            times[j].append((time.perf_counter() - t) / n_blocks)
    return [float(np.median(t)) * 1e6 for t in times]


def main():
    global BLOCK, N_CH
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--blocks", type=int, default=20000)
    ap.add_argument("--against", metavar="REV", help="also time rtctl/safety.py at this git revision")
    ap.add_argument("--block", type=int, default=BLOCK)
    ap.add_argument("--channels", type=int, default=N_CH)
    args = ap.parse_args()
    BLOCK, N_CH = args.block, args.channels
    cases = ["none", "dc fast", "dc engaged", "sma off", "sma fast", "sma engaged"]
    if args.against:
        old = safety_at(args.against)
        variants = ((old.Limiter, driver(old.limit_block)), (Limiter, drive))
        rows = []
        for c in cases:
            t_old, t_new = time_case(c, args.blocks, 15, variants)
            rows.append(dict(case=c, us_per_block_at_rev=t_old, us_per_block=t_new, speedup=t_old / t_new))
        print(json.dumps(dict(fs=FS, block=BLOCK, channels=N_CH, blocks=args.blocks, against=args.against,
                              results=rows), indent=None if args.json else 2))
        if not args.json:
            print(f"\n{'case':12s} {args.against[:10]:>10s} {'now':>9s} {'speedup':>8s}"
                  "   (us per block, medians of 15)")
            for r in rows:
                print(f"{r['case']:12s} {r['us_per_block_at_rev']:10.2f} {r['us_per_block']:9.2f} {r['speedup']:8.2f}")
        return
    us = {c: time_case(c, args.blocks, 7)[0] for c in cases}
    base = {"none": us["none"], "dc fast": us["none"], "dc engaged": us["none"],
            "sma off": us["sma off"], "sma fast": us["sma off"], "sma engaged": us["sma off"]}
    rows = [dict(case=c, us_per_block=us[c], ratio=us[c] / base[c], share_of_block=us[c] / (BLOCK / FS * 1e6))
            for c in cases]
    print(json.dumps(dict(fs=FS, block=BLOCK, channels=N_CH, blocks=args.blocks, results=rows),
                     indent=None if args.json else 2))
    if args.json:
        return
    print(f"\n{'case':12s} {'us/block':>9s} {'x baseline':>11s} {'% of block':>11s}")
    for r in rows:
        print(f"{r['case']:12s} {r['us_per_block']:9.2f} {r['ratio']:11.2f} {100 * r['share_of_block']:10.2f}%")


if __name__ == "__main__":
    main()
