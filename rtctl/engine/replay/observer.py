"""``rtctl replay --mode observer``: the recorded drive and currents through the observer and
controller offline.

The recorded scene (``--set`` changes on top: another observer or controller setting) is built
with the recorded backend's latency, and its block function runs stage by stage: each block's
sensed currents are the recorded record's, and right after the limiter the recorded drive
replaces the rig's own, so the observer sees exactly what the device was driven with and what
it answered, and the controller acts on those estimates. Per block and channel the report
holds the offline estimate beside the recorded one (``estimated_um``), and the drive the offline
controller commanded (its rms over the block) beside the recorded drive's.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...trace import TraceError
from . import scene_of


def run_offline(reader, overrides=()):
    """Per block: the offline estimates (µm) and commanded drive rms (V), ``(n, channels)`` each."""
    from ..rig import build

    scene = scene_of(reader, overrides, backend="sim", latency=True)
    if not (scene.control.observe or scene.control.mode == "closed"):
        raise TraceError(f"{reader.path}: the recorded scene has no observer (control.observe = false, control.mode = "
                         f"{scene.control.mode!r}): add one with --set control.observe=true")
    rig = build(scene, device_in_block=False)  # no plant in the stages: the recorded currents feed them
    drive, sensed = reader.records["drive"], reader.records["sensed"]
    if drive.shape[1:] != rig.out.shape or sensed.shape[1:] != rig.sensed.shape:
        raise TraceError(f"{reader.path}: the recorded scene's rig has drive {rig.out.shape} and sensed "
                         f"{rig.sensed.shape} per block; the trace {drive.shape[1:]} and {sensed.shape[1:]}")
    lim = [i for i, s in enumerate(rig.stages) if s.name == "limiter"][0]
    n = reader.n_blocks
    est = np.full((n, rig.n_channels), np.nan)
    cmd = np.zeros((n, rig.n_channels))
    rig.reset()
    for k in range(n):
        rig.apply_schedule(k)
        np.copyto(rig.sensed, np.nan_to_num(sensed[k].astype(float)))
        for i, st in enumerate(rig.stages):
            st.call()
            if i == lim:
                cmd[k] = np.sqrt(np.mean(rig.out ** 2, axis=1))
                np.copyto(rig.out, np.nan_to_num(drive[k].astype(float)))
        est[k] = rig.estimated_amp * 1e6
    return est, cmd, rig.channel_names


def replay_observer(reader, out: Path, overrides=()) -> dict:
    if reader.n_blocks < 1:
        raise TraceError(f"{reader.path}: no blocks to replay ({reader.recovery()})")
    est, cmd, names = run_offline(reader, overrides)
    drive = np.asarray(reader.records["drive"], dtype=float)
    rec_cmd = np.sqrt(np.mean(drive ** 2, axis=2))
    rec_est = (np.asarray(reader.records["estimated_um"], dtype=float) if "estimated_um" in reader.dtype.names
               else np.full_like(est, np.nan))
    n_run = run_blocks(reader)
    rows = []
    for c, name in enumerate(names):
        both = np.isfinite(est[:, c]) & np.isfinite(rec_est[:, c])
        d = np.abs(est[both, c] - rec_est[both, c])
        ref = np.nanmax(np.abs(rec_est[both, c])) if both.any() else np.nan
        live = np.isfinite(rec_cmd[:, c]) & (np.arange(reader.n_blocks) < n_run)  # the run's fade aside
        dc = np.abs(cmd[live, c] - rec_cmd[live, c])
        rows.append({"channel": name, "blocks_estimated": int(both.sum()),
                     "estimate_max_abs_um": float(d.max()) if d.size else None,
                     "estimate_max_rel": float(d.max() / ref) if d.size and ref > 0 else None,
                     "estimate_final_um": float(est[-1, c]) if np.isfinite(est[-1, c]) else None,
                     "recorded_final_um": float(rec_est[-1, c]) if np.isfinite(rec_est[-1, c]) else None,
                     "command_max_abs_v": float(dc.max()) if dc.size else None,
                     "command_max_rel": float(dc.max() / max(rec_cmd[live, c].max(), 1e-300)) if dc.size else None})
    est_rel = [r["estimate_max_rel"] for r in rows if r["estimate_max_rel"] is not None]
    cmd_rel = [r["command_max_rel"] for r in rows if r["command_max_rel"] is not None]
    line = (f"observer replay of {reader.n_blocks} blocks: offline estimates within "
            f"{max(est_rel):.2g} of the recorded ones (largest gap relative to a channel's largest estimate)"
            if est_rel else f"observer replay of {reader.n_blocks} blocks: the trace holds no recorded estimates")
    if cmd_rel:
        line += f"; commanded drive rms within {max(cmd_rel):.2g} of the recorded drive's"
        if n_run < reader.n_blocks:
            line += f" (over the run's {n_run} blocks; the {reader.n_blocks - n_run} fade blocks after it left out)"
    rep = {"mode": "observer", "blocks": reader.n_blocks, "channels": rows, "line": line, "exit": 0}
    out.mkdir(parents=True, exist_ok=True)
    t = (np.arange(reader.n_blocks) + 1) * reader.block / reader.fs
    with open(out / "observer.csv", "w") as f:
        f.write("t_s,channel,estimate_um,recorded_estimate_um,command_rms_v,recorded_drive_rms_v\n")
        for k in range(reader.n_blocks):
            for c, name in enumerate(names):
                f.write(f"{t[k]:.6g},{name},{est[k, c]:.6g},{rec_est[k, c]:.6g},{cmd[k, c]:.6g},{rec_cmd[k, c]:.6g}\n")
    _plot(out / "observer.png", t, est, rec_est, cmd, rec_cmd, names, line)
    rep["out"] = str(out)
    (out / "replay.json").write_text(json.dumps(rep, indent=1))
    rep["details"] = [f"{r['channel']:<16} estimate gap {_g(r['estimate_max_abs_um'])} um, command gap "
                      f"{_g(r['command_max_abs_v'])} V" for r in rows]
    return rep


def run_blocks(reader) -> int:
    """Blocks of the run itself (its fade blocks follow): from the run's summary.json beside the
    trace, else the recorded scene's duration; all blocks of a trace whose writer never closed it."""
    import math

    if not reader.closed:
        return reader.n_blocks
    try:
        s = json.loads((reader.path.parent / "summary.json").read_text())
        return int(round(s["duration_s"] * s["fs"] / s["block"]))
    except (OSError, ValueError, KeyError, TypeError):
        pass
    dur = ((reader.meta.get("scene") or {}).get("timing") or {}).get("duration")
    return math.ceil(dur * reader.fs / reader.block) if dur else reader.n_blocks


def _g(x):
    return "-" if x is None else f"{x:.3g}"


def _plot(path, t, est, rec_est, cmd, rec_cmd, names, title) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    for c, name in enumerate(names[:8]):
        line, = a.plot(t, est[:, c], lw=1, label=name)
        a.plot(t, rec_est[:, c], lw=1, ls="--", color=line.get_color())
        b.plot(t, cmd[:, c], lw=1, color=line.get_color())
        b.plot(t, rec_cmd[:, c], lw=1, ls="--", color=line.get_color())
    a.set_ylabel("estimate, um (dashed: recorded)")
    b.set_ylabel("drive rms, V (dashed: recorded)")
    b.set_xlabel("time, s")
    a.set_title(title if len(title) < 110 else title[:107] + "...", fontsize=8)
    a.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
