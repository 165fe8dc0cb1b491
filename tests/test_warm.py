"""``rtctl warm``: a run that stops after a few blocks, and a first run after warming that compiles
nothing (numba's own compile events, counted in a fresh interpreter with an empty cache)."""

import os
import subprocess
import sys
import textwrap
import time

import pytest

from rtctl import scene
from rtctl.engine import run as run_mod
from rtctl.trace import TraceReader


def test_run_stops_after_blocks(tmp_path):
    s = scene.load("line-bimorph-5-closed")
    res = run_mod.run(s, out_dir=tmp_path, plot=False, blocks=4)
    assert res.summary["duration_s"] == pytest.approx(4 * s.timing.block / s.timing.fs, rel=1e-12)
    reader = TraceReader(tmp_path / "trace")
    # the 4 blocks and the fade to zero after them (one block here) that ends every run
    assert reader.n_blocks == 5 and reader.signal("drive").shape[-1] == 5 * s.timing.block


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


COUNT_COMPILES = textwrap.dedent("""
    import sys
    from numba.core import event
    compiled = []
    class Count(event.Listener):
        def on_start(self, ev):
            compiled.append(ev.data["dispatcher"].py_func.__qualname__)
        def on_end(self, ev):
            pass
    event.register("numba:compile", Count())
    from rtctl.cli import main
    code = main(["run", "line-bimorph-5", "--quiet", "--no-plot", "--duration", "0.05", "--out", sys.argv[1]])
    print("compiled:", code, len(compiled), sorted(set(compiled))[:10])
""")


@pytest.mark.slow
def test_warm_then_run_compiles_nothing(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    warm = subprocess.run([sys.executable, "-m", "rtctl.engine.warm", "line-bimorph-5"], env=env,
                          capture_output=True, text=True, timeout=900)
    assert warm.returncode == 0, warm.stderr
    assert "compiling the kernels of line-bimorph-5" in warm.stderr
    assert "line-bimorph-5 ready" in warm.stderr
    probe = subprocess.run([sys.executable, "-c", COUNT_COMPILES, str(tmp_path / "out")], env=env,
                           capture_output=True, text=True, timeout=900)
    assert probe.returncode == 0, probe.stderr
    code, n, names = probe.stdout.splitlines()[-1].split(" ", 3)[1:]
    assert (code, n) == ("0", "0"), names
