"""Cached kernels are keyed on the whole package, wherever numba caches them: a kernel has its
callees from other files compiled into it, so a stamp of its own file alone would load stale code."""

import os
import subprocess
import sys

PROBE = r"""
import os
from numba.core import caching
from rtctl import _numba, safety, _step
impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl")
for fn in (safety.limit_block, _step.step_tones):
    py = fn.py_func
    loc = next(l for l in (c.from_function(py, py.__code__.co_filename) for c in impl._locator_classes) if l is not None)
    assert loc.get_source_stamp() == _numba.package_stamp(), type(loc).__name__
    print(type(loc).__name__, loc.get_cache_path())
"""


def run_probe(tmp_path, cache_dir):
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    if cache_dir:
        env["NUMBA_CACHE_DIR"] = str(cache_dir)
    r = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_kernels_cached_in_a_users_numba_cache_dir_are_stamped_with_the_package(tmp_path):
    out = run_probe(tmp_path, tmp_path / "cache")
    assert out.count("RtctlStamped") == 2 and str(tmp_path / "cache") in out, out


def test_kernels_cached_beside_the_package_are_stamped_with_the_package(tmp_path):
    out = run_probe(tmp_path, None)
    assert out.count("RtctlStamped") == 2, out
