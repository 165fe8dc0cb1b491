"""``rtctl bench control``: closed-loop tracking error and settle time against block size (the
control rate), with the real-time factor of each run beside them: error against run time."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

BLOCKS = (16, 32, 64, 128, 256)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rtctl bench control", description=__doc__.splitlines()[0])
    p.add_argument("scene", nargs="?", default="line-bimorph-5", metavar="SCENE",
                   help="scene file or bundled name (default %(default)s); run with control.mode = closed")
    p.add_argument("--blocks", default=",".join(map(str, BLOCKS)),
                   help="block sizes, comma-separated (default %(default)s)")
    p.add_argument("--duration", type=float, default=1.5, metavar="S", help="seconds per run (default %(default)s)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene key (repeatable)")
    p.add_argument("--out", metavar="DIR", help="write control.json and control.png here")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    return p


def measure(scene_name: str, blocks, duration: float, overrides=()) -> dict:
    """One closed-loop run per block size; per controlled, reachable channel the true amplitude's
    error against its target, the estimate's error against the truth and the settle time."""
    from .. import scene as scenes
    from .run import run

    rows = []
    for b in blocks:
        sc = scenes.load(scene_name, [*overrides, "control.mode=closed", f"timing.block={b}",
                                      f"timing.duration={duration}"])
        s = _run(run, sc)
        fs = s["fs"]
        chans = [c for c in s["channels"] if c.get("controlled") and not c.get("saturated")
                 and c.get("error_pct") is not None]
        rows.append({
            "block": b, "control_rate_hz": fs / b, "block_ms": 1e3 * b / fs,
            "realtime_factor": s["realtime_factor"], "block_time_us_p99": s["block_time_us"]["p99"],
            "channels": [{"name": c["name"], "freq_hz": c["freq_hz"], "error_pct": c["error_pct"],
                          "estimate_error_pct": c.get("estimate_error_pct"), "settle_ms": c["settle_ms"]}
                         for c in chans],
            "max_abs_error_pct": max((abs(c["error_pct"]) for c in chans), default=math.nan),
            "max_settle_ms": max((c["settle_ms"] or math.inf for c in chans), default=math.nan),
            "saturated": [c["name"] for c in s["channels"] if c.get("saturated")],
        })
    return {"scene": scene_name, "duration_s": duration, "runs": rows}


def _run(run, sc):
    import tempfile

    with tempfile.TemporaryDirectory() as d:  # the report needs the trace; nothing is kept
        return run(sc, out_dir=d, plot=False).summary


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = result["runs"]
    names = sorted({c["name"] for r in runs for c in r["channels"]})
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    for n in names:
        pts = [(r["block"], c) for r in runs for c in r["channels"] if c["name"] == n]
        lab = f"{n} ({pts[0][1]['freq_hz']:g} Hz)"
        ax[0].plot([b for b, _ in pts], [abs(c["error_pct"]) for _, c in pts], "o-", label=lab)
        ax[1].plot([b for b, _ in pts], [c["settle_ms"] or math.nan for _, c in pts], "o-", label=lab)
    ax[2].plot([r["block"] for r in runs], [r["realtime_factor"] for r in runs], "ks-")
    for a, y in zip(ax, ("|true - target| / target, %", "settle (5 % band), ms", "real-time factor")):
        a.set_xscale("log", base=2)
        a.set_xlabel("block, samples")
        a.set_ylabel(y)
        a.grid(True, alpha=0.3)
    ax[0].legend(fontsize=7)
    fig.suptitle(f"{result['scene']}: closed-loop error and settle against block size (control rate)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    a = _parser().parse_args(argv)
    try:
        blocks = [int(x) for x in a.blocks.split(",") if x.strip()]
        if not blocks:  # nothing to measure: an empty table and an empty plot
            raise ValueError
    except ValueError:
        print(f"rtctl bench control: error: --blocks {a.blocks!r}: give block sizes like 16,32,64", file=sys.stderr)
        return 2
    if a.out is not None:  # before the runs, not after them
        from ..outpath import writable_dir

        out = writable_dir(a.out, "--out", files=("control.json", "control.png"))
    res = measure(a.scene, blocks, a.duration, a.overrides)
    if a.out is not None:
        (out / "control.json").write_text(json.dumps(res, indent=1))
        plot(res, out / "control.png")
    if a.json:
        print(json.dumps(res, indent=1))
        return 0
    print(f"{'block':>6} {'rate Hz':>8} {'RTF':>7} {'max |err| %':>12} {'max settle ms':>14}  saturated")
    for r in res["runs"]:
        print(f"{r['block']:6d} {r['control_rate_hz']:8.0f} {r['realtime_factor']:7.1f} {r['max_abs_error_pct']:12.2f} "
              f"{r['max_settle_ms']:14.1f}  {', '.join(r['saturated']) or '-'}")
    return 0
