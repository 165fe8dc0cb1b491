"""A finger that lifts off or lands, told from the first block of currents read after it.

The observer reads a tone over a window of whole periods (25 ms at 40 Hz), so a lift-off shows in
its estimates only a window's share at a time, and a loop that waits for them lets the tip swing
at up to twice its target meanwhile. The currents themselves show the event at once: in the first
block read after a lift-off the free beam rings at its own modes, hundreds of times the sensor
noise (bench/ring_test.py). So each block, per channel, this stage asks every load the observer
knows (its finger sets and the free tip) to explain the block: its steady currents for the drive
the window holds (each tone through the candidate's segment readings per drive volt, the drive's
folded images included: the observer's own design), plus a free level and free sines at that
load's two lowest modes (the ring the event leaves, any amplitude and phase). The free tip wins
when its residual is under every finger's by :data:`LIFT_RATIO`. The test runs only where it
means something: the channel's finger candidate in use, its drive held (the block's drive is the
window's phasors within :data:`LIFT_HELD`), and the block's currents ringing (the energy of their
first difference :data:`LIFT_JUMP` times the block before's). A lift-off sets the channel's flag
for the controller's release rule, in the block read, which drops the drive one block later.

Measured (bench/ring_test.py, the closed-loop sweep's 33 devices, the first block read after each
finger event, every tone under 500 Hz and the beat pairs): the free tip explained the block best
after every lift-off, by 1.52 times (rms) or more, and a finger after every press (2.23) and
landing (2.29).

A landing is told alike where the channel reads through the free tip's candidate (after a
lift-off, on a beam whose drive's images tell the loads apart): a finger better than the free tip
by the same ratio puts the channel on that finger's candidate at once, where the observer's own
votes took half a window and read the loaded beam through the free tip's images meanwhile (15-20 %
high on a 20 mm beam). Its gates differ (:data:`LAND_JUMP`, :data:`LAND_HELD`): a landing damps
the beam, so the currents' first difference barely moves.
"""

from __future__ import annotations

import math

import numpy as np

from .._numba import kernel
from ..dsp import _kernels as _dk
from ..errors import ModelError
from . import _kernels as _ldk

#: The free tip's residual must be under every finger's by this factor (rms) for a lift-off.
LIFT_RATIO = 1.3
#: The block is tested only where the energy of its currents' first difference (the ring's share:
#: a low tone's own is small) is this many times the block before's (rms factor squared: 5x). A
#: lift-off made it about 20 000 times at 10-120 Hz and 21-23 for the 250 / 30 Hz beat pairs
#: (their own first difference is large), which this leaves to the release rule's estimates: at
#: 10 a finger three times stiffer than the model's, ringing after a correction 74 ms after a press
#: on a 12 mm beam, opened the test at 18 and read as no finger (its loaded mode near the free one).
LIFT_JUMP = 25.0
#: ... and only where the window's drive phasors rebuild the block's drive within this share
#: (rms): the drive held over the window, so that the candidates' steady currents are the block's.
LIFT_HELD = 0.01
#: ... and for a landing within this share: the free tip's residual would jump at any change of
#: the drive, whose transient no candidate's steady currents hold (a correction of +0.46 % at
#: 250 Hz, ramped over one block, raised it 140 times; the finger's candidates explained that
#: block better). A window after each change of the drive goes untested (its phasors hold the old
#: drive), where the observer's votes still tell a landing.
LAND_HELD = 1e-4
#: Lowest modes of each candidate whose ring is left free.
RING_MODES = 2
#: A landing is looked for only where the free tip's residual (the candidate in use) is this many
#: times its level on the blocks before (``S_FREE``: their least, rising towards each later one
#: by ``LAND_RATE`` per block): the finger damps the beam, whose currents then change by 2-3 times
#: at most (their first difference's energy, no gate for a lift-off's), and the free tip no
#: longer explains them (its residual 4-7 times its level over the first blocks under a finger 3x
#: softer than the model's, 170-600 times under a stiffer one). The verdict alone, on every block,
#: would not do: on a device off its model the calibrated free tip may leave 2-3 times the noise
#: on a steady lifted block where a finger's candidate leaves less (250 Hz on a 12 mm beam), and
#: the observer then read the lifted beam through a finger's images, 2.9 % low.
LAND_JUMP = 3.0
LAND_RATE = 1.0 / 16.0
#: Columns of ``state`` per channel: the flag of this block (1: a lift-off, -1: a landing), the
#: first difference's energy of the block before, the free tip's residual's level (``LAND_JUMP``;
#: 0: none, the free tip not in use or the drive not held), then the last sample of each segment,
#: then each candidate's residual energy of the last test (A^2 over the block; what the flag was
#: decided on).
S_FLAG, S_PREV, S_FREE = 0, 1, 2
S_LAST = 3

_ZR, _ZI, _WR, _WI = _dk.ZR, _dk.ZI, _dk.WR, _dk.WI
_XR, _XI = _dk.X_R, _dk.X_I


@kernel
def lift_stage(u_ref, u_acc, pf_g, scale, pick, H, Hc, resid, free, watch, ly, lq, lz, lr, state, delay, head,
               sensed, c_index, c_state, lifted_row, c0):
    """Test each channel's block read for a lift-off (and write the flag of every controlled
    tone) or, where it reads through the free tip's candidate, a landing (and put it on the
    finger's).

    Runs before the group's observer stage: ``u_ref`` holds the drive's references at the first
    sample of this block, ``u_acc`` the drive's window sums of the block before, ``pick`` the
    candidate in use, and ``delay[head[0]]`` the drive the currents in ``sensed`` answer.

    Parameters
    ----------
    u_ref, u_acc, pf_g, scale, pick, H, Hc, resid
        The observer's (``Observer.args``); a landing writes ``pick``, ``H`` and ``resid``.
    free : ndarray of int64, shape (n_ch,)
        Each channel's candidate without a finger, where it is tested (-1: not tested).
    watch : ndarray of int64, shape (n_ch,)
        1 where a lift-off is looked for (a tone of the channel has the release rule), 0 where
        only a landing is.
    ly : ndarray, shape (n_ch, n_t, n_q, n_seg, 2)
        Each candidate's sensed current per drive volt at each tone and segment (real, imaginary).
    lq : ndarray, shape (n_q, block, n_cols)
        Each candidate's ring columns over a block, orthonormal.
    lz : ndarray, shape (n_t, block, 2)
        Scratch: a channel's drive per tone on the block's samples, as phasors.
    lr : ndarray, shape (block,)
        Scratch: a segment's residual.
    state : ndarray, shape (n_ch, S_LAST + n_seg + n_q)
        See ``S_FLAG`` ...; updated.
    delay, head, sensed
        The observer stage's drive ring and its currents of this block.
    c_index, c_state : ndarray
        A controller's index (row 0: each tone's observer channel, counted from ``c0``) and state:
        row ``lifted_row`` of ``c_state`` gets each tone's channel's flag.
    lifted_row, c0 : int
    """
    n_ch, n_t, n_q, n_seg = ly.shape[0], ly.shape[1], ly.shape[2], ly.shape[3]
    n = sensed.shape[1]
    drive = delay[head[0]]
    for c in range(n_ch):
        state[c, S_FLAG] = 0.0
        f = free[c]
        if f < 0:
            continue
        if pick[c] == f:  # (the lift-off's gate, unused while the free tip is in use, starts anew after)
            state[c, S_PREV] = 0.0
            _landing(u_ref, u_acc, pf_g, scale, pick, H, Hc, resid, ly, lq, lz, lr, state, drive, sensed, c, f)
            continue
        state[c, S_FREE] = 0.0  # (and the landing's level, once the free tip is in use again)
        if watch[c] == 0:
            continue
        d2 = 0.0
        for j in range(n_seg):
            row = c * n_seg + j
            d = sensed[row, 0] - state[c, S_LAST + j]
            a0 = d * d
            a1 = 0.0
            a2 = 0.0
            a3 = 0.0
            # four sums, so that the adds are four chains instead of one (the steady blocks' cost)
            m = 1
            while m + 3 < n:
                d = sensed[row, m] - sensed[row, m - 1]
                a1 += d * d
                d = sensed[row, m + 1] - sensed[row, m]
                a2 += d * d
                d = sensed[row, m + 2] - sensed[row, m + 1]
                a3 += d * d
                d = sensed[row, m + 3] - sensed[row, m + 2]
                a0 += d * d
                m += 4
            while m < n:
                d = sensed[row, m] - sensed[row, m - 1]
                a1 += d * d
                m += 1
            d2 += (a0 + a1) + (a2 + a3)
            state[c, S_LAST + j] = sensed[row, n - 1]
        before = state[c, S_PREV]
        state[c, S_PREV] = d2
        if not (before > 0.0 and d2 > LIFT_JUMP * before and d2 < math.inf):
            continue
        if not _drive_off(u_ref, u_acc, pf_g, scale, c, n_t, drive, lz) <= LIFT_HELD:
            continue
        e = S_LAST + n_seg
        for q in range(n_q):
            state[c, e + q] = _residual(ly, lq, lz, lr, sensed, c, q)
        lifted = True
        for q in range(n_q):
            if q != f and not (state[c, e + f] * LIFT_RATIO * LIFT_RATIO < state[c, e + q]):
                lifted = False
        if lifted:
            state[c, S_FLAG] = 1.0
    for i in range(c_state.shape[1]):
        c_state[lifted_row, i] = max(state[c0 + c_index[0, i], S_FLAG], 0.0)


@kernel
def _landing(u_ref, u_acc, pf_g, scale, pick, H, Hc, resid, ly, lq, lz, lr, state, drive, sensed, c, f):
    """Test channel ``c``, read through the free tip's candidate ``f``, for a landing: where the
    free tip's residual jumps over its level (``LAND_JUMP``) on a held drive (``LAND_HELD``) and
    a finger explains the block better by ``LIFT_RATIO``, the observer reads through that
    finger's candidate from this block on (its votes took half a window, and the free tip's
    images on a loaded beam read its tip up to 20 % high meanwhile), with the votes' smoothed
    losses as if every vote had gone to it: they must go against it as long to take it back."""
    n_t, n_q, n_seg = ly.shape[1], ly.shape[2], ly.shape[3]
    level = state[c, S_FREE]
    state[c, S_FREE] = 0.0
    if not _drive_off(u_ref, u_acc, pf_g, scale, c, n_t, drive, lz) <= LAND_HELD:
        return
    r = _residual(ly, lq, lz, lr, sensed, c, f)
    if not (r < math.inf):
        return
    state[c, S_FREE] = r if not (0.0 < level < r) else level + LAND_RATE * (r - level)
    if not (level > 0.0 and r > LAND_JUMP * level):
        return
    e = S_LAST + n_seg
    best = -1  # the finger that explains the block best
    for q in range(n_q):
        state[c, e + q] = r if q == f else _residual(ly, lq, lz, lr, sensed, c, q)
        if q != f and (best < 0 or state[c, e + q] < state[c, e + best]):
            best = q
    if best >= 0 and state[c, e + best] * LIFT_RATIO * LIFT_RATIO < state[c, e + f]:
        _ldk.use_load(H, Hc, pick, c, best)
        for q in range(n_q):
            resid[c, 0, q] = 1.0 if q == f else 0.0
        state[c, S_FLAG] = -1.0


@kernel
def _drive_off(u_ref, u_acc, pf_g, scale, c, n_t, drive, lz):
    """Write each tone's drive on the block's samples into ``lz`` as phasors (``x[m] = Re(D
    z[m])``, the drive as sent: the low-pass's response taken out of the window's ``D``) and
    return how far their sum is from the block's drive (rms, relative; inf: no drive)."""
    n = drive.shape[1]
    sc = scale[c]
    for k in range(n_t):
        us = c * n_t + k
        g, ph = pf_g[c, k, 0], pf_g[c, k, 1]
        xr, xi = sc * u_acc[_XR, us] * g, sc * u_acc[_XI, us] * g
        cr, ci = math.cos(ph), -math.sin(ph)
        dr, di = xr * cr - xi * ci, xr * ci + xi * cr
        zr, zi = u_ref[_ZR, us], u_ref[_ZI, us]
        wr, wi = u_ref[_WR, us], u_ref[_WI, us]
        for m in range(n):
            lz[k, m, 0] = dr * zr - di * zi
            lz[k, m, 1] = dr * zi + di * zr
            t = zr * wr - zi * wi
            zi = zr * wi + zi * wr
            zr = t
    e = 0.0
    ed = 0.0
    for m in range(n):
        x = 0.0
        for k in range(n_t):
            x += lz[k, m, 0]
        v = drive[c, m]
        e += (v - x) * (v - x)
        ed += v * v
    return math.sqrt(e / ed) if ed > 0.0 else math.inf


@kernel
def _residual(ly, lq, lz, lr, sensed, c, q):
    """Candidate ``q``'s residual energy on channel ``c``'s block: the currents less its steady
    currents for the drive in ``lz``, less their projection on its ring columns, summed over the
    segments."""
    n_t, n_seg = ly.shape[1], ly.shape[3]
    n, n_cols = lq.shape[1], lq.shape[2]
    e = 0.0
    for j in range(n_seg):
        for m in range(n):
            p = 0.0
            for k in range(n_t):
                p += ly[c, k, q, j, 0] * lz[k, m, 0] - ly[c, k, q, j, 1] * lz[k, m, 1]
            lr[m] = sensed[c * n_seg + j, m] - p
        for m in range(n):
            e += lr[m] * lr[m]
        for col in range(n_cols):
            p = 0.0
            for m in range(n):
                p += lq[q, m, col] * lr[m]
            e -= p * p
    return max(e, 0.0)


class LiftTest:
    """The lift-off test of an :class:`~rtctl.selfsense.rt.Observer`'s channels (see the module).

    Parameters
    ----------
    observer : Observer
        Its candidates (one without a finger, one or more with), beam, front end and tones.
    channels : array_like of int, optional
        The observer's channels to test for a landing (default all): those with a controlled tone.
    watched : array_like of int, optional
        Those of them also tested for a lift-off (default all): those with a tone the release
        rule watches (elsewhere the flag would be read by no one).

    Attributes
    ----------
    active : bool
        False where the observer has no free candidate or no finger's (nothing to tell apart), or
        where a candidate's modes cannot be found (``why`` says which): the rig then leaves the
        stage out, and lift-offs are told by the release rule's estimates alone.
    why : str
    """

    def __init__(self, observer, channels=None, watched=None):
        ob = observer
        loads = ob.image_loads if ob.frontend is not None else ob.image_loads[:1]
        n_ch, n_t, n_seg, block = ob.n_channels, ob.n_tones, ob.n_seg, ob.block
        self.observer = ob
        self.active = any(x is None for x in loads) and any(x is not None for x in loads)
        self.why = ""
        n_q = len(loads)
        n_cols = 1 + 2 * RING_MODES
        self.ly = np.zeros((n_ch, n_t, n_q, n_seg, 2))
        self.lq = np.zeros((n_q, block, n_cols))
        self.lz = np.zeros((n_t, block, 2))
        self.lr = np.zeros(block)
        free = [q for q, x in enumerate(loads) if x is None]
        self.free = np.full(n_ch, -1, dtype=np.int64)
        self.free[np.arange(n_ch) if channels is None else np.asarray(channels, dtype=np.int64)] = \
            free[0] if self.active else -1
        self.watch = np.zeros(n_ch, dtype=np.int64)
        self.watch[np.arange(n_ch) if watched is None else np.asarray(watched, dtype=np.int64)] = 1
        self.watch[self.free < 0] = 0
        self.state = np.zeros((n_ch, S_LAST + n_seg + n_q))
        if not self.active:
            return
        per_volt = ob.readings_per_volt
        for c in range(n_ch):
            for k in np.flatnonzero(ob.freqs[c] > 0.0):
                for q in range(n_q):
                    y = per_volt[float(ob.freqs[c, k])][q]
                    self.ly[c, k, q, :, 0] = y.real
                    self.ly[c, k, q, :, 1] = y.imag
        t = np.arange(block) / ob.fs
        for q, load in enumerate(loads):
            try:
                modes = (ob.beam.natural_frequencies(RING_MODES) if load is None
                         else ob.beam.loaded_frequencies(load, RING_MODES))
            except ModelError as e:
                self.active, self.why = False, f"the modes of candidate load {q}: {e}"
                return
            cols = [np.ones(block)] + [f(2 * np.pi * fm * t) for fm in modes for f in (np.cos, np.sin)]
            self.lq[q], _ = np.linalg.qr(np.stack(cols, axis=1))

    def reset(self) -> None:
        self.state[...] = 0.0

    def stage_args(self, observer_args: dict, controller, c0: int = 0) -> dict:
        """:func:`lift_stage`'s arguments: the observer stage's (``ObserverStage.args``), this
        test's, and the flags' destination, ``controller``'s state (its channels from ``c0``)."""
        from ..control._kernels import LIFTED

        a = observer_args
        return dict(u_ref=a["u_ref"], u_acc=a["u_acc"], pf_g=a["pf_g"], scale=a["scale"], pick=a["pick"],
                    H=a["H"], Hc=a["Hc"], resid=a["resid"], free=self.free, watch=self.watch, ly=self.ly,
                    lq=self.lq, lz=self.lz, lr=self.lr, state=self.state, delay=a["delay"], head=a["head"],
                    sensed=a["sensed"], c_index=controller.index, c_state=controller.state, lifted_row=LIFTED,
                    c0=int(c0))
