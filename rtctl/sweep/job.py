"""One sweep from its ``--vary`` to its table: validate every point, skip the ones an earlier run
in the same directory finished, compute the rest (:mod:`rtctl.sweep.engine`), write the table
and the plots."""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import RtctlError
from . import points as points_mod
from . import results, spec

#: Points per task for the cheap ``--what`` (model, reach: ~2-20 ms a point): enough to make
#: Dask's per-task cost (~2 ms) small, few enough to keep every worker busy to the end and to
#: lose little when a worker dies. ``selfsense`` and ``run`` points (~1 s) go one per task.
CHUNK_MAX = 16
EXPENSIVE = ("selfsense", "run")


@dataclass
class SweepResult:
    """What :func:`sweep` returns: the table's rows (product order), the directory and files it
    wrote, and ``meta`` (what ``sweep.json`` holds: counts, times, engine)."""

    rows: list[dict]
    out: Path
    meta: dict
    table: Path | None = None
    csv: Path | None = None
    plots: list[Path] = field(default_factory=list)

    @property
    def failed(self) -> list[dict]:
        return [r for r in self.rows if r["error"] is not None]


def _raw(scene_mod, text: str, sets) -> dict | None:
    """The scene's TOML with the ``--set`` items applied, unvalidated (None when it does not
    parse: the points' validation then says why)."""
    import tomllib

    try:
        data = tomllib.loads(text)
        for item in sets:
            scene_mod.apply_override(data, item)
    except (tomllib.TOMLDecodeError, RtctlError, RecursionError):
        return None
    return data


def plan(source, varies, whats, sets=()):
    """The scene's text and origin and every point, each validated as ``--set`` values are (a bad
    one raises RtctlError naming the point) and checked against ``whats``."""
    from .. import scene as scene_mod

    path = scene_mod.resolve(source)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise RtctlError(f"{path}: cannot read: {e}") from None
    origin = str(path)
    pts = spec.product(varies, _raw(scene_mod, text, sets))
    for p in pts:
        try:
            points_mod.check(scene_mod.loads(text, [*sets, *p.overrides], origin), whats)
        except RtctlError as e:
            raise RtctlError(f"point {p.index} ({', '.join(p.overrides)}): {e}") from None
    return text, origin, pts


def sweep(source, vary, what="model", sets=(), out=None, scheduler=None, workers=None, runner=None,
          progress=False, plot=True, chunk=None, compute=None, say=None) -> SweepResult:
    """Run a sweep (``rtctl sweep``) and write its directory.

    Parameters
    ----------
    source : str or Path
        Scene file or bundled scene name.
    vary : list of str or Vary
        ``KEY=SPEC`` items (:mod:`rtctl.sweep.spec`).
    what : str or sequence of str
        ``model``, ``reach``, ``selfsense``, ``run``, or several (:mod:`rtctl.sweep.points`).
    sets : sequence of str
        ``--set`` strings every point gets.
    out : str or Path, optional
        The sweep's directory (default ``out/NAME-sweep``); one holding this sweep is resumed.
    scheduler, workers
        Where to compute (:class:`rtctl.sweep.engine.Engine`).
    runner : callable, optional
        The engine's ``run``, for ``what = run``.
    progress : bool
        A progress bar on stderr (points done/failed, ETA).
    chunk : int, optional
        Points per task (default: :data:`CHUNK_MAX` or fewer for cheap points, 1 otherwise).
    compute : callable, optional
        The function each task runs (default :func:`rtctl.sweep.points.compute`).
    say : callable, optional
        Takes a line of news (the local cluster starting).
    """
    from .engine import Engine

    whats = points_mod.parse_whats(what) if isinstance(what, str) else tuple(what)
    points_mod.parse_whats(",".join(whats))
    varies = [v if isinstance(v, spec.Vary) else spec.parse(v) for v in vary]
    if not varies:
        raise RtctlError("give at least one --vary KEY=SPEC")
    if "run" in whats and runner is None:
        raise RtctlError("--what run needs the engine's run function")
    engine = Engine(scheduler, workers)  # its arguments checked before the points
    text, origin, pts = plan(source, varies, whats, sets)
    if out is None:
        from .. import scene as scene_mod

        out = Path("out") / f"{scene_mod.loads(text, list(sets), origin).scene.name}-sweep"
    from ..outpath import writable_dir

    out = writable_dir(out, "--out")  # a file in the way or /proc: said before the first point, not after
    store = results.Store(out, results.identity(text, origin, sets, whats))
    records = {p.index: store.previous[p.overrides] for p in pts if p.overrides in store.previous}
    todo = [p for p in pts if p.index not in records]
    meta = {"vary": [v.text for v in varies], "points": len(pts), "reused": len(records), "computed": 0,
            "failed": 0, "engine": "none: every point was done"}
    t_start = time.perf_counter()
    bar = None
    store.open(meta)
    try:
        if todo:
            if say and engine.workers != 0:
                say(f"{'connecting to ' + scheduler if scheduler else 'starting a local Dask cluster'} "
                    f"for {len(todo)} points")
            with engine:
                engine.everywhere(points_mod.warm, whats)
                t_up = time.perf_counter()
                n = chunk or (1 if set(whats) & set(EXPENSIVE) or engine.client is None else
                              max(1, min(CHUNK_MAX, len(todo) // (4 * engine.n_workers))))
                tasks = [{"text": text, "origin": origin, "set": list(sets), "what": whats, "runner": runner,
                          "points": [[p.index, list(p.overrides)] for p in todo[i:i + n]]}
                         for i in range(0, len(todo), n)]
                bar = _bar(len(pts), len(records), progress)

                def done(task, res, err):
                    if res is None:
                        res = [{"index": i, "metrics": {}, "error": err, "seconds": math.nan}
                               for i, _ in task["points"]]
                    recs = []
                    for r in res:
                        rec = {"set": list(pts[r["index"]].overrides), "metrics": r["metrics"], "error": r["error"],
                               "seconds": r["seconds"]}
                        records[r["index"]] = rec
                        recs.append(rec)
                        meta["computed"] += 1
                        meta["failed"] += r["error"] is not None
                    store.append(recs)
                    if bar is not None:
                        bar.update(len(recs))
                        bar.set_postfix_str(f"failed {meta['failed']}", refresh=False)

                engine.map(compute or points_mod.compute, tasks, done)
                t_end = time.perf_counter()
                meta.update(engine=engine.describe(), workers=engine.n_workers, points_per_task=n,
                            startup_s=t_up - t_start, compute_s=t_end - t_up,
                            points_per_s=len(todo) / (t_end - t_up) if t_end > t_up else math.inf)
    finally:
        if bar is not None:
            bar.close()
        store.close()
    meta["wall_s"] = time.perf_counter() - t_start
    table = results.rows(pts, varies, records)
    res = SweepResult(table, Path(out), meta)
    store.write_meta(meta)
    res.table, res.csv = store.write_table(table, {"vary": meta["vary"]})
    if plot:
        from .plots import plot as make_plots

        res.plots = make_plots(table, varies, whats, out)
    # figures of an earlier sweep here (another --vary, or this one plotted before --no-plot)
    # would sit beside a table they do not show
    for old in Path(out).glob("plot_*.png"):
        if old not in res.plots and old.is_file():
            old.unlink()
    return res


def _bar(total: int, initial: int, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, unit="pt", file=sys.stderr, dynamic_ncols=True, mininterval=0.2,
                leave=False)
