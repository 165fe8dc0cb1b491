"""Cost of the simulated bimorph channel group: ns per channel-sample, real-time headroom.

Runs ``SimGroup`` (48 channels, 4 modes, 3-branch finger, amplifier, 2-segment current sense:
16 states) at 48 kHz in blocks of 32, called the way the loop calls it (from a numba function),
and compares with baselines in the same process: the same kernel running the dense fallback
realization (``form="dense"``), a numpy matmul per sample over all channels (dense discrete
model) and ``scipy.signal.dlsim`` per channel. Compile time is reported apart. Beside the
kernel's time: its floating-point operations per channel-sample and the share of the core's
float64 peak they run at (``bench/roofline.py``). Prints one JSON object, then a table.

    python bench/plant.py [--channels 48] [--seconds 2] [--chunk 8]
"""

import argparse
import json
import os
import time

# one BLAS thread before numpy loads: the numpy baseline and the core's peak are one core's
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import roofline  # noqa: E402
import scipy.signal  # noqa: E402
from numba import njit  # noqa: E402

from rtctl.plant import (  # noqa: E402
    BUILTIN,
    TRUTH_NAMES,
    Amplifier,
    BeamSpec,
    BimorphPlant,
    CurrentSense,
    Layer,
    MaxwellLoad,
    SimGroup,
    build_fe,
    sim_group_process,
)

FS, BLOCK = 48000.0, 32


@njit
def _run_blocks(args, drive, sensed, truth, n_blocks):
    status = 0
    for _ in range(n_blocks):
        status |= sim_group_process(*args, drive, sensed, truth)
    return status


def build(n_channels, chunk=8, form="auto"):
    pzt = BUILTIN["PZT-5A"]
    fe = build_fe(BeamSpec(15e-3, 1.5e-3, (Layer(pzt, 0.3e-3), Layer(pzt, 0.3e-3)),
                           "parallel", (0.5, 0.5), 0.01))
    finger = MaxwellLoad(1e-4, 300.0, ((300.0, 0.004), (150.0, 0.07), (80.0, 1.4)))
    plant = BimorphPlant(fe, Amplifier(20e3), CurrentSense(100.0, 15e3), finger, n_modes=4)
    return SimGroup(plant, FS, n_channels, chunk=chunk, form=form)


def output_macs(group):
    """Multiply-adds per channel-sample of the output stage (tiles of the plan + feedthrough)."""
    plan = group.args[5]
    return int(sum(nr * w for nr, w in zip(plan[:, 0], plan[:, 4]))) + \
        int(np.count_nonzero(group.args[4]))


def best_of(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times), float(np.median(times))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--channels", type=int, default=48)
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--chunk", type=int, default=8, help="SimGroup chunk (default: its default)")
    a = ap.parse_args(argv)
    nc = a.channels
    t0 = time.perf_counter()
    group = build(nc, a.chunk)
    build_s = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    drive = np.ascontiguousarray(rng.normal(size=(nc, BLOCK)) * 20.0)
    sensed = np.empty((nc * group.n_seg, BLOCK))
    truth = np.empty((nc, len(TRUTH_NAMES), BLOCK))
    t0 = time.perf_counter()
    _run_blocks(group.args, drive, sensed, truth, 1)
    compile_s = time.perf_counter() - t0

    n_blocks = int(a.seconds * FS / BLOCK)
    best, median = best_of(lambda: _run_blocks(group.args, drive, sensed, truth, n_blocks), 5)
    samples = n_blocks * BLOCK * nc
    ns_kernel = best / samples * 1e9
    med_kernel = median / samples * 1e9
    t0 = time.perf_counter()
    for _ in range(n_blocks // 4):
        group.process(drive, sensed, truth)
    ns_python = (time.perf_counter() - t0) / (n_blocks // 4 * BLOCK * nc) * 1e9

    # Silence after activity: the subnormal flush keeps the cost flat.
    zeros = np.zeros_like(drive)
    _run_blocks(group.args, zeros, sensed, truth, int(2 * FS / BLOCK))
    best_quiet, _ = best_of(lambda: _run_blocks(group.args, zeros, sensed, truth, n_blocks), 3)
    ns_quiet = best_quiet / samples * 1e9

    # Baseline 0: the same kernel on the dense fallback realization (16 x 16 state matrix,
    # dense output matrix), interleaved with the modal runs.
    dense = build(nc, a.chunk, form="dense")
    _run_blocks(dense.args, drive, sensed, truth, 1)
    modal_t, dense_t = [], []
    for _ in range(5):
        modal_t.append(best_of(lambda: _run_blocks(group.args, drive, sensed, truth,
                                                   n_blocks // 4), 1)[0])
        dense_t.append(best_of(lambda: _run_blocks(dense.args, drive, sensed, truth,
                                                   n_blocks // 4), 1)[0])
    ns_dense = float(np.median(dense_t)) / (n_blocks // 4 * BLOCK * nc) * 1e9
    ns_modal_paired = float(np.median(modal_t)) / (n_blocks // 4 * BLOCK * nc) * 1e9

    # Baseline 1: numpy, dense discrete model, all channels per sample (x: states x channels).
    sysd = group.sysd
    A, B, C, D = sysd.A, sysd.B[:, 0], sysd.C, sysd.D[:, 0]
    n_np = int(0.05 * FS)
    u = rng.normal(size=(n_np, nc))
    x = np.zeros((A.shape[0], nc))
    t0 = time.perf_counter()
    for k in range(n_np):
        _ = C @ x + np.outer(D, u[k])
        x = A @ x + np.outer(B, u[k])
    ns_numpy = (time.perf_counter() - t0) / (n_np * nc) * 1e9

    # Baseline 2: scipy.signal.dlsim, one channel at a time.
    n_dl = int(0.05 * FS)
    ud = rng.normal(size=n_dl)
    t0 = time.perf_counter()
    scipy.signal.dlsim((A, sysd.B, C, sysd.D, 1.0 / FS), ud)
    ns_dlsim = (time.perf_counter() - t0) / n_dl * 1e9

    per_second = ns_kernel * 1e-9 * nc * FS
    flops = roofline.plant_flops(group)
    peak = roofline.core_peak_gflops()
    out = {
        "fs": FS, "block": BLOCK, "channels": nc, "states": group.n_states,
        "outputs": len(TRUTH_NAMES) + group.n_seg, "form": group.modal.form,
        "cascade": group.modal.is_cascade, "output_macs_per_channel_sample": output_macs(group),
        "dense_output_macs_per_channel_sample": (len(TRUTH_NAMES) + group.n_seg) * group.n_states,
        "chunk": a.chunk, "modal_cond": group.modal.cond,
        "build_s": build_s, "compile_s": compile_s,
        "ns_per_channel_sample": ns_kernel, "ns_per_channel_sample_median": med_kernel,
        "ns_per_channel_sample_from_python": ns_python,
        "ns_per_channel_sample_after_silence": ns_quiet,
        "plant_share_of_realtime": per_second, "realtime_factor_plant_only": 1.0 / per_second,
        "baseline_dense_kernel_ns": ns_dense, "speedup_vs_dense_kernel": ns_dense / ns_modal_paired,
        "baseline_numpy_ns": ns_numpy, "baseline_dlsim_ns": ns_dlsim,
        "speedup_vs_numpy": ns_numpy / ns_kernel, "speedup_vs_dlsim": ns_dlsim / ns_kernel,
        "flops_per_channel_sample": flops, "core_peak_gflops": peak,
        "ns_per_channel_sample_at_peak": roofline.at_peak_ns(flops["total"], peak),
        "share_of_peak": flops["total"] / ns_kernel / peak,
    }
    print(json.dumps(out))
    print(f"{'what':<42}{'ns / channel-sample':>20}")
    for name, v in (("SimGroup kernel from njit (best)", ns_kernel),
                    ("SimGroup kernel from njit (median)", med_kernel),
                    ("SimGroup.process from Python", ns_python),
                    ("after 2 s of silence (subnormal flush)", ns_quiet),
                    ("same kernel, dense realization (median)", ns_dense),
                    ("numpy matmul per sample (dense)", ns_numpy),
                    ("scipy.signal.dlsim per channel", ns_dlsim)):
        print(f"{name:<42}{v:>20.2f}")
    print(f"{nc} channels x {group.n_states} states ({group.modal.form}"
          f"{', cascade' if group.modal.is_cascade else ''}, {output_macs(group)} output "
          f"multiply-adds per channel-sample): {100 * per_second:.1f} % of one core in real time "
          f"at {FS:.0f} Hz (x{1 / per_second:.0f}); compile {compile_s:.2f} s, build "
          f"{build_s:.2f} s")
    print(f"{flops['total']} flops per channel-sample (recursion {flops['recursion']}, outputs "
          f"{flops['outputs']}, ADC {flops['adc']}): {flops['total'] / ns_kernel:.1f} GFLOP/s, "
          f"{100 * out['share_of_peak']:.0f} % of the core's float64 peak ({peak:.1f} GFLOP/s, "
          f"dgemm on one thread); at the peak {out['ns_per_channel_sample_at_peak']:.2f} ns per "
          f"channel-sample")


if __name__ == "__main__":
    main()
