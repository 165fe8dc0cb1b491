"""CPU time per block of the switched-pin kernel: the one generated for the model's switch pattern
(``HybridGroup.kernel``) against the generic ``hybrid_process``, on a scene's own drive.

Runs the scene once with the simulated device outside the block function, keeping the drive every
hybrid group receives; then replays those blocks through both kernels in one process, alternating
which goes first, and reports the means of the per-block minima over the passes (a block
preempted in one pass counts with its time from another) and whether every output and state
agreed bitwise.

    python bench/hybrid.py [--scenes dot-4x4,solenoid-3x3,bimodal-4x4] [--passes 3]
"""

import argparse
import time

import numpy as np

from rtctl import scene
from rtctl.engine.rig import build
from rtctl.plant.hybrid import HybridGroup, hybrid_process


def record(name):
    s = scene.load(name)
    rig = build(s, device_in_block=False)
    dev, drives = rig.device, []
    write = dev.write

    def keep():
        drives.append(dev._drive.copy())
        return write()

    dev.write = keep
    for k in range(int(s.timing.duration * s.timing.fs / s.timing.block)):
        rig.apply_schedule(k)
        rig.advance()
    return rig, np.array(drives)


def compare(name, passes):
    rig, drives = record(name)
    for (kern, args), (g, ch, _) in zip(rig.device._calls, rig.device.groups):
        if not isinstance(g, HybridGroup):
            continue
        g.reset()
        state, (drive, sensed, truth) = args[:-3], args[-3:]
        runs = [(fn, [a.copy() if a.flags.writeable else a for a in state], sensed.copy(), truth.copy())
                for fn in (hybrid_process, kern)]
        t = np.full((2, len(drives)), np.inf)
        same = True
        for p in range(passes):
            for _, a, _, _ in runs:
                for x, x0 in zip(a, state):
                    if x.flags.writeable:
                        x[...] = x0
            for k, d in enumerate(drives):
                drive[...] = d[ch]
                for i in ((0, 1) if (k + p) % 2 else (1, 0)):
                    fn, a, sv, tv = runs[i]
                    t0 = time.thread_time()
                    fn(*a, drive, sv, tv)
                    t[i, k] = min(t[i, k], time.thread_time() - t0)
                if p == 0:
                    same &= all(np.array_equal(x, y) for x, y in zip(runs[0][2:], runs[1][2:]))
                    same &= all(np.array_equal(x, y) for x, y in zip(runs[0][1], runs[1][1]))
        us = t.mean(axis=1) * 1e6
        print(f"{name:14} {type(g).__name__:14} generic {us[0]:7.1f} us/block  generated {us[1]:7.1f} "
              f"us/block  x{us[0] / us[1]:.2f}  bitwise the same: {same}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="dot-4x4,solenoid-3x3,bimodal-4x4")
    ap.add_argument("--passes", type=int, default=3)
    a = ap.parse_args(argv)
    for name in a.scenes.split(","):
        compare(name, a.passes)


if __name__ == "__main__":
    main()
