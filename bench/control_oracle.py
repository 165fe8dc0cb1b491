"""What no controller can beat after a finger event: the closed-loop sweep's tones driven by an
oracle that knows the device.

``bench/control_sweep.py`` judges the closed loop's settle time and overshoot after each finger
event against max(5 periods, 50 ms) and 10 %. Part of what it finds is the beam's: a finger that
lifts off multiplies the amplitude at the held drive before any loop can see it, and a drive
changed at the right moment to the right value still rings in the beam's loaded modes. This bench
separates the two. Every tone of the sweep runs open loop on the same device, through the same
events, and at each event an oracle (reading the device's secret, as the sweep's referee does)
moves each sine's amplitude to what puts the new load's tip exactly on the target, ramped over one
block:

* ``at event``: in the event's own block (clairvoyant: no controller that is not told of the
  event can do this);
* ``next block``: one block later, the first block whose drive a loop could set after reading
  the event's block (no loop that reads its device one block at a time acts sooner);
* ``after warm``: ``WARM`` blocks later, when the closed loop's observer first holds a window
  with nothing of the old load in it (the earliest a correction on a clean estimate can come).

Per tone and segment it prints the time to stay within 5 % of the target and the overshoot of
each, with the same windows as the sweep (``report.against_target``). Where even the oracle at the
event misses a clause, that miss is the beam's, not the loop's; where the oracle in the next block
misses it, no loop that acts on what it has read meets it (the block's); where the oracle after
warm misses it, no loop that waits for a clean window meets it. ``--against FILE`` (``control_sweep.py
--json`` output) adds the closed loop's figures and sorts its misses by these two.

    python bench/control_oracle.py [--quick] [--against SWEEP.json] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import control_sweep as cs
import numpy as np


def _warm_blocks(device: dict) -> list[int]:
    """Per sweep tone, the closed loop's WARM (blocks from a command to a window of nothing
    older): what the controller of the sweep's scene waits for."""
    from rtctl import scene
    from rtctl.control._kernels import WARM
    from rtctl.engine.rig import build

    rig = build(scene.load(cs.SCENE, [*cs.overrides(device, calibrated=False), "events=[]", "timing.duration=0.1"]))
    out = []
    for bank in rig.stimulus.bank_index:
        ctl, j = rig.controlled[bank[0]]
        out.append(int(ctl.state[WARM, j]))
    return out


def oracle(device: dict, delays: list[int]) -> dict:
    """One open-loop run of the sweep's tones on ``device``: each sine's amplitude set for the
    target by the device's own response under the finger of each segment, moved ``delays[n]``
    blocks after each event. Returns the true tip (um), its times (s) and the event times."""
    from rtctl import scene
    from rtctl.dsp._kernels import P_AMP, P_FLAG, P_RAMP
    from rtctl.engine.rig import build
    from rtctl.events import block_of

    s = scene.load(cs.SCENE, [*cs.overrides(device, calibrated=False), "control.mode=open", "control.observe=false"])
    fs, block = s.timing.fs, s.timing.block
    vmax = s.actuator[0].max_voltage
    rig = build(s)
    g = cs.gains(device)
    tid = rig.queue.target_id(rig.bank.pending)

    def amplitudes(seg: int, n: int) -> np.ndarray:
        target = cs.TONES[n][2] * 1e-6
        gain = g[seg][n] * 1e-6  # m/V per sine
        return np.minimum(target / gain.size / gain, vmax / gain.size)  # out of reach: the cap

    moves: dict[int, list] = {0: [(0, n) for n in range(len(cs.TONES))]}
    ev_blocks = [block_of(at, fs, block) for at, _ in cs.EVENTS]
    for seg, kb in enumerate(ev_blocks, start=1):
        for n, d in enumerate(delays):
            moves.setdefault(kb + d, []).append((seg, n))
    n_blocks = int(round(cs.DURATION * fs)) // block
    tip = np.zeros((len(cs.TONES), n_blocks * block))
    for k in range(n_blocks):
        rig.apply_schedule(k)
        for seg, n in moves.get(k, ()):
            bank = rig.stimulus.bank_index[n]
            for b, a in zip(bank, amplitudes(seg, n)):
                rig.queue.post(tid, P_AMP, b, a)
                rig.queue.post(tid, P_RAMP, b, float(block))
                rig.queue.post(tid, P_FLAG, b, 1.0)
        rig.queue.publish()
        rig.advance()
        tip[:, k * block:(k + 1) * block] = rig.truth[:len(cs.TONES), 0, :] * 1e6
    return {"tip": tip, "t": np.arange(tip.shape[1]) / fs, "events": [kb * block / fs for kb in ev_blocks]}


#: Blocks after the event at which the oracle also moves the drive: how soon a loop would have to
#: act to meet what the oracle after ``WARM`` misses (0 and 1 are ``at event`` and ``next block``).
LADDER = (0, 1, 2, 4, 8, 16, 32)


def figures(device: dict) -> list[dict]:
    """Per tone, per event segment: the oracle's settle time and overshoot at the event, in the
    next block, after each of ``LADDER``'s delays and after the closed loop's WARM."""
    from rtctl import scene
    from rtctl.engine import report

    vmax = scene.load(cs.SCENE).actuator[0].max_voltage
    g = cs.gains(device)
    warm = _warm_blocks(device)
    ladder = {d: oracle(device, [d] * len(cs.TONES)) for d in LADDER}
    runs = {"at_event": ladder[0], "next_block": ladder[1], "after_warm": oracle(device, warm)}
    ends = runs["at_event"]["events"][1:] + [cs.DURATION]
    rows = []
    for n, (f, b, target) in enumerate(cs.TONES):
        freqs = list(cs._freqs(f, b))
        for i, t0 in enumerate(runs["at_event"]["events"], start=1):
            row = {"device": cs.label(device), "freq_hz": f, "beat_hz": b, "target_um": target,
                   "segment": cs.SEGMENTS[i], "warm_blocks": warm[n],
                   "reachable": target <= cs.reach(g[i][n], vmax),
                   "required_ms": 1e3 * max(5.0 / (b or f), 0.05)}
            for name, r in runs.items():
                row[name] = report.against_target(r["tip"][n], r["t"], freqs, t0, ends[i - 1], target)
            row["ladder"] = {d: report.against_target(r["tip"][n], r["t"], freqs, t0, ends[i - 1], target)
                             for d, r in ladder.items()}
            rows.append(row)
    return rows


def _acts_by(row: dict, clause: str) -> int | None:
    """The latest of ``LADDER``'s delays (blocks) up to which the oracle meets ``clause`` at every
    delay; None if it misses it at the event."""
    last = None
    for d in LADDER:
        if clause in _misses(row["ladder"][d], row["required_ms"]):
            break
        last = d
    return last


def _misses(fig: dict, required: float) -> set:
    out = set()
    if cs.late(fig["settle_ms"], required):
        out.add("settle")
    if not fig["overshoot_pct"] < cs.OVERSHOOT_PCT:
        out.add("overshoot")
    return out


def _closed(sweep: dict) -> dict:
    """The sweep's calibrated segments by (device, freq, beat, target, segment)."""
    out = {}
    for c in sweep["cases"]:
        if not c["calibrated"]:
            continue
        for r in c["tones"]:
            for sg in r["segments"]:
                out[(c["label"], r["freq_hz"], r["beat_hz"], r["target_um"], sg["segment"])] = sg
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the sweep's five devices instead of all 33")
    ap.add_argument("--against", help="control_sweep.py --json output: sort its misses by the oracle's")
    ap.add_argument("--json", action="store_true", help="print only the JSON object")
    a = ap.parse_args(argv)
    rows = []
    for dev in cs.devices(a.quick):
        rows += figures(dev)
        if not a.json:
            print(f"  {cs.label(dev)}: done", file=sys.stderr)
    closed = _closed(json.loads(Path(a.against).read_text())) if a.against else {}
    counts = {"closed": 0, "beam": 0, "block": 0, "latency": 0, "loop": 0}
    acts: dict[int, int] = {}  # the latency class by how soon the oracle must act to meet them
    for r in rows:
        if not r["reachable"]:
            continue
        sg = closed.get((r["device"], r["freq_hz"], r["beat_hz"], r["target_um"], r["segment"]))
        if sg is None:
            continue
        r["closed"] = {"settle_ms": sg["settle_ms"], "overshoot_pct": sg["overshoot_pct"]}
        got, beam, block, late = (_misses(x, r["required_ms"])
                                  for x in (r["closed"], r["at_event"], r["next_block"], r["after_warm"]))
        r["closed_misses"] = {m: "beam" if m in beam else "block" if m in block else "latency" if m in late
                              else "loop" for m in sorted(got)}
        counts["closed"] += len(got)
        for m, why in r["closed_misses"].items():
            counts[why] += 1
            if why == "latency":
                by = _acts_by(r, m)
                acts[by] = acts.get(by, 0) + 1
    result = {"rows": rows, "closed_misses": counts if closed else None,
              "latency_acts_by_blocks": {str(d): acts[d] for d in sorted(acts)} if closed else None}
    print(json.dumps(result, indent=1))
    if a.json:
        return 0
    print()
    print(f"{'device':<28}{'tone':<12}{'segment':<8}{'req ms':>7}  {'at event':<16}{'next block':<16}"
          f"{'after warm':<18}{'closed loop':<16}closed-loop misses")
    print(f"{'':<28}{'':<12}{'':<8}{'':>7}  " + f"{'settle ms ovs%':<16}" * 3 + f"  {'settle ms ovs%':<16}")

    def cell(x):
        return f"{cs.fmt(x['settle_ms'], '.0f'):>6} {x['overshoot_pct']:+8.1f}  "

    for r in rows:
        if not r["reachable"]:
            continue
        tone = f"{r['freq_hz']:g}" + (f"/{r['beat_hz']:g}" if r["beat_hz"] else "") + " Hz"
        why = ", ".join(f"{m}: {w}" for m, w in r.get("closed_misses", {}).items())
        print(f"{r['device']:<28}{tone:<12}{r['segment']:<8}{r['required_ms']:7.0f}  {cell(r['at_event'])}"
              f"{cell(r['next_block'])}{cell(r['after_warm'])}  {cell(r['closed']) if 'closed' in r else '':<16}{why}")
    if closed:
        print(f"\nclosed-loop misses after events: {counts['closed']}; the oracle at the event misses them too "
              f"(the beam's): {counts['beam']}; the oracle in the next block does (no loop acting on what it has read "
              f"meets them): {counts['block']}; only the oracle after WARM does (no loop waiting for a clean "
              f"window meets them): {counts['latency']}; the oracle meets them (the loop's own): {counts['loop']}")
        from rtctl import scene

        timing = scene.load(cs.SCENE).timing
        block_ms = 1e3 * timing.block / timing.fs
        for d in sorted(acts):
            later = LADDER.index(d) + 1
            then = f"not after {LADDER[later]}" if later < len(LADDER) else "still after it"
            print(f"  {acts[d]} of those the oracle meets acting up to {d} blocks ({d * block_ms:.1f} ms) after "
                  f"the event, {then}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
