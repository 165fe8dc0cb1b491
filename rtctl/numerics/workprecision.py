"""Error against wall time: our kernels, dlsim and solve_ivp on each registered problem.

Practice as in DiffEqDevTools / SciMLBenchmarks (docs/references.md, Numerics): the error is the
largest deviation from the problem's stated reference on the output grid (relative to each
output's peak, worst output), the time is the minimum over warm repeats with building and
compiling apart, adaptive methods sweep ``rtol`` and fixed-step kernels sweep rate or substeps.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import asdict, dataclass

from rtctl.errors import ModelError
from rtctl.numerics.problems import Problem, integrate, relative_error

__all__ = ["Entry", "work_precision", "problem_entries", "speedups", "time_best",
           "SOLVE_IVP_METHODS", "RTOLS", "RTOLS_QUICK", "TARGET_ERROR"]

SOLVE_IVP_METHODS = ("Radau", "BDF", "LSODA", "RK45")
RTOLS = tuple(10.0 ** -e for e in range(3, 11))          # 1e-3 ... 1e-10
RTOLS_QUICK = (1e-4, 1e-8)
#: "Equal error" of the done criterion: relative error at or below this.
TARGET_ERROR = 1e-6


@dataclass(frozen=True)
class Entry:
    """One point of the work-precision diagram.

    Attributes
    ----------
    plant, method, setting : str
    error : float or None
        Relative error against the problem's reference (``None``: the run failed).
    wall_s : float
        Best wall time of a run, s.
    ours : bool
    form : str
        Realization that ran (``modal``, ``dense``, ``group``; ``adaptive`` for solve_ivp).
    """

    plant: str
    method: str
    setting: str
    error: float | None
    wall_s: float
    ours: bool = False
    form: str = ""

    def as_json(self) -> dict:
        d = asdict(self)
        return {k: d[k] for k in ("plant", "method", "setting", "error", "wall_s")}


def time_best(fn, min_total: float = 0.2, max_repeats: int = 15):
    """Run ``fn`` until ``min_total`` seconds are spent (at least twice unless one run takes
    longer than ``min_total``) and return ``(last result, best time)``."""
    best, spent, count, out = math.inf, 0.0, 0, None
    while count < max_repeats and (count < 2 or spent < min_total):
        t0 = time.perf_counter()
        out = fn()
        dt = time.perf_counter() - t0
        best, spent, count = min(best, dt), spent + dt, count + 1
        if dt > min_total:
            break
    return out, best


def _finite_or_none(e):
    return None if not math.isfinite(e) else float(e)


def problem_entries(problem: Problem, methods=SOLVE_IVP_METHODS, rtols=RTOLS,
                    max_wall_s: float = 20.0, progress=None) -> list:
    """All entries of one problem: every setting, then every ``solve_ivp`` method x ``rtol``.

    A method's tighter tolerances are skipped once its runs took longer than ``max_wall_s``
    in total (reported through ``progress``; keeps the report within its time budget on a
    loaded machine, BDF being slow on lightly damped modes).
    """
    say = progress or (lambda msg: None)
    ref = problem.reference_outputs()
    out = []
    for st in problem.settings:
        go = st.prepare()
        y, wall = time_best(go)
        out.append(Entry(problem.name, st.method, st.setting,
                         _finite_or_none(relative_error(y, ref)), wall, st.ours,
                         getattr(go, "form", "")))
        say(f"  {problem.name:10s} {st.method:20s} {st.setting:12s} "
            f"err {out[-1].error if out[-1].error is not None else float('nan'):9.2e}  "
            f"{wall * 1e3:9.3f} ms")
    for method in methods:
        spent = 0.0
        for rtol in rtols:
            y, wall = integrate(problem, method, rtol)
            spent += wall
            out.append(Entry(problem.name, method, f"rtol {rtol:.0e}",
                             _finite_or_none(relative_error(y, ref)), wall, False, "adaptive"))
            say(f"  {problem.name:10s} {method:20s} rtol {rtol:.0e}   "
                f"err {out[-1].error if out[-1].error is not None else float('nan'):9.2e}  "
                f"{wall * 1e3:9.3f} ms")
            if spent > max_wall_s and rtol != rtols[-1]:
                say(f"  {problem.name:10s} {method}: {spent:.1f} s > {max_wall_s:g} s spent, "
                    "tighter tolerances skipped")
                break
    return out


def work_precision(problems, quick: bool = False, progress=None) -> list:
    """Entries of every problem (``problems``: iterable of :class:`Problem`)."""
    rtols = RTOLS_QUICK if quick else RTOLS
    out = []
    for p in problems:
        if progress:
            progress(f"{p.name}: {p.description}")
        try:
            out += problem_entries(p, rtols=rtols, max_wall_s=4.0 if quick else 25.0,
                                   progress=progress)
        except ModelError as exc:   # e.g. a reference that cannot be computed: say so, go on
            if progress:
                progress(f"{p.name}: skipped: {exc}")
    return out


def speedups(entries, target: float = TARGET_ERROR) -> list:
    """At equal error: our fastest run reaching ``target`` against each baseline's fastest.

    Returns
    -------
    list of dict
        ``{plant, baseline, ours, ours_wall_s, baseline_setting, baseline_wall_s, ratio}``;
        ``ratio`` is None when either side never reached ``target``.
    """
    res = []
    for plant in dict.fromkeys(e.plant for e in entries):
        es = [e for e in entries if e.plant == plant and e.error is not None
              and e.error <= target]
        ours = min((e for e in es if e.ours), key=lambda e: e.wall_s, default=None)
        for base in dict.fromkeys(e.method for e in entries if e.plant == plant and not e.ours):
            fam = [e for e in es if e.method == base]
            b = min(fam, key=lambda e: e.wall_s, default=None)
            res.append({
                "plant": plant, "baseline": base,
                "ours": f"{ours.method} {ours.setting}" if ours else None,
                "ours_wall_s": ours.wall_s if ours else None,
                "baseline_setting": b.setting if b else None,
                "baseline_wall_s": b.wall_s if b else None,
                "ratio": b.wall_s / ours.wall_s if (b and ours) else None,
            })
    return res


def stderr_progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)
