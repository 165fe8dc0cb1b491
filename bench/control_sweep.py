"""Closed-loop acceptance sweep on ``sim``: devices off their model, with and without calibration,
through finger events; every tone's true amplitude against its target.

The criterion: on devices with ``io.mismatch`` factors up to +-10 % on d31, E and eps33T, damping
x0.5 ... x2 and finger k0 x0.3 ... x3 (geometry and density as the scene states them), after
calibration (``control.calibrate = "auto"``), every reachable tone's true amplitude is within 2 %
of its target in steady state (aim: 1 %), within 5 % from max(5 periods, 50 ms) after its start and
after each finger event on, and never more than 10 % above it (overshoot); uncalibrated, the
report shows the error as it is. A beat pair's period is its envelope's, 1 / beat.

Scene: ``line-bimorph-5-closed`` (its 50 g and 200 g finger sets), one tone per channel, the finger
pressing with 200 g at 1 s, lifting at 2 s and returning at 3 s, the run ending at 4 s: segments
of 1 s hold the 10 Hz tone's 500 ms and a steady window after it. Per tone and segment: the
report's steady amplitude (``start``, ``events``) and, from the trace's true tip with the report's
own windows (``report.against_target``), the time to stay within 5 % of the target and the
overshoot. A segment is judged only where the target is reachable: the device's own tip per volt
(this bench is the referee, as the report is: it may read the secret) under that segment's
finger, times the tone's share of max_voltage. ``step`` is how far the event alone moves the
amplitude at the drive held before it (what no loop can act on before it sees it).

The beat pairs 40/10 and 250/30 Hz (35 + 45, 235 + 265 Hz) repeat every 200 ms; the observer reads
the first over whole periods of both tones (200 ms, twice its 100 ms beat) and the second over one
beat period by least squares (33 ms); 255/30 Hz (240 + 270 Hz) repeats with its beat, 33 ms.

Targets: the first eleven are half the least reach over the grid's devices and finger states
(``--targets`` recomputes it), so they are reachable everywhere; the last three 80 % of the
nominal device's reach under the 50 g finger: near the cap, out of reach under 200 g.

    python bench/control_sweep.py [--quick] [--json] [--jobs N] [--targets] [--set KEY=VALUE ...]

Prints one JSON object (``--json``: only that), then a table: per tone and segment the steady
error (%), the time to stay within 5 % against the time required (ms) and the overshoot (%),
``!`` where the criterion is missed, ``~`` where the error is within 2 % but over the 1 % aim.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

# before numpy loads, as the rtctl command does: the models' matrices are small, and BLAS threads
# on a busy 2-core machine slow a plant's discretization a hundredfold
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

SCENE = "line-bimorph-5-closed"
DURATION = 4.0
EVENTS = ((1.0, {"finger.preload": 1.96}), (2.0, {"finger.contact": False}), (3.0, {"finger.contact": True}))
SEGMENTS = ("start", "200 g", "lifted", "back")
#: (Hz, beat Hz, target um)
TONES = ((10, 0, 6.8), (25, 0, 6.5), (40, 0, 6.3), (80, 0, 6.0), (120, 0, 6.0), (250, 0, 6.5), (500, 0, 10.5),
         (1000, 0, 4.4), (40, 10, 6.3), (250, 30, 6.6), (255, 30, 6.6), (40, 0, 26.3), (250, 0, 28.4), (1000, 0, 20.1))
STEADY_PCT, AIM_PCT, OVERSHOOT_PCT = 2.0, 1.0, 10.0
FACTORS = {"d31": (0.9, 1.1), "E": (0.9, 1.1), "eps33T": (0.9, 1.1), "damping": (0.5, 2.0), "finger_k0": (0.3, 3.0)}
LOW = {k: v[0] for k, v in FACTORS.items()}
HIGH = {k: v[1] for k, v in FACTORS.items()}
QUICK = ({}, LOW, HIGH, {"d31": 0.9, "E": 1.1, "eps33T": 0.9, "damping": 2.0, "finger_k0": 0.3},
         {"d31": 1.1, "E": 0.9, "eps33T": 1.1, "damping": 0.5, "finger_k0": 3.0})


def devices(quick: bool) -> list[dict]:
    """The nominal device and every corner of FACTORS (QUICK: five of them)."""
    if quick:
        return [dict(d) for d in QUICK]
    return [{}] + [dict(zip(FACTORS, c)) for c in itertools.product(*FACTORS.values())]


def label(device: dict) -> str:
    short = {"d31": "d", "E": "E", "eps33T": "e", "damping": "z", "finger_k0": "k"}
    return " ".join(f"{short[k]}{v:g}" for k, v in device.items()) or "nominal"


def _toml(v) -> str:
    return json.dumps(v) if not isinstance(v, bool) else str(v).lower()


def overrides(device: dict, tones=TONES, calibrated=True, events=EVENTS, duration=DURATION) -> list[str]:
    items = ", ".join(f"{{channel = {i}, freq = {f:g}, beat = {b:g}, voltage = 1.0, target_um = {r:g}}}"
                      for i, (f, b, r) in enumerate(tones))
    evs = ", ".join(f"{{at = {at:g}, set = {{{', '.join(f'{json.dumps(k)} = {_toml(v)}' for k, v in s.items())}}}}}"
                    for at, s in events)
    return [f"actuator.lateral.grid=[1, {len(tones)}]", f"stimulus.tones=[{items}]", f"events=[{evs}]",
            f"timing.duration={duration:g}", "control.mode=closed",
            f"control.calibrate={'auto' if calibrated else 'off'}",
            *(f"io.mismatch.{k}={v:g}" for k, v in device.items())]


def gains(device: dict, tones=TONES, events=EVENTS, extra=()) -> list[list[np.ndarray]]:
    """Per segment, per tone: the device's true tip per commanded volt (um/V) at each of its
    frequencies, under the finger of that segment (``extra``: the run's ``--set`` overrides, a
    beam of another geometry, say)."""
    from rtctl import scene
    from rtctl.io.sim import build_group, device_models

    key = json.dumps([device, tones, events, list(extra)])
    if key in _GAINS:  # the calibrated and the uncalibrated run of a device share them
        return _GAINS[key]
    states, held = [[]], {}
    for _, sets in events:
        held.update(sets)
        states.append([f"{k}={_toml(v)}" for k, v in held.items()])
    out = []
    for st in states:
        s = scene.load(SCENE, [*extra, *(f"io.mismatch.{k}={v:g}" for k, v in device.items()), "events=[]", *st])
        plant = build_group(device_models(s), s.actuator[0], 0, s.timing.fs, s.timing.block).plant
        out.append([1e6 * np.abs(plant.frequency_response(_freqs(f, b))[:, 0]) for f, b, _ in tones])
    _GAINS[key] = out
    return out


_GAINS: dict = {}


def reach(gain: np.ndarray, vmax: float) -> float:
    """The amplitude (um) at the cap: each of the tone's sines at its share of max_voltage."""
    return float(gain.sum()) * vmax / gain.size


def _freqs(f, b):
    return np.array([f - b / 2, f + b / 2]) if b else np.array([float(f)])


def case(device: dict, calibrated: bool, tones=TONES, events=EVENTS, duration=DURATION, extra=()) -> dict:
    """One closed-loop run of ``device`` and its figures per tone (:func:`judge`)."""
    from rtctl import scene
    from rtctl.engine import report
    from rtctl.engine.run import run
    from rtctl.trace import TraceReader

    s = scene.load(SCENE, [*overrides(device, tones, calibrated, events, duration), *extra])
    vmax = s.actuator[0].max_voltage
    g = gains(device, tones, events, extra)
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        summary = run(s, out_dir=d, plot=False).summary
        wall = time.perf_counter() - t0
        reader = TraceReader(Path(d) / "trace")
        n = int(round(summary["duration_s"] * summary["fs"]))
        t = np.arange(n) / summary["fs"]
        ends = [ev["t_s"] for ev in summary["events"]] + [summary["duration_s"]]
        rows = []
        for ch, (f, b, target) in enumerate(tones):
            r = summary["channels"][ch]
            tip, drive = reader.signal("tip_um", ch)[:n], reader.signal("drive", ch)[:n]
            segs = [r["start"], *r["events"]] if "start" in r else [{"t_s": 0.0, "true_um": r["true_um"]}]
            period = 1.0 / (b or f)
            out = []
            for i, sg in enumerate(segs):
                cap = reach(g[i][ch], vmax)
                fig = report.against_target(tip, t, r["freqs_hz"], sg["t_s"], ends[i], target)
                true = sg["true_um"]
                # an independent reading of the settled amplitude: the drive actually sent over the
                # report's window (the segment's last analysis window), through the device's response
                m = (t >= ends[i] - report.analysis_window(ends[i] - sg["t_s"], r["freqs_hz"])) & (t < ends[i])
                ref = float(np.dot(report.fit_amplitudes(drive[m], t[m], r["freqs_hz"]), g[i][ch]))
                out.append({"segment": SEGMENTS[i], "t_s": sg["t_s"], "cap_um": cap, "reachable": target <= cap,
                            "step_pct": 100.0 * (cap / reach(g[i - 1][ch], vmax) - 1.0) if i else None,
                            "true_um": true, "reference_um": ref,
                            "error_pct": None if true is None else 100.0 * (true / target - 1.0),
                            "required_ms": 1e3 * max(5 * period, 0.05), **fig})
            rows.append(judge({"name": r["name"], "freq_hz": f, "beat_hz": b, "target_um": target,
                               "error_pct": r["error_pct"], "true_um": r["true_um"],
                               "saturated": bool(r.get("saturated")), "reachable_um": r.get("reachable_um"),
                               "uncertainty_pct": r.get("uncertainty_pct"), "observer_gain": r.get("observer_gain"),
                               "segments": out}))
    cal = summary.get("calibration") or {}
    return {"device": device, "label": label(device), "calibrated": calibrated, "wall_s": wall,
            "calibration_s": cal.get("wall_s", 0.0) + cal.get("fit_s", 0.0),
            "calibration": "calibration" in summary, "warnings": summary["warnings"], "tones": rows}


def guarded(device: dict, calibrated: bool, extra=()) -> dict:
    """:func:`case`, or what stopped it (a failed calibration is a miss of every tone, not the end
    of the sweep)."""
    t0 = time.perf_counter()
    try:
        return case(device, calibrated, extra=extra)
    except Exception as e:  # any failure of the run is a finding
        return {"device": device, "label": label(device), "calibrated": calibrated, "wall_s": time.perf_counter() - t0,
                "calibration_s": 0.0, "error": f"{type(e).__name__}: {e}", "tones": []}


def judge(row: dict) -> dict:
    """``misses``: each clause of the criterion a reachable segment fails, as text; ``honest``:
    every segment's reported amplitude is the truth (within 0.5 % of the independent reading), the
    row's the last one's, and its error that amplitude's; ``saturation_right``: it says saturated
    exactly when the last target is out of reach (the controller's view: uncalibrated, a biased
    estimate misleads it)."""
    misses = []
    for sg in row["segments"]:
        if not sg["reachable"]:
            continue
        where = f"{row['name']} {row['freq_hz']:g}{'/' + format(row['beat_hz'], 'g') if row['beat_hz'] else ''} Hz, " \
                f"{sg['segment']}"
        if sg["error_pct"] is None or abs(sg["error_pct"]) > STEADY_PCT:
            misses.append(f"{where}: steady error {fmt(sg['error_pct'], '+.2f')} % (limit {STEADY_PCT:g} %)")
        if late(sg["settle_ms"], sg["required_ms"]):
            misses.append(f"{where}: within 5 % after {fmt(sg['settle_ms'], '.0f')} ms "
                          f"(required {sg['required_ms']:.0f} ms)")
        if not sg["overshoot_pct"] < OVERSHOOT_PCT:
            alone = "" if sg["step_pct"] is None else f", the event alone {sg['step_pct']:+.0f} %"
            misses.append(f"{where}: overshoot {sg['overshoot_pct']:+.1f} % (limit {OVERSHOOT_PCT:g} %{alone})")
    last = row["segments"][-1]
    row["misses"] = misses
    row["beyond_aim"] = [sg["segment"] for sg in row["segments"] if sg["reachable"] and sg["error_pct"] is not None
                         and AIM_PCT < abs(sg["error_pct"]) <= STEADY_PCT]
    true = row["true_um"]
    row["honest"] = (true is not None and true == last["true_um"]
                     and all(sg["true_um"] is not None and abs(sg["true_um"] / sg["reference_um"] - 1.0) < 5e-3
                             for sg in row["segments"])
                     and math.isclose(row["error_pct"], 100.0 * (true / row["target_um"] - 1.0), rel_tol=1e-9))
    row["saturation_right"] = row["saturated"] == (not last["reachable"])
    return row


def late(settle_ms, required_ms) -> bool:
    """Whether a settle time misses its bound (None: never settled). The settle times fall on
    half-window steps of a time axis built from sample counts: one that lands on the bound by
    construction may read a few ulps over it."""
    return settle_ms is None or settle_ms > required_ms * (1.0 + 1e-9)


def fmt(v, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def least_reach(tones=TONES, events=EVENTS, extra=()) -> list[float]:
    """Per tone, the least reach (um at max_voltage) over every device of the grid and every
    segment's finger (``extra``: the run's ``--set`` overrides, a beam of another geometry)."""
    from rtctl import scene

    vmax = scene.load(SCENE, list(extra)).actuator[0].max_voltage
    least = [math.inf] * len(tones)
    for dev in devices(quick=False):
        for seg in gains(dev, tones, events, extra):
            least = [min(x, reach(gain, vmax)) for x, gain in zip(least, seg)]
    return least


def print_table(cases: list[dict]) -> None:
    cell = 24
    print(f"{'device':<28}{'cal':<4}{'tone':<12}{'target':>7}  " + "".join(f"{s:<{cell}}" for s in SEGMENTS)
          + "sat    honest  verdict")
    print(f"{'':<28}{'':<4}{'':<12}{'um':>7}  " + f"{'err% settle/req ms ovs%':<{cell}}" * len(SEGMENTS))
    for c in cases:
        if c.get("error"):
            print(f"{c['label']:<28}{'yes' if c['calibrated'] else 'no':<4}RUN FAILED: {c['error']}")
        for r in c["tones"]:
            tone = f"{r['freq_hz']:g}" + (f"/{r['beat_hz']:g}" if r["beat_hz"] else "") + " Hz"
            cells = []
            for sg in r["segments"]:
                if not sg["reachable"]:
                    cells.append(f"(reach {sg['cap_um']:.1f})")
                    continue
                e, st, ov = sg["error_pct"], sg["settle_ms"], sg["overshoot_pct"]
                mark = "!" if e is None or abs(e) > STEADY_PCT else "~" if abs(e) > AIM_PCT else ""
                cells.append(f"{fmt(e, '+.1f')}{mark} "
                             f"{fmt(st, '.0f')}/{sg['required_ms']:.0f}"
                             f"{'!' if late(st, sg['required_ms']) else ''} "
                             f"{ov:+.0f}{'!' if not ov < OVERSHOOT_PCT else ''}")
            verdict = "-" if not c["calibrated"] else ("meets" if not r["misses"] else f"MISSES {len(r['misses'])}")
            print(f"{c['label']:<28}{'yes' if c['calibrated'] else 'no':<4}{tone:<12}{r['target_um']:7.1f}  "
                  + "".join(f"{x:<{cell}}" for x in cells)
                  + f"{('yes' if r['saturated'] else 'no') + ('' if r['saturation_right'] else '(!)'):<7}"
                  f"{'yes' if r['honest'] else 'NO':<8}{verdict}")
        print(f"{'':<28}wall {c['wall_s']:.1f} s (calibration {c['calibration_s']:.1f} s)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print only the JSON object")
    ap.add_argument("--quick", action="store_true", help="five devices instead of the nominal one and all 32 corners")
    ap.add_argument("--targets", action="store_true", help="print each tone's least reach over the grid and exit")
    ap.add_argument("--jobs", type=int, default=1, help="cases run in this many processes")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a scene override for every run (e.g. control.rise_s=0.02); repeatable")
    a = ap.parse_args(argv)
    if a.targets:
        for (f, b, r), x in zip(TONES, least_reach(extra=a.set)):
            print(f"{f:g} Hz beat {b:g}: least reach {x:.2f} um, half {x / 2:.2f}; target {r:g} um")
        return 0
    cases, tasks = [], [(dev, cal) for dev in devices(a.quick) for cal in (True, False)]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(a.jobs) as pool:
        for c in pool.map(guarded, *zip(*tasks), [tuple(a.set)] * len(tasks)):
            cases.append(c)
            if not a.json:
                print(f"  {c['label']:<28} calibrated {'yes' if c['calibrated'] else 'no ':<3}: {c['wall_s']:.1f} s, "
                      f"{sum(len(r['misses']) for r in c['tones'])} misses {c.get('error') or ''}", file=sys.stderr)
    cal = [c for c in cases if c["calibrated"]]
    result = {"scene": SCENE, "set": a.set, "duration_s": DURATION,
              "events": [{"at": at, "set": s} for at, s in EVENTS], "wall_s": time.perf_counter() - t0, "cases": cases,
              "calibrated_tones": len(TONES) * len(cal),
              "calibrated_tones_meeting": sum(not r["misses"] for c in cal for r in c["tones"]),
              "beyond_aim": [f"{c['label']}: {r['name']} {r['freq_hz']:g} Hz, {x}" for c in cal for r in c["tones"]
                             for x in r["beyond_aim"]],
              "misses": [f"{c['label']}: run failed: {c['error']}" for c in cal if c.get("error")]
              + [m for c in cal for r in c["tones"] for m in (f"{c['label']}: {x}" for x in r["misses"])],
              "failed_runs": [f"{c['label']} cal={c['calibrated']}: {c['error']}" for c in cases if c.get("error")],
              "dishonest": [f"{c['label']} cal={c['calibrated']}: {r['name']}" for c in cases for r in c["tones"]
                            if not r["honest"]],
              "saturation_wrong": [f"{c['label']} cal={c['calibrated']}: {r['name']}" for c in cases
                                   for r in c["tones"] if not r["saturation_right"]]}
    print(json.dumps(result, indent=1))
    if not a.json:
        print()
        print_table(cases)
        sat = result["saturation_wrong"]
        print(f"\ncalibrated: {result['calibrated_tones_meeting']} of {result['calibrated_tones']} tones meet the "
              f"criterion in every reachable segment; {len(result['misses'])} misses; "
              f"{len(result['beyond_aim'])} steady errors within 2 % but over the 1 % aim (~)\n"
              f"failed runs {len(result['failed_runs'])}; dishonest rows {len(result['dishonest'])}; saturated "
              f"flag wrong {len(sat)} (calibrated {sum(' cal=True' in x for x in sat)}); "
              f"{len(cases)} runs in {result['wall_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
