"""The ``rtctl`` command line.

Every expected failure (bad scene, bad value, unavailable component, device trouble) prints one
line to stderr and exits with status 2; a run that ends on a fault exits with 1 after its trace
and summary are written; Ctrl-C exits with 130 after the outputs have faded to zero. Heavy
modules are imported inside the commands that need them.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

# Before numpy loads: single-threaded BLAS. The matrices rtctl builds are small (tens of
# states), BLAS threads only fight the real-time loop for cores, and on a busy 2-core machine
# two threads made one plant discretization take 9.5 s instead of 0.085 s.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from . import __version__  # noqa: E402
from .errors import RtctlError  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help (0) or a usage error (2): returned like any command's status
        return _exit_status(e)
    debug = args.debug or bool(os.environ.get("RTCTL_DEBUG"))
    try:
        return args.func(args)
    except RtctlError as e:
        if debug:
            raise
        print(f"rtctl: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into `head` and the like: not an error
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print("rtctl: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # an rtctl bug: one line, and the way to the traceback
        if debug:
            raise
        print(f"rtctl: internal error: {type(e).__name__}: {e} (rerun with --debug for the traceback)", file=sys.stderr)
        return 3


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rtctl", description="Real-time control of tactile displays.")
    p.add_argument("--version", action="version", version=f"rtctl {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def scene_cmd(name, help_, func):
        s = sub.add_parser(name, help=help_, description=help_)
        s.add_argument("scene", metavar="SCENE", help="scene file or bundled scene name (see `rtctl scenes`)")
        s.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                       help="override a scene key, e.g. --set timing.block=64 (repeatable)")
        s.add_argument("--json", action="store_true", help="print one JSON object")
        s.set_defaults(func=func)
        return s

    r = scene_cmd("run", "run the loop (default backend: simulated rig)", _run)
    r.add_argument("--duration", type=float, metavar="S", help="override timing.duration")
    r.add_argument("--out", metavar="DIR",
                   help="output directory (default out/SCENE_NAME); a run replaces the trace/, summary.json "
                        "and plot.png of an earlier run there (with --no-plot its plot.png is removed) and "
                        "leaves every other file alone")
    r.add_argument("--realtime", action="store_true",
                   help="pace blocks to the wall clock, count deadline misses, and ask the OS for SCHED_FIFO "
                        "(timing.priority), mlockall and a CPU (timing.cpu); a refused request is one line, "
                        "and the run goes on")
    r.add_argument("--no-plot", action="store_true", help="skip plot.png")
    r.add_argument("--quiet", action="store_true", help="no progress bar")

    pl = sub.add_parser("play", help="play an .ahap or .haptic pattern on a scene's display",
                        description="play an .ahap (Core Haptics) or .haptic (Meta Haptics Studio) pattern on a "
                                    "scene's display, mapped by the scene's stimulus.pattern (docs/stimulus.md)")
    pl.add_argument("pattern", metavar="PATTERN", help=".ahap or .haptic file")
    pl.add_argument("--scene", required=True, metavar="SCENE", help="scene file or bundled scene name")
    pl.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override a scene key, e.g. --set stimulus.pattern.channel=3 (repeatable)")
    pl.add_argument("--json", action="store_true", help="print one JSON object")
    pl.add_argument("--duration", type=float, metavar="S",
                    help="override timing.duration (default: the scene's, or longer to hold the pattern); "
                         "scene events after it are dropped")
    pl.add_argument("--out", metavar="DIR", help="output directory (default out/SCENE_NAME-PATTERN)")
    pl.add_argument("--no-plot", action="store_true", help="skip plot.png")
    pl.add_argument("--quiet", action="store_true", help="no progress bar")
    pl.set_defaults(func=_play, realtime=False)

    s = sub.add_parser("scenes", help="list the bundled scenes", description="list the bundled scenes")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=_scenes)

    scene_cmd("check", "validate a scene; list what it needs and what it leaves out", _check)
    scene_cmd("model", "actuator model facts: natural frequencies, static values, capacitance", _model)
    c = scene_cmd("calibrate", "measure each bimorph group's segment currents with the finger lifted and fit "
                  "the model's factors (use the file with control.calibration)", _calibrate)
    c.add_argument("--out", metavar="FILE", help="calibration file to write (default out/SCENE_NAME/calibration.json)")

    # Tools living in their own subpackages parse their own options (``main(argv)``).
    _tool(sub, "check-trace", "verify on every sample of a run's trace what the limiter promises (TRACE [--json])",
          "rtctl.check:main")
    _tool(sub, "selfsense", "transfer-matrix admittance plots and the observer accuracy sweep (SCENE ...)",
          "rtctl.selfsense.cli:main")
    _tool(sub, "render", "render an image to per-pin parameters (IMAGE [--method ...])", "rtctl.render.cli:main")
    _tool(sub, "sweep", "design sweep on Dask: model, reach, selfsense or run over the product of --vary values "
          "(SCENE --vary KEY=SPEC ...)", "rtctl.cli:_sweep_main")
    _tool(sub, "replay", "replay a trace: re-run and compare bit by bit (resim), the recorded drive into the "
          "simulated plant (plant), or through the observer offline (observer) (TRACE [--mode ...])",
          "rtctl.engine.replay.cli:main")
    _tool(sub, "warm", "compile scenes' kernels into numba's cache ahead of their first run ([SCENE ...] [--all]; "
          "default the demo's scene)", "rtctl.engine.warm:main")
    b = sub.add_parser("bench", help="benchmarks: `bench numerics` (work-precision, stability), `bench render`, "
                       "`bench control`, `bench realtime`, `bench faults`",
                       description="benchmarks (the loop's own speed: make bench)")
    bsub = b.add_subparsers(dest="bench", required=True)
    _tool(bsub, "numerics", "work-precision report and the stability cases", "rtctl.numerics.cli:main")
    _tool(bsub, "render", "HIA update and preprocessing times per rendering method", "rtctl.render.bench:main_bench")
    _tool(bsub, "control", "closed-loop error and settle time against block size, with the real-time factor",
          "rtctl.engine.bench_control:main")
    _tool(bsub, "realtime", "the paced loop's deadline misses and wake-up lateness against cyclictest, under "
          "an optional load", "rtctl.engine.bench_realtime:main")
    _tool(bsub, "faults", "seeded runs of every bundled scene with random faults, each trace checked "
          "([--runs N] [--json])", "rtctl.engine.bench_faults:main")
    _name_choices(bsub)
    e = sub.add_parser("emulate", help="run a scene's simulated display as a device: `emulate audio SCENE` "
                       "(a JACK client) or `emulate serial SCENE` (a pin controller behind a pseudo-terminal)",
                       description="run a scene's simulated display as a device")
    esub = e.add_subparsers(dest="emulator", required=True)
    _tool(esub, "audio", "the scene's simulated plant as a JACK client (SCENE ...)", "rtctl.emulate.audio:main")
    _tool(esub, "serial", "a Dot/SMA pin controller (firmware + plant) behind a pseudo-terminal (SCENE ...)",
          "rtctl.emulate.serial:main")
    _name_choices(esub)
    t = sub.add_parser("trace", help="`trace info TRACE`: what a trace holds and how much of it was recovered; "
                       "`trace export TRACE --format npz|csv|wav`",
                       description="read a run's trace (a trace directory or a run's output directory)")
    tsub = t.add_subparsers(dest="trace_command", required=True)
    ti = tsub.add_parser("info", help="layout, what made it, blocks recovered", description="layout, what made it, "
                         "blocks recovered (a killed run's torn tail is ignored)")
    ti.add_argument("trace", metavar="TRACE")
    ti.add_argument("--json", action="store_true", help="print one JSON object")
    ti.set_defaults(func=_trace_info)
    te = tsub.add_parser("export", help="write the trace for numpy (npz), a spreadsheet (csv) or an audio editor "
                         "(wav: the drive as the amplifier's input sees it)", description="export a trace")
    te.add_argument("trace", metavar="TRACE")
    te.add_argument("--format", choices=("npz", "csv", "wav"), default="npz")
    te.add_argument("--out", metavar="FILE", help="file to write (default TRACE.FORMAT beside the trace directory)")
    te.add_argument("--volts-per-fs", type=float, metavar="V",
                    help="wav: drive volts at digital full scale (default the scene's io.volts_per_fs)")
    te.set_defaults(func=_trace_export)
    _name_choices(tsub)
    d = sub.add_parser("devices", help="audio, serial and DAQ devices this machine has",
                       description="audio, serial and DAQ devices this machine has")
    d.add_argument("--json", action="store_true", help="print one JSON object")
    d.set_defaults(func=_devices)
    return p


def _name_choices(sub) -> None:
    """Show the subcommands as ``{a,b}`` in the usage and in "the following arguments are
    required" (argparse names a metavar-less subcommand slot by its dest there)."""
    sub.metavar = "{" + ",".join(sub.choices) + "}"


def _tool(sub, name: str, help_: str, target: str) -> None:
    """A command whose words all go to ``target`` (``module:function`` taking ``argv``), which
    parses them, --help included, with a parser of its own."""
    # Its only prefix character is one no word starts with, so every word, a leading --help or
    # --json too, lands in ``rest`` for the tool; with "-" argparse would take a leading option
    # for one of this parser's, find none, and reject it before the tool ever saw it.
    t = sub.add_parser(name, help=help_, description=help_, add_help=False, prefix_chars="\0")
    t.add_argument("rest", nargs=argparse.REMAINDER)
    t.set_defaults(func=_delegate, target=target)


def _delegate(args) -> int:
    import importlib

    module, func = args.target.split(":")
    try:
        return int(getattr(importlib.import_module(module), func)(list(args.rest)) or 0)
    except SystemExit as e:  # the tool's own argparse: --help or a usage error
        return _exit_status(e)


def _sweep_main(argv) -> int:
    """``rtctl sweep``: its points may be whole runs, and only the command line imports the
    engine, so it hands the sweep the engine's ``run`` (imported when a sweep asks for it)."""
    from .sweep.cli import main

    return main(argv, runner=_engine_run)


def _engine_run():
    from .engine.run import run

    return run


def _exit_status(e: SystemExit) -> int:
    """The status the interpreter would exit with for ``e``."""
    if e.code is None or isinstance(e.code, int):
        return e.code or 0
    print(e.code, file=sys.stderr)
    return 1


def _load(args):
    from . import scene

    overrides = list(args.overrides)
    if getattr(args, "duration", None) is not None:
        overrides.append(f"timing.duration={args.duration!r}")
    from .validity import check

    s = scene.load(args.scene, overrides)
    for w in check(s):  # a model near the edge of its validity: said once, before anything runs
        print(f"rtctl: warning: {w}", file=sys.stderr)
    return s


def _print_json(obj) -> None:
    print(json.dumps(obj, indent=1, allow_nan=False, default=_json_default))


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def _scenes(args) -> int:
    from . import scene

    rows = []
    for name in scene.bundled():
        s = scene.load(name)
        rows.append({"name": name, "description": s.scene.description, "channels": s.n_channels,
                     "backend": s.io.backend, "path": s.source})
    if args.json:
        _print_json({"scenes": rows})
    else:
        w = max(len(r["name"]) for r in rows)
        for r in rows:
            print(f"{r['name']:<{w}}  {r['channels']:>3} ch  {r['description']}")
    return 0


def _check(args) -> int:
    from .engine.admit import admit
    from .needs import needs, unavailable_message

    s = _load(args)
    admit(s)  # what the run refuses before it runs, by the run's own checks: their errors here
    n = needs(s)
    valid = not n.unavailable  # a component the run cannot have: the run refuses it, so check does
    if args.json:
        _print_json({"scene": s.scene.name, "valid": valid, **n.to_dict(), "modules": list(n.modules)})
    else:
        print(f"{s.source}: {'valid' if valid else 'invalid'} ({s.n_channels} channels, backend {s.io.backend})")
        print("needs:")
        for c, why in n.needed.items():
            print(f"  {c:<16} {why}")
        print("leaves out:")
        print("  " + ", ".join(n.left_out))
    if n.unavailable:
        c = n.unavailable[0]
        print(f"rtctl: error: {unavailable_message(c, n.needed[c])}", file=sys.stderr)
        return 2
    return 0


def _model(args) -> int:
    from .model_report import model_facts

    s = _load(args)
    facts = model_facts(s)
    if args.json:
        _print_json({"scene": s.scene.name, "actuators": facts})
        return 0
    for name, f in facts.items():
        print(f"actuator {name}:")
        for k, v in f.items():
            if isinstance(v, list):
                v = ", ".join(f"{x:.6g}" for x in v)
            elif isinstance(v, float):
                v = f"{v:.6g}"
            print(f"  {k:<34} {v}")
    return 0


def _calibrate(args) -> int:
    from .engine.calibrate import calibrate, default_path, write
    from .engine.run import run
    from .outpath import writable_file

    s = _load(args)
    # before the measurement, not after it
    target = writable_file(default_path(s) if args.out is None else args.out, "--out")
    doc = calibrate(s, run, lambda text: print(f"rtctl: {text}", file=sys.stderr))
    path = write(doc, target)
    doc["file"] = str(path)
    if args.json:
        _print_json(doc)
        return 0
    ex = doc["excitation"]
    for name, g in doc["groups"].items():
        lines, use = g["lines_hz"], g["limits_used"]
        print(f"{name}: {len(lines)} lines {lines[0]:g}-{lines[-1]:g} Hz at {g['volts_per_line']:.3g} V each on "
              f"{g['channels']} channels, finger {ex['finger']}; peak <= {use['max_voltage']['used']:.3g} V of "
              f"{use['max_voltage']['bound']:g} V, slew {100 * use['slew']['share']:.1f} %, current "
              f"{100 * use['current']['share']:.1f} %, sensed {100 * use['sense']['share']:.1f} % of full scale: "
              "the limiter did not act")
    print(f"measurement: {ex['duration_s']:.2f} s of excitation (settle {ex['settle_s']:.2f} s, window "
          f"{ex['window_s']:g} s), {ex['wall_s']:.1f} s wall; fit {doc['fit_s']:.1f} s")
    head = (f"{'group':<12}{'E':>8}{'d31':>8}{'eps33T':>8}{'damping':>9}{'rho':>8}{'resid %':>9}{'cond':>7}"
            f"{'uncert %':>10}")
    print(head)
    print("-" * len(head))
    for name, g in doc["groups"].items():
        f = g["factors"]
        rho = f"{f['rho']:8.4f}" if "rho" in f else f"{'-':>8}"
        how = (f"mass {g['anchor']['mass_kg'] * 1e6:.4g} mg within {100 * g['anchor']['mass_tolerance']:g} %"
               if g["anchor"] else f"thickness and density within {100 * g['tolerance']:g} %")
        print(f"{name:<12}{f['E']:8.4f}{f['d31']:8.4f}{f['eps33T']:8.4f}{f['damping']:9.3f}{rho}"
              f"{g['residual_pct']:9.3f}{g['cond']:7.1f}{g['uncertainty_pct']:10.2f}  ({how})")
    for w in doc["warnings"]:
        print(f"rtctl: warning: {w}", file=sys.stderr)
    print(f"written to {path}; use it with --set control.calibration={path}")
    return 0


def _play(args) -> int:
    from .play import pattern_scene

    s, warnings = pattern_scene(args.pattern, args.scene, args.overrides, args.duration)
    for w in warnings:
        print(f"rtctl: warning: {w}", file=sys.stderr)
    out = args.out if args.out is not None else os.path.join(
        "out", f"{s.scene.name}-{os.path.splitext(os.path.basename(args.pattern))[0]}")
    return _run_scene(s, out, args)


def _run(args) -> int:
    s = _load(args)
    return _run_scene(s, os.path.join("out", s.scene.name) if args.out is None else args.out, args)


def _run_scene(s, out, args) -> int:
    from .engine.report import print_table
    from .engine.run import run

    result = run(s, out_dir=out, realtime=args.realtime, plot=not args.no_plot,
                 progress=not (args.quiet or args.json))
    if args.json:
        _print_json(result.summary)
    else:
        print_table(result.summary)
        cal = result.summary.get("calibration")
        if cal:
            scale = ", ".join(f"{g} within {u:.2g} %" for g, u in cal["uncertainty_pct"].items())
            print(f"models calibrated by {cal['file']} (amplitude scale: {scale})")
        # name plot.png only when this run left one: --no-plot, a plot that failed to write (a full
        # disk) or a run with no blocks to plot leaves none (an earlier run's is removed first)
        plotted = os.path.isfile(os.path.join(out, "plot.png"))
        print(f"trace, summary.json{' and plot.png' if plotted else ''} in {out}")
    for msg in result.summary["faults"]:
        print(f"rtctl: fault: {msg}", file=sys.stderr)
    if result.interrupted:
        s = result.summary
        blocks = round(s["duration_s"] * s["fs"] / s["block"])
        print(f"rtctl: interrupted after {s['duration_s']:.2f} s ({blocks} blocks); trace and summary in {out}",
              file=sys.stderr)
        return 130
    return 1 if result.summary["faults"] else 0


def _trace_info(args) -> int:
    from .trace_export import format_info, info, open_trace

    d = info(open_trace(args.trace))
    if args.json:
        _print_json(d)
    else:
        print(format_info(d))
    return 0


def _trace_export(args) -> int:
    from .trace_export import export, open_trace

    _, line = export(open_trace(args.trace), args.format, args.out, args.volts_per_fs)
    print(line)
    return 0


def _devices(args) -> int:
    from .io.devices import format_table, list_devices

    found = list_devices()
    if args.json:
        _print_json(found)
    else:
        print(format_table(found))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

