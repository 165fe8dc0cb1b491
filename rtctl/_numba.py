"""Numba flags in one place (as stumpy's ``config.py``), and the package stamp of cached kernels.

``FASTMATH`` allows contraction (FMA), reciprocals, no signed zeros and approximate functions,
but *not* ``nnan``/``ninf``: NaN and Inf checks must keep working in every kernel, because
the safety limiter relies on them before anything reaches an amplifier. Nor ``reassoc``: with
it, code numba has just compiled and the same code loaded from its cache sum in different
orders, and a closed-loop run carries that last bit on (the demo's tips differed by 0.1 um and
one settle time by 18 ms between an empty and a warm cache); without it both give bitwise the
same trace. It cost 0-6 % of the CPU time of the bimorph scenes and ~13 % of the switched and
SMA ones (``bench/fastmath.py``).

**Package stamp.** Numba's cache checks only the source file of the cached function itself, yet
a cached kernel has its callees (from other files) compiled into it: after an edit or an upgrade
that touches only a callee, the caller would load stale machine code -- with changed array
layouts, that is a segfault, not a slow start. So each kernel of this package gets a cache of
its own whose freshness stamp is :func:`package_stamp` (every ``.py`` file of the package):
any change recompiles every kernel. That cache is built from numba's internal classes
(``numba.core.caching``); if they are missing or not shaped as expected, the kernel runs
**uncached** -- compiled in each process, never loaded from a cache that might be stale -- and
:data:`CACHE_NOTE` says why. Numba's own classes are left as they are: other code in the
process caches the way numba does.

Kernels outside the package -- the modules that :mod:`rtctl._codegen` generates into a cache
directory -- are cached by numba's default locators, keyed by their own file: their file name
hashes their source, which carries the package stamp, so a changed package writes a new module
with a cache of its own.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
from pathlib import Path

from numba import njit

__all__ = ["kernel", "kernel_exact", "package_stamp", "FASTMATH", "TINY", "CACHE_NOTE"]

PACKAGE_DIR = Path(__file__).resolve().parent

FASTMATH = frozenset({"nsz", "arcp", "contract", "afn"})

# Smallest magnitude a recursive state keeps. Subnormal floats (< 2.2e-308) make kernels ~100x
# slower once states decay after silence; anything below 1e-200 is zero for every SI quantity
# we carry (metres, amperes, volts, newtons), so recursive updates flush below this.
TINY = 1e-200

#: Why rtctl kernels run uncached, or None while every kernel is cached under the package
#: stamp. Read it as ``rtctl._numba.CACHE_NOTE`` (it is set when a kernel is decorated).
CACHE_NOTE: str | None = None


def kernel(fn):
    """Compile ``fn`` as a real-time kernel: cached, GIL-free, the house fastmath set."""
    return _cached(njit(nogil=True, fastmath=set(FASTMATH))(fn))


def kernel_exact(fn):
    """Like :func:`kernel` but with strict IEEE semantics (no fastmath at all).

    For kernels whose result must not depend on contraction or approximate functions, e.g.
    phase accumulators checked to 1e-9 over an hour of samples.
    """
    return _cached(njit(nogil=True)(fn))


@functools.cache
def package_stamp(root: Path = PACKAGE_DIR) -> bytes:
    """SHA-256 over every ``.py`` file of the package (path and content).

    The freshness stamp of every cached kernel of the package (see the module docstring).
    """
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.digest()


def _note(reason: str) -> None:
    global CACHE_NOTE
    if CACHE_NOTE is None:
        CACHE_NOTE = f"rtctl kernels run uncached (compiled in every process): {reason}"


def _in_package(py_func) -> bool:
    try:
        Path(inspect.getfile(py_func)).resolve().relative_to(PACKAGE_DIR)
    except (TypeError, ValueError):
        return False
    return True


def _cached(disp):
    """Give the dispatcher ``disp`` (compiled with ``cache=False``) its cache: stamped with the
    package for a kernel of the package, numba's own for one outside it; none when that cannot
    be done as expected."""
    py_func = getattr(disp, "py_func", None)
    if py_func is None:  # NUMBA_DISABLE_JIT: a plain function, nothing to cache
        return disp
    if not _in_package(py_func):
        try:
            disp.enable_caching()
        except Exception as exc:  # noqa: BLE001 - whatever numba changed, run uncached
            _note(f"{py_func.__qualname__}: numba's enable_caching failed ({type(exc).__name__}: {exc})")
        return disp
    try:
        cache_class, locators = _stamped_cache_class()
        before = disp._cache
        if type(before).__name__ != "NullCache":
            raise TypeError(f"an uncached dispatcher's cache is a {type(before).__name__}, not a NullCache")
        cache = cache_class(py_func)
        # Check what the cache will compare on load, not what it was asked to use: a locator
        # list overridden by NUMBA_CACHE_LOCATOR_CLASSES, or a renamed attribute, fails here.
        if not isinstance(cache._impl.locator, locators):
            raise TypeError(f"numba chose the locator {type(cache._impl.locator).__name__}, not a stamped one")
        if cache._cache_file._source_stamp != package_stamp():
            raise TypeError("the cache file does not carry the package stamp")
        disp._cache = cache
    except Exception as exc:  # noqa: BLE001 - anything unexpected: uncached, never stale
        _note(f"{py_func.__qualname__}: {type(exc).__name__}: {exc} (numba {_numba_version()})")
    return disp


def _numba_version() -> str:
    import numba

    return getattr(numba, "__version__", "?")


@functools.cache
def _stamped_cache_class():
    """Numba's function cache, its locators stamped with :func:`package_stamp`.

    Returns ``(cache class, tuple of the stamped locator classes)``. Raises when numba's
    caching classes are not there.
    """
    from numba.core import caching

    def stamped(base):
        class Locator(base):
            def get_source_stamp(self):
                return package_stamp()

        Locator.__name__ = Locator.__qualname__ = f"RtctlStamped{base.__name__}"
        return Locator

    # A user's NUMBA_CACHE_DIR first (numba's order), then beside the sources, then user-wide;
    # no unstamped locator after them: a kernel none of them can place runs uncached.
    locators = tuple(stamped(getattr(caching, n))
                     for n in ("UserProvidedCacheLocator", "InTreeCacheLocator", "UserWideCacheLocator"))

    class Impl(caching.CompileResultCacheImpl):
        _locator_classes = list(locators)

    class Cache(caching.FunctionCache):
        _impl_class = Impl

    Impl.__name__ = Impl.__qualname__ = "RtctlStampedCacheImpl"
    Cache.__name__ = Cache.__qualname__ = "RtctlStampedFunctionCache"
    return Cache, locators
