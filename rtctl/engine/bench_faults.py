"""``rtctl bench faults``: fault campaigns. N seeded runs of every bundled scene (open and closed
loop), each with faults drawn at random (``io.faults``), each trace checked sample by sample
(:func:`rtctl.check.check_trace`), each fault's outcome compared with the one it must have
(:func:`rtctl.io.faults.expected`, docs/faults.md).

The rig of a scene is built once and run again for every seed (a run's faults are loaded into
the simulated device between runs), so a run costs its blocks, not a build. A failing seed is
printed with the one ``rtctl run`` command that reproduces it.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

#: (scene, extra overrides): every bundled scene as it is (the closed-loop one under control)
DEFAULT_DURATION = 0.25
BEYOND = ("nonfinite", "voltage", "slew", "mean", "temperature", "fade", "end")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rtctl bench faults", description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=20, metavar="N", help="seeded runs per scene (default %(default)s)")
    p.add_argument("--seed", type=int, default=1, help="first seed (default %(default)s)")
    p.add_argument("--faults", type=int, default=3, metavar="K", help="at most K faults per run (1..K by seed; "
                   "default %(default)s)")
    p.add_argument("--duration", type=float, default=DEFAULT_DURATION, metavar="S",
                   help="seconds per run (default %(default)s)")
    p.add_argument("--scenes", default="", help="comma-separated scene names (default: every bundled scene)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    return p


def overrides(duration: float, seed: int, n_faults: int) -> list[str]:
    """The ``--set`` items of one campaign run (its events dropped: they are tied to the scene's
    own length)."""
    return [f"timing.duration={duration:g}", "events=[]", f"io.faults.random={n_faults}", f"io.faults.seed={seed}"]


def command(name: str, sets: list[str]) -> str:
    """The ``rtctl run`` command that reproduces a run."""
    return "rtctl run " + name + "".join(f" --set '{s}'" for s in sets) + " --out out/fault-repro"


def judge(faults, ctx, status, summary) -> dict:
    """Compare one run's faults with what the run shows.

    The run must end on the first fault that ends runs (a stopped device at its block; the xrun
    guard at the block the documented bucket overflows, :func:`rtctl.io.faults.xrun_fault_block`)
    and on no other; each flagging fault that began before the end must show its bit from its
    block on (a NaN/inf reading hidden on every block by a dropped block or a stopped device
    excepted: that reading never arrived). Returns per injected fault (one that began before the
    run ended) its expected outcome and whether it was detected, the run's outcome (``fade``,
    ``flag`` when a flagging fault's bit was seen, else ``ride``) and what is wrong, in words."""
    from .. import safety
    from ..io.faults import expected, xrun_fault_block

    ended = int(round(summary["duration_s"] * summary["fs"] / summary["block"]))
    faulted = bool(summary["faults"])
    ends = [(f.start, safety.DEVICE_LOST, f.kind) for f in faults if f.kind == "device_stopped"]
    fire = xrun_fault_block(faults, ctx)
    if fire is not None:
        ends.append((fire, safety.XRUN_BURST, "xrun guard"))
    want = min(ends) if ends else None
    if want is not None and want[0] >= ctx.n_blocks:
        want = None
    problems, injected, flagged = [], [], False
    if want is not None:
        at, bit, what = want
        if not faulted:
            problems.append(f"{what} at block {at}: the run did not end on it")
        elif ended != at + 1 or not status[at] & bit:
            problems.append(f"{what} should end the run at block {at} with {safety.STATUS_NAMES[bit]!r}; it ended at "
                            f"block {ended - 1}: " + "; ".join(summary["faults"]))
    elif faulted:
        problems.append("the run ended on a fault no injected fault calls for: " + "; ".join(summary["faults"]))
    silent = {k for f in faults if f.kind in ("block_dropped", "xrun_burst", "device_stopped")
              for k in range(f.start, ctx.n_blocks if f.kind == "device_stopped" else f.start + max(1, f.blocks))}
    for f in sorted(faults, key=lambda f: f.start):
        if f.start >= ended:
            continue  # the run ended (on an earlier fault) before this one began
        outcome, bit = expected(f, ctx)
        if outcome == "fade":   # judged above, for the run
            hit = want is not None and f.start <= want[0] and faulted and bool(status[ended - 1] & bit)
            if f.kind == "xrun_burst" and (want is None or want[2] != "xrun guard"):
                outcome, bit = "flag", safety.IO_XRUN   # ended by another fault first
        if outcome == "flag":
            seen = status[f.start:ended] & bit
            if f.kind in ("sensed_nan", "sensed_inf"):
                live = [k for k in range(f.start, min(f.stop, ended)) if k not in silent]
                if not live:
                    outcome, bit = "ride", 0   # never delivered: a dropped block or a stopped device took it
                seen = status[live] & bit if live else seen[:0]
            hit = bool(bit) and bool((seen != 0).any())
            flagged |= hit
            if bit and not hit:
                problems.append(f"{f.kind} at block {f.start}: no {safety.STATUS_NAMES[bit]!r} seen")
        elif outcome == "ride":
            hit = False
        injected.append({"kind": f.kind, "start": f.start, "expected": outcome, "detected": hit})
    outcome = "fade" if faulted else "flag" if flagged else "ride"
    return {"injected": injected, "outcome": outcome, "problems": problems}


def campaign(name: str, runs: int, seed0: int, max_faults: int, duration: float, say=None) -> dict:
    """``runs`` seeded runs of scene ``name``; its row of the table, with the failing seeds."""
    from .. import scene as scenes
    from ..check import TraceUnreadable, check_trace
    from .rig import build
    from .run import run

    base = overrides(duration, seed0, max_faults)
    t0 = time.perf_counter()
    rig = build(scenes.load(name, base))
    build_s = time.perf_counter() - t0
    inj = rig.device.faults
    row = {"scene": name, "control": rig.scene.control.mode, "runs": 0, "faults_injected": 0, "faults_detectable": 0,
           "faults_detected": 0, "outcomes": {"ride": 0, "flag": 0, "fade": 0}, "mismatched": 0,
           "samples_beyond_limits": 0, "unreadable_traces": 0, "build_s": round(build_s, 2), "failing": [],
           "by_kind": {}}
    tmp = Path(tempfile.mkdtemp(prefix="rtctl-faults-"))
    from ..io.faults import plan

    try:
        for i in range(runs):
            seed = seed0 + i
            n = 1 + (seed % max(1, max_faults))
            sets = overrides(duration, seed, n)
            sc = scenes.load(name, sets)
            faults = plan(sc, inj.ctx)
            inj.load(faults)
            out = tmp / f"run-{seed}"
            why = []
            res = run(sc, out_dir=out, plot=False, rig=rig)
            try:
                rep = check_trace(out)
            except TraceUnreadable as e:
                rep = None
                row["unreadable_traces"] += 1
                why.append(f"trace unreadable: {e}")
            if rep is not None:
                beyond = sum(rep["violations"][k] for k in BEYOND)
                row["samples_beyond_limits"] += beyond
                if rep["violations"]["records"] or rep["violations"]["summary"]:
                    row["unreadable_traces"] += 1
                why += [f"{k}: {rep['first'][k]}" for k, v in rep["violations"].items() if v]
                import numpy as np

                from ..trace import TraceReader

                status = np.asarray(TraceReader(out / "trace").status, dtype=np.int64)
                j = judge(faults, inj.ctx, status, res.summary)
                why += j["problems"]
                row["outcomes"][j["outcome"]] += 1
                row["mismatched"] += bool(j["problems"])
                for f in j["injected"]:
                    row["faults_injected"] += 1
                    k = row["by_kind"].setdefault(f["kind"], {"injected": 0, "ride": 0, "flag": 0, "fade": 0,
                                                              "detected": 0})
                    k["injected"] += 1
                    k[f["expected"]] += 1
                    if f["expected"] != "ride":
                        row["faults_detectable"] += 1
                        row["faults_detected"] += f["detected"]
                        k["detected"] += f["detected"]
            row["runs"] += 1
            if why:
                row["failing"].append({"seed": seed, "faults": [f.to_dict() for f in faults], "why": why,
                                       "command": command(name, sets)})
            shutil.rmtree(out, ignore_errors=True)
            if say is not None:
                say(f"{name}: {i + 1}/{runs}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    row["wall_s"] = round(time.perf_counter() - t0, 2)
    return row


def main(argv=None) -> int:
    """Exit 0 when every run kept every limit, every trace was readable and every fault had the
    outcome it must have; 1 otherwise."""
    a = _parser().parse_args(argv)
    from .. import scene as scenes
    from ..errors import RtctlError

    if a.runs < 1 or a.faults < 1 or not (0 < a.duration <= 60):
        print("rtctl bench faults: error: --runs and --faults must be >= 1 and --duration in (0, 60] s",
              file=sys.stderr)
        return 2
    names = [s for s in a.scenes.split(",") if s] or scenes.bundled()
    say = None if a.json or not sys.stderr.isatty() else (lambda m: print(f"\r{m:<60}", end="", file=sys.stderr))
    rows, t0 = [], time.perf_counter()
    for name in names:
        try:
            rows.append(campaign(name, a.runs, a.seed, a.faults, a.duration, say))
        except RtctlError as e:
            print(f"rtctl bench faults: error: {name}: {e}", file=sys.stderr)
            return 2
    if say is not None:
        print("\r" + " " * 62 + "\r", end="", file=sys.stderr)
    keys = ("runs", "faults_injected", "faults_detectable", "faults_detected", "mismatched", "samples_beyond_limits",
            "unreadable_traces")
    total = {k: sum(r[k] for r in rows) for k in keys}
    total["outcomes"] = {o: sum(r["outcomes"][o] for r in rows) for o in ("ride", "flag", "fade")}
    total["wall_s"] = round(time.perf_counter() - t0, 1)
    failing = [{"scene": r["scene"], **f} for r in rows for f in r["failing"]]
    result = {"runs_per_scene": a.runs, "first_seed": a.seed, "max_faults": a.faults, "duration_s": a.duration,
              "scenes": [{k: v for k, v in r.items() if k != "failing"} for r in rows], "total": total,
              "failing": failing}
    if a.json:
        print(json.dumps(result, indent=1))
    else:
        _table(result)
    return 0 if not failing else 1


def _table(result) -> None:
    head = f"{'scene':<24}{'ctl':<7}{'runs':>5}{'faults':>7}{'detect':>9}{'ride':>6}{'flag':>6}{'fade':>6}" \
           f"{'wrong':>6}{'beyond':>7}{'unread':>7}{'wall s':>8}"
    print(head)
    print("-" * len(head))
    for r in result["scenes"] + [{"scene": "total", "control": "", **result["total"]}]:
        o = r["outcomes"]
        print(f"{r['scene']:<24}{r['control']:<7}{r['runs']:>5}{r['faults_injected']:>7}"
              f"{str(r['faults_detected']) + '/' + str(r['faults_detectable']):>9}{o['ride']:>6}{o['flag']:>6}"
              f"{o['fade']:>6}{r['mismatched']:>6}{r['samples_beyond_limits']:>7}{r['unreadable_traces']:>7}"
              f"{r['wall_s']:>8}")
    print("detect: faults whose status bit was seen / faults that must show one; wrong: runs whose outcome "
          "differs from docs/faults.md;\nbeyond: samples beyond a limit (must be 0); unread: traces unreadable "
          "(must be 0)")
    for f in result["failing"]:
        print(f"FAIL {f['scene']} seed {f['seed']}: {'; '.join(f['why'])}\n  {f['command']}")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
