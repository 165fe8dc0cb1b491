"""Benchmark of the rtctl.dsp kernels at the loop's block size, against naive numpy in-process.

Prints one JSON object, then a table (``--json``: only the JSON). Kernel times are taken the way
the loop runs them: from an ``@njit`` driver that steps many blocks (no Python call per block).
The numpy baselines do the same work per block with vectorized numpy (sin/cos per sample).
Compile times are measured apart, with an empty numba cache.

    python bench/dsp.py [--json] [--blocks N]
"""

import argparse
import atexit
import json
import os
import shutil
import sys
import tempfile
import time

if "NUMBA_CACHE_DIR" not in os.environ:  # an empty cache, so compile times are real
    os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="rtctl-bench-numba-")
    atexit.register(shutil.rmtree, os.environ["NUMBA_CACHE_DIR"], ignore_errors=True)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import numpy as np  # noqa: E402
from numba import njit  # noqa: E402

from rtctl.dsp import LockIn, OscillatorBank, PulseTrain  # noqa: E402
from rtctl.dsp import _kernels as K  # noqa: E402

FS = 48000.0
BLOCK = 32


# ---- njit drivers: many blocks per call, as the loop's block step would -------------------------
@njit(nogil=True)
def drive_osc(state, pending, chan, out, n_blocks, mode):
    """mode 0: steady; 1: new amplitude every block; 2: new frequency every block."""
    nt = state.shape[1]
    for b in range(n_blocks):
        out[:] = 0.0
        if mode == 1:
            for i in range(nt):
                pending[K.P_AMP, i] = 0.5 + 0.25 * (b & 1)
                pending[K.P_FLAG, i] = 1.0
        elif mode == 2:
            for i in range(nt):
                pending[K.P_FREQ, i] = 200.0 + i + 10.0 * (b & 1)
                pending[K.P_FLAG, i] = 1.0
        K.osc_bank_process(state, pending, chan, out)


@njit(nogil=True)
def drive_pulse(state, pending, out, n_blocks):
    for _ in range(n_blocks):
        out[:] = 0.0
        K.pulse_process(state, pending, out)


@njit(nogil=True)
def drive_lockin(ref, pending, chan, acc, ring, solve, x, out, n_blocks):
    for _ in range(n_blocks):
        K.lockin_process(ref, pending, chan, acc, ring, solve, x, out)


def best_time(fn, repeat=5):
    """Minimum wall time of ``fn()`` over ``repeat`` runs (the least disturbed one)."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def first_call(fn):
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


# ---- numpy baselines: same work per block, vectorized over tones and samples ----------------
def numpy_osc(n_tones, n_blocks):
    chan = np.arange(n_tones) % 48
    inc = (200.0 + np.arange(n_tones)) / FS
    amp = np.ones(n_tones)
    phase = np.zeros(n_tones)
    k = np.arange(BLOCK)
    out = np.zeros((48, BLOCK))
    for _ in range(n_blocks):
        out[:] = 0.0
        y = amp[:, None] * np.cos(2 * np.pi * (phase[:, None] + inc[:, None] * k))
        np.add.at(out, chan, y)
        phase = (phase + inc * BLOCK) % 1.0


def numpy_pulse(n_ch, n_blocks):
    pos = np.zeros(n_ch)
    inc = (100.0 + np.arange(n_ch)) / FS
    duty = np.full(n_ch, 0.5)
    k = np.arange(BLOCK)
    out = np.zeros((n_ch, BLOCK))
    for _ in range(n_blocks):
        p = (pos[:, None] + inc[:, None] * k) % 1.0
        out[:] = np.where(p < duty[:, None], 1.0, 0.0)
        pos = (pos + inc * BLOCK) % 1.0


def numpy_lockin(n_ch, n_freq, window, n_blocks):
    n_slots = n_ch * n_freq
    inc = (200.0 + np.arange(n_slots)) / FS
    phase = np.zeros(n_slots)
    chan = np.repeat(np.arange(n_ch), n_freq)
    ring = np.zeros((window // BLOCK, n_slots), complex)
    s = np.zeros(n_slots, complex)
    k = np.arange(BLOCK)
    x = np.random.default_rng(0).standard_normal((n_ch, BLOCK))
    for b in range(n_blocks):
        ref = np.exp(-2j * np.pi * (phase[:, None] + inc[:, None] * k))
        part = np.sum(x[chan] * ref, axis=1)
        idx = b % ring.shape[0]
        s += part - ring[idx]
        ring[idx] = part
        phase = (phase + inc * BLOCK) % 1.0
        _ = 2.0 / window * np.abs(s), np.angle(s)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print only the JSON object")
    ap.add_argument("--blocks", type=int, default=20000, help="blocks per timed kernel run")
    args = ap.parse_args()
    nb = args.blocks
    nb_np = max(200, nb // 20)  # numpy is slow: fewer blocks, per-sample figures stay comparable
    rows = []
    compile_s = {}

    for n_tones in (48, 128):
        chan = np.arange(n_tones) % 48
        bank = OscillatorBank(48, chan, FS, 200.0 + np.arange(n_tones), 1.0, ramp=BLOCK)
        out = np.zeros((48, BLOCK))
        if not compile_s:
            compile_s["osc_bank_process"] = first_call(lambda bank=bank, out=out: drive_osc(*bank.args, out, 1, 0))
        np_ns = best_time(lambda n_tones=n_tones: numpy_osc(n_tones, nb_np), 3) / (nb_np * BLOCK * n_tones) * 1e9
        for mode, label in ((0, "steady"), (1, "amp change every block"), (2, "freq change every block")):
            bank.reset()
            secs = best_time(lambda bank=bank, out=out, mode=mode: drive_osc(*bank.args, out, nb, mode))
            ns = secs / (nb * BLOCK * n_tones) * 1e9
            rows.append(dict(kernel="osc_bank_process", case=f"{n_tones} tones, {label}", unit="ns/tone-sample",
                             ns=ns, numpy_ns=np_ns, speedup=np_ns / ns))

    train = PulseTrain(48, FS, 100.0 + np.arange(48), 0.5)
    out = np.zeros((48, BLOCK))
    compile_s["pulse_process"] = first_call(lambda: drive_pulse(*train.args, out, 1))
    ns = best_time(lambda: drive_pulse(*train.args, out, nb)) / (nb * BLOCK * 48) * 1e9
    np_ns = best_time(lambda: numpy_pulse(48, nb_np), 3) / (nb_np * BLOCK * 48) * 1e9
    rows.append(dict(kernel="pulse_process", case="48 channels", unit="ns/channel-sample",
                     ns=ns, numpy_ns=np_ns, speedup=np_ns / ns))

    window = 4800
    lock = LockIn(48, 200.0 + np.arange(96).reshape(48, 2), FS, window, hop=BLOCK)
    x = np.random.default_rng(0).standard_normal((48, BLOCK))
    est = np.zeros((48, 2, 2))
    compile_s["lockin_process"] = first_call(lambda: drive_lockin(*lock.args, x, est, 1))
    ns = best_time(lambda: drive_lockin(*lock.args, x, est, nb)) / (nb * BLOCK * 96) * 1e9
    np_ns = best_time(lambda: numpy_lockin(48, 2, window, nb_np), 3) / (nb_np * BLOCK * 96) * 1e9
    rows.append(dict(kernel="lockin_process", case=f"48 ch x 2 freq, W={window}", unit="ns/slot-sample",
                     ns=ns, numpy_ns=np_ns, speedup=np_ns / ns))

    steady48 = rows[0]["ns"]
    result = dict(
        fs=FS,
        block=BLOCK,
        blocks_timed=nb,
        results=rows,
        compile_s=compile_s,
        # share of the 20 ns per channel-sample budget of the whole block step (48 tones / 48 ch)
        osc_share_of_budget=steady48 / 20.0,
    )
    print(json.dumps(result, indent=None if args.json else 2))
    if args.json:
        return
    print()
    print(f"{'kernel':18s} {'case':32s} {'ns':>7s} {'numpy ns':>9s} {'speedup':>8s}  unit")
    for r in rows:
        print(f"{r['kernel']:18s} {r['case']:32s} {r['ns']:7.3f} {r['numpy_ns']:9.2f} {r['speedup']:8.1f}  {r['unit']}")
    print("compile (s, empty cache): " + ", ".join(f"{k} {v:.2f}" for k, v in compile_s.items()))


if __name__ == "__main__":
    main()
