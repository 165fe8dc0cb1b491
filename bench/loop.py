"""Real-time factor of the whole block step: synthesis + simulated plant + limiter.

With the self-sensing observer off and on (``control.observe``: lock-in of drive and segment
currents, observer matrices, tip waveform) and in closed loop (``control.mode = "closed"``: the
group's one observer stage with a lock-in window per channel, and its one controller stage), for
1, 16, 48 and 128 bimorph channels (the demo scene's beam: 4 modes, 3-branch finger, amplifier,
2-segment current sense; one tone per channel) at blocks of 16, 32, 64 and 256 samples at 48 kHz,
times ``Rig.advance`` (read, ``@njit`` step, write: everything the loop does per block except the
trace) and, in the same process, a plain numpy implementation of the same step (``np.cos``
synthesis, ``np.clip`` and a per-sample slew loop, the same discrete plant as a dense matmul per
sample, numpy noise and quantization).

Compile time is measured apart, in child processes with an empty and then a warm numba cache
(``NUMBA_CACHE_DIR``), so it shows both the cold cost and what caching saves across runs.

    python bench/loop.py [--json] [--seconds 0.5] [--quick]

Prints one JSON object (``--json``: only that), then a table.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

FS = 48000.0
CHANNELS = (1, 16, 48, 128)
BLOCKS = (16, 32, 64, 256)


def scene_for(n_channels: int, block: int, observe: bool = False, closed: bool = False):
    from rtctl import scene

    rng = np.random.default_rng(n_channels)
    freqs = rng.uniform(20.0, 900.0, n_channels)
    tones = ", ".join(f"{{channel = {i}, freq = {f:.3f}, voltage = 20.0}}" for i, f in enumerate(freqs))
    rows = -(-n_channels // 64)  # a grid side is at most 64
    assert n_channels % rows == 0
    return scene.load("line-bimorph-5", [
        f"actuator.lateral.grid=[{rows}, {n_channels // rows}]", f"timing.block={block}", f"stimulus.tones=[{tones}]",
        "timing.duration=3600", f"control.observe={'true' if observe else 'false'}",
        f"control.mode={'closed' if closed else 'open'}",
    ])


def time_rig(rig, seconds: float, repeats: int = 3) -> tuple[float, float]:
    """(real-time factor, p99 block time us) of ``rig.advance``: the median over ``repeats``
    runs of ~``seconds`` / ``repeats`` wall time each (the machines are noisy; one unlucky
    stretch should not set the figure), p99 over all blocks."""
    for _ in range(50):
        rig.advance()
    period = rig.block / rig.fs
    times, rtfs = [], []
    for _ in range(repeats):
        n = 0
        t_end = time.perf_counter() + seconds / repeats
        t0 = time.perf_counter()
        while time.perf_counter() < t_end or n < 30:
            a = time.perf_counter_ns()
            rig.advance()
            times.append(time.perf_counter_ns() - a)
            n += 1
        rtfs.append(n * period / (time.perf_counter() - t0))
    return float(np.median(rtfs)), float(np.percentile(times, 99)) * 1e-3


class NumpyStep:
    """The same block step in plain numpy: what one would write without numba."""

    def __init__(self, rig):
        group = rig.device.groups[0][0]
        sysd = group.sysd
        self.A, self.B, self.C, self.D = sysd.A, sysd.B[:, 0], sysd.C, sysd.D[:, 0]
        self.n = rig.n_channels
        self.block = rig.block
        self.fs = rig.fs
        self.freq = np.array([t.freq for t in rig.tones])
        self.amp = np.array([t.voltage for t in rig.tones])
        self.phase = np.zeros(self.n)
        self.x = np.zeros((self.A.shape[0], self.n))
        self.v_prev = np.zeros(self.n)
        p = rig.limiter.params
        self.vmax, self.dvmax = p[0], p[1]
        s = group.sense
        self.lsb, self.noise, self.shunt = s.lsb_v, s.noise_rms_v, s.shunt_ohm
        self.rng = np.random.default_rng(0)

    def step(self):
        n, b = self.n, self.block
        k = np.arange(b)
        ph = self.phase[:, None] + self.freq[:, None] * k / self.fs
        out = self.amp[:, None] * np.cos(2 * np.pi * ph)
        self.phase = (self.phase + self.freq * b / self.fs) % 1.0
        out = np.clip(out, -self.vmax[:, None], self.vmax[:, None])
        for i in range(b):  # slew limit is a recursion over samples
            dv = np.clip(out[:, i] - self.v_prev, -self.dvmax, self.dvmax)
            out[:, i] = self.v_prev = self.v_prev + dv
        y = np.empty((self.C.shape[0], n, b))
        for i in range(b):
            y[:, :, i] = self.C @ self.x + np.outer(self.D, out[:, i])
            self.x = self.A @ self.x + np.outer(self.B, out[:, i])
        sensed = y[4:] * self.shunt + self.rng.normal(0.0, self.noise, y[4:].shape)
        sensed = np.round(sensed / self.lsb) * self.lsb / self.shunt
        return out, sensed, y[:4]


def time_numpy(rig, seconds: float) -> float:
    step = NumpyStep(rig)
    step.step()
    period = rig.block / rig.fs
    n = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds or n < 5:
        step.step()
        n += 1
    return n * period / (time.perf_counter() - t0)


def compile_times() -> dict:
    """Build the 48-channel rig in fresh processes: empty numba cache, then the warm one."""
    here = os.path.dirname(os.path.abspath(__file__))
    code = (f"import time; t = time.perf_counter(); import sys; sys.path.insert(0, {here!r}); "
            "from loop import scene_for; from rtctl.engine.rig import build; build(scene_for(48, 32)); "
            "print(time.perf_counter() - t)")
    out = {}
    with tempfile.TemporaryDirectory() as d:
        env = dict(os.environ, NUMBA_CACHE_DIR=d)
        for key in ("compile_s", "cached_build_s"):
            r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
            out[key] = float(r.stdout.strip().splitlines()[-1])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print only the JSON object")
    ap.add_argument("--seconds", type=float, default=0.9, help="wall time per configuration")
    ap.add_argument("--quick", action="store_true", help="48 channels at block 32 only")
    a = ap.parse_args(argv)
    from rtctl.engine.rig import build

    configs = [(48, 32)] if a.quick else [(c, b) for c in CHANNELS for b in BLOCKS]
    results = []
    for c, b in configs:
        rig = build(scene_for(c, b))
        obs_rig = build(scene_for(c, b, observe=True))
        cl_rig = build(scene_for(c, b, closed=True))  # observer (a window per channel) + controller
        for r in (rig, obs_rig, cl_rig):
            r.apply_schedule(0)  # every tone (every controller) on from the first block
        # interleaved, so all see the same machine load; mean RTF, worst p99
        trips = [tuple(time_rig(r, a.seconds / 3) for r in (rig, obs_rig, cl_rig)) for _ in range(2)]
        rtf, o_rtf, c_rtf = (float(np.mean([p[i][0] for p in trips])) for i in (0, 1, 2))
        p99, o_p99, c_p99 = (max(p[i][1] for p in trips) for i in (0, 1, 2))
        np_rtf = time_numpy(rig, min(a.seconds, 0.3))
        results.append({"channels": c, "block": b, "realtime_factor": rtf, "block_time_us_p99": p99,
                        "observer_realtime_factor": o_rtf, "observer_block_time_us_p99": o_p99,
                        "closed_loop_realtime_factor": c_rtf, "closed_loop_block_time_us_p99": c_p99,
                        "block_period_us": 1e6 * b / FS, "numpy_realtime_factor": np_rtf,
                        "speedup_vs_numpy": rtf / np_rtf})
        if not a.json:
            print(f"  {c:4d} ch  block {b:4d}: x{rtf:7.1f}, observer on x{o_rtf:7.1f}, closed loop x{c_rtf:7.1f} "
                  f"(numpy x{np_rtf:6.2f})", file=sys.stderr)
    report = {"fs": FS, "results": results, **compile_times(),
              "states_per_channel": build(scene_for(1, 32)).device.groups[0][0].n_states}
    print(json.dumps(report, indent=1))
    if not a.json:
        print()
        print(f"{'channels':>8} {'block':>6} {'RTF':>8} {'p99 us':>8} {'observer on':>12} {'p99 us':>8} "
              f"{'closed loop':>12} {'p99 us':>8} {'period us':>10} {'numpy RTF':>10} {'speed-up':>9}")
        for r in results:
            print(f"{r['channels']:8d} {r['block']:6d} {r['realtime_factor']:8.1f} {r['block_time_us_p99']:8.1f} "
                  f"{r['observer_realtime_factor']:12.1f} {r['observer_block_time_us_p99']:8.1f} "
                  f"{r['closed_loop_realtime_factor']:12.1f} {r['closed_loop_block_time_us_p99']:8.1f} "
                  f"{r['block_period_us']:10.1f} {r['numpy_realtime_factor']:10.2f} {r['speedup_vs_numpy']:9.1f}")
        print(f"compile (empty cache) {report['compile_s']:.1f} s; "
              f"build with warm cache {report['cached_build_s']:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
