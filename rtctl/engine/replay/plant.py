"""``rtctl replay --mode plant``: the recorded drive into the scene model's simulated plant.

Whatever backend recorded the trace (the simulated rig, an audio interface, a DAQ, a serial
pin controller), its ``drive`` record is what went to the amplifier; here it drives the
simulated plant of the recorded scene's *model* (no simulated device's mismatch, ``--set`` changes on
top), block by block, with the scene's events (a finger lifting) at their blocks. The plant's
sensed currents are compared with the recorded ones: the recorded currents answering drive block
``k`` sit in record ``k + L`` (``L``: the backend's latency in blocks; the lag that fits best
of 0 to :data:`MAX_LAG` is used and named, beside the recorded ``latency_blocks``).

The model's currents carry no sensor noise (``sense.noise`` = 0), so the residual's floor is the
recorded device's own noise over its signal (about 1 % on the demo scene's weakest rows, 0.2 %
over all). ``--skip S`` leaves the first seconds out of the comparison (the plant still runs
through them): a device that started listening a few blocks into the run (an emulator that
connected late) is not at rest where the model is.

Per sensed row and per window of :data:`WINDOW_S`: the residual ``rms(sim - rec) / rms(rec)`` in
%, and the phase of the simulated against the recorded current (the angle of the sum of their
analytic signals' product, degrees; positive: the model leads). Over the whole run: the same
per row, and the device-over-model gain ``sum(rec * sim) / sum(sim * sim)``: a device whose
currents are 10 % larger than the model's shows a residual near 10 % and a gain near 1.10.
Where the trace holds the true tip (a simulated recording), the simulated tip is compared too.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ...trace import TraceError
from . import scene_of

WINDOW_S = 0.1
MAX_LAG = 8
#: Residual (%) under which the model is said to match the device.
MATCH_PCT = 1.0
#: A residual up to this multiple of the recorded sensor noise's own is that noise, not the model.
NOISE_EXPLAINS = 1.25


def simulate(reader, overrides=()):
    """The simulated plant's answer to the recorded drive: sensed currents ``(n, rows, block)``
    (row ``k``: the currents of drive block ``k``) and the true tip, µm, ``(n, channels, block)``."""
    from ..rig import build

    scene = scene_of(reader, overrides, backend="sim", model_only=True, quiet=True)
    rig = build(scene, device_in_block=False)  # the recorded drive, not the block's, reaches the plant
    drive = reader.records["drive"]
    if rig.fs != reader.fs or rig.block != reader.block or drive.shape[1] != rig.n_channels:
        raise TraceError(f"{reader.path}: the recorded scene builds a rig of {rig.n_channels} channels at "
                         f"{rig.fs:g} Hz, block {rig.block}; the trace has {drive.shape[1]} at {reader.fs:g} Hz, "
                         f"block {reader.block}")
    n = reader.n_blocks
    sensed = np.zeros((n, *rig.sensed.shape), dtype=np.float32)
    tip = np.zeros((n, rig.n_channels, rig.block), dtype=np.float32)
    rig.reset()
    dev = rig.device
    for k in range(n):
        rig.apply_schedule(k)
        rig.step()  # the scene's own block: its parameter changes (events) reach the plant
        np.copyto(rig.out, np.nan_to_num(drive[k].astype(float)))  # a dropped record: 0 V
        dev.write()
        dev.read()
        sensed[k] = rig.sensed
        tip[k] = rig.truth[:, 0, :] * 1e6
    return sensed, tip, rig.sensed_names, rig.channel_names


def _best_lag(rec, sim, start):
    n = len(rec)
    best = (np.inf, start)
    for lag in range(0, min(MAX_LAG, n - 1) + 1):
        r, s = rec[lag:].astype(float), sim[: n - lag].astype(float)
        ok = np.isfinite(r).all(axis=(1, 2))
        num, den = np.sum((r[ok] - s[ok]) ** 2), np.sum(r[ok] ** 2)
        if den > 0 and num / den < best[0]:
            best = (num / den, lag)
    return best[1]


def residuals(rec, sim, fs, block, names):
    """Per-row residual (%) and phase (degrees) per window and overall, and the gain."""
    from scipy.signal import hilbert

    n, rows, _ = rec.shape
    r = rec.transpose(1, 0, 2).reshape(rows, -1).astype(float)
    s = sim.transpose(1, 0, 2).reshape(rows, -1).astype(float)
    bad = ~np.isfinite(r)
    r[bad], s[bad] = 0.0, 0.0
    # a comparison shorter than one window (a short trace, a late --skip) is one shorter window
    w = min(max(block, int(round(WINDOW_S * fs / block)) * block), r.shape[1])
    nw = max(1, r.shape[1] // w)
    hr, hs = hilbert(r, axis=1), hilbert(s, axis=1)
    rr = (r[:, : nw * w] ** 2).reshape(rows, nw, w).sum(axis=2)
    dd = ((s - r)[:, : nw * w] ** 2).reshape(rows, nw, w).sum(axis=2)
    cross = (hs * np.conj(hr))[:, : nw * w].reshape(rows, nw, w).sum(axis=2)
    live = rr > 1e-12 * max(rr.max(), 1e-300)
    res_w = np.where(live, 100 * np.sqrt(dd / np.where(live, rr, 1)), np.nan)
    ph_w = np.where(live, np.degrees(np.angle(cross)), np.nan)
    per_row = []
    for i, name in enumerate(names):
        den = np.sum(r[i] ** 2)
        ss = np.sum(s[i] ** 2)
        per_row.append({"row": name,
                        "residual_pct": float(100 * np.sqrt(np.sum((s[i] - r[i]) ** 2) / den)) if den > 0 else None,
                        "phase_deg": float(np.degrees(np.angle(np.sum(hs[i] * np.conj(hr[i]))))) if den > 0 else None,
                        "gain": float(np.sum(r[i] * s[i]) / ss) if ss > 0 else None})
    total = float(100 * np.sqrt(np.sum((s - r) ** 2) / np.sum(r ** 2))) if np.sum(r ** 2) > 0 else None
    gain = float(np.sum(r * s) / np.sum(s * s)) if np.sum(s * s) > 0 else None
    t = (np.arange(nw) + 0.5) * w / fs
    return {"residual_pct": total, "gain": gain, "rows": per_row,
            "window_s": w / fs, "t_s": t, "window_residual_pct": res_w, "window_phase_deg": ph_w}


def replay_plant(reader, out: Path, overrides=(), skip_s: float = 0.0) -> dict:
    if "sensed" not in reader.dtype.names or reader.dtype["sensed"].shape[0] == 0:
        raise TraceError(f"{reader.path}: the trace has no sensed currents to compare the plant with")
    if reader.n_blocks < 2:
        raise TraceError(f"{reader.path}: {reader.n_blocks} blocks: too short to replay")
    sim, tip, names, channels = simulate(reader, overrides)
    rec = np.asarray(reader.records["sensed"])
    if rec.shape[1] != sim.shape[1]:
        raise TraceError(f"{reader.path}: the trace has {rec.shape[1]} sensed rows, the scene's plant {sim.shape[1]}")
    recorded_lag = int(reader.meta.get("latency_blocks") or 1)
    lag = _best_lag(rec, sim, recorded_lag)
    n = len(rec) - lag
    # NaN, infinity or a skip past the end: refused, not clamped to the last block
    k0 = int(round(skip_s * reader.fs / reader.block)) if math.isfinite(skip_s) and skip_s >= 0 else -1
    if not 0 <= k0 < n:
        raise TraceError(f"--skip {skip_s:g}: must be >= 0 and shorter than the "
                         f"{n * reader.block / reader.fs:g} s of the trace compared")
    res = residuals(rec[lag + k0:], sim[k0:n], reader.fs, reader.block, names)
    res["noise_floor_pct"], floors = _noise_floor(reader, rec[lag + k0:], names)
    for row, floor in zip(res["rows"], floors):
        row["noise_floor_pct"] = floor
    res["t_s"] = res["t_s"] + k0 * reader.block / reader.fs
    rep = {"mode": "plant", "blocks": n - k0, "skip_s": k0 * reader.block / reader.fs,
           "latency_blocks": lag, "recorded_latency_blocks": recorded_lag,
           **{k: v for k, v in res.items() if not k.startswith("window") and k != "t_s"}, "window_s": res["window_s"]}
    if "tip_um" in reader.dtype.names:  # a simulated recording's truth: the tip, same block
        rt = np.asarray(reader.records["tip_um"], dtype=float)
        den = np.nansum(rt ** 2)
        rep["tip_residual_pct"] = (float(100 * np.sqrt(np.nansum((tip[k0:] - rt[k0:]) ** 2) / np.nansum(rt[k0:] ** 2)))
                                   if den > 0 else None)
    # the worst row the noise does not explain: an idle channel's row (the device's noise against
    # the model's nothing) is 100 % whatever the model is worth
    rows = [r for r in res["rows"] if r["residual_pct"] is not None]
    telling = [r for r in rows
               if r["noise_floor_pct"] is None or r["residual_pct"] > NOISE_EXPLAINS * r["noise_floor_pct"]]
    driven = [r for r in rows if r["gain"] is not None]  # else: the model's currents are all zero there
    worst = max(telling or driven or rows, key=lambda r: r["residual_pct"], default=None)
    rep["line"] = _line(rep, worst)
    rep["exit"] = 0
    out.mkdir(parents=True, exist_ok=True)
    _table(out / "residual.csv", res, names)
    _plot(out / "plant.png", res, names, rep["line"])
    rep["out"] = str(out)
    (out / "replay.json").write_text(json.dumps(rep, indent=1))
    rep["details"] = [f"{r['row']:<24} residual {r['residual_pct']:8.3f} %  phase {r['phase_deg']:+7.2f} deg  "
                      + ("gain - (the model's are zero)" if r["gain"] is None else f"gain {r['gain']:.4f}")
                      + (" (the sensor's noise)" if r in rows and r not in telling else "")
                      for r in res["rows"] if r["residual_pct"] is not None]
    return rep


def _noise_floor(reader, rec, names):
    """The residual (%) the recorded device's sensor noise alone gives against noiseless model
    currents, over all rows and per row: ``rms(noise) / rms(rec)``, the noise the recorded scene
    gives its ADC input (V rms) over its shunt. Where the recorded currents are small (a settle
    tail of 0 V, an idle channel) it nears 100 %: there the residual measures the noise, not the
    model."""
    scene = scene_of(reader)
    # a bimorph's segment currents pass the sense chain's noise (rtctl.plant.frontend.CurrentSense);
    # the other groups' sensed rows carry none here
    sigma = {g.name: g.sense.noise / g.sense.shunt for g in scene.actuator if g.type == "bimorph"}
    s = np.array([sigma.get(name.rsplit(".", 2)[0], 0.0) for name in names])
    r = rec.astype(float)
    r[~np.isfinite(r)] = 0.0  # a dropped record: compared as 0 (residuals)
    per = r.shape[0] * r.shape[2]
    den = np.sum(r ** 2, axis=(0, 2))
    rows = [float(100 * x * np.sqrt(per / d)) if d > 0 else None for x, d in zip(s, den)]
    total = float(100 * np.sqrt(np.sum(s ** 2) * per / np.sum(den))) if np.sum(den) > 0 else None
    return total, rows


def _line(rep, worst) -> str:
    if rep["residual_pct"] is None:
        return "plant replay: the recorded currents are all zero: nothing to compare"
    if rep["gain"] is None:
        return (f"plant replay of {rep['blocks']} blocks: the model's currents are all zero where the recorded "
                f"ones are not ({rep['residual_pct']:.3g} % rms residual)")
    lag = rep["latency_blocks"]
    lat = (f"latency {lag} blocks" + ("" if lag == rep["recorded_latency_blocks"] else
                                      f" (the trace says {rep['recorded_latency_blocks']})"))
    head = (f"plant replay of {rep['blocks']} blocks, {lat}: residual {rep['residual_pct']:.3g} % rms "
            f"(worst {worst['row']} {worst['residual_pct']:.3g} %, phase {worst['phase_deg']:+.2f} deg)")
    tip = f", tip {rep['tip_residual_pct']:.3g} %" if rep.get("tip_residual_pct") is not None else ""
    if rep["residual_pct"] < MATCH_PCT:
        return f"{head}{tip}: the model matches the device (under {MATCH_PCT:g} %)"
    floor = rep.get("noise_floor_pct")
    if floor is not None and rep["residual_pct"] <= NOISE_EXPLAINS * floor:
        return (f"{head}{tip}: the sensor's noise alone gives {floor:.3g} % over currents this small: the comparison "
                f"cannot tell the model from the device (compare where they are driven: a shorter --skip)")
    return (f"{head}{tip}: the device differs from the model: its currents are {rep['gain']:.4g} x the model's "
            f"({100 * (rep['gain'] - 1):+.3g} %)")


def _table(path, res, names) -> None:
    with open(path, "w") as f:
        f.write("t_s,row,residual_pct,phase_deg\n")
        for j, t in enumerate(res["t_s"]):
            for i, name in enumerate(names):
                f.write(f"{t:.6g},{name},{res['window_residual_pct'][i, j]:.6g},{res['window_phase_deg'][i, j]:.6g}\n")


def _plot(path, res, names, title) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    for i, name in enumerate(names):
        a.plot(res["t_s"], res["window_residual_pct"][i], label=name, lw=1)
        b.plot(res["t_s"], res["window_phase_deg"][i], lw=1)
    a.set_ylabel("residual, % rms")
    b.set_ylabel("phase sim - rec, deg")
    b.set_xlabel("time, s")
    a.set_title(title if len(title) < 110 else title[:107] + "...", fontsize=8)
    if len(names) <= 12:
        a.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
