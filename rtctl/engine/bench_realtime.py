"""``rtctl bench realtime``: the paced loop against cyclictest on the same period, under the same
load, back to back: deadline misses and wake-up lateness, and what the machine allows.

cyclictest (Debian ``rt-tests``) is the standard measure of how late a Linux machine wakes a
periodic thread: the loop cannot be expected to do better, and should not do much worse. Per
scheduling policy (``SCHED_FIFO`` at ``timing.priority``, then ``SCHED_OTHER``), the loop runs
``rtctl run SCENE --realtime`` for ``--seconds``, then cyclictest runs as many periods.

Both are counted in the loop's currency. A cyclictest wake-up is *late* when it comes later
than the period less the loop's median block time (the slack the loop had); one that is ``L``
late would have cost the loop every block due before it caught up, ``ceil(L / (period -
block time)) - 1`` deadlines (cyclictest itself skips the periods it overslept and counts one
sample). The loop's stalls (runs of consecutive misses) are the counterpart of cyclictest's late
wake-ups. ``--load N`` runs ``stress-ng --cpu N`` through both. Without cyclictest or stress-ng
the bench says so in one line and goes on without them. docs/realtime.md tells how to read it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time

#: The acceptance bounds: the loop's misses at most cyclictest's + 5 under SCHED_FIFO, at most
#: twice cyclictest's + 5 under SCHED_OTHER (which a 2-core VM shares with everything else).
BOUNDS = {"fifo": (1, 5), "other": (2, 5)}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rtctl bench realtime", description=__doc__.splitlines()[0])
    p.add_argument("scene", nargs="?", default="line-bimorph-5", metavar="SCENE",
                   help="scene file or bundled name (default %(default)s)")
    p.add_argument("--seconds", type=float, default=10.0, metavar="S", help="seconds per run (default %(default)s)")
    p.add_argument("--load", type=int, default=0, metavar="N",
                   help="busy processes through both runs: stress-ng --cpu N (default none)")
    p.add_argument("--rounds", type=int, default=3,
                   help="split --seconds into this many alternations of the two (default %(default)s)")
    p.add_argument("--block", type=int, default=32, help="samples per block (default %(default)s)")
    p.add_argument("--policy", choices=("both", "fifo", "other"), default="both",
                   help="scheduling policies to measure (default %(default)s)")
    p.add_argument("--priority", type=int, default=80, help="SCHED_FIFO priority of both (default %(default)s)")
    p.add_argument("--cpu", type=int, default=-1, help="CPU both run on (default any)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene key of the loop's runs (repeatable)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    return p


def parse_cyclictest(text: str) -> dict:
    """cyclictest's ``-q -h N`` output, one thread: ``{"hist": [count per us], "overflows",
    "max", "total"}``."""
    hist, found = [], {}
    for line in text.splitlines():
        m = re.match(r"^(\d+)\s+(\d+)", line)
        if m:
            i = int(m.group(1))
            hist += [0] * (i + 1 - len(hist))
            hist[i] = int(m.group(2))
            continue
        m = re.match(r"^# (Total|Max Latencies|Histogram Overflows):\s*(\d+)", line)
        if m:
            found[m.group(1)] = int(m.group(2))
    if "Max Latencies" not in found:
        raise ValueError("no '# Max Latencies' line: not cyclictest -q -h output")
    return {"hist": hist, "overflows": found.get("Histogram Overflows", 0), "max": found["Max Latencies"],
            "total": found.get("Total", sum(hist) + found.get("Histogram Overflows", 0))}


#: cyclictest's histogram, us: a wake-up later than this is an overflow, counted at this value.
HIST_US = 100_000


def late_wakeups(parsed: dict, threshold_us: float) -> int:
    """Wake-ups at least ``threshold_us`` late (every histogram overflow is)."""
    t = max(0, math.ceil(threshold_us))
    return int(sum(parsed["hist"][t:]) + parsed["overflows"])


def blocks_missed(late_us: float, slack_us: float) -> int:
    """Deadlines a loop with ``slack_us`` to spare per period (period less block time) misses
    when a wake-up is ``late_us`` late: that block and every one that falls due before the
    catch-up, run back to back, is done again."""
    if slack_us <= 0:
        return 1
    return max(0, math.ceil(late_us / slack_us) - 1)


def cyclictest_blocks(parsed: dict, slack_us: float) -> int:
    """The loop's deadline misses that cyclictest's wake-ups stand for (an overflow counted as
    :data:`HIST_US` late: a lower bound)."""
    n = sum(c * blocks_missed(i, slack_us) for i, c in enumerate(parsed["hist"]) if c)
    return int(n + parsed["overflows"] * blocks_missed(len(parsed["hist"]), slack_us))


def hist_percentiles(parsed: dict) -> dict:
    """p50, p99, p99.9 (us, a bucket's lower edge; an overflow counts as the maximum) and max."""
    hist, total = parsed["hist"], parsed["total"]
    out = {}
    for name, q in (("p50", 0.5), ("p99", 0.99), ("p999", 0.999)):
        need, seen, val = q * total, 0, parsed["max"]
        for i, c in enumerate(hist):
            seen += c
            if seen >= need:
                val = i
                break
        out[name] = float(val)
    out["max"] = float(parsed["max"])
    return out


def _loop_run(scene: str, seconds: float, block: int, priority: int, cpu: int, overrides) -> dict:
    """One ``rtctl run --realtime`` in its own process: its summary, and from its trace each run
    block's lateness, block time and whether it missed."""
    import numpy as np

    from ..safety import DEADLINE_MISSED
    from ..trace import TraceReader

    with tempfile.TemporaryDirectory() as d:
        sets = [*overrides, f"timing.duration={seconds}", f"timing.block={block}", f"timing.priority={priority}",
                f"timing.cpu={cpu}"]
        cmd = [sys.executable, "-m", "rtctl.cli", "run", scene, "--realtime", "--json", "--quiet", "--no-plot",
               "--out", d, *[a for s in sets for a in ("--set", s)]]
        p = subprocess.run(cmd, capture_output=True, text=True)
        if p.returncode not in (0, 1) or not p.stdout.strip():
            return {"error": (p.stderr.strip().splitlines() or [f"exit status {p.returncode}"])[-1]}
        s = json.loads(p.stdout)
        n = round(s["duration_s"] * s["fs"] / s["block"])
        r = TraceReader(f"{d}/trace")
        late = np.asarray(r.records["wake_late_us"][:n, 0], dtype=float)
        took = r.compute_us[:n]
        missed = (r.status[:n] & DEADLINE_MISSED) != 0
    return {"summary": s, "late": late, "took": took, "missed": missed}


def _loop_total(parts: list) -> dict:
    import numpy as np

    from .pace import wake_stats

    bad = [p["error"] for p in parts if "error" in p]
    if bad:
        return {"error": bad[0]}
    late, took, missed = (np.concatenate([p[k] for p in parts]) for k in ("late", "took", "missed"))
    last = parts[-1]["summary"]
    out = {"blocks": int(missed.size), "deadline_misses": int(sum(p["summary"]["deadline_misses"] for p in parts)),
           "late_wakeups": int(sum(p["summary"]["late_wakeups"] for p in parts)),
           "overruns": int(sum(p["summary"]["overruns"] for p in parts)),
           "trace_dropped": int(sum(p["summary"]["trace_dropped"] for p in parts)),
           **wake_stats(late, missed),
           "block_time_us": {"p50": float(np.percentile(took, 50)), "p99": float(np.percentile(took, 99)),
                             "max": float(took.max())},
           "realtime": last.get("realtime")}
    return out


def _cyclictest(exe: str, policy: str, priority: int, interval_us: int, loops: int, cpu: int) -> dict:
    # cyclictest's -p (even -p 0) switches its policy to SCHED_FIFO, priority 0 then defaults to 2:
    # under SCHED_OTHER it is left out, and the measuring thread's policy is read back from /proc.
    cmd = [exe, "-q", "-m", "-t", "1", "-i", str(interval_us), "-l", str(loops), "-h", str(HIST_US),
           f"--policy={policy}"]
    if policy == "fifo":
        cmd += ["-p", str(priority)]
    if cpu >= 0:
        cmd += ["-a", str(cpu)]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen = _thread_policy(p)
    out, err = p.communicate()
    try:
        res = {"parsed": parse_cyclictest(out), "cmd": " ".join(cmd)}
    except ValueError:
        why = (err.strip().splitlines() or [f"exit status {p.returncode}"])[-1]
        return {"error": why, "cmd": " ".join(cmd)}
    want = POLICIES[policy]
    if seen is not None and seen != want:
        name = {v: k for k, v in POLICIES.items()}.get(seen, str(seen))
        return {"error": f"cyclictest's measuring thread ran {name}, not {policy}", "cmd": " ".join(cmd)}
    res["thread_policy"] = policy if seen is not None else None
    return res


#: Linux scheduling policy numbers (``/proc/PID/task/TID/stat`` field 41).
POLICIES = {"other": 0, "fifo": 1}


def _thread_policy(p, timeout: float = 2.0):
    """The scheduling policy of the one thread of process ``p`` that is not its main thread
    (cyclictest's measuring thread), read from /proc a moment after it exists (it sets its own
    policy as it starts); None where it cannot be read."""
    t_end = time.monotonic() + timeout
    while p.poll() is None and time.monotonic() < t_end:
        try:
            tids = [t for t in os.listdir(f"/proc/{p.pid}/task") if int(t) != p.pid]
            if tids:
                time.sleep(0.1)
                with open(f"/proc/{p.pid}/task/{tids[0]}/stat") as f:
                    stat = f.read()
                return int(stat[stat.rindex(")") + 2:].split()[38])  # field 41; comm may hold spaces
        except (OSError, ValueError, IndexError):
            return None
        time.sleep(0.005)
    return None


def _cyclictest_total(parts: list, period_us: float, slack_us: float) -> dict:
    bad = [p for p in parts if "error" in p]
    if bad:
        return {"error": bad[0]["error"], "cmd": bad[0]["cmd"]}
    size = max(len(p["parsed"]["hist"]) for p in parts)
    hist = [sum(p["parsed"]["hist"][i] if i < len(p["parsed"]["hist"]) else 0 for p in parts) for i in range(size)]
    parsed = {"hist": hist, "overflows": sum(p["parsed"]["overflows"] for p in parts),
              "max": max(p["parsed"]["max"] for p in parts), "total": sum(p["parsed"]["total"] for p in parts)}
    return {"cmd": parts[0]["cmd"], "interval_us": round(period_us), "loops": parsed["total"],
            "threshold_us": slack_us, "late_wakeups": late_wakeups(parsed, slack_us),
            "deadline_misses": cyclictest_blocks(parsed, slack_us), "latency_us": hist_percentiles(parsed)}


def measure(a) -> dict:
    """Per policy and round, the loop then cyclictest for ``seconds / rounds`` each; rounds
    interleave the policies, so a change in the machine's background load falls on both."""
    from .. import scene as scenes

    sc = scenes.load(a.scene, [*a.overrides, f"timing.block={a.block}"])
    fs, block = float(sc.timing.fs), int(sc.timing.block)
    period_us = 1e6 * block / fs
    if a.seconds / a.rounds < block / fs:  # a round without one whole block measures nothing, a million times
        from ..errors import SceneError

        raise SceneError(f"--seconds {a.seconds:g} over --rounds {a.rounds} leaves {a.seconds / a.rounds:.3g} s a "
                         f"round, less than one block ({period_us:.0f} us); give fewer rounds or more seconds")
    res = {"scene": a.scene, "fs": fs, "block": block, "period_us": period_us, "seconds": a.seconds,
           "rounds": a.rounds, "load": {"cpu": a.load, "tool": None}, "cyclictest": shutil.which("cyclictest"),
           "notes": [], "runs": []}
    if res["cyclictest"] is None:
        res["notes"].append("cyclictest not installed (Debian: rt-tests): the loop runs alone")
    stress = None
    if a.load > 0:
        exe = shutil.which("stress-ng")
        if exe is None:
            res["notes"].append(f"stress-ng not installed (Debian: stress-ng): running without --load {a.load}")
        else:
            stress = subprocess.Popen([exe, "--cpu", str(a.load), "-q"], stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL)
            res["load"]["tool"] = f"stress-ng --cpu {a.load}"
            time.sleep(1.0)  # the workers running before anything is measured
    policies = ("fifo", "other") if a.policy == "both" else (a.policy,)
    each = a.seconds / a.rounds
    loops, cts = {p: [] for p in policies}, {p: [] for p in policies}
    try:
        for _ in range(a.rounds):
            for pol in policies:
                prio = a.priority if pol == "fifo" else 0
                loops[pol].append(_loop_run(a.scene, each, block, prio, a.cpu, a.overrides))
                if res["cyclictest"]:
                    cts[pol].append(_cyclictest(res["cyclictest"], pol, a.priority, round(period_us),
                                                round(each * 1e6 / period_us), a.cpu))
    finally:
        if stress is not None:
            stress.terminate()
            try:
                stress.wait(timeout=10)
            except subprocess.TimeoutExpired:
                stress.kill()
    for pol in policies:
        loop = _loop_total(loops[pol])
        row = {"policy": pol, "priority": a.priority if pol == "fifo" else 0, "loop": loop, "cyclictest": None}
        if cts[pol]:
            slack = period_us - (loop.get("block_time_us") or {}).get("p50", 0.0)
            row["cyclictest"] = _cyclictest_total(cts[pol], period_us, slack)
        _judge(row)
        res["runs"].append(row)
    return res


def _judge(row: dict) -> None:
    lm = row["loop"].get("deadline_misses")
    cm = (row["cyclictest"] or {}).get("deadline_misses")
    if lm is None or cm is None:
        return
    f, plus = BOUNDS[row["policy"]]
    row["ratio"] = lm / cm if cm else None
    row["bound"] = f * cm + plus
    row["within"] = lm <= row["bound"]


def _fmt(x, spec=".0f") -> str:
    return "-" if x is None else format(x, spec)


def _row(policy, who, misses, stalls, late, overrun, lat: dict, note: str) -> str:
    cells = [_fmt(misses, "d"), _fmt(stalls, "d"), _fmt(late, "d"), _fmt(overrun, "d")]
    cells += [_fmt(lat.get(q), ".1f") for q in ("p50", "p99", "p999")] + [_fmt(lat.get("max"))]
    widths = (7, 7, 6, 8, 8, 8, 9, 8)
    return f"{policy:<8}{who:<12}" + "".join(f"{c:>{w}}" for c, w in zip(cells, widths)) + f"  {note}"


def print_table(res: dict) -> None:
    load = res["load"]["tool"] or "no load"
    print(f"{res['scene']}: block {res['block']} at {res['fs']:g} Hz (period {res['period_us']:.1f} us), "
          f"{res['seconds']:g} s each in {res['rounds']} rounds, {load}")
    print(f"{'policy':<8}{'who':<12}{'misses':>7}{'stalls':>7}{'late':>6}{'overrun':>8}{'p50 us':>8}{'p99 us':>8}"
          f"{'p99.9 us':>9}{'max us':>8}  note")
    for r in res["runs"]:
        lp, ct = r["loop"], r["cyclictest"] or {}
        rt = lp.get("realtime") or {}
        note = lp.get("error") or rt.get("sched", "")
        if rt.get("refused"):
            note += "; refused: " + "; ".join(rt["refused"])
        print(_row(r["policy"], "rtctl loop", lp.get("deadline_misses"), lp.get("miss_bursts"), lp.get("late_wakeups"),
                   lp.get("overruns"), lp.get("wake_late_us") or {}, note))
        if ct:
            note = ct.get("error") or (f"stalls: wake-ups >= {ct['threshold_us']:.0f} us late; misses: the blocks "
                                       f"they cost (-i {ct['interval_us']})")
            print(_row("", "cyclictest", ct.get("deadline_misses"), ct.get("late_wakeups"), None, None,
                       ct.get("latency_us") or {}, note))
        if "bound" in r:
            ratio = "-" if r["ratio"] is None else f"{r['ratio']:.2f}"
            f, plus = BOUNDS[r["policy"]]
            print(f"{'':<8}misses loop/cyclictest {ratio}; bound {'' if f == 1 else f'{f} x '}cyclictest + {plus} = "
                  f"{r['bound']}: {'within' if r['within'] else 'OVER'}")


def main(argv=None) -> int:
    a = _parser().parse_args(argv)
    # written so that NaN fails too; at most a day, as a scene's timing.duration
    if not 0 < a.seconds <= 86400 or a.load < 0 or a.rounds < 1 or not 1 <= a.priority <= 99:
        print("rtctl bench realtime: error: --seconds in (0, 86400], --load >= 0, --rounds >= 1 and --priority in "
              "1..99",
              file=sys.stderr)
        return 2
    res = measure(a)
    for n in res["notes"]:
        print(f"rtctl bench realtime: {n}", file=sys.stderr)
    if a.json:
        print(json.dumps(res, indent=1))
    else:
        print_table(res)
    return 0
