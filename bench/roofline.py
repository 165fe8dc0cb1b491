"""The machine's limit beside a measured figure: floating-point operations per channel-sample of
the simulated bimorph group against the core's float64 peak.

The core's peak is what OpenBLAS's ``dgemm`` (numpy's ``@`` on 512 x 512 float64 matrices, one
BLAS thread) reaches on this core: a library kernel tuned to the last cycle, not ours. The
plant's operations are counted from its realization, as its kernel
(``rtctl.plant._kernels.sim_group_process``) needs them (a multiply and an add are two, fused or
not; comparisons, rounding and copies are none):

* modal recursion: ``7`` per oscillating pair (``sigma x1 + (omega x2 + u)``, ``sigma x2 -
  omega x1``), ``2`` per real mode (``lambda x + u``); dense fallback: ``2 n + 1`` per state
  (``b u`` and the ``n`` products of the state matrix's row);
* outputs ``C x + D u``: per row with ``k`` nonzero terms, ``2 k - 1`` (exact zeros of the
  cascade realization are skipped by the kernel's tiles, its padding is not counted);
* ADC, per sensed stream: ``7`` (the two noise tables' sum, gain and noise scale, scale to
  codes and the half for rounding, back to amperes).

Hardware counters would count what ran; a virtual machine rarely exposes them, and the count
above is the one the algorithm needs (what the tiles' padding wastes shows as a lower share of
the peak). ``bench/plant.py`` and ``bench/scaling.py`` report these figures beside their own.
"""

from __future__ import annotations

import os

# before numpy loads: the peak is one core's, and a threaded BLAS would report the machine's
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import time  # noqa: E402

import numpy as np  # noqa: E402

#: float64 operations of one ADC reading (see the module's docstring)
ADC_FLOPS = 7
#: of one oscillating pair's step, and of one real mode's
PAIR_FLOPS, REAL_FLOPS = 7, 2


def core_peak_gflops(n: int = 512, repeats: int = 5) -> float:
    """The best of ``repeats`` ``dgemm`` of two ``n x n`` float64 matrices, GFLOP/s (``2 n^3``
    operations each)."""
    rng = np.random.default_rng(0)
    a, b = rng.random((n, n)), rng.random((n, n))
    a @ b  # the library's first call sets up its buffers
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t0)
    return 2.0 * n ** 3 / best * 1e-9


def output_flops(c: np.ndarray, d: np.ndarray) -> int:
    """Operations of ``y = C x + D u`` for one input: ``2 k - 1`` per row of ``k`` nonzero terms.

    >>> output_flops(np.array([[1.0, 0.0, 2.0], [0.0, 0.0, 0.0]]), np.array([0.5, 0.0]))
    5
    """
    k = np.count_nonzero(np.asarray(c), axis=1) + (np.asarray(d).ravel() != 0)
    return int(np.sum(np.maximum(2 * k - 1, 0)))


def recursion_flops(form: int, a: np.ndarray, reals: np.ndarray, b: np.ndarray) -> int:
    """Operations of one step of the state recursion, per channel, as the kernel's arguments
    hold it: ``form`` 0 (modal: ``a`` the pairs' ``(sigma, omega)``, unit input gains) or 1
    (dense: ``a`` the state matrix, ``b`` the input column, counted as :func:`output_flops`).

    >>> recursion_flops(0, np.zeros((6, 2)), np.zeros(4), np.zeros(16))
    50
    """
    if form == 0:
        return PAIR_FLOPS * a.shape[0] + REAL_FLOPS * reals.size
    return output_flops(a, b)


def plant_flops(group) -> dict:
    """Operations per channel-sample of a ``rtctl.plant.SimGroup`` (bimorph), by part."""
    sizes, a, reals, b = group.args[:4]
    ms = group.modal.sys
    out = {"recursion": recursion_flops(int(sizes[0]), a, reals, b),
           "outputs": output_flops(ms.C, np.asarray(ms.D)[:, 0]), "adc": ADC_FLOPS * int(sizes[2])}
    out["total"] = sum(out.values())
    return out


def at_peak_ns(flops: float, peak_gflops: float) -> float:
    """ns that ``flops`` take at ``peak_gflops``.

    >>> at_peak_ns(194, 50.0)
    3.88
    """
    return float(flops) / peak_gflops
