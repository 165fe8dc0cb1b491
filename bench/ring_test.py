"""Which load rings in the first block of currents read after a finger event: a test a loop could
run on every block, measured on the closed-loop sweep's devices.

``bench/control_oracle.py`` shows that the currents of that block tell a lift-off plainly (d' in
the thousands) but not how a loop could read it: over one block (0.7 ms) a 10-250 Hz tone is a
fraction of its period, and the event's own ring dominates (a tone read from that block alone is
off by 10-360 fold). This bench asks each load the observer knows (the calibrated model's finger
sets and the free tip) to explain the block: its steady currents for the drive held before the
event (the tone through the segment admittances, with the drive's folded images, as the observer's
design has them), plus a free level and free sines at that load's two lowest modes (the ring it
would leave, any amplitude and phase): the design of the loop's own test
(``rtctl.selfsense.lift``), evaluated here in numpy on a drive fitted by least squares. The load
whose residual is least is the test's verdict: the free tip after a lift-off, a finger after a
press or a landing.

Per device, tone and event it prints each load's residual (rms over the block's samples and
segments, in sensor-noise units: the scene's noise and the ADC's quantization at the shunt), the
verdict, and the free tip's residual over the best finger's, and the same on the last
block read before the event, where the load in use should explain the currents to the noise.
Nothing here reads the device's secret: the loads are the calibrated model's, the drive and
currents what a loop reads.

    python bench/ring_test.py [--quick] [--json] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile

import control_sweep as cs
import numpy as np
from control_oracle import noise_rms

#: Blocks of held drive the tones' phasors are fitted over, ending with the event's block.
DRIVE_BLOCKS = 16


def load_names(observer) -> list[str]:
    """The observer's candidate loads (its finger sets, the free tip), named, in its order."""
    return ["free" if load is None else f"finger k0 {load.k0:g} N/m" for load in observer.image_loads]


def residuals(lift, sensed, drives, c: int, kb: int) -> np.ndarray:
    """Each candidate's residual energy (A^2) on channel ``c``'s block ``kb``: the currents
    ``sensed`` (rows of the channel's segments) less the candidate's steady currents for the
    drive, less their projection on its ring columns (the lift-off test's ``ly`` and ``lq``: the
    observer's design). The drive's phasors are fitted by least squares to ``drives`` (the
    channel's last ``DRIVE_BLOCKS`` blocks of drive, ending with ``kb``), not read from the
    lock-in as the test in the loop reads them."""
    obs = lift.observer
    block, fs, n_seg = obs.block, obs.fs, obs.n_seg
    fr = obs.freqs[c][obs.freqs[c] > 0]
    t = np.arange((kb - DRIVE_BLOCKS + 1) * block, (kb + 1) * block)
    w = 2 * np.pi * fr / fs
    cols = np.concatenate([np.cos(np.outer(t, w)), -np.sin(np.outer(t, w))], axis=1)
    sol = np.linalg.lstsq(cols, np.asarray(drives).reshape(-1), rcond=None)[0]
    u = sol[:fr.size] + 1j * sol[fr.size:]  # x = Re(u exp(j w t))
    z = np.exp(1j * np.outer(t[-block:], w))
    out = np.zeros(lift.ly.shape[2])
    for q in range(out.size):
        for j in range(n_seg):
            y = lift.ly[c, :fr.size, q, j, 0] + 1j * lift.ly[c, :fr.size, q, j, 1]
            r = sensed[j] - np.real(z @ (y * u))
            out[q] += r @ r - np.sum((lift.lq[q].T @ r) ** 2)
    return out


def device_rows(device: dict, extra=()) -> list[dict]:
    """One calibrated closed-loop run of ``device`` through the sweep's events: the test on the
    first block read after each event and on the last before it, per tone."""
    from rtctl import scene
    from rtctl.engine.calibrate import auto
    from rtctl.engine.rig import build
    from rtctl.engine.run import run
    from rtctl.events import block_of
    from rtctl.selfsense.lift import LiftTest

    s = scene.load(cs.SCENE, [*cs.overrides(device), *extra])
    with tempfile.TemporaryDirectory() as d:
        s, _ = auto(s, d, run, say=None)
        rig = build(s)  # reads the calibration file
    fs, block = s.timing.fs, s.timing.block
    obs = rig.observer_stages[0][1].observer
    lift = LiftTest(obs)
    names = load_names(obs)
    noise = noise_rms(s)
    n_seg = obs.n_seg
    ev_blocks = [block_of(at, fs, block) for at, _ in cs.EVENTS]
    # the sensed block read in advance k holds the currents of block k - latency
    reads = {kb + rig.latency + d: (i, d) for i, kb in enumerate(ev_blocks) for d in (-1, 0)}
    drives = np.zeros((DRIVE_BLOCKS, *rig.out.shape))
    rows = []
    for k in range(max(reads) + 1):
        rig.apply_schedule(k)
        rig.advance()
        drives[k % DRIVE_BLOCKS] = rig.out
        if k not in reads:
            continue
        i, d = reads[k]
        kb = k - rig.latency  # the block whose currents were read
        order = [(kb - m) % DRIVE_BLOCKS for m in range(DRIVE_BLOCKS - 1, -1, -1)]
        for ch in range(len(cs.TONES)):
            e = residuals(lift, rig.sensed[ch * n_seg:(ch + 1) * n_seg], drives[order, ch], ch, kb)
            rms = {name: float(np.sqrt(max(x, 0.0) / (n_seg * block)) / noise) for name, x in zip(names, e)}
            finger = min(v for n, v in rms.items() if n != "free")
            rows.append({"device": cs.label(device), "freq_hz": cs.TONES[ch][0], "beat_hz": cs.TONES[ch][1],
                         "target_um": cs.TONES[ch][2], "event": cs.SEGMENTS[i + 1],
                         "read": "first after" if d == 0 else "last before",
                         "rms_sigma": rms, "verdict": min(rms, key=rms.get),
                         "free_over_finger": rms["free"] / finger})
    return rows


def _right(row: dict) -> bool:
    return (row["verdict"] == "free") == (row["event"] == "lifted")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the sweep's five devices instead of all 33")
    ap.add_argument("--json", action="store_true", help="print only the JSON object")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a scene override for every run (as control_sweep.py --set: a beam of another geometry)")
    a = ap.parse_args(argv)
    rows = []
    for dev in cs.devices(a.quick):
        rows += device_rows(dev, a.set)
        if not a.json:
            print(f"  {cs.label(dev)}: done", file=sys.stderr)
    first = [r for r in rows if r["read"] == "first after"]
    summary = []
    for f, b, _ in dict.fromkeys((f, b, 0) for f, b, _ in cs.TONES):
        line = {"freq_hz": f, "beat_hz": b}
        for ev in cs.SEGMENTS[1:]:
            rs = [r for r in first if (r["freq_hz"], r["beat_hz"], r["event"]) == (f, b, ev)]
            # how far the right side (free after a lift-off, a finger else) is ahead of the other
            ahead = [1.0 / r["free_over_finger"] if ev == "lifted" else r["free_over_finger"] for r in rs]
            line[ev] = {"right": sum(x > 1.0 for x in ahead), "of": len(rs), "least_ratio": min(ahead)}
        summary.append(line)
    print(json.dumps({"set": a.set, "rows": rows, "summary": summary}, indent=1))
    if a.json:
        return 0
    print()
    print(f"{'device':<28}{'tone':<12}{'event':<8}{'read':<13}{'verdict':<22}{'free/finger':>11}  residuals (sigma)")
    for r in rows:
        tone = f"{r['freq_hz']:g}" + (f"/{r['beat_hz']:g}" if r["beat_hz"] else "") + " Hz"
        mark = "" if r["read"] == "last before" or _right(r) else "  WRONG"
        res = "  ".join(f"{n} {v:.1f}" for n, v in r["rms_sigma"].items())
        print(f"{r['device']:<28}{tone:<12}{r['event']:<8}{r['read']:<13}{r['verdict']:<22}"
              f"{r['free_over_finger']:11.2f}  {res}{mark}")
    print("\nfirst block read after each event: right verdicts, and the least ratio by which the right side "
          "(the free tip after a lift-off, a finger after a press or a landing) explains the block better")
    print(f"{'tone':<12}" + "".join(f"{ev:<22}" for ev in cs.SEGMENTS[1:]))
    for line in summary:
        tone = f"{line['freq_hz']:g}" + (f"/{line['beat_hz']:g}" if line["beat_hz"] else "") + " Hz"
        print(f"{tone:<12}" + "".join(f"{line[ev]['right']:>3} of {line[ev]['of']:<3} x{line[ev]['least_ratio']:<10.2f}"
                                      for ev in cs.SEGMENTS[1:]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
