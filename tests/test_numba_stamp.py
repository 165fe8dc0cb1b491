"""Cached kernels are keyed on the whole package, wherever numba caches them: a kernel has its
callees from other files compiled into it, so a stamp of its own file alone would load stale code.
When the stamp cannot be applied as expected, kernels run uncached, never from a stale cache.

Each case runs fresh interpreters on a throw-away package ``rtctl`` in ``tmp_path``: its
``__init__.py`` is empty, its ``_numba.py`` is the real one, and two probe modules stand for a
caller and a callee in different files. Cache hits and misses are numba's own counters
(``dispatcher.stats``); the files written are looked for on disk.
"""

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import rtctl._numba

CALLEE = """
from rtctl._numba import kernel


@kernel
def callee(x):
    return x + {step}
"""

CALLER = """
from rtctl._numba import kernel
from rtctl._probe_callee import callee


@kernel
def caller(x):
    return 2.0 * callee(x)
"""

# A kernel outside the package, imported from its file as rtctl._codegen imports the modules it
# generates: it calls a package kernel and must be cached by numba's default locators.
OUTSIDE = """
from rtctl._numba import kernel
from rtctl._probe_callee import callee


@kernel
def outer(x):
    return callee(x) + 0.5
"""

PROBE = """
import importlib.util, json, sys
{prelude}
import rtctl, rtctl._numba as N
assert rtctl.__file__.startswith(sys.argv[1]), rtctl.__file__   # the copy, not the repo's
if sys.argv[2] == "outside":
    spec = importlib.util.spec_from_file_location("probe_outside", sys.argv[3])
    mod = importlib.util.module_from_spec(spec)
    sys.modules["probe_outside"] = mod
    spec.loader.exec_module(mod)
    fn = mod.outer
else:
    from rtctl._probe_caller import caller as fn
y = fn(1.0)
print(json.dumps({{"y": y, "hits": sum(fn.stats.cache_hits.values()),
                  "misses": sum(fn.stats.cache_misses.values()), "note": N.CACHE_NOTE}}))
"""


def make_package(root: Path, step: str = "1.0") -> Path:
    pkg = root / "rtctl"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    shutil.copy(rtctl._numba.__file__, pkg / "_numba.py")
    (pkg / "_probe_callee.py").write_text(CALLEE.format(step=step))
    (pkg / "_probe_caller.py").write_text(CALLER)
    return pkg


def run(root: Path, cache_dir=None, prelude="", what="caller", env_extra=None) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_CACHE")}
    env["PYTHONPATH"] = str(root)
    if cache_dir:
        env["NUMBA_CACHE_DIR"] = str(cache_dir)
    env.update(env_extra or {})
    r = subprocess.run([sys.executable, "-c", PROBE.format(prelude=textwrap.dedent(prelude)), str(root), what,
                        str(root / "outside" / "outside_mod.py")],
                       capture_output=True, text=True, env=env, cwd=root, timeout=240)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def cache_files(root: Path) -> list:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.suffix in (".nbi", ".nbc"))


@pytest.mark.parametrize("where", ["beside the sources", "NUMBA_CACHE_DIR"])
def test_an_edit_of_a_callee_in_another_file_recompiles_the_caller(tmp_path, where):
    pkg = make_package(tmp_path)
    cache_dir = tmp_path / "cache" if where == "NUMBA_CACHE_DIR" else None
    first = run(tmp_path, cache_dir)
    assert (first["y"], first["misses"], first["hits"], first["note"]) == (4.0, 1, 0, None)
    again = run(tmp_path, cache_dir)
    assert (again["y"], again["hits"], again["misses"]) == (4.0, 1, 0)   # the cache works
    written = cache_files(tmp_path)
    assert any("_probe_caller.caller" in f for f in written), written
    assert all(f.startswith("cache/") for f in written) == (cache_dir is not None), written
    # Only the callee's file changes (same length, same lines); the caller's is untouched.
    (pkg / "_probe_callee.py").write_text(CALLEE.format(step="2.0"))
    edited = run(tmp_path, cache_dir)
    assert (edited["y"], edited["misses"], edited["hits"]) == (6.0, 1, 0)


# Numba's internals moved or reshaped, as a future numba may have them (each a prelude run
# before rtctl is imported).
BROKEN = {
    "no CompileResultCacheImpl": "from numba.core import caching; del caching.CompileResultCacheImpl",
    "no locator classes": """
        from numba.core import caching
        for n in ("UserProvidedCacheLocator", "InTreeCacheLocator", "UserWideCacheLocator"):
            delattr(caching, n)
        """,
    "stamp attribute renamed": """
        from numba.core import caching
        _init = caching.IndexDataCacheFile.__init__
        def _renamed(self, *a, **k):
            _init(self, *a, **k)
            self._freshness = self.__dict__.pop("_source_stamp")
        caching.IndexDataCacheFile.__init__ = _renamed
        """,
}


@pytest.mark.parametrize("how", [*BROKEN, "NUMBA_CACHE_LOCATOR_CLASSES"])
def test_without_the_stamp_machinery_kernels_run_uncached(tmp_path, how):
    # NUMBA_CACHE_LOCATOR_CLASSES makes numba ignore any class's own locator list; patching
    # numba's class for the whole process, a kernel then ran a callee's old code after an edit.
    make_package(tmp_path)
    prelude = BROKEN.get(how, "")
    env = {"NUMBA_CACHE_LOCATOR_CLASSES": "InTreeCacheLocator"} if how not in BROKEN else None
    for _ in range(2):   # a second process finds nothing either
        got = run(tmp_path, tmp_path / "cache", prelude=prelude, env_extra=env)
        assert (got["y"], got["hits"], got["misses"]) == (4.0, 0, 1), got
        assert got["note"] and got["note"].startswith("rtctl kernels run uncached"), got
    assert cache_files(tmp_path) == []


def test_a_kernel_outside_the_package_is_cached_by_its_own_file(tmp_path):
    make_package(tmp_path)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "outside_mod.py").write_text(OUTSIDE)
    first = run(tmp_path, what="outside")
    assert (first["y"], first["misses"], first["note"]) == (2.5, 1, None)
    again = run(tmp_path, what="outside")
    assert (again["y"], again["hits"], again["misses"]) == (2.5, 1, 0)
    assert any(f.startswith("outside/__pycache__/outside_mod.outer") for f in cache_files(tmp_path))


def test_every_kernel_of_the_package_is_cached_under_the_stamp(tmp_path):
    # The real package: with this numba, no kernel falls back to running uncached.
    code = """
import importlib, pkgutil, json, rtctl, rtctl._numba as N
from numba.core.registry import CPUDispatcher
mods = ["rtctl.safety", "rtctl.dsp._kernels", "rtctl.plant._kernels", "rtctl.plant.hybrid",
        "rtctl.plant._sma_kernels", "rtctl.plant._pvdf_kernels", "rtctl.io.sim"]
kernels = [f for m in mods for f in vars(importlib.import_module(m)).values()
           if isinstance(f, CPUDispatcher) and f.py_func.__module__ == m]
print(json.dumps({"note": N.CACHE_NOTE, "n": len(kernels),
                  "paths": sorted({f.stats.cache_path for f in kernels})}))
"""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_CACHE")}
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "cache")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=240)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout.strip().splitlines()[-1])
    assert d["note"] is None and d["n"] >= 10, d
    assert all(p.startswith(str(tmp_path / "cache")) for p in d["paths"]), d
