"""Numba flags in one place (as stumpy's ``config.py``).

``FASTMATH`` allows reassociation, contraction and approximate functions so loops vectorize,
but *not* ``nnan``/``ninf``: NaN and Inf checks must keep working in every kernel, because
the safety limiter relies on them before anything reaches an amplifier.
"""

import functools
import hashlib
from pathlib import Path

from numba import njit

PACKAGE_DIR = Path(__file__).resolve().parent

FASTMATH = frozenset({"nsz", "arcp", "contract", "afn", "reassoc"})


def kernel(fn):
    """Compile ``fn`` as a real-time kernel: cached, GIL-free, the house fastmath set."""
    return njit(cache=True, nogil=True, fastmath=set(FASTMATH))(fn)


def kernel_exact(fn):
    """Like :func:`kernel` but with strict IEEE semantics (no fastmath at all).

    For kernels whose result must not depend on reassociation, e.g. phase accumulators
    checked to 1e-9 over an hour of samples.
    """
    return njit(cache=True, nogil=True)(fn)


# Smallest magnitude a recursive state keeps. Subnormal floats (< 2.2e-308) make kernels ~100x
# slower once states decay after silence; anything below 1e-200 is zero for every SI quantity
# we carry (metres, amperes, volts, newtons), so recursive updates flush below this.
TINY = 1e-200


@functools.lru_cache(maxsize=None)
def package_stamp(root: Path = PACKAGE_DIR) -> bytes:
    """SHA-256 over every ``.py`` file of the package (path and content).

    Numba's cache checks only the source file of the cached function itself, yet a cached
    kernel has its callees (from other files) compiled into it: after an edit or an upgrade
    that touches only a callee, the caller would load stale machine code -- with changed array
    layouts, that is a segfault, not a slow start. rtctl's kernels are stamped with the whole
    package instead, so any change recompiles them.
    """
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.digest()


def _install_package_stamp() -> None:
    try:
        from numba.core import caching
    except ImportError:  # pragma: no cover - numba reorganized its internals
        return

    def stamped(base):
        class Locator(base):
            def get_source_stamp(self):
                return package_stamp()

            @classmethod
            def from_function(cls, py_func, py_file):
                try:
                    Path(py_file).resolve().relative_to(PACKAGE_DIR)
                except ValueError:
                    return None
                return super().from_function(py_func, py_file)

        Locator.__name__ = Locator.__qualname__ = f"RtctlStamped{base.__name__}"
        return Locator

    impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)
    names = ("InTreeCacheLocator", "UserWideCacheLocator", "_InTreeCacheLocator", "_UserWideCacheLocator")
    bases = [getattr(caching, n) for n in names if hasattr(caching, n)]
    if impl is None or not bases or any(c.__name__.startswith("RtctlStamped") for c in impl._locator_classes):
        return
    user = [c for c in impl._locator_classes if "UserProvided" in c.__name__]
    rest = [c for c in impl._locator_classes if c not in user]
    # A user's NUMBA_CACHE_DIR still wins, stamped too (it once was not: after an edit of a callee,
    # a kernel cached there ran the callee's old code); then ours (in-tree, else user-wide); then
    # numba's own for code outside the package.
    impl._locator_classes = [stamped(c) for c in user] + user + [stamped(b) for b in bases] + rest


_install_package_stamp()
