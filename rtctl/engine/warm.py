"""``rtctl warm``: compile a scene's kernels into numba's on-disk cache ahead of its first run.

A scene's first run compiles its block function and every kernel in it (the demo: 20-40 s of LLVM
on a 2-core machine; the cached run after it starts in ~2 s). The set-up step of ``make`` runs
``rtctl warm`` once, saying so, so that the first ``make demo`` does not stall silently; the
cache is stamped with the package (:mod:`rtctl._numba`), so an edit makes the next run or warm
compile again.

Warming runs the whole scene (events included) on the simulated backend but stops after a few
blocks, writing into a temporary directory: the same rig, block function, loop and trace kernels
as the real run, so the real run loads all of them from the cache.

    rtctl warm [SCENE ...] [--all] [--quiet]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time

#: What ``rtctl warm`` compiles without arguments: the demo's scene (``make demo``).
DEMO = "line-bimorph-5-closed"


def warm(s) -> float:
    """Run scene ``s`` (loaded with ``io.backend=sim``) for a few blocks, so that numba compiles
    (or loads) everything its run needs; returns the wall seconds taken."""
    from .run import run

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="rtctl-warm-") as tmp:
        run(s, out_dir=tmp, plot=False, blocks=4)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    from .. import scene

    p = argparse.ArgumentParser(prog="rtctl warm", description="compile scenes' kernels into numba's cache "
                                "ahead of their first run (the set-up step of make does the demo's)")
    p.add_argument("scenes", nargs="*", metavar="SCENE", help=f"scene files or bundled names (default {DEMO})")
    p.add_argument("--all", action="store_true", help="every bundled scene")
    p.add_argument("--quiet", action="store_true", help="no messages")
    args = p.parse_args(argv)
    names = list(args.scenes) + (scene.bundled() if args.all else [])
    scenes = [scene.load(name, ["io.backend=sim"]) for name in names or [DEMO]]  # bad input: one line, first
    for name, s in zip(names or [DEMO], scenes):
        if not args.quiet:
            print(f"rtctl: compiling the kernels of {name} into numba's cache (once per install or "
                  "change; 20-40 s on 2 cores, a few when cached) ...", file=sys.stderr, flush=True)
        took = warm(s)
        if not args.quiet:
            print(f"rtctl: {name} ready ({took:.1f} s)", file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
