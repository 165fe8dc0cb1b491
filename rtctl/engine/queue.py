"""Parameter changes handed from the engine's thread to the block function, lock-free.

Every array a block kernel reads as *pending parameters* (an oscillator bank's, a pulse train's)
has one writer: the block function, which drains this queue first thing in every block. The
engine's thread (the only producer) posts scalar writes ``target[row, col] = value`` and then
publishes them as one batch: the block function applies a batch whole, at a block boundary, or
not yet. So a schedule change can never land half-applied, whichever thread runs the block
(the engine's own, or an audio device's callback).

Threading contract (as sounddevice states its callback's):

* :meth:`ParamQueue.post` and :meth:`ParamQueue.publish` are called from one thread only (the
  engine's); they never wait while there is room, and a full queue makes ``publish`` wait for the
  block function to drain (at most a few blocks), or raise :class:`QueueFull` after ``timeout``.
* :func:`drain` runs inside the block function (no allocation, no locks, no Python); it reads the
  producer's write index, applies every record up to it, then advances the read index.
* Each index has one writer; a memory fence orders the records before the index that publishes
  them (and the reads before the index that frees their slots).
"""

from __future__ import annotations

import time

import numpy as np
from numba import carray

from .._codegen import fence, voidptr_at
from .._numba import kernel

#: Record fields: target (index into the tuple of pending arrays), row, column, value.
N_FIELD = 4
#: ``heads``: records published (written by the producer), records applied (by the consumer).
WRITE, READ = 0, 1


class QueueFull(RuntimeError):
    """The block function has not drained the queue in time (it is not running)."""


@kernel
def drain(ring, heads, targets):
    """Apply every published record: ``target t [row, col] = value``, target ``t`` reached through
    row ``t`` of the address table ``targets`` (address, elements, columns). Returns 0 (a status)."""
    w = heads[WRITE]
    fence()  # the records up to w are visible once w is
    r = heads[READ]
    cap = ring.shape[0]
    while r < w:
        i = r % cap
        t = int(ring[i, 0])
        dst = carray(voidptr_at(targets[t, 0]), (targets[t, 1],), np.float64)
        dst[int(ring[i, 1]) * targets[t, 2] + int(ring[i, 2])] = ring[i, 3]
        r += 1
    fence()  # every read above happens before the slots are handed back
    heads[READ] = r
    return 0


@kernel
def _publish(ring, heads, staged, n):
    """Copy ``n`` staged records into the ring, then publish them (fence, write index)."""
    cap = ring.shape[0]
    w = heads[WRITE]
    for j in range(n):
        i = (w + j) % cap
        for f in range(N_FIELD):
            ring[i, f] = staged[j, f]
    fence()
    heads[WRITE] = w + n


class ParamQueue:
    """The single-producer/single-consumer queue of pending-parameter writes.

    Parameters
    ----------
    targets : sequence of ndarray
        The pending-parameter arrays (float64, 2-D, C-contiguous) records may write; the block
        function alone writes them once they are registered here.
    capacity : int
        Records the ring holds; the largest batch the engine posts between two blocks must fit.
    """

    def __init__(self, targets, capacity: int = 1 << 14):
        self.targets = tuple(targets) or (np.zeros((1, 1)),)
        for t in self.targets:
            if t.dtype != np.float64 or t.ndim != 2 or not t.flags.c_contiguous:
                raise TypeError("a pending-parameter target must be a C-contiguous 2-D float64 array")
        self.ring = np.zeros((capacity, N_FIELD))
        self.heads = np.zeros(2, dtype=np.int64)
        self._staged = np.zeros((capacity, N_FIELD))
        self._n = 0
        self._ids = {id(t): i for i, t in enumerate(self.targets)}
        # the targets by address: one argument of one type however many there are (a tuple of a
        # thousand arrays is a type numba will not build, and a new one for every count); read-only,
        # so a checkpoint takes it for the constant it is (the targets themselves are saved)
        self.table = np.array([(t.__array_interface__["data"][0], t.size, t.shape[1]) for t in self.targets],
                              dtype=np.int64)
        self.table.flags.writeable = False

    @property
    def args(self) -> tuple:
        """The :func:`drain` stage's arguments (the targets as an address table: keep ``targets``
        alive and unmoved while the block function can run)."""
        return self.ring, self.heads, self.table

    def target_id(self, array) -> int:
        try:
            return self._ids[id(array)]
        except KeyError:
            raise ValueError("not a registered pending-parameter array") from None

    def post(self, target: int, row: int, cols, values) -> None:
        """Stage ``targets[target][row, cols] = values`` (``cols`` an int, a slice or an index
        array; ``values`` broadcast to it). Nothing is visible until :meth:`publish`."""
        cols = np.arange(self.targets[target].shape[1])[cols]
        cols = np.atleast_1d(cols)
        vals = np.broadcast_to(np.asarray(values, dtype=np.float64), cols.shape)
        n = cols.size
        if self._n + n > self._staged.shape[0]:
            raise QueueFull(f"{self._n + n} parameter writes in one batch; the queue holds "
                            f"{self._staged.shape[0]}")
        s = self._staged[self._n:self._n + n]
        s[:, 0], s[:, 1], s[:, 2], s[:, 3] = target, row, cols, vals
        self._n += n

    def publish(self, timeout: float = 1.0) -> None:
        """Hand the staged batch to the block function (waits while the ring lacks room)."""
        n = self._n
        if n == 0:
            return
        cap = self.ring.shape[0]
        end = None
        while self.heads[WRITE] + n - self.heads[READ] > cap:
            now = time.monotonic()
            end = end or now + timeout
            if now > end:
                raise QueueFull("the block function did not drain the parameter queue within "
                                f"{timeout:g} s")
            time.sleep(1e-4)
        _publish(self.ring, self.heads, self._staged, n)
        self._n = 0

    def pending(self) -> int:
        """Records published but not yet applied."""
        return int(self.heads[WRITE] - self.heads[READ])

    def reset(self) -> None:
        self.heads[:] = 0
        self._n = 0
