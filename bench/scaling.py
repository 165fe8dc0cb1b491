"""Real-time factor against channel count and modes per channel, open and closed loop.

The demo scene's bimorph (3-branch finger, amplifier, 2-segment current sense; one tone per
channel) at block 32 and 48 kHz, ``actuator.lateral.beam.modes`` from 2 to 12 and 1 to 1024
channels; per configuration the CPU-time factor of ``Rig.advance`` (simulated time over this
thread's CPU time: the wall clock of a shared machine mostly measures the other processes) and
the wall-clock one, open loop and closed loop (observer + controller per channel). Reports the
largest channel count that runs at 1.5x real time or more (50 % headroom on one core) and, per
configuration, the CPU time per channel-sample.

    python bench/scaling.py [--channels 1,16,64,256,1024] [--modes 2,4,8,12] [--blocks 300] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from loop import scene_for  # noqa: E402

FS, BLOCK = 48000.0, 32


def measure(channels: int, modes: int, closed: bool, blocks: int) -> dict:
    from rtctl import scene
    from rtctl.engine.rig import build

    s = scene_for(channels, BLOCK, closed=closed)
    s = scene.load("line-bimorph-5", [*s.overrides, f"actuator.lateral.beam.modes={modes}"])
    rig = build(s)
    rig.apply_schedule(0)
    for _ in range(20):
        rig.advance()
    w0, c0 = time.perf_counter(), time.thread_time()
    for _ in range(blocks):
        rig.advance()
    cpu, wall = time.thread_time() - c0, time.perf_counter() - w0
    sim = blocks * BLOCK / FS
    return {"channels": channels, "modes": modes, "closed": closed, "cpu_rtf": sim / cpu, "wall_rtf": sim / wall,
            "ns_per_channel_sample": 1e9 * cpu / (blocks * BLOCK * channels),
            "states_per_channel": int(rig.device.groups[0][0].n_states)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--channels", default="1,16,64,256,1024")
    ap.add_argument("--modes", default="2,4,8,12")
    ap.add_argument("--blocks", type=int, default=300, help="timed blocks per configuration")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    chans = [int(x) for x in a.channels.split(",")]
    modes = [int(x) for x in a.modes.split(",")]
    rows = []
    for closed in (False, True):
        for m in modes:
            for c in chans:
                try:
                    r = measure(c, m, closed, max(20, a.blocks // max(1, c // 64)))
                except Exception as e:  # noqa: BLE001 - a configuration the engine cannot build: say which
                    print(f"  {'closed' if closed else 'open  '} modes {m:2d} {c:5d} ch: cannot run "
                          f"({type(e).__name__}: {str(e).splitlines()[0]})", file=sys.stderr, flush=True)
                    continue
                rows.append(r)
                if not a.json:
                    print(f"  {'closed' if closed else 'open  '} modes {m:2d} ({r['states_per_channel']} states) "
                          f"{c:5d} ch: CPU x{r['cpu_rtf']:8.2f}  wall x{r['wall_rtf']:8.2f}  "
                          f"{r['ns_per_channel_sample']:7.1f} ns per channel-sample", file=sys.stderr, flush=True)
    largest = {}
    for closed in (False, True):
        for m in modes:
            ok = [r["channels"] for r in rows if r["closed"] == closed and r["modes"] == m and r["cpu_rtf"] >= 1.5]
            largest[f"{'closed' if closed else 'open'} modes {m}"] = max(ok) if ok else 0
    print(json.dumps({"fs": FS, "block": BLOCK, "rows": rows, "largest_channels_at_1.5x": largest}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
