"""Cost of the self-sensing observer stage alone (``observe_stage``), and of its parts.

Builds the ``bench/loop.py`` rigs (line-bimorph-5, N lateral channels, one random tone each,
block 32) with ``control.observe = true`` (one window for the group) and closed-loop control (a
window per channel, least squares), runs them into steady state, then calls the observer
stage's kernel on its own arguments from a compiled loop (no dispatch per call): median over
repeats of the mean time per call. Each rig's stage is also timed without its drive step's
correction (the first difference's lock-in), alternating with the stage as it runs. ``--parts``
times the pieces the stage is made of the same way: the two lock-ins split into demodulation,
oscillator bookkeeping, hop and estimate, then the observer products, the tip waveform and the
amplitudes. The stage is timed against its reference twin (``tests/twin_observer.py``, the
kernels before they were rewritten for speed), alternating in this process; the parts are the
twin's.

    python bench/observer.py [--channels 1,16,48,128] [--parts] [--calls 2000] [--repeats 15]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from numba import njit

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests"))

import twin_observer as dk  # noqa: E402  (the kernels before the rewrite: the parts are timed there)
from loop import scene_for  # noqa: E402

from rtctl.dsp import _kernels as osc  # noqa: E402
from rtctl.selfsense.stage import observe_stage  # noqa: E402


@njit(cache=True)
def rep_stage(n, *args):
    s = 0
    for _ in range(n):
        s |= observe_stage(*args)
    return s


@njit(cache=True)
def rep_twin(n, *args):
    s = 0
    for _ in range(n):
        s |= dk.observe_stage(*args)
    return s


@njit(cache=True)
def rep_lockin(n, ref, pend, chan, acc, ring, solve, x, out):
    for _ in range(n):
        dk.lockin_process(ref, pend, chan, acc, ring, solve, x, out)


@njit(cache=True)
def rep_demod(n, ref, chan, acc, x):
    # the demodulation of one block with the clock put back: the references keep rotating
    for _ in range(n):
        dk._lockin_demod(ref, chan, acc, x, 0, x.shape[1], False)


@njit(cache=True)
def rep_advance(n, ref, m):
    for _ in range(n):
        osc._osc_advance(ref, m)


@njit(cache=True)
def rep_hop(n, ref, acc, ring):
    for i in range(n):
        dk._lockin_hop(ref, acc, ring, i)


@njit(cache=True)
def rep_estimate(n, ref, acc, solve):
    for _ in range(n):
        dk._lockin_estimate(ref, acc, solve)


@njit(cache=True)
def rep_products(n, u_acc, i_acc, H, scale, est):
    """The observer matrices applied to the window sums (``observer_process`` after its lock-ins,
    without the waveform)."""
    XR, XI = dk.X_R, dk.X_I
    for _ in range(n):
        n_ch, n_t, n_est = est.shape[0], est.shape[1], est.shape[2]
        n_seg = H.shape[3] - 1
        for c in range(n_ch):
            sc = scale[c]
            for k in range(n_t):
                us = c * n_t + k
                dr = sc * u_acc[XR, us]
                di = sc * u_acc[XI, us]
                for e in range(n_est):
                    hr = H[c, k, e, 0, 0]
                    hi = H[c, k, e, 0, 1]
                    zr = hr * dr - hi * di
                    zi = hr * di + hi * dr
                    for j in range(n_seg):
                        js = (c * n_seg + j) * n_t + k
                        sr = sc * i_acc[XR, js]
                        si = sc * i_acc[XI, js]
                        hr = H[c, k, e, 1 + j, 0]
                        hi = H[c, k, e, 1 + j, 1]
                        zr += hr * sr - hi * si
                        zi += hr * si + hi * sr
                    est[c, k, e, 0] = zr
                    est[c, k, e, 1] = zi


@njit(cache=True)
def rep_wave(n, u_ref, est, wave):
    ZR, ZI, WR, WI = osc.ZR, osc.ZI, osc.WR, osc.WI
    for _ in range(n):
        n_ch, n_t = est.shape[0], est.shape[1]
        m = wave.shape[1]
        for c in range(n_ch):
            for s in range(m):
                wave[c, s] = 0.0
            for k in range(n_t):
                us = c * n_t + k
                xr, xi = est[c, k, 0, 0], est[c, k, 0, 1]
                zr, zi = u_ref[ZR, us], u_ref[ZI, us]
                wr, wi = u_ref[WR, us], -u_ref[WI, us]
                for s in range(m - 1, -1, -1):
                    t = zr * wr - zi * wi
                    zi = zr * wi + zi * wr
                    zr = t
                    wave[c, s] += xr * zr - xi * zi


@njit(cache=True)
def rep_amp(n, est, amp, delay, out):
    for _ in range(n):
        delay[0, :, :] = out
        for c in range(est.shape[0]):
            a = 0.0
            for j in range(est.shape[1]):
                a += np.hypot(est[c, j, 0, 0], est[c, j, 0, 1])
            amp[c] = a


@njit(cache=True)
def _fmul_chain(n, y):
    x = 1.0
    for _ in range(n):
        x = x * y  # strict IEEE (no reassoc): one dependent chain
    return x


def ghz() -> float:
    """Clock estimate: a chain of dependent float64 multiplies (4 cycles each on this core)."""
    _fmul_chain(10, 1.0000001)
    best = np.inf
    for _ in range(5):
        t = time.perf_counter()
        _fmul_chain(20_000_000, 1.0000001)
        best = min(best, time.perf_counter() - t)
    return 4 * 20_000_000 / best / 1e9


def rig_stage(n_ch: int, closed: bool, warm_blocks: int = 300):
    from rtctl.engine.rig import build

    rig = build(scene_for(n_ch, 32, observe=not closed, closed=closed))
    rig.apply_schedule(0)
    for _ in range(warm_blocks):
        rig.advance()
    st = next(s for s in rig.stages if s.name.startswith("observer"))
    return rig, st


def timed(fn, args, calls, repeats):
    fn(2, *args)
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn(calls, *args)
        ts.append((time.perf_counter() - t) / calls)
    return 1e6 * float(np.median(ts))


# what the stage took since the twin: the image loads' choice, the low-pass, a drive step's correction
SINCE_TWIN = ("Hc", "pick", "resid", "contact", "lag", "pf", "pf_z", "pf_x", "pf_g", "d_acc", "d_edge",
              "invJ", "Kc")


def twin_args(st):
    """The stage's arguments, copied, for the twin (whose scratch slot held the currents' outputs)."""
    a = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in st.args.items()  # the rig keeps its own
         if k not in SINCE_TWIN}
    a["back"] = np.zeros((a["i_acc"].shape[1] // a["est"].shape[1], a["est"].shape[1], 2))
    return a


def alternate(st, calls, repeats):
    """(old, new) us per block: the twin and the package's stage, alternating, medians."""
    old, new = tuple(twin_args(st).values()), tuple(st.args.values())
    rep_twin(2, *old)
    rep_stage(2, *new)
    to, tn = [], []
    for _ in range(repeats):
        for fn, args, ts in ((rep_twin, old, to), (rep_stage, new, tn)):
            t = time.perf_counter()
            fn(calls, *args)
            ts.append((time.perf_counter() - t) / calls)
    return 1e6 * float(np.median(to)), 1e6 * float(np.median(tn))


def steps_cost(st, calls, repeats):
    """(without, with) us per block: the stage without a drive step's correction (``Kc`` with no
    rows: the first difference's window sums are not formed, its hops' edge terms still are) and as
    it runs, alternating."""
    with_ = tuple(st.args.values())
    a = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in st.args.items()}
    a["Kc"] = np.zeros((0, *a["Kc"].shape[1:]))
    without = tuple(a.values())
    rep_stage(2, *without)
    rep_stage(2, *with_)
    t0, t1 = [], []
    for _ in range(repeats):
        for args, ts in ((without, t0), (with_, t1)):
            t = time.perf_counter()
            rep_stage(calls, *args)
            ts.append((time.perf_counter() - t) / calls)
    return 1e6 * float(np.median(t0)), 1e6 * float(np.median(t1))


def parts(st, calls, repeats):
    a = twin_args(st)
    u = [a[k] for k in ("u_ref", "u_pend", "u_chan", "u_acc", "u_ring", "u_solve")]
    i = [a[k] for k in ("i_ref", "i_pend", "i_chan", "i_acc", "i_ring", "i_solve")]
    drive, sensed = a["delay"][0], a["sensed"]
    out = {}
    for name, lk, x, o in (("drive", u, drive, a["u_out"]), ("current", i, sensed, a["back"])):
        ref, pend, chan, acc, ring, solve = lk
        out[f"{name} lock-in"] = timed(rep_lockin, (*lk, x, o), calls, repeats)
        r2 = ref.copy()
        out[f"  {name} demod"] = timed(rep_demod, (r2, chan, acc.copy(), x), calls, repeats)
        r2 = ref.copy()
        out[f"  {name} osc advance"] = timed(rep_advance, (r2, 32), calls, repeats)
        out[f"  {name} hop"] = timed(rep_hop, (ref.copy(), acc.copy(), ring.copy()), calls, repeats)
        out[f"  {name} estimate"] = timed(rep_estimate, (ref, acc.copy(), solve), calls, repeats)
    out["products (H)"] = timed(rep_products, (a["u_acc"], a["i_acc"], a["H"], a["scale"], a["est"].copy()),
                                calls, repeats)
    out["wave"] = timed(rep_wave, (a["u_ref"], a["est"], a["wave"].copy()), calls, repeats)
    out["amp + delay"] = timed(rep_amp, (a["est"], a["amp"].copy(), a["delay"].copy(), a["out"]), calls, repeats)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--channels", default="1,16,48,128")
    ap.add_argument("--calls", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--parts", action="store_true")
    a = ap.parse_args(argv)
    f = ghz()
    print(f"clock ~{f:.2f} GHz (dependent float multiply chain)")
    for n_ch in (int(x) for x in a.channels.split(",")):
        for closed in (False, True):
            _, st = rig_stage(n_ch, closed)
            old, new = alternate(st, a.calls, a.repeats)
            cyc = 1e3 * f / (n_ch * 32)
            print(f"{n_ch:4d} ch {'closed ' if closed else 'observe'}: stage {old:7.2f} -> {new:7.2f} us/block "
                  f"(x{old / new:4.2f}), {old * cyc:5.1f} -> {new * cyc:5.1f} cycles per channel-sample")
            off, on = steps_cost(st, a.calls, a.repeats)
            print(f"{'':12s}a drive step's correction: {off:7.2f} -> {on:7.2f} us/block (x{on / off:4.2f})")
            if a.parts:
                for k, v in parts(st, a.calls, a.repeats).items():
                    print(f"      {k:24s} {v:7.2f} us  {v * 1e3 * f / (n_ch * 32):6.1f} cyc/ch-sample")
    return 0


if __name__ == "__main__":
    sys.exit(main())
