"""The self-sensing stage of the block function: one observed bimorph group per stage.

A group's channels share one stage even when each has a lock-in window of its own (closed-loop
control: whole periods of the channel's own tones): a stage per channel would repeat per channel
the call's fixed work (the two lock-ins' bookkeeping, loops that vectorize only across channels),
about 1.1 us per channel and block against 0.3 us for a channel of a shared stage (48 channels,
block 32).

Imported only by scenes that observe (``control.observe`` or closed-loop control), so an
open-loop scene never compiles it. The observer must pair each block of sensed currents with the
drive that produced them: the backend hands back currents ``L`` blocks after the drive went out
(one on the ``sim`` backend, the measured round trip on an audio interface), so the drive waits
in a ring of ``L`` blocks.
"""

import numpy as np

from .._numba import kernel
from ..safety import ESTIMATE_NONFINITE
from .rt import ObserverRows, observer_process


@kernel
def observe_stage(u_ref, u_pend, u_chan, u_acc, u_ring, u_solve, i_ref, i_pend, i_chan, i_acc, i_ring, i_solve,
                  u_out, back, H, Hc, pick, resid, contact, lag, scale, est, wave, pf, pf_z, pf_x, pf_g,
                  d_acc, d_edge, invJ, Kc, delay, head, out, sensed, amp):
    """Observe one block and push this block's drive into the delay ring.

    Parameters
    ----------
    u_ref ... Kc
        ``Observer.args`` (see :func:`rtctl.selfsense.rt.observer_process`).
    delay : ndarray, shape (L, n_ch, block)
        The drive of the last ``L`` blocks; ``delay[head[0]]`` is the oldest, the one the
        currents in ``sensed`` answer.
    head : ndarray int64, shape (1,)
    out : ndarray, shape (n_ch, block)
        This block's drive (after the limiter).
    sensed : ndarray, shape (n_ch * n_seg, block)
        The currents the backend delivered at the start of this block, A.
    amp : ndarray, shape (n_ch,)
        Written: estimated tip amplitude per channel, m: the sum over its tones (the envelope
        peak of a beat pair).

    Returns
    -------
    int
        0 or ``ESTIMATE_NONFINITE``.
    """
    k = head[0]
    s = observer_process(u_ref, u_pend, u_chan, u_acc, u_ring, u_solve, i_ref, i_pend, i_chan, i_acc, i_ring, i_solve,
                         u_out, back, H, Hc, pick, resid, contact, lag, scale, est, wave, pf, pf_z, pf_x,
                         pf_g, d_acc, d_edge, invJ, Kc, delay[k], sensed)
    delay[k, :, :] = out
    head[0] = (k + 1) % delay.shape[0]
    for c in range(est.shape[0]):
        a = 0.0
        for j in range(est.shape[1]):
            a += np.hypot(est[c, j, 0, 0], est[c, j, 0, 1])
        amp[c] = a
    return ESTIMATE_NONFINITE if s != 0 else 0


class ObserverStage:
    """An observer with its drive delay ring and amplitude output: the stage's arguments and its
    reset, for a rig to wrap into its stage list."""

    ARG_NAMES = ("u_ref", "u_pend", "u_chan", "u_acc", "u_ring", "u_solve", "i_ref", "i_pend", "i_chan", "i_acc",
                 "i_ring", "i_solve", "u_out", "back", "H", "Hc", "pick", "resid", "contact", "lag", "scale", "est",
                 "wave", "pf", "pf_z", "pf_x", "pf_g", "d_acc", "d_edge", "invJ", "Kc", "delay", "head", "out",
                 "sensed", "amp")

    def __init__(self, observer, latency_blocks: int, out, sensed, amp):
        self.observer = observer
        self.delay = np.zeros((max(1, int(latency_blocks)), observer.n_channels, observer.block))
        self.head = np.zeros(1, dtype=np.int64)
        self.amp = amp
        self.args = dict(zip(self.ARG_NAMES, (*observer.args, self.delay, self.head, out, sensed, amp)))

    def reset(self) -> None:
        self.observer.reset()
        self.delay[...] = 0.0
        self.head[0] = 0
        self.amp[...] = 0.0

    def channels(self, c0: int, c1: int) -> "ObserverChannels":
        """Channels ``c0 .. c1 - 1`` of this stage (indices within its group)."""
        return ObserverChannels(self, c0, c1)


class ObserverChannels:
    """Some channels of an :class:`ObserverStage`, for a consumer that is per channel or per
    few channels: ``observer`` is an :class:`~rtctl.selfsense.rt.ObserverRows` of them, ``stage``
    the stage that runs them (it alone is in the stage list and resets them)."""

    def __init__(self, stage: ObserverStage, c0: int, c1: int):
        self.stage = stage
        self.observer = ObserverRows(stage.observer, c0, c1)
        self.amp = stage.amp[c0:c1]
