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
* ``first read``: ``latency + 1`` blocks later (``first_read``): the device delivers a block's
  currents ``latency`` blocks after it (the I/O latency), and a controller sets the amplitudes of
  the block after the one it reads in, so this is the first block whose drive a loop could set
  after reading anything of the event (two blocks on ``sim``; the ladder's one block later is
  clairvoyant too);
* ``after warm``: ``WARM`` blocks later, when the closed loop's observer first holds a window
  with nothing of the old load in it (the earliest a correction on a clean estimate can come).

Per tone and segment it prints the time to stay within 5 % of the target and the overshoot of
each, with the same windows as the sweep (``report.against_target``). Where even the oracle at the
event misses a clause, that miss is the beam's, not the loop's; where the oracle at the first read
misses it, no loop that steps its drive on what it has read meets it (the block's); where only the
oracle after warm misses it, no loop that waits for a clean window meets it (latency).

What the currents tell by then (``information``): the same held drive run noise-free with and
without the event, and the difference of the sensed currents a loop has read by the time it sets
each ``LADDER`` delay's drive, over the sensor noise (the scene's rms noise and the ADC's
quantization): ``d' = sqrt(sum of squared differences) / noise``. It is what an ideal test that
knows both loads has to decide the event on (its error probability is ``Phi(-d'/2)``), and one
over it is the best relative precision with which any estimator places the new load between the
two. A latency miss with a large d' at the delay the oracle must act by is within reach in
principle of a loop that tests each block's currents for the event; 0 means nothing of the event
has been read yet. ``--against FILE`` (``control_sweep.py --json`` output) adds the closed loop's
figures and sorts its misses by these classes.

    python bench/control_oracle.py [--quick] [--against SWEEP.json] [--json] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import control_sweep as cs
import numpy as np


def _loop_blocks(device: dict, extra=()) -> tuple[list[int], int]:
    """Per sweep tone, the closed loop's WARM (blocks from a command to a window of nothing
    older): what the controller of the sweep's scene waits for; and the first delay (blocks
    after an event) whose drive a loop can set on currents read from after it: the device's I/O
    latency, then the controller's block (it sets the next block's amplitudes)."""
    from rtctl import scene
    from rtctl.control._kernels import WARM
    from rtctl.engine.rig import build

    rig = build(scene.load(cs.SCENE, [*cs.overrides(device, calibrated=False), *extra, "events=[]",
                                      "timing.duration=0.1"]))
    out = []
    for bank in rig.stimulus.bank_index:
        ctl, j = rig.controlled[bank[0]]
        out.append(int(ctl.state[WARM, j]))
    return out, int(rig.latency) + 1


def _held_sensed(device: dict, events, seg: int, k0: int, n: int, noisy: bool = False, extra=()) -> np.ndarray:
    """The sensed currents (A, as the ADC reads them) the loop reads in blocks ``k0 ... k0 + n - 1`` of an
    open-loop run through ``events`` (noise-free unless ``noisy``), every tone's drive set from
    the start for its target under segment ``seg``'s finger and held."""
    from rtctl import scene
    from rtctl.dsp._kernels import P_AMP, P_FLAG, P_RAMP
    from rtctl.engine.rig import build

    s = scene.load(cs.SCENE, [*cs.overrides(device, calibrated=False, events=events), *extra, "control.mode=open",
                              "control.observe=false", *([] if noisy else ["actuator.lateral.sense.noise=0"])])
    rig = build(s)
    tid = rig.queue.target_id(rig.bank.pending)
    out = np.zeros((rig.sensed.shape[0], n * s.timing.block))
    for k in range(k0 + n):
        rig.apply_schedule(k)
        for n_tone in range(len(cs.TONES) if k == 0 else 0):
            amps = _amplitudes(device, seg, n_tone, s.actuator[0].max_voltage, extra)
            for b, a in zip(rig.stimulus.bank_index[n_tone], amps):
                rig.queue.post(tid, P_AMP, b, a)
                rig.queue.post(tid, P_RAMP, b, float(s.timing.block))
                rig.queue.post(tid, P_FLAG, b, 1.0)
        rig.queue.publish()
        rig.advance()  # reads the currents the device delivers in this block, then drives it
        if k >= k0:
            out[:, (k - k0) * s.timing.block:(k - k0 + 1) * s.timing.block] = rig.sensed
    return out


def noise_rms(s) -> float:
    """What the ADC adds to each sensed sample (a segment's current, A), rms: the scene's noise
    and the quantization, both in volts at the shunt."""
    sense = s.actuator[0].sense
    volts = np.hypot(sense.noise, 2.0 * sense.full_scale / 2.0 ** sense.bits / np.sqrt(12.0))
    return float(volts / sense.shunt)


def information(device: dict, extra=()) -> list[list[dict]]:
    """Per event, per tone: d' of the currents a loop has read by the time it sets the drive of
    each ``LADDER`` delay (``{delay: d'}``), the drive held at the one for the segment before."""
    from rtctl import scene
    from rtctl.events import block_of

    s = scene.load(cs.SCENE, list(extra))
    block, noise = s.timing.block, noise_rms(s)
    horizon = max(LADDER)
    out = []
    for j, (at, _) in enumerate(cs.EVENTS, start=1):
        kb = block_of(at, s.timing.fs, block)
        with_, without = (_held_sensed(device, cs.EVENTS[:m], j - 1, kb, horizon, extra=extra) for m in (j, j - 1))
        rows = with_.shape[0] // len(cs.TONES)
        per_tone = []
        for n in range(len(cs.TONES)):
            d = with_[n * rows:(n + 1) * rows] - without[n * rows:(n + 1) * rows]
            energy = np.cumsum((d * d).sum(axis=0))
            # the drive of delay D is set in block kb + D - 1, on what was read up to its end
            per_tone.append({dl: float(np.sqrt(energy[dl * block - 1]) / noise) if dl else 0.0 for dl in LADDER})
        out.append(per_tone)
    return out


def _amplitudes(device: dict, seg: int, n: int, vmax: float, extra=()) -> np.ndarray:
    """Each sine's amplitude (V) of tone ``n`` for its target under segment ``seg``'s finger (the
    device's own response), capped where out of reach."""
    target = cs.TONES[n][2] * 1e-6
    gain = cs.gains(device, extra=extra)[seg][n] * 1e-6  # m/V per sine
    return np.minimum(target / gain.size / gain, vmax / gain.size)


def oracle(device: dict, delays: list[int], extra=()) -> dict:
    """One open-loop run of the sweep's tones on ``device``: each sine's amplitude set for the
    target by the device's own response under the finger of each segment, moved ``delays[n]``
    blocks after each event. Returns the true tip (um), its times (s) and the event times."""
    from rtctl import scene
    from rtctl.dsp._kernels import P_AMP, P_FLAG, P_RAMP
    from rtctl.engine.rig import build
    from rtctl.events import block_of

    s = scene.load(cs.SCENE, [*cs.overrides(device, calibrated=False), *extra, "control.mode=open",
                              "control.observe=false"])
    fs, block = s.timing.fs, s.timing.block
    vmax = s.actuator[0].max_voltage
    rig = build(s)
    tid = rig.queue.target_id(rig.bank.pending)

    def amplitudes(seg: int, n: int) -> np.ndarray:
        return _amplitudes(device, seg, n, vmax, extra)

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
#: act to meet what the oracle after ``WARM`` misses (0 is ``at event``; ``first read`` is added).
LADDER = (0, 1, 2, 4, 8, 16, 32)


def figures(device: dict, extra=()) -> list[dict]:
    """Per tone, per event segment: the oracle's settle time and overshoot at the event, at the
    first read, after each of ``LADDER``'s delays and after the closed loop's WARM; and the
    currents' d' at each delay (:func:`information`)."""
    from rtctl import scene
    from rtctl.engine import report

    vmax = scene.load(cs.SCENE, list(extra)).actuator[0].max_voltage
    g = cs.gains(device, extra=extra)
    warm, first = _loop_blocks(device, extra)
    ladder = {d: oracle(device, [d] * len(cs.TONES), extra) for d in sorted({*LADDER, first})}
    runs = {"at_event": ladder[0], "first_read": ladder[first], "after_warm": oracle(device, warm, extra)}
    told = information(device, extra)
    ends = runs["at_event"]["events"][1:] + [cs.DURATION]
    rows = []
    for n, (f, b, target) in enumerate(cs.TONES):
        freqs = list(cs._freqs(f, b))
        for i, t0 in enumerate(runs["at_event"]["events"], start=1):
            row = {"device": cs.label(device), "freq_hz": f, "beat_hz": b, "target_um": target,
                   "segment": cs.SEGMENTS[i], "warm_blocks": warm[n], "first_read_blocks": first,
                   "reachable": target <= cs.reach(g[i][n], vmax),
                   "required_ms": 1e3 * max(5.0 / (b or f), 0.05), "dprime": told[i - 1][n]}
            for name, r in runs.items():
                row[name] = report.against_target(r["tip"][n], r["t"], freqs, t0, ends[i - 1], target)
            row["ladder"] = {d: report.against_target(r["tip"][n], r["t"], freqs, t0, ends[i - 1], target)
                             for d, r in ladder.items() if d in LADDER}
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


def classify(row: dict) -> dict:
    """The closed loop's misses of a row (``row["closed"]``) by class: ``beam`` (the oracle at the
    event misses it too), ``block`` (the oracle at the first read), ``latency`` (only the oracle
    after WARM), ``loop`` (the oracle meets it)."""
    got, beam, block, late = (_misses(row[k], row["required_ms"])
                              for k in ("closed", "at_event", "first_read", "after_warm"))
    return {m: "beam" if m in beam else "block" if m in block else "latency" if m in late else "loop"
            for m in sorted(got)}


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
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a scene override for every run (as control_sweep.py --set: a beam of another geometry)")
    a = ap.parse_args(argv)
    sweep = json.loads(Path(a.against).read_text()) if a.against else {}
    if a.against and sweep.get("set", []) != a.set:
        print(f"--against {a.against} was swept with --set {sweep.get('set', [])}, this run has {a.set}: "
              "its misses would be sorted by another device's oracle", file=sys.stderr)
        return 2
    rows = []
    for dev in cs.devices(a.quick):
        rows += figures(dev, a.set)
        if not a.json:
            print(f"  {cs.label(dev)}: done", file=sys.stderr)
    closed = _closed(sweep) if a.against else {}
    counts = {"closed": 0, "beam": 0, "block": 0, "latency": 0, "loop": 0}
    acts: dict[int, list] = {}  # the latency class by how soon the oracle must act: d' by then
    for r in rows:
        if not r["reachable"]:
            continue
        sg = closed.get((r["device"], r["freq_hz"], r["beat_hz"], r["target_um"], r["segment"]))
        if sg is None:
            continue
        r["closed"] = {"settle_ms": sg["settle_ms"], "overshoot_pct": sg["overshoot_pct"]}
        r["closed_misses"] = classify(r)
        counts["closed"] += len(r["closed_misses"])
        for m, why in r["closed_misses"].items():
            counts[why] += 1
            if why == "latency":
                by = _acts_by(r, m)
                acts.setdefault(by, []).append(r["dprime"][by])
    result = {"rows": rows, "closed_misses": counts if closed else None,
              "latency_acts_by_blocks": {str(d): len(acts[d]) for d in sorted(acts)} if closed else None}
    print(json.dumps(result, indent=1))
    if a.json:
        return 0
    print()
    print(f"{'device':<28}{'tone':<12}{'segment':<8}{'req ms':>7}  {'at event':<16}{'first read':<16}"
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
              f"{cell(r['first_read'])}{cell(r['after_warm'])}  {cell(r['closed']) if 'closed' in r else '':<16}{why}")
    if closed:
        print(f"\nclosed-loop misses after events: {counts['closed']}; the oracle at the event misses them too "
              f"(the beam's): {counts['beam']}; the oracle at the first read does (no loop stepping its drive on "
              f"what it has read meets them): {counts['block']}; only the oracle after WARM does (no loop waiting "
              f"for a clean window meets them): {counts['latency']}; the oracle meets them (the loop's own): "
              f"{counts['loop']}")
        from rtctl import scene

        timing = scene.load(cs.SCENE, a.set).timing
        block_ms = 1e3 * timing.block / timing.fs
        for d in sorted(acts):
            later = LADDER.index(d) + 1
            then = f"not after {LADDER[later]}" if later < len(LADDER) else "still after it"
            print(f"  {len(acts[d])} of those the oracle meets acting up to {d} blocks ({d * block_ms:.1f} ms) after "
                  f"the event, {then}; the currents read by then: d' {min(acts[d]):.3g} ... {max(acts[d]):.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
