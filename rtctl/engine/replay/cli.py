"""``rtctl replay TRACE [--mode resim|plant|observer] [--out DIR] [--json] [--set KEY=VALUE ...]``.

Exit status: 0 when the replay agrees (resim: bitwise, last-bit or within tolerance; plant and
observer: a report was made), 1 when resim finds a difference, 2 on bad input (one line)."""

from __future__ import annotations

import argparse
import json
import sys

MODES = ("resim", "plant", "observer")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rtctl replay", description="replay a recorded trace against the simulation")
    p.add_argument("trace", metavar="TRACE", help="a trace directory or a run's output directory")
    p.add_argument("--mode", choices=MODES, default="resim",
                   help="resim: re-run the recorded scene on sim and compare bit by bit (default); plant: the "
                        "recorded drive into the scene's simulated plant, currents compared; observer: the recorded "
                        "drive and currents through the observer and controller offline")
    p.add_argument("--out", metavar="DIR", help="where the re-run's trace (resim) or the report, table and plot "
                   "(plant, observer) go (default: resim keeps nothing; plant and observer TRACE/../replay-MODE)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="change the recorded scene (e.g. another observer setting for --mode observer)")
    p.add_argument("--skip", type=float, default=0.0, metavar="S",
                   help="plant: leave the first S seconds out of the comparison (the plant still runs through them)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    from ...trace_export import open_trace

    reader = open_trace(args.trace)
    say = None if args.json else (lambda text: print(f"rtctl: {text}", file=sys.stderr))
    if args.mode == "resim":
        from .resim import resim

        rep = resim(reader, args.out, args.overrides, say)
    elif args.mode == "plant":
        from .plant import replay_plant

        rep = replay_plant(reader, _out(reader, args), args.overrides, args.skip)
    else:
        from .observer import replay_observer

        rep = replay_observer(reader, _out(reader, args), args.overrides)
    if args.json:
        print(json.dumps(rep, indent=1, default=_plain))
    else:
        for extra in rep.get("details", []):
            print(extra)
        print(rep["line"])
    return int(rep["exit"])


def _out(reader, args):
    from ...outpath import writable_dir

    # checked before the replay runs; an empty --out is refused, not taken for the default
    return writable_dir(reader.path.parent / f"replay-{args.mode}" if args.out is None else args.out, "--out")


def _plain(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)
