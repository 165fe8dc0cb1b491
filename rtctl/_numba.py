"""Numba flags in one place (as stumpy's ``config.py``).

``FASTMATH`` allows reassociation, contraction and approximate functions so loops vectorize,
but *not* ``nnan``/``ninf``: NaN and Inf checks must keep working in every kernel, because
the safety limiter relies on them before anything reaches an amplifier.
"""

from numba import njit

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
