"""Golden traces: a compact fingerprint of what each bundled scene does, kept in tests/golden/.

A fingerprint is a short run of the scene on the simulated device (:data:`DURATION`; the
closed-loop scene's finger events moved inside it), reduced to per-frame, per-row envelopes of
the trace and the run's summary figures:

* every per-sample signal (drive, sensed currents, true tip displacement, velocity, force and
  voltage, the plant's probes, the observer's tip estimate): RMS and peak ``|x|`` per frame of
  :data:`FRAME_S` and per row;
* the true tip displacement and the drive at each tone of a channel: amplitude and phase by
  lock-in (against ``cos``/``sin`` of absolute time) over the largest whole number of the tone's
  periods that ends with the frame (the frame itself when a period is longer);
* every per-block signal (targets, estimates, temperatures) at the end of each frame;
* the summary's per-channel figures (true and estimated amplitude, error, settle times, peak
  voltage, limits, contact, felt), its warnings, faults and events.

The tolerances (:data:`RTOL`, :data:`TOLERANCES`) and why they are what they are:
docs/golden.md. ``python -m rtctl.engine.golden`` rewrites the goldens and prints what changed;
``--check`` only compares (exit 1 on a difference).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

#: Seconds each scene runs for its golden, and the frame its envelopes are taken over.
DURATION = 0.3
FRAME_S = 0.02
#: Overrides beyond the duration: the closed-loop scene's press, lift and return inside the run.
OVERRIDES = {"line-bimorph-5-closed": ["events.0.at=0.08", "events.1.at=0.15", "events.2.at=0.22"]}
#: Significant digits stored (the trace is float32: 7 digits is what it holds).
DIGITS = 7
#: |new - golden| <= RTOL * |golden| + RTOL / 10 * (largest |value| of that quantity in the golden);
#: phases within 10 * RTOL rad where the amplitude exceeds PHASE_FLOOR of its largest. The
#: default holds for a scene whose trace moves smoothly with its constants; the scenes listed in
#: TOLERANCES move in steps (docs/golden.md has the measurements behind each figure).
RTOL = 1e-5
TOLERANCES = {
    # an end-stop impact or contact switch moves by a sub-step: frame peaks of tip force change by
    # ~5e-5 under any perturbation from 4 ulp to 1e-9 of the finger stiffness
    "solenoid-3x3": 3e-4,
    # the controllers act on the estimates block by block: 1e-9 of the finger stiffness moves one
    # channel's 250 Hz amplitude by 5e-4
    "line-bimorph-5-closed": 3e-3,
}
PHASE_FLOOR = 1e-3


def tolerance(name: str) -> float:
    """The relative tolerance of scene ``name``'s golden."""
    return TOLERANCES.get(name, RTOL)


#: Summary fields that are timing, not behaviour.
TIMING = ("realtime_factor", "cpu_realtime_factor", "block_time_us", "build_s", "deadline_misses", "late_wakeups",
          "overruns", "trace_dropped", "block_function", "numba_cache", "io")

DEFAULT_DIR = Path(__file__).resolve().parents[2] / "tests" / "golden"


def overrides(name: str) -> list:
    return [*OVERRIDES.get(name, []), f"timing.duration={DURATION}"]


def _round(x):
    """Floats to :data:`DIGITS` significant digits, recursively; NaN and inf as None/strings."""
    if isinstance(x, dict):
        return {k: _round(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_round(v) for v in x]
    if isinstance(x, np.ndarray):
        return _round(x.tolist())
    if isinstance(x, (float, np.floating)):
        x = float(x)
        if math.isnan(x):
            return None
        if math.isinf(x):
            return "inf" if x > 0 else "-inf"
        return float(f"{x:.{DIGITS - 1}e}")
    if isinstance(x, np.integer):
        return int(x)
    return x


def _lockin(x: np.ndarray, t: np.ndarray, f: float, frame: int, n_frames: int, fs: float):
    """Amplitude and phase of ``x`` at ``f`` per frame (see the module docstring)."""
    per = fs / f
    amp, ph = np.zeros(n_frames), np.zeros(n_frames)
    for i in range(n_frames):
        end = (i + 1) * frame
        m = math.floor(frame / per)
        n = int(round(m * per)) if m >= 1 else frame
        seg, ts = x[end - n:end], t[end - n:end]
        z = 2.0 * np.sum(seg * np.exp(-2j * np.pi * f * ts)) / n
        amp[i], ph[i] = abs(z), np.angle(z)
    return amp, ph


def fingerprint(name: str, extra=()) -> dict:
    """Run bundled scene ``name`` (plus overrides ``extra``) and reduce it to its golden."""
    from .. import scene
    from ..check import check_trace
    from ..trace import TraceReader
    from .run import run

    over = [*overrides(name), *extra]
    sc = scene.load(name, over)
    with tempfile.TemporaryDirectory() as d:
        res = run(sc, d, plot=False)
        # every sample of the golden run against the limiter's promises: a violation is in the
        # golden (and fails its comparison) rather than hidden behind envelopes
        checked = check_trace(d)
        tr = TraceReader(Path(d) / "trace")
        fs, block = tr.fs, tr.block
        frame_blocks = max(1, int(round(FRAME_S * fs / block)))
        n_frames = tr.n_blocks // frame_blocks
        frame = frame_blocks * block
        n = n_frames * frame
        t = np.arange(n) / fs
        env = {}
        for sig in tr.dtype.names[3:]:
            if sig == "wake_late_us" or tr.records[sig].size == 0:
                continue
            x = tr.signal(sig)
            if sig in tr.layout["per_block"]:
                env[sig] = {"end": x[:, frame_blocks - 1:n_frames * frame_blocks:frame_blocks]}
                continue
            x = x[:, :n].reshape(x.shape[0], n_frames, frame)
            env[sig] = {"rms": np.sqrt(np.mean(x * x, axis=2)), "peak": np.max(np.abs(x), axis=2)}
        lockin = {}
        for row in res.summary["channels"]:
            ch = tr.channels.index(row["name"])
            for sig in ("tip_um", "drive"):
                if sig not in tr.dtype.names:
                    continue
                x = tr.signal(sig, ch)[:n]
                for f in row.get("freqs_hz") or ():
                    a, p = _lockin(x, t, float(f), frame, n_frames, fs)
                    lockin[f"{sig} {row['name']} {f:g} Hz"] = {"amp": a, "phase": p}
        summary = {k: v for k, v in res.summary.items() if k not in TIMING}
    # through JSON, as a golden file is: string keys, lists
    g = {"scene": name, "overrides": over, "fs": fs, "block": block, "frame_blocks": frame_blocks,
         "frames": n_frames, "blocks": tr.n_blocks, "channels": tr.channels, "envelopes": env,
         "lockin": lockin, "summary": summary,
         "invariants": {"ok": checked["ok"], "violations": checked["violations"]}}
    return json.loads(json.dumps(_round(g)))


# --- comparison ----------------------------------------------------------------------------------

def _flat(x, path=""):
    """``{path: leaf}`` of a nested golden; a leaf is a scalar or a list of scalars."""
    if isinstance(x, dict):
        items = x.items()
    elif isinstance(x, list) and any(isinstance(v, (dict, list)) for v in x):
        items = ((f"[{i}]", v) for i, v in enumerate(x))
    else:
        return {path: x}
    out = {}
    for k, v in items:
        out.update(_flat(v, f"{path}{k}" if k.startswith("[") else (f"{path}.{k}" if path else k)))
    return out


def _is_num(v) -> bool:
    return v is None or v in ("inf", "-inf") or (isinstance(v, (int, float)) and not isinstance(v, bool))


def _numbers(v):
    """A numeric leaf as a float array (None: NaN), or None when the leaf is not numeric."""
    vals = v if isinstance(v, list) else [v]
    if not vals or not all(_is_num(u) for u in vals) or all(u is None for u in vals) and not isinstance(v, list):
        return None
    return np.array([math.nan if u is None else float(u) for u in vals])


def compare(golden: dict, new: dict) -> list[str]:
    """One line per quantity of ``new`` outside the tolerances of ``golden`` (empty: the same)."""
    lines = []
    rtol = tolerance(golden.get("scene", ""))
    atol, phase_tol = rtol / 10, 10 * rtol
    for key in ("scene", "fs", "block", "frame_blocks", "channels"):
        if golden.get(key) != new.get(key):
            lines.append(f"{key}: {golden.get(key)!r} -> {new.get(key)!r}")
    if lines:
        return lines
    for key in ("frames", "blocks"):
        if golden.get(key) != new.get(key):
            lines.append(f"{key}: {golden.get(key)!r} -> {new.get(key)!r}")
    if golden.get("frames") != new.get("frames"):
        # a run of another length (its settle tail follows the model): the frames both have
        # still say what moved in them
        n = min(golden.get("frames", 0), new.get("frames", 0))
        golden, new = _first_frames(golden, n), _first_frames(new, n)
    part = ("envelopes", "lockin", "summary", "invariants")
    g, h = _flat({k: golden.get(k, {}) for k in part}), _flat({k: new.get(k, {}) for k in part})
    scales = _scales(g)
    for key in sorted(set(g) | set(h)):
        if key not in g or key not in h:
            lines.append(f"{key}: {'new' if key not in g else 'gone'}")
            continue
        x, y = _numbers(g[key]), _numbers(h[key])
        if x is None or y is None or x.shape != y.shape:
            if g[key] != h[key]:
                lines.append(f"{key}: {g[key]!r} -> {h[key]!r}")
            continue
        if key.endswith(".phase"):
            amp = _numbers(g[key[:-len("phase")] + "amp"])
            top = np.max(np.abs(amp[np.isfinite(amp)]), initial=0.0)
            on = np.isfinite(amp) & (amp > PHASE_FLOOR * top)
            d = np.abs(np.angle(np.exp(1j * (y - x))))
            bad = on & ~(d <= phase_tol)
            if np.any(bad):
                i = int(np.argmax(np.where(bad, d, -1.0)))
                lines.append(f"{key}[{i}]: {x[i]:.7g} -> {y[i]:.7g} rad (off by {d[i]:.2g} rad, "
                             f"tolerance {phase_tol:g})")
            continue
        tol = atol * scales.get(key.split("[")[0], 0.0) + rtol * np.abs(np.nan_to_num(x, posinf=0.0, neginf=0.0))
        d = np.abs(y - x)
        bad = (np.isnan(x) != np.isnan(y)) | (~np.isnan(x) & ~(d <= tol) & (x != y))
        if np.any(bad):
            i = int(np.argmax(np.where(bad, np.nan_to_num(d / np.maximum(tol, 1e-300), nan=np.inf), -1.0)))
            rel = d[i] / abs(x[i]) if x[i] else math.inf
            lines.append(f"{key}[{i}]: {x[i]:.7g} -> {y[i]:.7g} (relative {rel:.2g}; tolerance "
                         f"{tol[i]:.2g})")
    return lines


def _first_frames(g: dict, n: int) -> dict:
    """``g`` with its per-frame quantities cut to the first ``n`` frames."""
    g = json.loads(json.dumps(g))
    for sig in g.get("envelopes", {}).values():
        for k, rows in sig.items():
            sig[k] = [row[:n] if isinstance(row, list) else row for row in rows]
    for q in g.get("lockin", {}).values():
        for k, v in q.items():
            q[k] = v[:n]
    return g


def _scales(flat: dict) -> dict:
    """Per quantity, its largest finite |value| over its rows (``a.rms[3]``: every ``a.rms[i]``)."""
    out: dict = {}
    for k, v in flat.items():
        x = _numbers(v)
        if x is not None and np.any(np.isfinite(x)):
            stem = k.split("[")[0]
            out[stem] = max(out.get(stem, 0.0), float(np.max(np.abs(x[np.isfinite(x)]))))
    return out


# --- files and command ---------------------------------------------------------------------------

def path_of(name: str, directory=DEFAULT_DIR) -> Path:
    return Path(directory) / f"{name}.json"


def load(name: str, directory=DEFAULT_DIR) -> dict:
    return json.loads(path_of(name, directory).read_text())


def write(golden: dict, directory=DEFAULT_DIR) -> Path:
    p = path_of(golden["scene"], directory)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(golden, separators=(",", ":"), sort_keys=True) + "\n")
    return p


def main(argv=None) -> int:
    from .. import scene

    ap = argparse.ArgumentParser(prog="python -m rtctl.engine.golden",
                                 description="Rewrite the golden traces of the bundled scenes (tests/golden/) "
                                             "and print what changed; --check only compares.")
    ap.add_argument("scenes", nargs="*", help="bundled scenes (default: all)")
    ap.add_argument("--check", action="store_true", help="compare only; exit 1 on a difference")
    ap.add_argument("--dir", default=str(DEFAULT_DIR), help="where the goldens are (default: %(default)s)")
    a = ap.parse_args(argv)
    names = a.scenes or scene.bundled()
    unknown = sorted(set(names) - set(scene.bundled()))
    if unknown:
        print(f"rtctl golden: error: {', '.join(unknown)}: not a bundled scene ({', '.join(scene.bundled())})",
              file=sys.stderr)
        return 2
    changed = 0
    for name in names:
        new = fingerprint(name)
        p = path_of(name, a.dir)
        if not p.exists():
            diff = ["no golden yet"]
        else:
            diff = compare(json.loads(p.read_text()), new)
        changed += bool(diff)
        if not diff:
            same = p.exists() and json.loads(p.read_text()) == new
            print(f"{name}: {'identical' if same else f'unchanged (within tolerance {tolerance(name):g})'}")
        else:
            print(f"{name}: {len(diff)} difference(s) beyond tolerance {tolerance(name):g}")
        for line in diff[:20]:
            print(f"  {line}")
        if len(diff) > 20:
            print(f"  ... and {len(diff) - 20} more")
        if not a.check:
            w = write(new, a.dir)
            print(f"  wrote {w} ({w.stat().st_size / 1e3:.1f} kB)")
    if a.check:
        return 1 if changed else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
