"""``rtctl selfsense SCENE [--out DIR] [--json]``: admittance plots and the observer accuracy sweep.

For every bimorph group of the scene: the TMM twin's natural frequencies, the tip velocity and
admittance per volt for the finger loads of :func:`~rtctl.selfsense.sweep.finger_loads` (plot:
``DIR/selfsense_<group>.png``), and the accuracy sweep of the two-segment observer on the
simulated FE plant at the scene's sample rate and front end, with and without +-5 % model
mismatch (``DIR/selfsense_<group>.json``). The simulated truth keeps every mode up to 5 fs
(:func:`~rtctl.selfsense.sweep.truth_modes`, 8 for the bundled beam), not the loop plant's
``beam.modes`` (4 in the bundled scenes; by default every mode to 1.5 fs and near 2-4 fs): the DAC staircase's
images reach the currents through modes up to ~4 fs, and the 4-mode plant misses them
(docs/selfsense.md, Sec. 5). ``--truth-modes 4`` scores against the loop plant instead.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

from rtctl.errors import RtctlError

MISMATCHES = (None, {"thickness": 0.05}, {"d31": -0.05}, {"finger": 0.05})


def _parser():
    p = argparse.ArgumentParser(prog="rtctl selfsense", description=__doc__.splitlines()[0])
    p.add_argument("scene", metavar="SCENE")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--out", default="out/selfsense", metavar="DIR")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--freqs", default="10,250,1000", help="sweep frequencies, Hz (comma list)")
    p.add_argument("--beat", type=float, default=10.0, help="beat of the pairs, Hz (0: tones only)")
    p.add_argument("--snr", type=float, default=60.0, help="current-sense SNR, dB")
    p.add_argument("--no-mismatch", action="store_true", help="skip the +-5 %% mismatch cases")
    p.add_argument("--truth-modes", type=int, default=None, metavar="N",
                   help="modes of the simulated truth plant (default: all up to 5 fs)")
    return p


def run(scene_name, overrides=(), out="out/selfsense", freqs=(10.0, 250.0, 1000.0), beat=10.0,
        snr_db=60.0, mismatch=True, truth_modes=None) -> dict:
    """Everything ``rtctl selfsense`` computes, as a dict (see the module docstring)."""
    from rtctl import scene as scene_mod
    from rtctl.models import Models
    from rtctl.outpath import writable_dir
    from rtctl.selfsense.facts import tmm_facts
    from rtctl.selfsense.plots import admittance_figure
    from rtctl.selfsense.sweep import finger_loads, run_case, sweep
    from rtctl.selfsense.sweep import truth_modes as converged_modes
    from rtctl.selfsense.tmm import TMMBeam

    sc = scene_mod.load(scene_name, list(overrides))
    outdir = writable_dir(out, "--out")
    models = Models(sc)
    result = {"scene": sc.scene.name, "groups": {}}
    fs = float(sc.timing.fs)
    for g in sc.actuator:
        if g.type != "bimorph":
            continue
        fe = models.beam(g)
        finger = models.finger(g)
        kw = dict(fs=fs, block=int(sc.timing.block), amplifier_hz=g.amplifier.bandwidth,
                  aa_cutoff_hz=g.sense.aa_cutoff, aa_order=g.sense.aa_order, shunt=g.sense.shunt,
                  n_modes=truth_modes or converged_modes(fe, fs, models.plant_modes(g)))
        loads = finger_loads(finger)
        beam = TMMBeam.from_fe(fe)
        fgrid = np.geomspace(5.0, 2000.0, 200)
        model = {name: beam.response(fgrid, ld) for name, ld in loads.items()}
        est = {}
        for name, ld in loads.items():
            fe_pts = np.array([20.0, 60.0, 150.0, 300.0, 600.0, 1200.0])
            e, t = [], []
            for f in fe_pts:
                r = run_case(fe, ld, [f], [10.0], snr_db=snr_db, **kw)
                e.append(2j * np.pi * f * r["est"][0] / 10.0)
                t.append(2j * np.pi * f * r["true"][0] / 10.0)
            est[name] = (fe_pts, np.array(e), np.array(t))
        png = outdir / f"selfsense_{g.name}.png"
        admittance_figure(fgrid, model, est, png)
        mm = MISMATCHES if mismatch else (None,)
        sw = sweep(fe, finger, freqs=tuple(freqs), volts=10.0, snr_db=snr_db, mismatches=mm,
                   beat_hz=beat, **kw)
        facts = tmm_facts(fe, finger)
        entry = {**facts, "plot": str(png), "loop_plant_modes": models.plant_modes(g), **sw}
        (outdir / f"selfsense_{g.name}.json").write_text(json.dumps(entry, indent=1))
        result["groups"][g.name] = entry
    if not result["groups"]:
        raise RtctlError(f"{sc.source}: no bimorph actuator group: self-sensing needs one")
    return result


def main(argv=None) -> int:
    """Entry point of ``rtctl selfsense``; returns the exit status."""
    args = _parser().parse_args(argv)
    try:
        freqs = tuple(float(x) for x in args.freqs.split(",") if x.strip())
    except ValueError:
        print(f"rtctl selfsense: error: --freqs must be numbers in Hz, got {args.freqs!r}", file=sys.stderr)
        return 2
    try:
        if args.truth_modes is not None and args.truth_modes < 1:
            raise RtctlError(f"--truth-modes must be >= 1, got {args.truth_modes}")
        # each written so that NaN fails it too
        if not freqs or not all(0 < f < math.inf for f in freqs):
            raise RtctlError(f"--freqs {args.freqs!r}: give finite frequencies > 0 Hz, e.g. 10,250,1000")
        if not 0 <= args.beat <= 2 * min(freqs):  # a pair's lower sine, f - beat / 2, must not go below 0 Hz
            raise RtctlError(f"--beat {args.beat:g}: must be in [0, {2 * min(freqs):g}] Hz (twice the lowest of "
                             "--freqs; 0: tones only)")
        if not -math.inf < args.snr <= math.inf:
            raise RtctlError(f"--snr {args.snr:g}: give a number of dB (inf: no noise)")
        res = run(args.scene, args.overrides, args.out, freqs, args.beat, args.snr, not args.no_mismatch,
                  args.truth_modes)
    except RtctlError as e:
        print(f"rtctl selfsense: error: {e}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(res))
        return 0
    for name, g in res["groups"].items():
        print(f"{name}: TMM modes {', '.join(f'{f:.0f}' for f in g['tmm_natural_frequencies_hz'])} Hz, "
              f"loaded {', '.join(f'{f:.0f}' for f in g['tmm_loaded_natural_frequencies_hz'])} Hz; plot {g['plot']}")
        modes = sorted({c["truth_modes"] for c in g["cases"]})
        print(f"truth plant: {', '.join(map(str, modes))} modes "
              f"(the loop plant keeps {g['loop_plant_modes']})")
        print(f"{'f Hz':>7} {'beat':>5} {'load':>5} {'mismatch':>18} {'amp %':>7} {'ph deg':>7} {'F %':>7} {'cond':>6}")
        for c in g["cases"]:
            mm = ",".join(f"{k}{v:+.0%}" for k, v in c["mismatch"].items()) or "-"
            print(f"{c['freq_hz']:7.1f} {c['beat_hz']:5.1f} {c['load']:>5} {mm:>18} {c['amp_err_pct']:7.3f} "
                  f"{c['phase_err_deg']:7.3f} {c['force_err_pct']:7.2f} {c['cond']:6.2f}")
    return 0
