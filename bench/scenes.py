"""Real-time factor of every bundled scene, this checkout against another, side by side.

    python bench/scenes.py [--against DIR] [--repeats 3] [--scenes a,b] [--json]

``DIR`` is another source tree of the package (e.g. ``git worktree add /tmp/old HEAD~3``, or a
``git archive`` of it unpacked): each tree runs in child processes of its own, with its own numba
cache; a first child per tree compiles (not timed), then ``--repeats`` rounds alternate the
trees so both see the same machine load, and the figures are medians over the rounds. Per
scene: the wall-clock factor of ``rtctl run`` (as ``rtctl run --json`` reports it) and the
CPU-time factor of the same blocks (simulated time over the thread's CPU time: on a machine
shared with other processes the wall clock mostly measures them); and ``bench/loop.py
--quick``'s three rigs (48 bimorph channels at block 32). Without ``--against``: this checkout
alone.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
from fastmath import child

HERE = Path(__file__).resolve().parent


def main(argv=None) -> int:
    from rtctl import scene

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", help="another source tree of the package (the directory holding rtctl/)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scenes", help="comma-separated scene names (default: every bundled scene)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    scenes = a.scenes.split(",") if a.scenes else scene.bundled()
    trees = {"this": str(HERE.parent)}
    if a.against:
        trees["against"] = str(Path(a.against).resolve())
    runs: dict[str, list[dict]] = {t: [] for t in trees}
    with tempfile.TemporaryDirectory(prefix="rtctl-scenes-") as tmp:
        caches = {t: os.path.join(tmp, t) for t in trees}
        for t, path in trees.items():  # compile, untimed
            child(None, scenes, caches[t], path)
        for _ in range(a.repeats):
            for t, path in trees.items():
                runs[t].append(child(None, scenes, caches[t], path))
    keys = list(runs["this"][0])
    med = {t: {k: float(np.median([r[k] for r in rs])) for k in keys} for t, rs in runs.items()}
    report = {"trees": trees, "repeats": a.repeats, "median_rtf": med, "runs": runs}
    if a.against:
        report["speedup"] = {k: med["this"][k] / med["against"][k] for k in keys}
    print(json.dumps(report, indent=1))
    if not a.json:
        head = f"{'':34}{'this':>9}" + (f"{'against':>10}{'speed-up':>10}" if a.against else "")
        print(f"\n{head}   (median real-time factors of {a.repeats} alternating rounds)")
        for k in keys:
            row = f"{k:34}{med['this'][k]:9.1f}"
            if a.against:
                row += f"{med['against'][k]:10.1f}{report['speedup'][k]:10.2f}"
            print(row)
    return 0


if __name__ == "__main__":
    sys.exit(main())
