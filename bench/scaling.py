"""Real-time factor against channel count and modes per channel, open and closed loop.

The demo scene's bimorph (3-branch finger, amplifier, 2-segment current sense; one tone per
channel) at block 32 and 48 kHz, ``actuator.lateral.beam.modes`` from 2 to 12 and 1 to 1024
channels; per configuration the CPU-time factor of ``Rig.advance`` (simulated time over this
thread's CPU time: the wall clock of a shared machine mostly measures the other processes) and
the wall-clock one, open loop and closed loop (the group's observer and controller stages), and
the rig's build time (the observer's design; numba compiling or loading the composed block
function). Reports the largest channel count that runs at 1.5x real time or more (50 % headroom
on one core) and, per configuration, the CPU time per channel-sample beside the machine's limit:
the simulated plant's floating-point operations per channel-sample and the time they take at the
core's float64 peak (``bench/roofline.py``; the observer, controller, oscillators and limiter
come on top of it).

    python bench/scaling.py [--channels 1,16,64,256,1024] [--modes 2,4,8,12] [--blocks 300]
                            [--loops open,closed] [--per-channel-upto N] [--rounds 3] [--json]

``--per-channel-upto N``: closed-loop configurations of up to N channels are also run with a
controller stage per channel (tests/per_channel_rig.py, as the rig was before one controller
served a group), in the same process, timed interleaved with the group controller's.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

# one BLAS thread before numpy loads: the core's peak is one core's
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))
import roofline  # noqa: E402
from loop import scene_for  # noqa: E402

FS, BLOCK = 48000.0, 32


def _timed(rig, blocks: int) -> tuple[float, float]:
    """(CPU seconds, wall seconds) of ``blocks`` calls of ``rig.advance``."""
    w0, c0 = time.perf_counter(), time.thread_time()
    for _ in range(blocks):
        rig.advance()
    return time.thread_time() - c0, time.perf_counter() - w0


def measure(channels: int, modes: int, closed: bool, blocks: int, twin: bool = False, rounds: int = 3) -> dict:
    """One configuration; ``twin``: also the closed loop with a controller stage per channel
    (tests/per_channel_rig.py, the arrangement before one controller served a group), built
    and timed in this process, its timed stretches interleaved with the rig's."""
    from rtctl import scene
    from rtctl.engine.rig import build

    s = scene_for(channels, BLOCK, closed=closed)
    s = scene.load("line-bimorph-5", [*s.overrides, f"actuator.lateral.beam.modes={modes}"])
    rigs, builds = [], []
    for make in [build] + ([_per_channel_rig] if twin else []):
        t0 = time.perf_counter()
        rigs.append(make(s))
        builds.append(time.perf_counter() - t0)
    for rig in rigs:
        rig.apply_schedule(0)
        for _ in range(20):
            rig.advance()
    cpu, wall = [0.0] * len(rigs), [0.0] * len(rigs)
    for k in range(rounds):  # interleaved, the order alternating: both see the same machine load
        for i in (range(len(rigs)) if k % 2 == 0 else reversed(range(len(rigs)))):
            c, w = _timed(rigs[i], -(-blocks // rounds))
            cpu[i], wall[i] = cpu[i] + c, wall[i] + w
    sim = rounds * -(-blocks // rounds) * BLOCK / FS
    out = {"channels": channels, "modes": modes, "closed": closed, "cpu_rtf": sim / cpu[0], "wall_rtf": sim / wall[0],
           "ns_per_channel_sample": 1e9 * cpu[0] / (sim * FS * channels), "build_s": builds[0],
           "states_per_channel": int(rigs[0].device.groups[0][0].n_states),
           "plant_flops_per_channel_sample": roofline.plant_flops(rigs[0].device.groups[0][0])["total"]}
    if twin:
        out.update(per_channel_build_s=builds[1], per_channel_cpu_rtf=sim / cpu[1], per_channel_wall_rtf=sim / wall[1])
    return out


def _per_channel_rig(s):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from per_channel_rig import PerChannelRig

    return PerChannelRig(s)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--channels", default="1,16,64,256,1024")
    ap.add_argument("--modes", default="2,4,8,12")
    ap.add_argument("--blocks", type=int, default=300, help="timed blocks per configuration")
    ap.add_argument("--loops", default="open,closed", help="which of open, closed to measure")
    ap.add_argument("--per-channel-upto", type=int, default=0,
                    help="closed loop up to this many channels: also a controller per channel, in this process")
    ap.add_argument("--rounds", type=int, default=3, help="timed stretches per configuration (interleaved)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    loops = [x == "closed" for x in a.loops.split(",")]
    chans = [int(x) for x in a.channels.split(",")]
    modes = [int(x) for x in a.modes.split(",")]
    rows = []
    peak = roofline.core_peak_gflops()
    if not a.json:
        print(f"core's float64 peak (dgemm, one thread): {peak:.1f} GFLOP/s", file=sys.stderr, flush=True)
    for closed in loops:
        for m in modes:
            for c in chans:
                try:
                    r = measure(c, m, closed, max(20, a.blocks // max(1, c // 64)), closed and c <= a.per_channel_upto,
                                a.rounds)
                except Exception as e:  # noqa: BLE001 - a configuration the engine cannot build: say which
                    print(f"  {'closed' if closed else 'open  '} modes {m:2d} {c:5d} ch: cannot run "
                          f"({type(e).__name__}: {str(e).splitlines()[0]})", file=sys.stderr, flush=True)
                    continue
                r["plant_ns_at_peak"] = roofline.at_peak_ns(r["plant_flops_per_channel_sample"], peak)
                rows.append(r)
                if not a.json:
                    print(f"  {'closed' if closed else 'open  '} modes {m:2d} ({r['states_per_channel']} states) "
                          f"{c:5d} ch: CPU x{r['cpu_rtf']:8.2f}  wall x{r['wall_rtf']:8.2f}  "
                          f"{r['ns_per_channel_sample']:7.1f} ns per channel-sample (the plant's "
                          f"{r['plant_flops_per_channel_sample']} flops at the peak: {r['plant_ns_at_peak']:4.1f})  "
                          f"build {r['build_s']:6.1f} s"
                          + (f"  | a controller per channel: CPU x{r['per_channel_cpu_rtf']:8.2f} wall "
                             f"x{r['per_channel_wall_rtf']:8.2f} build {r['per_channel_build_s']:6.1f} s"
                             if "per_channel_cpu_rtf" in r else ""), file=sys.stderr, flush=True)
    largest = {}
    for closed in loops:
        for m in modes:
            ok = [r["channels"] for r in rows if r["closed"] == closed and r["modes"] == m and r["cpu_rtf"] >= 1.5]
            largest[f"{'closed' if closed else 'open'} modes {m}"] = max(ok) if ok else 0
    print(json.dumps({"fs": FS, "block": BLOCK, "core_peak_gflops": peak, "rows": rows,
                      "largest_channels_at_1.5x": largest}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
