"""Speed of the kernels with and without one fastmath flag, side by side.

Each variant runs in child processes of its own, with its own numba cache directory and
``rtctl._numba.FASTMATH`` set before any kernel is decorated: the house set, and the house set
without ``--drop`` (default ``reassoc``). A first child per variant compiles (not timed); then
``--repeats`` rounds alternate the variants, so both see the same machine load, and the figures
are medians over the rounds. Per child: ``rtctl run SCENE`` (its real-time factor, as ``rtctl
run --json`` reports it) for every bundled scene, and ``bench/loop.py --quick``'s three rigs (48
bimorph channels at block 32: open loop, observer on, closed loop); each also as a CPU-time
factor (simulated time over the thread's CPU time for the same blocks), which a machine shared
with other processes leaves far less noisy than the wall clock.

    python bench/fastmath.py [--drop reassoc] [--repeats 3] [--scenes a,b] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

CHILD = """
import json, sys, tempfile
import rtctl._numba as N
if sys.argv[1] != "null":
    N.FASTMATH = frozenset(json.loads(sys.argv[1]))
sys.path.insert(0, {bench!r})
from loop import scene_for, time_rig
from rtctl import scene
from rtctl.engine.rig import build
from rtctl.engine.run import run
import time


def cpu_rtf(rig, n_blocks, schedule=True):
    # simulated seconds per second of this thread's CPU time over n_blocks of advance: time the
    # OS gave other processes is not counted (the wall-clock factor of a loaded machine is mostly that)
    t0 = time.thread_time()
    for k in range(n_blocks):
        if schedule:
            rig.apply_schedule(k)
        rig.advance()
    return n_blocks * rig.block / rig.fs / (time.thread_time() - t0)


# the CPU time of the run's loop thread (Loop.run, in this thread): every block of the run with
# its fade and settle tail, as `rtctl run` runs them; the drain thread's trace writing aside
from rtctl.engine import loop as _loop
_real_run, _cpu = _loop.Loop.run, {{}}


def _timed_run(self, *a, **kw):
    t0 = time.thread_time()
    res = _real_run(self, *a, **kw)
    _cpu["rtf"] = self.rig.blocks * self.rig.block / self.rig.fs / (time.thread_time() - t0)
    return res


_loop.Loop.run = _timed_run
out = {{}}
for name in json.loads(sys.argv[2]):
    s = scene.load(name)
    with tempfile.TemporaryDirectory() as tmp:
        out[name + " (run, wall)"] = run(s, out_dir=tmp, plot=False, report=False).summary["realtime_factor"]
    out[name + " (run, cpu)"] = _cpu["rtf"]
    rig = build(s)
    out[name + " (cpu)"] = cpu_rtf(rig, int(s.timing.duration * s.timing.fs / s.timing.block))
for label, kw in (("loop48 open", {{}}), ("loop48 observer", {{"observe": True}}),
                  ("loop48 closed", {{"closed": True}})):
    rig = build(scene_for(48, 32, **kw))
    rig.apply_schedule(0)
    out[label + " (wall)"] = time_rig(rig, 0.6)[0]
    out[label + " (cpu)"] = cpu_rtf(rig, 1500, schedule=False)
print(json.dumps(out))
"""


def child(flags, scenes, cache: str, pythonpath: str | None = None) -> dict:
    """One child's figures: ``flags`` the fastmath set (None: the package's own), the package
    from ``pythonpath`` (default: as this process finds it), its numba cache in ``cache``."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    if pythonpath is not None:  # and run there: `python -c` puts its working directory first on sys.path
        env["PYTHONPATH"] = pythonpath
    p = subprocess.run([sys.executable, "-c", CHILD.format(bench=str(HERE)),
                        "null" if flags is None else json.dumps(sorted(flags)), json.dumps(scenes)],
                       env=env, capture_output=True, text=True, check=True, cwd=pythonpath)
    return json.loads(p.stdout.splitlines()[-1])


def main(argv=None) -> int:
    from rtctl import _numba, scene

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drop", default="reassoc", help="the flag left out of the house set")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scenes", help="comma-separated scene names (default: every bundled scene)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    scenes = a.scenes.split(",") if a.scenes else scene.bundled()
    house = set(_numba.FASTMATH)
    variants = {"house": house, f"no {a.drop}": house - {a.drop}}
    runs: dict[str, list[dict]] = {v: [] for v in variants}
    with tempfile.TemporaryDirectory(prefix="rtctl-fastmath-") as tmp:
        caches = {v: os.path.join(tmp, f"cache{i}") for i, v in enumerate(variants)}
        for v, flags in variants.items():  # compile, untimed
            child(flags, scenes, caches[v])
        for _ in range(a.repeats):
            for v, flags in variants.items():
                runs[v].append(child(flags, scenes, caches[v]))
    keys = list(runs["house"][0])
    med = {v: {k: float(np.median([r[k] for r in rs])) for k in keys} for v, rs in runs.items()}
    other = f"no {a.drop}"
    report = {"flags": {v: sorted(f) for v, f in variants.items()}, "repeats": a.repeats, "median_rtf": med,
              "ratio": {k: med[other][k] / med["house"][k] for k in keys}, "runs": runs}
    print(json.dumps(report, indent=1))
    if not a.json:
        print(f"\n{'':34}{'house':>9}{other:>14}{'ratio':>8}   (median real-time factors of {a.repeats} "
              "alternating rounds)")
        for k in keys:
            print(f"{k:34}{med['house'][k]:9.1f}{med[other][k]:14.1f}{report['ratio'][k]:8.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
