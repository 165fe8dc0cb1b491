"""The invariant checker: what the final limiter promises, verified on every sample of a trace.

``rtctl check-trace TRACE [--json]`` (TRACE: a run's directory or its ``trace/``) and
:func:`check_trace` check, from the trace alone and the limits the run wrote into it
(``meta.limits``, :meth:`rtctl.safety.Limiter.bounds`):

============== ===============================================================================
``nonfinite``  no drive sample is NaN or infinite (placeholders of dropped records excepted)
``voltage``    ``|v| <= max_voltage`` on every sample
``slew``       ``|v[i] - v[i-1]| <= max_step`` between consecutive samples, across blocks, from 0 V
``mean``       the running mean the limiter bounds (a piezo's DC offset, an SMA spring's duty),
               recomputed from the samples, within its bound before the final fade begins
``temperature`` a block over the temperature limit carries ``OVERTEMP``
``fade``       after a block with a fault bit, every channel reaches 0 V within the fade (one block,
               longer only where the slew bound needs it), never rising, and stays there
``end``        the trace ends with every output at 0 V
``records``    records numbered 0, 1, 2, ... with none missing
``summary``    with the run's ``summary.json``: it is strict JSON; its faults are there exactly when
               a record carries a fault bit; its warnings are the other bits seen before the fade;
               its duration matches the records
============== ===============================================================================

The trace stores float32: each bound is checked with a tolerance of 1e-6 of the channel's
``max_voltage`` (float32 rounding is 6e-8 of it), far below any violation worth the name.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from . import safety
from .errors import RtctlError

INVARIANTS = ("nonfinite", "voltage", "slew", "mean", "temperature", "fade", "end", "records", "summary")
_REL = 1e-6


class TraceUnreadable(RtctlError):
    """The trace cannot be read, or has no limits to check against."""


def _open(path):
    from .errors import TraceError
    from .trace import TraceReader

    p = Path(path)
    tdir = p / "trace" if (p / "trace" / "trace.json").exists() else p
    try:
        r = TraceReader(tdir)
    except TraceError as e:  # its own line names the trace and what is wrong with it
        raise TraceUnreadable(str(e)) from None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise TraceUnreadable(f"{path}: not a readable rtctl trace ({e})") from None
    limits = r.layout.get("meta", {}).get("limits")
    if not limits:
        raise TraceUnreadable(f"{tdir}: the trace holds no limits (meta.limits): it was written by an "
                              "rtctl without the invariant checker; run the scene again")
    if "drive" not in (r.dtype.names or ()):
        raise TraceUnreadable(f"{tdir}: the trace has no drive signal")
    summary = None
    sp = tdir.parent / "summary.json"
    if tdir.name == "trace" and sp.exists():
        summary = sp
    return r, limits, summary


def check_trace(path, summary=None) -> dict:
    """Check the trace at ``path`` (a run directory or its trace directory) against its limits;
    ``summary``: a summary dict or file to check it against (default: the run's summary.json
    beside the trace, if there is one).

    Returns
    -------
    dict
        ``ok``, ``blocks``, ``channels``, ``samples``, ``dropped`` (placeholder records), ``cut``
        (why its writer closed it early, a full disk: its last record is not the run's end, and
        the summary's fault is that failure; None otherwise),
        ``violations`` (invariant -> samples or blocks violating it), ``first`` (invariant -> where
        it first failed, in words).

    Raises
    ------
    TraceUnreadable
    """
    r, lim, found = _open(path)
    if summary is None:
        summary = found
    # a trace its writer closed early (a full disk): it ends where the write failed, not where the
    # run faded out, and the run's fault (that failure) is in the summary, not in a record
    cut = r.layout.get("write_error")
    rep = {"trace": str(path), "ok": True, "blocks": int(r.n_blocks), "channels": len(r.channels),
           "samples": 0, "dropped": 0, "violations": {k: 0 for k in INVARIANTS}, "first": {}, "cut": cut}

    def bad(name, count, where):
        if count:
            rep["violations"][name] += int(count)
            rep["first"].setdefault(name, where)

    n_b, blk = int(r.n_blocks), int(r.block)
    rec = r.records
    status = np.asarray(rec["status"], dtype=np.int64) if n_b else np.zeros(0, dtype=np.int64)
    placeholder = (status & safety.TRACE_DROPPED) != 0
    rep["dropped"] = int(placeholder.sum())
    numbers = np.asarray(rec["block"], dtype=np.int64) if n_b else np.zeros(0, dtype=np.int64)
    wrong = np.nonzero(numbers != np.arange(n_b))[0]
    bad("records", wrong.size, f"record {wrong[0]} is numbered {numbers[wrong[0]]}" if wrong.size else "")
    drive = np.asarray(rec["drive"], dtype=float) if n_b else np.zeros((0, len(r.channels), blk))
    n_ch = drive.shape[1]
    vmax = np.asarray(lim["max_voltage"], dtype=float)
    step = np.asarray(lim["max_step"], dtype=float)
    if vmax.size != n_ch:
        raise TraceUnreadable(f"{path}: meta.limits has {vmax.size} channels, the drive {n_ch}")
    rep["samples"] = int(n_b * n_ch * blk)
    tol = _REL * vmax[:, None]
    name = r.channels

    def where(b, c, i=None):
        s = f"block {b}, channel {name[c] if c < len(name) else c}"
        return s if i is None else s + f", sample {i}"

    live = ~placeholder
    v = drive.transpose(1, 0, 2)  # (channel, block, sample)
    finite = np.isfinite(v)
    nf = ~finite & live[None, :, None]
    if nf.any():
        c, b, i = (int(x[0]) for x in np.nonzero(nf))
        bad("nonfinite", nf.sum(), where(b, c, i) + f": {v[c, b, i]}")
    vv = np.where(finite & live[None, :, None], v, 0.0)
    over = np.abs(vv) > vmax[:, None, None] + tol[:, :, None]
    if over.any():
        c, b, i = (int(x[0]) for x in np.nonzero(over))
        bad("voltage", over.sum(), where(b, c, i) + f": {vv[c, b, i]:.6g} V beyond {vmax[c]:g} V")
    # slew: consecutive samples, the first from 0 V; a step into or out of a placeholder is not one
    flat = vv.reshape(n_ch, -1)
    ok_s = np.repeat(live, blk)
    prev = np.concatenate([np.zeros((n_ch, 1)), flat[:, :-1]], axis=1)
    pair = ok_s & np.concatenate([[True], ok_s[:-1]])
    jump = (np.abs(flat - prev) > step[:, None] + tol) & pair[None, :]
    if jump.any():
        c, j = (int(x[0]) for x in np.nonzero(jump))
        bad("slew", jump.sum(), where(j // blk, c, j % blk)
            + f": step {flat[c, j] - prev[c, j]:.6g} V beyond {step[c]:.6g} V per sample")

    faults = np.nonzero(((status & safety.FAULTS) != 0) & ~placeholder)[0]
    first_fault = int(faults[0]) if faults.size else None
    summ = _summary(summary, rep, bad)
    run_blocks = None
    if summ is not None:
        try:
            run_blocks = int(round(float(summ["duration_s"]) * float(summ["fs"]) / float(summ["block"])))
        except (KeyError, TypeError, ValueError):
            bad("summary", 1, "summary.json has no duration_s, fs or block")
    # where the final fade begins: after a fault's block, else where the summary says the run ended
    fade_from = first_fault + 1 if first_fault is not None else run_blocks
    if fade_from is None:
        fade_from = max(0, n_b - 1 - int(math.ceil((np.max(vmax / step) + 1) / blk)))
    fade_from = min(fade_from, n_b)
    _check_mean(vv, lim, blk, fade_from, live, bad, where)
    if "temperature" in (r.dtype.names or ()) and n_b:
        temp = np.asarray(rec["temperature"], dtype=float)  # (block, channel)
        tmax = np.asarray(lim["temperature"], dtype=float)
        hot = (temp > tmax[None, :] + 1e-3) & ((status & safety.OVERTEMP) == 0)[:, None] & live[:, None]
        if hot.any():
            b, c = (int(x[0]) for x in np.nonzero(hot))
            bad("temperature", hot.sum(), where(b, c) + f": {temp[b, c]:.4g} degC over {tmax[c]:g} degC "
                "without OVERTEMP")
    if first_fault is not None:
        _check_fade(flat, first_fault, blk, step, tol[:, 0], ok_s, bad, where)
    if n_b and np.any(flat[:, -1] != 0.0) and live[-1] and not cut:
        c = int(np.nonzero(flat[:, -1])[0][0])
        bad("end", int(np.count_nonzero(flat[:, -1])), where(n_b - 1, c, blk - 1) + f": ends at {flat[c, -1]:.6g} V")
    if summ is not None:
        _check_summary(summ, status, first_fault, run_blocks, fade_from, n_b, bad, cut)
    rep["ok"] = not any(rep["violations"].values())
    return rep


def _check_mean(vv, lim, blk, fade_from, live, bad, where):
    """The running means the limiter bounds, recomputed block by block before the fade."""
    from scipy.signal import lfilter

    kind = np.asarray(lim["mean_kind"], dtype=int)
    if not np.any(kind != safety.MEAN_OFF) or fade_from <= 0:
        return
    bound = np.asarray(lim["mean_bound"], dtype=float)
    alpha = np.asarray(lim["mean_alpha"], dtype=float)
    scale = np.asarray(lim["mean_scale"], dtype=float)
    thr = np.asarray(lim["mean_threshold"], dtype=float)
    vmax = np.asarray(lim["max_voltage"], dtype=float)
    x = vv[:, :fade_from, :]
    for c in np.nonzero(kind != safety.MEAN_OFF)[0]:
        a = -math.expm1(-blk * alpha[c])
        row = x[c]
        if kind[c] == safety.MEAN_DC:
            measures, tols = [row.mean(axis=1)], [_REL * vmax[c]]
        elif kind[c] == safety.MEAN_DUTY:
            measures = [scale[c] * np.mean(np.maximum(row, 0.0) ** 2, axis=1),
                        scale[c] * np.mean(np.minimum(row, 0.0) ** 2, axis=1)]
            tols = [4 * _REL] * 2
        else:  # commanded time: a sample rounding across the threshold moves the measure by 1/blk
            measures = [np.mean(row > thr[c], axis=1), np.mean(row < -thr[c], axis=1)]
            tols = [4 * _REL + 2 * a / blk] * 2
        for b_k, t in zip(measures, tols):
            m = lfilter([a], [1.0, -(1.0 - a)], b_k)
            over = (np.abs(m) > bound[c] + t) & live[:fade_from]
            if over.any():
                b = int(np.nonzero(over)[0][0])
                bad("mean", over.sum(), where(b, int(c)) + f": running mean {m[b]:.6g} beyond {bound[c]:.6g}")


def _check_fade(flat, k, blk, step, tol, ok_s, bad, where):
    """After fault block ``k``: every channel at 0 V within the fade, magnitude never rising."""
    start = (k + 1) * blk
    if start >= flat.shape[1]:
        bad("fade", 1, f"block {k}: the trace ends at the fault's block, without its fade")
        return
    last = np.abs(flat[:, start - 1])
    need = int(max(blk, np.floor(np.max(last / step)) + 1))
    tail = np.abs(flat[:, start:])
    rising = (np.diff(np.concatenate([last[:, None], tail], axis=1), axis=1) > tol[:, None]) & ok_s[None, start:]
    if rising.any():
        c, j = (int(x[0]) for x in np.nonzero(rising))
        bad("fade", rising.sum(), where((start + j) // blk, c, (start + j) % blk) + ": output rises during the fade")
    late = (tail[:, need:] != 0.0) & ok_s[None, start + need:]
    if late.any():
        c, j = (int(x[0]) for x in np.nonzero(late))
        j += start + need
        bad("fade", late.sum(), where(j // blk, c, j % blk) + f": {flat[c, j]:.6g} V after the fade "
            f"({need} samples) should have reached 0 V")
    if tail.shape[1] < need:
        bad("fade", 1, f"block {k}: the trace ends {need - tail.shape[1]} samples before the fade does")


def _summary(summary, rep, bad):
    if summary is None:
        return None
    if isinstance(summary, dict):
        return summary
    try:
        text = Path(summary).read_text()
        return json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(f"{c} is not JSON")))
    except (OSError, ValueError) as e:
        bad("summary", 1, f"{summary}: not strict JSON ({e})")
        return None


def _check_summary(summ, status, first_fault, run_blocks, fade_from, n_b, bad, cut=None):
    faults = summ.get("faults") or []
    # (the trace's own write failure is a fault of the run that no record can carry)
    written = bool(cut) and (summ.get("trace") or {}).get("error") is not None
    if bool(faults) != (first_fault is not None) and not (written and faults and first_fault is None):
        bad("summary", 1, f"summary lists {len(faults)} faults, the records {'a' if first_fault is not None else 'no'} "
            "fault bit")
    if run_blocks is not None and run_blocks > n_b and not cut:
        bad("summary", 1, f"summary says {run_blocks} blocks ran, the trace has {n_b} records")
    words = set(summ.get("warnings") or [])
    seen_all = int(np.bitwise_or.reduce(status)) if status.size else 0
    before = status[: min(fade_from, n_b)]
    placeholder = (before & safety.TRACE_DROPPED) != 0
    seen_run = int(np.bitwise_or.reduce(before[~placeholder])) if before.size else 0
    quiet = safety.FAULTS | safety.DEADLINE_MISSED | safety.TRACE_DROPPED
    for bit, text in safety.STATUS_NAMES.items():
        if bit & quiet:
            continue
        if text in words and not seen_all & bit:
            bad("summary", 1, f"summary warns '{text}', no record carries the bit")
        if seen_run & bit and text not in words:
            bad("summary", 1, f"records carry '{text}', the summary does not warn of it")


def main(argv=None) -> int:
    """``rtctl check-trace TRACE [--json]``: 0 when every invariant holds, 1 when one does not,
    2 when the trace cannot be read."""
    import argparse
    import sys

    p = argparse.ArgumentParser(prog="rtctl check-trace", description="verify on every sample of a trace what "
                                "the final limiter promises (docs/faults.md)")
    p.add_argument("trace", metavar="TRACE", help="a run's output directory or its trace/ directory")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    a = p.parse_args(argv)
    try:
        rep = check_trace(a.trace)
    except TraceUnreadable as e:
        print(f"rtctl check-trace: error: {e}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(rep, indent=1))
    else:
        state = "ok" if rep["ok"] else "VIOLATED"
        print(f"{a.trace}: {state}: {rep['blocks']} blocks x {rep['channels']} channels ({rep['samples']} samples), "
              f"{rep['dropped']} dropped records")
        for k in INVARIANTS:
            n = rep["violations"][k]
            if k == "end" and rep["cut"]:
                print(f"  {k:<12} not checked: the trace ends early ({rep['cut']})")
                continue
            print(f"  {k:<12} {'ok' if not n else f'{n} violations; first: ' + rep['first'][k]}")
    return 0 if rep["ok"] else 1
