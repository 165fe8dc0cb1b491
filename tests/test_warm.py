"""``rtctl warm``: a run that stops after a few blocks; a first run after warming that compiles
nothing (numba's own compile events, counted in a fresh interpreter); and the same closed loop
from the cache and freshly compiled, bitwise (no ``reassoc`` in the fastmath set)."""

import os
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from rtctl import scene
from rtctl.engine import run as run_mod
from rtctl.trace import TraceReader


def test_run_stops_after_blocks(tmp_path):
    s = scene.load("line-bimorph-5-closed")
    res = run_mod.run(s, out_dir=tmp_path, plot=False, blocks=4)
    assert res.summary["duration_s"] == pytest.approx(4 * s.timing.block / s.timing.fs, rel=1e-12)
    reader = TraceReader(tmp_path / "trace")
    # the 4 blocks, then the requested stop's fade and the tips' settle tail that end every run
    stop, per_s = res.summary["stop"], s.timing.fs / s.timing.block
    tail = round(stop["fade_s"] * per_s) + round(stop["settle_s"] * per_s)
    assert stop["by"] == "end" and tail > 0
    assert reader.n_blocks == 4 + tail and reader.signal("drive").shape[-1] == (4 + tail) * s.timing.block


def test_notice_prints_only_when_late(capsys):
    late = run_mod._Notice(0.05, "compiling", True)
    time.sleep(0.5)
    late.cancel()
    on_time = run_mod._Notice(5.0, "never", True)
    on_time.cancel()
    run_mod._Notice(0.0, "disabled", False).cancel()
    time.sleep(0.1)
    err = capsys.readouterr().err
    assert err == "rtctl: compiling\n"


RUN_COUNTING_COMPILES = textwrap.dedent("""
    import sys
    from numba.core import event
    compiled = []
    class Count(event.Listener):
        def on_start(self, ev):
            compiled.append(ev.data["dispatcher"].py_func.__qualname__)
        def on_end(self, ev):
            pass
    event.register("numba:compile", Count())
    from rtctl import scene
    from rtctl.engine.run import run
    res = run(scene.load("line-bimorph-5-closed"), out_dir=sys.argv[1], plot=False, report=False, blocks=400)
    print("compiled:", len(compiled), sorted(set(compiled))[:10])
""")


def _run_counting(cache, out) -> tuple[int, str]:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    p = subprocess.run([sys.executable, "-c", RUN_COUNTING_COMPILES, str(out)], env=env, capture_output=True,
                       text=True, timeout=900)
    assert p.returncode == 0, p.stderr
    _, n, names = p.stdout.splitlines()[-1].split(" ", 2)
    return int(n), names


@pytest.mark.slow
def test_warm_then_run_compiles_nothing_and_matches_a_fresh_compile_bitwise(tmp_path):
    """After ``rtctl warm`` the demo compiles nothing; and its closed loop, run from the cache,
    gives bitwise the trace of a run that compiled everything itself (an empty cache)."""
    warm_cache = tmp_path / "warm"
    env = dict(os.environ, NUMBA_CACHE_DIR=str(warm_cache))
    warm = subprocess.run([sys.executable, "-m", "rtctl.engine.warm"], env=env, capture_output=True, text=True,
                          timeout=900)
    assert warm.returncode == 0, warm.stderr
    assert "compiling the kernels of line-bimorph-5-closed" in warm.stderr
    assert "line-bimorph-5-closed ready" in warm.stderr
    n, names = _run_counting(warm_cache, tmp_path / "from_cache")
    assert n == 0, names
    n, _ = _run_counting(tmp_path / "empty", tmp_path / "fresh")
    assert n > 0  # it did compile
    a, b = TraceReader(tmp_path / "from_cache" / "trace"), TraceReader(tmp_path / "fresh" / "trace")
    assert a.n_blocks == b.n_blocks > 400  # the 400 blocks, the stop's fade and the settle tail
    for field in a.records.dtype.names:
        if field in ("compute_us", "late_us"):  # wall-clock timings
            continue
        assert np.array_equal(np.asarray(a.records[field]), np.asarray(b.records[field])), field


def test_warm_names_a_bad_scene_in_one_line_before_compiling_anything(capsys):
    from rtctl.cli import main

    assert main(["warm", "line-bimorph-5", "no-such-scene"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no-such-scene" in err and "compiling" not in err
