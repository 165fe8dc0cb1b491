"""``rtctl sweep SCENE --vary KEY=SPEC [--vary ...] [--what model|reach|selfsense|run] [--set K=V ...]
[--scheduler ADDRESS] [--workers N] [--out DIR] [--json] [--quiet] [--no-plot]``: a design sweep
over the cartesian product of the ``--vary`` values, computed on Dask (docs/sweep.md)."""

from __future__ import annotations

import argparse
import json
import sys

from ..jsonsafe import strict
from .points import WHATS
from .spec import parse, short, toml_literal

#: Columns the printed table shows, by ``--what`` (suffixes; the files have every column).
SHOWN = {
    "model": (".f1_hz", ".f1_loaded_hz", ".deflection_per_volt_m", ".blocked_force_per_volt_n", ".capacitance_f"),
    "reach": (".reach_um", ".margin_db", ".felt"),
    "selfsense": (".amp_err_pct", ".phase_err_deg", ".force_err_pct"),
    "run": (".true_um", ".error_pct", ".settle_ms", ".felt"),
}
#: Rows printed; a longer table prints its first and last rows around an ellipsis.
MAX_PRINTED = 40


def _parser():
    p = argparse.ArgumentParser(
        prog="rtctl sweep", description="design sweep over the product of the --vary values, on Dask",
        epilog="SPEC: a:b:n (n values, linear), a:b:n:log, or a list [x, y, z]; K1,K2=SPEC sets several keys "
               "to each value. Resume: rerun with the same --out.")
    p.add_argument("scene", metavar="SCENE", help="scene file or bundled scene name")
    p.add_argument("--vary", action="append", default=[], metavar="KEY=SPEC", required=True,
                   help="a scene key and its values (repeatable: the points are the product)")
    p.add_argument("--what", default="model", metavar="|".join(WHATS),
                   help="what each point computes (default model; several: comma-separated)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene key at every point (repeatable)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="a running Dask scheduler, e.g. tcp://host:8786 "
                   "(default: a local cluster of worker processes)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="worker processes of the local cluster (default: one per core; 0: in this process)")
    p.add_argument("--out", metavar="DIR", help="the sweep's directory (default out/NAME-sweep); an existing "
                   "sweep there is resumed")
    p.add_argument("--json", action="store_true", help="print one JSON object (the rows and the summary)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--no-plot", action="store_true", help="skip the plots")
    return p


def main(argv=None, runner=None) -> int:
    """Entry point of ``rtctl sweep``; ``runner``: a function returning the engine's ``run`` (the
    command line's; asked for only when ``--what`` has ``run``)."""
    from .job import sweep
    from .points import parse_whats

    args = _parser().parse_args(argv)
    whats = parse_whats(args.what)
    run = runner() if ("run" in whats and runner is not None) else None

    def say(text):
        if not args.json:
            print(f"rtctl: {text}", file=sys.stderr)

    try:
        res = sweep(args.scene, args.vary, whats, args.overrides, args.out, args.scheduler, args.workers, run,
                    progress=not (args.quiet or args.json) and sys.stderr.isatty(), plot=not args.no_plot,
                    say=say)
    except KeyboardInterrupt:
        print("rtctl: interrupted; the finished points are kept: rerun with the same --out to resume",
              file=sys.stderr)
        return 130
    m = res.meta
    if args.json:
        doc = {"scene": args.scene, "what": list(whats), "out": str(res.out), "table": str(res.table),
               "csv": str(res.csv), "plots": [str(p) for p in res.plots], "summary": m, "rows": res.rows}
        print(json.dumps(strict(doc), indent=1, allow_nan=False))
    else:
        head = f"{args.scene}: {m['points']} points (--what {','.join(whats)})"
        if m["computed"]:
            print(f"{head}: {m['computed']} computed on {m['engine']} in {m['wall_s']:.1f} s (start-up "
                  f"{m['startup_s']:.1f} s, then {m['points_per_s']:.3g} points/s), {m['reused']} from an "
                  f"earlier run, {m['failed']} failed")
        else:
            print(f"{head}: every one from an earlier run in {res.out}")
        print_rows(res.rows, [parse(v).name for v in args.vary], whats)
        print(f"table: {res.table}, {res.csv}" + (f"; plots: {', '.join(str(p) for p in res.plots)}"
                                                 if res.plots else ""))
    if res.failed:
        r = res.failed[0]
        print(f"rtctl: {len(res.failed)} of {len(res.rows)} points failed; first: point {r['point']}: {r['error']}",
              file=sys.stderr)
        return 1
    return 0


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "NO"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def print_rows(rows: list[dict], keys: list[str], whats) -> None:
    """The table on stdout: the point, the varied keys, the headline metrics, the error."""
    if not rows:
        return
    cols = ["point", *keys]
    for w in whats:
        cols += [c for suffix in SHOWN[w] for c in rows[0] if c.endswith(suffix) and c not in cols]
    if any(r["error"] for r in rows):
        cols.append("error")
    shown = rows if len(rows) <= MAX_PRINTED else rows[:MAX_PRINTED // 2] + [None] + rows[-MAX_PRINTED // 2:]
    # a varied key's value as --set would take it (true, not yes); a metric's for reading
    cells = [["..." if r is None else toml_literal(r[c]) if c in keys and isinstance(r[c], bool) else _fmt(r[c])
              for c in cols] for r in shown]
    heads = [short(c) if c in keys else c for c in cols]
    widths = [max(len(c), *(len(x[i]) for x in cells)) for i, c in enumerate(heads)]
    print("  ".join(c.rjust(w) if c != "error" else c for c, w in zip(heads, widths)).rstrip())
    for x in cells:
        print("  ".join(v.rjust(w) if c != "error" else v for c, v, w in zip(cols, x, widths)).rstrip())
