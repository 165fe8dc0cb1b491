"""What ``rtctl trace info`` says about a trace and what ``rtctl trace export`` writes.

Exports for tools that know nothing of rtctl: ``npz`` (numpy: one array per signal, as
:meth:`rtctl.trace.TraceReader.signal` returns it, plus ``time``, ``block``, ``status``,
``compute_us`` and the names), ``csv`` (a spreadsheet: one row per sample, per-block values held
over their block) and ``wav`` (an audio editor: the drive as the amplifier's input sees it, i.e.
the converter's output: volts over ``io.volts_per_fs``, clipped at full scale, on the device
outputs ``io.outputs`` names, float32).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .errors import RtctlError
from .outpath import writable_file
from .trace import TraceError, TraceReader

FORMATS = ("npz", "csv", "wav")
#: Blocks per piece of a CSV written piece by piece (a long trace never sits in memory as text).
CSV_PIECE = 512


def open_trace(path) -> TraceReader:
    """The trace at ``path``: a trace directory, or a run's ``--out`` directory holding ``trace/``."""
    if isinstance(path, str) and not path.strip():  # Path("") is "." and would read the working directory
        raise TraceError("the trace path is empty (give a trace directory or a run's output directory)")
    p = Path(path)
    if not (p / "trace.json").exists() and (p / "trace" / "trace.json").exists():
        p = p / "trace"
    if not p.exists():
        raise TraceError(f"{path}: no such trace (give a trace directory or a run's output directory)")
    return TraceReader(p)


def row_names(r: TraceReader, name: str) -> list[str]:
    """Names of a signal's rows: the channels, the sensed rows, or ``name[i]``."""
    rows = r.dtype[name].shape[0]
    if name == "sensed" and len(r.meta.get("sensed_rows", [])) == rows:
        return list(r.meta["sensed_rows"])
    if len(r.channels) == rows:
        return list(r.channels)
    return [f"{name}[{i}]" for i in range(rows)]


def info(r: TraceReader) -> dict:
    """What the trace holds and what made it (``rtctl trace info --json``)."""
    from . import safety

    meta = r.meta
    seen = int(np.bitwise_or.reduce(r.status)) if r.n_blocks else 0
    scene = meta.get("scene") or {}
    signals = [{"name": n, "unit": r.units.get(n, ""), "rows": int(r.dtype[n].shape[0]),
                "per": "block" if n in r.layout["per_block"] else "sample"} for n in r.dtype.names[3:]]
    return {
        "path": str(r.path), "format": r.format, "fs": r.fs, "block": r.block, "blocks": r.n_blocks,
        "duration_s": r.n_blocks * r.block / r.fs, "channels": r.channels, "signals": signals,
        "closed": r.closed, "torn_bytes": r.torn_bytes, "bad_chunk": r.bad_chunk, "dropped": r.dropped,
        "recovery": r.recovery(), "status_seen": safety.describe(seen),
        "made_by": {k: meta[k] for k in ("rtctl", "source", "scene_sha256", "overrides", "seed", "backend",
                                         "device", "latency_blocks") if k in meta},
        "scene": (scene.get("scene") or {}).get("name"),
    }


def format_info(d: dict) -> str:
    lines = [f"{d['path']}: {d['format']}, {d['fs']:g} Hz, block {d['block']}, {len(d['channels'])} channels",
             f"  {d['recovery']}"]
    if d["dropped"]:
        lines.append(f"  {d['dropped']} placeholder records (dropped by a full trace ring)")
    if d["scene"]:
        lines.append(f"  scene {d['scene']}")
    for k, v in d["made_by"].items():
        if k == "rtctl" and isinstance(v, dict):
            v = (f"{v.get('version')} (source {str(v.get('package_sha256'))[:12]}, git {v.get('git')}), Python "
                 f"{v.get('python')}, numpy {v.get('numpy')}, scipy {v.get('scipy')}, numba {v.get('numba')}, "
                 f"{v.get('machine')} {v.get('cpu')}")
        lines.append(f"  {k}: {json.dumps(v) if not isinstance(v, str) else v}")
    if d["status_seen"]:
        lines.append("  status seen: " + "; ".join(d["status_seen"]))
    lines.append("  signals: " + ", ".join(f"{s['name']} ({s['unit']}, {s['rows']} rows per {s['per']})"
                                          for s in d["signals"]))
    return "\n".join(lines)


def default_out(r: TraceReader, fmt: str) -> Path:
    return r.path.with_name(r.path.name + "." + fmt)


def export(r: TraceReader, fmt: str, out=None, volts_per_fs: float | None = None) -> tuple[Path, str]:
    """Write the trace as ``fmt`` to ``out`` (default beside the trace directory); returns the
    path and one line saying what was written."""
    if fmt not in FORMATS:
        raise RtctlError(f"trace export: format {fmt!r} is not one of {', '.join(FORMATS)}")
    if not r.n_blocks:
        raise TraceError(f"{r.path}: no blocks to export ({r.recovery()})")
    out = writable_file(out if out is not None else default_out(r, fmt), "--out")
    return out, {"npz": _npz, "csv": _csv, "wav": _wav}[fmt](r, out, volts_per_fs)


def _npz(r, out, _):
    arrays = {n: r.signal(n) for n in r.dtype.names[3:]}
    arrays.update(time=r.time(), block=np.asarray(r.records["block"]), status=r.status, compute_us=r.compute_us,
                  fs=np.float64(r.fs), block_length=np.int64(r.block), channels=np.array(r.channels),
                  units=np.array(json.dumps(r.units)))
    for n in r.dtype.names[3:]:
        arrays[f"{n}_rows"] = np.array(row_names(r, n))
    with open(out, "wb") as f:
        np.savez(f, **arrays)
    return f"{out}: {len(arrays)} arrays, {r.n_blocks} blocks"


def _csv(r, out, _):
    names = r.dtype.names[3:]
    head = ["t_s", "block", "status"]
    for n in names:
        head += [f"{n}:{row} ({r.units.get(n, '')})" for row in row_names(r, n)]
    with open(out, "w") as f:
        f.write(",".join(head) + "\n")
        for b0 in range(0, r.n_blocks, CSV_PIECE):
            rec = r.records[b0:b0 + CSV_PIECE]
            nb = len(rec)
            cols = [(np.arange(b0 * r.block, (b0 + nb) * r.block) / r.fs)[:, None],
                    np.repeat(rec["block"], r.block)[:, None], np.repeat(rec["status"], r.block)[:, None]]
            for n in names:
                a = np.asarray(rec[n], dtype=float)
                if n in r.layout["per_block"]:  # (blocks, rows): held over the block's samples
                    cols.append(np.repeat(a, r.block, axis=0))
                else:  # (blocks, rows, block)
                    cols.append(a.transpose(0, 2, 1).reshape(-1, a.shape[1]))
            table = np.hstack(cols)
            np.savetxt(f, table, delimiter=",", fmt=["%.9g", "%d", "%d"] + ["%.9g"] * (table.shape[1] - 3))
    return f"{out}: {len(head)} columns, {r.n_blocks * r.block} rows"


def _wav(r, out, volts_per_fs):
    from scipy.io import wavfile

    if "drive" not in r.dtype.names:
        raise TraceError(f"{r.path}: the trace has no drive signal to export as audio")
    io = (r.meta.get("scene") or {}).get("io") or {}
    vfs = float(volts_per_fs if volts_per_fs is not None else io.get("volts_per_fs", 150.0))
    if not 0 < vfs < np.inf:  # infinity would scale every sample to 0: a silent all-zero file
        raise RtctlError(f"trace export: volts per full scale must be a finite number > 0, not {vfs:g}")
    rate = round(r.fs)
    if abs(rate - r.fs) > 1e-6 * r.fs:
        raise TraceError(f"{r.path}: sample rate {r.fs:g} Hz is not a whole number of hertz, as WAV needs")
    drive = r.signal("drive") / vfs
    n_ch = drive.shape[0]
    outputs = list(io.get("outputs") or range(n_ch))
    if len(outputs) != n_ch:
        outputs = list(range(n_ch))
    frames = np.zeros((drive.shape[1], max(outputs) + 1), dtype=np.float32)
    missing = ~np.isfinite(drive)
    clipped = int(np.count_nonzero(np.abs(drive[~missing]) > 1.0))
    for ch, o in enumerate(outputs):
        frames[:, o] = np.clip(np.nan_to_num(drive[ch], nan=0.0), -1.0, 1.0)
    wavfile.write(out, rate, frames)
    notes = [f"{frames.shape[1]} device outputs at {rate} Hz, float32, full scale = {vfs:g} V"]
    if clipped:
        notes.append(f"{clipped} samples clipped at full scale")
    if missing.any():
        notes.append(f"{int(missing.any(axis=0).sum())} samples of dropped records written as 0")
    return f"{out}: " + "; ".join(notes)
