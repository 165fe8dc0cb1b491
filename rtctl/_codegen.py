"""Generated numba code: compiled functions composed at run time from module-level kernels.

numba cannot cache a function composed from closures or function arguments, but it caches any
module-level function of an importable module. So a composed block function is written out as
source (kernels imported by module and name, arrays reached through an int64 table of addresses)
into a cache directory, under a name hashing that source, and imported from there: the next
process with the same composition finds the module and numba's cache of it.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
from pathlib import Path

from numba.core import cgutils, types
from numba.extending import intrinsic


@intrinsic
def voidptr_at(typingctx, addr):
    """An int64 address as a ``void *`` in compiled code (numba has no cast for that)."""
    def codegen(context, builder, sig, args):
        return builder.inttoptr(args[0], cgutils.voidptr_t)
    return types.voidptr(types.int64), codegen


@intrinsic
def fence(typingctx):
    """A sequentially consistent memory fence: stores before it are visible to another thread
    before stores after it (x86-64 orders stores anyway; AArch64 does not)."""
    def codegen(context, builder, sig, args):
        builder.fence("seq_cst")
        return context.get_dummy_value()
    return types.none(), codegen


def cache_dir() -> Path:
    """Where generated modules live: beside numba's cache when ``NUMBA_CACHE_DIR`` is set."""
    base = os.environ.get("NUMBA_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache")
    d = Path(base) / "rtctl-generated"
    d.mkdir(parents=True, exist_ok=True)
    return d


def load_generated(src: str, prefix: str = "rtctl_gen"):
    """Import generated source as a module kept in :func:`cache_dir` under a name hashing it
    (so numba's on-disk cache of its kernels is found again by the next process)."""
    digest = hashlib.sha256(src.encode()).hexdigest()[:20]
    path = cache_dir() / f"{prefix}_{digest}.py"
    if not path.exists():
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(src)
        tmp.replace(path)  # atomic: a concurrent run never imports half a file
    module = sys.modules.get(path.stem)
    if module is None:
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[path.stem] = module  # numba's cache and other generated modules refer to it by name
        spec.loader.exec_module(module)
    return module


def kernel_call(fn, args, name, fns: dict, imports: list) -> str:
    """Source text calling kernel ``fn`` on ``args`` (each named through ``name``), importing it
    into the generated module by its module and name."""
    py = getattr(fn, "py_func", None)
    mod = sys.modules.get(getattr(py, "__module__", ""), None)
    if py is None or getattr(mod, py.__name__, None) is not fn:
        raise TypeError(f"{fn!r} is not a module-level numba kernel")
    if fn not in fns:
        fns[fn] = f"k{len(fns)}"
        imports.append(f"from {py.__module__} import {py.__name__} as {fns[fn]}")
    return f"{fns[fn]}({', '.join(name(a) for a in args)})"
