"""``rtctl bench numerics``: the work-precision report and the stability cases.

    rtctl bench numerics [--out DIR] [--json] [--quick] [--only NAME ...]

Progress goes to stderr; stdout gets the table (or, with ``--json``, one JSON object
``{"work_precision": [...], "stability": [...], "speedups": [...], "references": {...}}``).
With ``--out`` the JSON, the table and ``work_precision.png`` are written there too. Exit status
0 when every stability case that ran passed, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

__all__ = ["main", "report", "format_table"]


def report(quick: bool = False, names=None, progress=None) -> dict:
    """Run every registered problem (or ``names``) and every stability case.

    Returns
    -------
    dict
        ``work_precision``: list of ``{plant, method, setting, error, wall_s}``;
        ``stability``: list of ``{case, passed, detail}``; ``speedups``: see
        :func:`~rtctl.numerics.workprecision.speedups`; ``references``: the reference and
        description of each problem; ``entries``: the :class:`Entry` objects (not JSON).
    """
    from rtctl.numerics import problems, stability, workprecision

    say = progress or (lambda msg: None)
    built = []
    for name in (names or list(problems.PROBLEMS)):
        try:
            built.append(problems.build(name, quick=quick))
        except ImportError as exc:  # a plant another engineer has not landed yet
            say(f"{name}: skipped ({exc})")
    entries = workprecision.work_precision(built, quick=quick, progress=say)
    say("stability cases")
    cases = stability.run_cases(quick=quick, progress=say)
    return {
        "work_precision": [e.as_json() for e in entries],
        "stability": [c.as_json() for c in cases],
        "speedups": workprecision.speedups(entries),
        "references": {p.name: {"description": p.description, "reference": p.reference_doc}
                       for p in built},
        "entries": entries,
    }


def format_table(rep: dict) -> str:
    """Human table of a :func:`report`."""
    lines = []
    for name, ref in rep["references"].items():
        lines += [f"{name}: {ref['description']}", f"  reference: {ref['reference']}"]
    lines.append("")
    lines.append(f"{'plant':13s} {'method':20s} {'setting':12s} {'error':>10s} {'wall ms':>11s}")
    for e in rep["work_precision"]:
        err = "failed" if e["error"] is None else f"{e['error']:.2e}"
        lines.append(f"{e['plant']:13s} {e['method']:20s} {e['setting']:12s} {err:>10s} "
                     f"{e['wall_s'] * 1e3:11.3f}")
    lines.append("")
    lines.append("at equal error (<= 1e-6): our fastest vs each baseline's fastest")
    for s in rep["speedups"]:
        ratio = "n/a (not reached)" if s["ratio"] is None else f"x{s['ratio']:.0f}"
        lines.append(f"  {s['plant']:13s} vs {s['baseline']:12s} {ratio:>18s}   "
                     f"({s['ours']} vs {s['baseline_setting']})")
    lines.append("")
    lines.append("stability")
    for c in rep["stability"]:
        verdict = {True: "pass", False: "FAIL", None: "n/a"}[c["passed"]]
        lines.append(f"  {verdict:4s} {c['case']:28s} {c['detail']}")
    return "\n".join(lines)


def main(argv=None) -> int:
    """Command line entry point; returns the exit status."""
    ap = argparse.ArgumentParser(prog="rtctl bench numerics",
                                 description="Work-precision report and stability cases.")
    ap.add_argument("--out", type=Path, help="write numerics.json, numerics.txt and "
                                             "work_precision.png to this directory")
    ap.add_argument("--json", action="store_true", help="print one JSON object to stdout")
    ap.add_argument("--quick", action="store_true", help="short runs, fewer settings (~30 s)")
    ap.add_argument("--only", nargs="+", metavar="PROBLEM",
                    help="work-precision problems to run (default: all registered)")
    a = ap.parse_args(argv)

    t0 = time.perf_counter()

    def progress(msg):
        print(f"[{time.perf_counter() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    rep = report(quick=a.quick, names=a.only, progress=progress)
    entries = rep.pop("entries")
    text = format_table(rep)
    if a.out is not None:
        from rtctl.numerics.plot import plot_work_precision
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "numerics.json").write_text(json.dumps(rep, indent=1))
        (a.out / "numerics.txt").write_text(text + "\n")
        plot_work_precision(entries, a.out / "work_precision.png")
        progress(f"wrote {a.out}/numerics.json, numerics.txt, work_precision.png")
    print(json.dumps(rep) if a.json else text)
    return 0 if all(c["passed"] is not False for c in rep["stability"]) else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
