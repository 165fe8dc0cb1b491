"""``rtctl replay --mode resim``: re-run a simulated trace's scene and compare record by record.

The recorded scene (validated, overrides applied), seed and rate run again on the simulated rig,
as fast as they go, and every recorded field is compared with the new trace's, timing aside
(``compute_us``, ``wake_late_us``, and the status bits a clock sets: deadline missed, record
dropped). Float32 values are compared by their bits; a difference is measured in float32 units
in the last place (ulps) and relative to its channel's rms over the recording.

Verdicts, with the tolerances they use:

* ``bitwise``: every bit equal. Expected when the package's source, Python, numpy, scipy, numba
  and the machine match (:data:`rtctl.provenance.BITWISE_KEYS`); said either way.
* ``last-bit``: the first difference is at most :data:`LAST_BIT_ULPS` ulps or :data:`LAST_BIT_REL`
  of the channel's rms, and either the provenance matches or every difference is within
  :data:`TOLERANCE_REL`. The same code gives these between a process that compiled its kernels
  and one that loaded them from numba's cache: the kernels' fastmath allows reassociation, and
  the two may sum in another order. A closed loop then carries the difference on, and it may
  grow (the report says how far and where). Not a change in behaviour (exit 0).
* ``within-tolerance``: where the provenance differs (another machine or library version),
  differences up to :data:`TOLERANCE_REL` of the channel's rms (exit 0).
* ``differs``: anything more; the first block, signal and channel that differ and by how much
  (exit 1).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from ... import safety
from ...provenance import differences, provenance
from ...trace import TraceError, TraceReader
from . import scene_of

LAST_BIT_ULPS = 4
LAST_BIT_REL = 1e-6
TOLERANCE_REL = 1e-4
#: Fields and status bits that depend on the clock, not on what the rig computed.
TIMING_FIELDS = ("compute_us", "wake_late_us")
TIMING_BITS = safety.DEADLINE_MISSED | safety.TRACE_DROPPED


def _row_names(reader, name):
    from ...trace_export import row_names

    return row_names(reader, name)


def _ulps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Float32 units in the last place between ``a`` and ``b`` (ordered integers of the bits)."""
    def ordered(x):
        i = x.view(np.int32).astype(np.int64)
        return np.where(i < 0, -(i & 0x7FFFFFFF), i)
    return np.abs(ordered(a) - ordered(b))


def compare(rec: TraceReader, new: TraceReader, n: int) -> dict:
    """Compare the first ``n`` records of two traces of one layout (timing aside)."""
    if rec.dtype != new.dtype:
        raise TraceError(f"{rec.path}: the re-run's record layout differs from the recording's "
                         "(another version of rtctl recorded it): nothing to compare bit by bit")
    keep = (np.asarray(rec.records["status"][:n]) & safety.TRACE_DROPPED) == 0  # placeholders have no data
    first = None  # (block, field order, row)
    worst = {"ulps": 0, "rel": 0.0}
    counts = {"values": 0, "blocks": np.zeros(n, dtype=bool)}
    sa = np.asarray(rec.records["status"][:n]) & ~TIMING_BITS
    sb = np.asarray(new.records["status"][:n]) & ~TIMING_BITS
    bad = (sa != sb) & keep
    if bad.any():
        k = int(np.argmax(bad))
        first = (k, -1, 0, {"signal": "status", "channel": None, "recorded": safety.describe(int(sa[k])),
                            "replayed": safety.describe(int(sb[k]))})
        counts["blocks"] |= bad
    for fi, name in enumerate(rec.dtype.names[3:]):
        if name in TIMING_FIELDS:
            continue
        a = np.asarray(rec.records[name][:n])[keep]
        b = np.asarray(new.records[name][:n])[keep]
        blocks = np.flatnonzero(keep)
        a2, b2 = a.reshape(len(a), a.shape[1], -1), b.reshape(len(b), b.shape[1], -1)  # (blocks, rows, samples)
        diff = a2.view(np.uint32) != b2.view(np.uint32)
        if not diff.any():
            continue
        rms = np.sqrt(np.nanmean(a2.astype(float) ** 2, axis=(0, 2)))  # per row
        rms = np.where(rms > 0, rms, np.inf)
        ad = np.abs(a2.astype(float) - b2.astype(float))
        both_nan = np.isnan(a2) & np.isnan(b2)
        ad[both_nan] = 0.0
        ad[np.isnan(ad)] = np.inf  # NaN on one side only
        rel = ad / rms[None, :, None]
        ulps = _ulps(a2, b2)
        ulps[both_nan] = 0
        worst["ulps"] = max(worst["ulps"], int(ulps[diff].max()))
        if float(rel[diff].max()) > worst["rel"]:
            bi, ri, _ = np.unravel_index(int(np.argmax(np.where(diff, rel, -1.0))), rel.shape)
            worst.update(rel=float(rel[diff].max()), where={"block": int(blocks[bi]), "signal": name,
                                                            "channel": _row_names(rec, name)[ri]})
        counts["values"] += int(diff.sum())
        anyb = diff.any(axis=(1, 2))
        counts["blocks"][blocks[anyb]] = True
        i = int(np.argmax(anyb))
        k, row = int(blocks[i]), int(np.argmax(diff[i].any(axis=1)))
        if first is None or (k, fi) < first[:2]:
            j = int(np.argmax(ad[i, row]))
            first = (k, fi, row, {"signal": name, "channel": _row_names(rec, name)[row],
                                  "recorded": float(a2[i, row, j]), "replayed": float(b2[i, row, j]),
                                  "abs": float(ad[i, row].max()), "rel_rms": float(rel[i, row].max()),
                                  "ulps": int(ulps[i, row].max()), "unit": rec.units.get(name, "")})
    out = {"values_differing": counts["values"], "blocks_differing": int(counts["blocks"].sum()),
           "max_ulps": worst["ulps"], "max_rel_rms": worst["rel"], "largest": worst.get("where"), "first": None}
    if first is not None:
        k = first[0]
        out["first"] = {"block": k, "t_s": k * rec.block / rec.fs, **first[3]}
    return out


def resim(reader: TraceReader, out_dir=None, overrides=(), say=None) -> dict:
    """Re-run ``reader``'s scene on the simulated rig (into ``out_dir``, else a temporary
    directory) and compare; returns the report (``verdict``, ``exit``, ``line``...)."""
    from ..run import run

    meta = reader.meta
    if meta.get("backend", "sim") != "sim":
        raise TraceError(f"{reader.path}: recorded on backend {meta.get('backend')!r}; resim re-runs the simulated "
                         "rig and compares bit by bit, which only a sim trace can match: use --mode plant or observer")
    scene = scene_of(reader, overrides)
    then, now = meta.get("rtctl") or {}, provenance()
    changed = differences(then, now) if then else ["the trace records no versions"]
    tmp = None
    if out_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="rtctl-resim-")
        out_dir = tmp.name
    try:
        if say:
            say(f"re-running {meta.get('scene_name', scene.scene.name)} ({reader.n_blocks} blocks recorded)")
        run(scene, out_dir=out_dir, realtime=False, plot=False, report=False)
        new = TraceReader(Path(out_dir) / "trace")
        n, note = _blocks_to_compare(reader, new)
        cmp = compare(reader, new, n)
    finally:
        if tmp is not None:
            tmp.cleanup()
    return _verdict(reader, cmp, n, note, changed, None if tmp is not None else str(out_dir))


def _blocks_to_compare(rec, new) -> tuple[int, str | None]:
    """Records both runs share: all, or those before the recording's end when it ended early
    (a killed run has no fade block; an interrupted one ends with its fade, which the re-run,
    going on, does not have)."""
    if rec.n_blocks >= new.n_blocks:
        return new.n_blocks, (None if rec.n_blocks == new.n_blocks else
                              f"the re-run has {new.n_blocks} blocks, the recording {rec.n_blocks}")
    n = rec.n_blocks - 1 if rec.closed else rec.n_blocks
    why = "interrupted: its fade block left out" if rec.closed else "not closed (killed)"
    return max(0, n), f"the recording ended early ({why}): compared its first {max(0, n)} blocks"


def _verdict(rec, cmp, n, note, changed, out) -> dict:
    same = not changed
    where = ("same package source, libraries and machine" if same else "differs from the recording in "
             + "; ".join(changed))
    f = cmp["first"]
    if f is None:
        verdict, code = "bitwise", 0
        line = f"bitwise identical over {n} blocks ({where})"
    else:
        at = (f"first at block {f['block']} ({f['t_s']:.4f} s), {f['signal']}"
              + (f" {f['channel']}" if f.get("channel") else ""))
        if f["signal"] == "status":
            size = f"recorded {f['recorded']}, replayed {f['replayed']}"
        else:
            size = (f"{f['recorded']:.9g} recorded, {f['replayed']:.9g} replayed {f['unit']}: "
                    f"{f['abs']:.3g} {f['unit']}, {f['rel_rms']:.2g} of its rms, {f['ulps']} ulps")
        last_bit = f["signal"] != "status" and (f["ulps"] <= LAST_BIT_ULPS or f["rel_rms"] <= LAST_BIT_REL)
        if last_bit and (same or cmp["max_rel_rms"] <= TOLERANCE_REL):
            verdict, code = "last-bit", 0
            big = cmp["largest"]
            grew = ("" if cmp["max_ulps"] <= LAST_BIT_ULPS else
                    f"; through the loop they grow to {cmp['max_rel_rms']:.2g} of a channel's rms ({big['signal']} "
                    f"{big['channel']} at block {big['block']})")
            line = (f"last-bit differences over {n} blocks: the first is {f['ulps']} float32 ulps ({at}), "
                    f"{cmp['values_differing']} values in {cmp['blocks_differing']} blocks differ{grew} -- a first "
                    f"difference of this size is what a fastmath kernel's reassociation gives (compiled in this "
                    f"process vs loaded from numba's cache), not a change in behaviour ({where})")
        elif not same and f["signal"] != "status" and cmp["max_rel_rms"] <= TOLERANCE_REL:
            verdict, code = "within-tolerance", 0
            line = (f"within tolerance ({TOLERANCE_REL:g} of each channel's rms) over {n} blocks: at most "
                    f"{cmp['max_rel_rms']:.2g}; {at} ({where})")
        else:
            verdict, code = "differs", 1
            line = f"differs: {at}: {size}; {cmp['blocks_differing']} blocks differ ({where})"
    if note:
        line += f"; {note}"
    return {"mode": "resim", "verdict": verdict, "exit": code, "line": line, "blocks_compared": n,
            "provenance_match": same, "provenance_differences": changed, **cmp, "out": out,
            "tolerances": {"last_bit_ulps": LAST_BIT_ULPS, "last_bit_rel_rms": LAST_BIT_REL,
                           "rel_rms": TOLERANCE_REL}}
