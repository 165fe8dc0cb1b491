"""Runs of blocks in one compiled call against one call per block from Python, same process.

    python bench/runs.py [--scenes a,b] [--repeats 5] [--realtime] [--json]

Per scene, one rig is built and run (``rtctl.engine.run.run`` with that rig, the trace written as
``rtctl run`` writes it) alternately with the loop's runs of blocks (rtctl/engine/chunk.py) and
with ``RTCTL_BLOCK_RUNS=0`` (one block per call from Python, what backends with Python I/O do),
``--repeats`` times each. Figures: medians of the wall-clock real-time factor (``realtime_factor``)
and of the CPU-time factor of the loop's thread (``cpu_realtime_factor``: simulated time over that
thread's CPU time, which a machine shared with other processes disturbs less), and their ratios.
With ``--realtime`` the runs are paced and the figures are the deadline misses instead.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile

import numpy as np


def main(argv=None) -> int:
    from rtctl import scene
    from rtctl.engine.rig import build
    from rtctl.engine.run import run

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", help="comma-separated scene names (default: every bundled scene)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--realtime", action="store_true", help="paced runs: count deadline misses")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    names = a.scenes.split(",") if a.scenes else scene.bundled()
    keys = ("deadline_misses", "miss_bursts") if a.realtime else ("realtime_factor", "cpu_realtime_factor")
    report = {}
    for name in names:
        sc = scene.load(name, a.overrides)
        rig = build(sc)
        got = {"runs": {k: [] for k in keys}, "python": {k: [] for k in keys}}
        with tempfile.TemporaryDirectory(prefix="rtctl-runs-") as tmp:
            for _ in range(a.repeats):
                for mode in ("python", "runs"):
                    os.environ["RTCTL_BLOCK_RUNS"] = "0" if mode == "python" else "1"
                    s = run(sc, tmp, realtime=a.realtime, plot=False, report=False, rig=rig).summary
                    for k in keys:
                        got[mode][k].append(float(s.get(k, 0)))
        os.environ.pop("RTCTL_BLOCK_RUNS", None)
        med = {m: {k: float(np.median(v)) for k, v in d.items()} for m, d in got.items()}
        report[name] = {"median": med, "all": got}
        if not a.realtime:
            report[name]["ratio"] = {k: med["runs"][k] / med["python"][k] for k in keys}
    print(json.dumps(report, indent=1))
    if not a.json:
        print(f"\n{'':26}" + "".join(f"{m + ' ' + k:>32}" for m in ("python", "runs") for k in keys))
        for name, r in report.items():
            cells = "".join(f"{r['median'][m][k]:32.1f}" for m in ("python", "runs") for k in keys)
            print(f"{name:26}{cells}" + ("" if a.realtime else "   x" + " / x".join(
                f"{r['ratio'][k]:.2f}" for k in keys)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
