"""Real-time observer of a group of bimorph channels: preallocated state for :func:`observer_process`."""

from __future__ import annotations

import functools
import math
from fractions import Fraction

import numpy as np
import scipy.signal

from rtctl.dsp import _kernels as _dk
from rtctl.dsp.lockin import MAX_LSQ_COND, LockIn, lsq_gram
from rtctl.errors import ModelError
from rtctl.selfsense import _kernels
from rtctl.selfsense.observer import EST_NAMES, MAX_COND, N_EST, design_many
from rtctl.selfsense.tmm import _load_stiffness

__all__ = ["Observer", "ObserverRows", "observer_process", "prefilter_cutoffs",
           "short_windows", "tone_window", "tone_windows"]

#: ``observer_process(*obs.args, drive, sensed) -> int`` (callable from other numba functions).
observer_process = _kernels.observer_process
STATUS_NONFINITE = _kernels.STATUS_NONFINITE


def tone_window(freqs, fs, hop, max_seconds=1.0) -> int:
    """Shortest multiple of ``hop`` samples holding a whole number of periods of every tone.

    Over such a window the lock-in has no leakage between the tones or from their mirrors.

    Parameters
    ----------
    freqs : array_like
        Tone frequencies, Hz (zeros and NaN ignored).
    fs : float
        Hz.
    hop : int
        Samples.
    max_seconds : float
        Give up beyond this and return the longest window (some leakage remains).

    Examples
    --------
    >>> tone_window([245.0, 255.0], 48000.0, 32)
    9600
    """
    f = np.asarray(freqs, dtype=float).ravel()
    f = f[np.isfinite(f) & (f > 0)]
    m_max = max(1, int(max_seconds * fs) // hop)
    # every candidate at once (a tone of no short whole-period window tries all of them: 1500 at
    # block 32, a numpy call each one by one, 25 ms per channel), in chunks that keep it small
    for m0 in range(1, m_max + 1, 256):
        m = np.arange(m0, min(m0 + 256, m_max + 1))
        cyc = f[None, :] * (m * hop)[:, None] / fs
        ok = np.all(np.abs(cyc - np.round(cyc)) < 1e-9, axis=1)
        if ok.any():
            return int(m[np.argmax(ok)]) * hop
    return m_max * hop


def holds_whole_periods(freqs, window, fs) -> bool:
    """Whether ``window`` samples hold a whole number of periods of every tone (zeros and NaN
    ignored): :func:`tone_window` gives up beyond ``max_seconds`` with a window that does not, and
    a lock-in over it leaks (one tone's mirror into its own reading: a 2 Hz tone over 47 104
    samples, block 1024, read 11 % high).

    >>> holds_whole_periods([2.0, 10.0], 24000, 48000.0), holds_whole_periods([2.0], 47104, 48000.0)
    (True, False)
    """
    f = np.asarray(freqs, dtype=float).ravel()
    cyc = f[np.isfinite(f) & (f > 0)] * int(window) / fs
    return bool(np.all(np.abs(cyc - np.round(cyc)) < 1e-9))


def block_window(freqs, fs, block, max_seconds=1.0) -> tuple[int, int]:
    """One lock-in window for every tone of ``freqs`` and its hop: :func:`tone_window` on the block
    grid (hop ``block``) when that holds whole periods, else the fewest samples that do with the
    largest divisor of ``block`` dividing them as hop (2 Hz at block 1024: 24 000 samples, hop
    64), unless that needs a hop under :data:`MIN_HOP` or more than ``max_seconds``: then the
    grid's window, leaking as it must.

    >>> block_window([2.0, 10.0], 48000.0, 32), block_window([2.0, 10.0], 48000.0, 1024)
    ((24000, 32), (24000, 64))
    """
    block = int(block)
    w0 = tone_window(freqs, fs, block, max_seconds)
    if holds_whole_periods(freqs, w0, fs):
        return w0, block
    f = np.asarray(freqs, dtype=float).ravel()
    f = f[np.isfinite(f) & (f > 0)]
    w = _whole_periods(f, fs)
    hop = math.gcd(block, w)
    if hop >= min(block, MIN_HOP) and w <= max_seconds * fs:
        return w, hop
    return w0, block


def tone_windows(freqs, fs, hop, max_seconds=1.0) -> np.ndarray:
    """:func:`tone_window` of each row's tones alone, shape (n_rows,), int64: per channel, the
    shortest window over which that channel's own tones leak nothing into one another.

    Examples
    --------
    >>> tone_windows([[2.0, 0.0], [245.0, 255.0], [250.0, 0.0]], 48000.0, 32).tolist()
    [24000, 9600, 192]
    """
    f = np.atleast_2d(np.asarray(freqs, dtype=float))
    return np.array([tone_window(row, fs, hop, max_seconds) for row in f], dtype=np.int64)


def _whole_periods(f, fs) -> int:
    """Fewest samples holding whole periods of every tone of ``f`` (Hz, > 0): the least common
    multiple of the numerators of ``fs / f`` (``W f / fs`` is whole exactly when ``fs / f``'s
    reduced numerator divides ``W``)."""
    w = 1
    for x in f:
        q = Fraction(fs).limit_denominator(1 << 20) / Fraction(float(x)).limit_denominator(1 << 20)
        w = w * q.numerator // math.gcd(w, q.numerator)
    return w


#: :func:`short_windows` leaves a channel's window on the block grid unless the grid makes it more
#: than this many times the shortest: a shorter window answers sooner but lets a ringing plant
#: leak more into the estimate (120 Hz over 400 samples instead of 800: a lifted beam with half the
#: damping settled 29 ms later after lift-off, for 4-12 ms gained elsewhere; bench/control_sweep.py)
SHORTEN = 2
#: ... but a shortest window at least this long (s) is taken even at twice: it already averages
#: the loaded beam's ring (tens of ms), and a window this long is what sets how soon the loop sees
#: a change (35 + 45 Hz: one 10 Hz beat, 100 ms, by least squares against 200 ms of whole periods
#: of both: under a finger whose slow branch still drifts, -3.8 % left at the end of a 1 s segment
#: and 750 ms to come within 5 %, against within 1.2 % and 250-450 ms; bench/control_sweep.py)
LONG_WINDOW_S = 0.05
#: The observer's choice of the load at the drive's images (``_kernels._pick_load``) smooths its
#: votes over half a channel's window, but not over less than this (s): a short window's votes are
#: noise-bound on a weak tone (250 Hz at 1 V, a window of 4 ms: over 2 ms its choice followed the
#: noise, and a start read 2.0 % off; over 25 ms, 0.8 %)
LOAD_LAG_S = 0.025
#: A closed-loop tone's window of whole periods is made a multiple of itself holding at least this
#: many periods of the channel's lowest tone, where that multiple is no longer than
#: :data:`RING_WINDOW_S`. A lock-in over ``N`` periods passes a sine at a relative distance ``d``
#: from its tone at ``|sinc(N d)|``: the loaded beam's first mode, which a finger landing or
#: lifting rings for tens of ms, sits 20-40 % from a 1 kHz tone (630-740 Hz under the finger,
#: 1.2 kHz lifted) and passes at 0.45-0.74 of its amplitude over 2 periods, at most 0.21 over 4.
#: After a landing the ring (1.4-2.2 um) then read as a 1 kHz tip of 1-2 um where it held 0.3.
MIN_PERIODS = 4
#: ... but no longer than this (s): a longer window answers later (500 Hz over 4 ms instead of
#: 2: starts and lift-offs 2-10 ms slower, bench/control_sweep.py --quick), and where the modes sit
#: within 20 % of the tone no window this short rejects them
RING_WINDOW_S = 0.004
#: nor does it make the lock-ins' hop shorter than this (each hop costs the ring update once more
#: per block for every slot of the group): a window of whole periods that would need it is read by
#: least squares on the block grid instead (48000 / 601 Hz: 608 samples, not 601 with a hop of 1)
MIN_HOP = 8


def short_windows(freqs, fs, block, max_seconds=1.0, max_cond=MAX_LSQ_COND, shorten=SHORTEN,
                  long_s=LONG_WINDOW_S, min_periods=MIN_PERIODS, ring_s=RING_WINDOW_S):
    """Per channel, a lock-in window over which its own tones are read without leakage from one
    another, not forced long by the block grid, and the hop that lets every channel have it.

    A channel's window is :func:`tone_window` on the block grid (whole periods of its tones, a
    multiple of ``block``), unless that is more than ``shorten`` times the shortest window without
    leakage, or at least twice a shortest window of ``long_s`` or more, which is then taken: either
    the fewest samples holding whole periods of all its tones (80 Hz: 600 samples at 48 kHz, where
    multiples of a 32-sample block need 2400), or, read by least squares, a multiple of ``block`` of
    at least one period of their closest spacing and of the lowest tone (a 235 + 265 Hz pair: 1600
    samples, one beat period, against 9600 for whole periods of both), if its condition number (as
    :class:`~rtctl.dsp.lockin.LockIn` reports it) is within ``max_cond``. The hop, shared by the
    channels' lock-ins, is the largest divisor of ``block`` dividing every window, so that each
    window still ends with the block; a window of whole periods that would need a hop under
    :data:`MIN_HOP` is not taken (least squares on the block grid, over at least one period of the
    lowest tone, may be). A window of whole periods holding fewer than ``min_periods`` of the
    lowest tone is then made the multiple of itself that holds them, if that is no longer than
    ``ring_s`` (:data:`MIN_PERIODS`: 1 kHz over 192 samples, not 96).

    Parameters
    ----------
    freqs : array_like, shape (n_channels, n_tones)
        Hz; 0 or NaN unused.
    fs : float
    block : int
    max_seconds : float
        As for :func:`tone_window`.
    max_cond : float
    shorten : float
        See :data:`SHORTEN`.
    long_s : float
        See :data:`LONG_WINDOW_S`.
    min_periods : int
    ring_s : float
        See :data:`MIN_PERIODS` and :data:`RING_WINDOW_S`.

    Returns
    -------
    windows : ndarray of int64, shape (n_channels,)
    lstsq : ndarray of bool, shape (n_channels,)
    hop : int

    Examples
    --------
    >>> w, lsq, hop = short_windows([[80.0, 0.0], [235.0, 265.0], [120.0, 0.0]], 48000.0, 32)
    >>> w.tolist(), lsq.tolist(), hop
    ([600, 1600, 800], [False, True, False], 8)
    >>> short_windows([[1000.0], [500.0], [1500.0]], 48000.0, 32)[0].tolist()
    [192, 96, 128]
    """
    f = np.atleast_2d(np.asarray(freqs, dtype=float))
    block = int(block)
    windows = np.zeros(f.shape[0], dtype=np.int64)
    lstsq = np.zeros(f.shape[0], dtype=bool)
    for c, row in enumerate(f):
        row = np.sort(row[np.isfinite(row) & (row > 0)])
        w0 = tone_window(row, fs, block, max_seconds)
        windows[c] = w0
        if row.size == 0:
            continue
        w = _whole_periods(row, fs)
        if math.gcd(block, w) < min(block, MIN_HOP):
            w = w0  # too fine a hop: not shorter than the block grid's
        if row.size == 1 or np.diff(row).min() > 0:
            span = fs / min(float(np.diff(row).min()) if row.size > 1 else math.inf, float(row[0]))
            wl = block * math.ceil(span / block - 1e-9)
            if wl < w and np.linalg.cond(lsq_gram(row, wl, fs) / (0.5 * wl)) <= max_cond:
                w, lstsq[c] = wl, True
        if w0 > shorten * w or (w0 >= 2 * w and w >= long_s * fs) or not holds_whole_periods(row, w0, fs):
            windows[c] = w
        else:
            lstsq[c] = False
        if not lstsq[c] and windows[c] * row[0] < min_periods * fs:
            longer = windows[c] * math.ceil(min_periods * fs / (windows[c] * row[0]) - 1e-9)
            if longer <= ring_s * fs + 1e-9:
                windows[c] = longer
    hop = math.gcd(block, *(int(x) for x in windows))
    return windows, lstsq, hop


#: A closed-loop channel's drive and currents are low-passed at this fraction of the loaded beam's
#: lowest mode (:func:`prefilter_cutoffs`): a finger landing rings that mode, far above a low
#: tone (742 Hz against 80 Hz on a half-damped beam under a stiff finger), and a window of one
#: period passes the ring into the tone's reading, where its current, which goes with velocity,
#: counts 9 times; over the 30 ms after such a landing the 80 Hz estimate was 37 % rms off the
#: tip (82 % at worst), low-passed at 240 Hz 8 % (18 %), at 160 Hz 10 %, at 480 Hz 14 %
PREFILTER_AT = 0.45
#: ... for the channels whose highest tone is at most 1 / this of the cutoff: a tone near the ring
#: gains little, and waits for the filter's memory all the same (120 and 500 Hz low-passed at 3x
#: their tone started 4-12 ms later, past their 50 ms, bench/control_sweep.py --quick)
PREFILTER_X = 3.0
#: ... and a cutoff under this fraction of the sample rate
PREFILTER_MAX = 0.4
#: A closed-loop tone waits for the low-pass's memory as for its window: until its impulse
#: response has fallen to this of its peak (240 Hz: 2.5 ms)
PREFILTER_DECAY = 0.1


def prefilter_cutoffs(freqs, fs, lowest_mode, at=PREFILTER_AT, x=PREFILTER_X, most=PREFILTER_MAX) -> np.ndarray:
    """Per channel, the drive's and currents' low-pass cutoff (Hz) for :class:`Observer`'s
    ``prefilter``: ``at`` times ``lowest_mode`` (Hz: the loaded beam's lowest mode, whose ring the
    filter is for), where the channel's highest tone is at most ``1 / x`` of that and the cutoff
    under ``most * fs``; else 0 (none).

    >>> prefilter_cutoffs([[80.0, 0.0], [35.0, 45.0], [120.0, 0.0], [0.0, 0.0]], 48000.0, 600.0).tolist()
    [270.0, 270.0, 0.0, 0.0]
    """
    f = np.atleast_2d(np.asarray(freqs, dtype=float))
    top = np.where(np.isfinite(f), f, 0.0).max(axis=1)
    fc = at * float(lowest_mode)
    ok = (top > 0) & (x * top <= fc) & (fc < most * fs)
    return np.where(ok, fc, 0.0)


class Observer:
    """Self-sensing observer for ``n_channels`` identical bimorphs, one block at a time.

    Per block: lock-in of the drive and of every sensed segment current at each channel's tones
    (a sliding window of whole periods), the per-frequency observer matrices of
    :func:`~rtctl.selfsense.observer.design` applied to those phasors, and the tip deflection
    rebuilt on the block's samples. Run it with ``observer_process(*obs.args, drive, sensed)``
    from a numba block step, or with :meth:`process`.

    The window is one for all channels (whole periods of every tone of the group) or one per
    channel (whole periods of that channel's own tones: ``window=tone_windows(freqs, fs,
    block)``); a channel's estimates are then those a one-channel observer on its own tones
    would give, with the per-call cost of one observer for all of them.

    Parameters
    ----------
    beam : TMMBeam
        Model of the actuators.
    freqs : array_like, shape (n_channels, n_tones)
        Driven frequencies per channel, Hz (both tones of a beat pair; 0 or NaN: unused slot).
    fs : float
        Hz.
    block : int
        Samples per block.
    frontend : FrontEnd, optional
        Drive and sense chain (default: ideal).
    window : int or array_like of int, shape (n_channels,), optional
        Lock-in window, samples, multiples of ``hop``: one for all channels, or one per channel
        (default :func:`block_window` of all tones, with its hop unless ``hop`` is given;
        :func:`short_windows` gives the shortest).
    hop : int, optional
        The lock-ins' hop, a divisor of ``block`` (default ``block``): every window ends with
        the block, so a window need only be a multiple of the hop (80 Hz's 600 samples with a hop
        of 8 at block 32); each hop costs the lock-ins' ring update once more per block.
    lstsq : bool or array_like of bool, shape (n_channels,), optional
        Channels whose tones are read by least squares (:class:`~rtctl.dsp.lockin.LockIn`):
        drive and currents alike, free of one another over windows of any length.
    image_load : MaxwellLoad, optional
        Load assumed for the aliased images.
    image_loads : sequence of MaxwellLoad or None, optional
        Further loads the images may see (None: a free tip, the finger lifted): each channel reads
        its currents through the candidate whose observer leaves the least tip-moment residual
        most often (:func:`~rtctl.selfsense._kernels._pick_load`), starting with ``image_load``.
    prefilter : float or array_like, shape (n_channels,), optional
        Low-pass the channel's drive and currents before the lock-ins (second-order Butterworth,
        cutoff Hz; 0 or None: not): a ring of the beam above the tones then leaks less into their
        reading (:func:`prefilter_cutoffs`). Its response at each tone is divided out of the
        observer matrices and the drive's reading, so steady estimates are unchanged.
    steps : bool
        Take a drive step's boundary term out of the windows that hold one (default): without
        it, such a window reads the tip several times too large (``_steps_design``; it costs the
        stage 2-7 %, bench/observer.py).
    rows : int
        How many of the leading ``EST_NAMES`` rows the block step computes (default all; 1: the
        tip alone, all a rig's controller and waveform read, which saves the stage about 5 % at
        48 channels). :meth:`phasors` of a row not kept is refused.
    max_cond : float
        Refuse ill-conditioned frequencies (also for four segments, whose tip estimate is less
        fragile than the support stiffness that :func:`~rtctl.selfsense.observer.design` guards
        with ``MAX_COND_SUPPORT``).
    wave : ndarray, shape (n_channels, block), optional
        Where the rebuilt tip deflection goes (e.g. rows of a rig's estimate buffer); default a
        new array.

    Attributes
    ----------
    window : int
        The longest channel's window, samples (the window, when it is one for all).
    windows : ndarray of int64, shape (n_channels,)
        Each channel's window, samples.
    scale : ndarray, shape (n_channels,)
        ``2 / windows``: a lock-in window sum to a phasor, per channel.
    H : ndarray, shape (n_channels, n_tones, N_EST, 1 + n_seg, 2)
        The observer matrices in use (a copy of one candidate's).
    Hc : ndarray, shape (n_channels, n_tones, n_loads, N_EST, 1 + n_seg, 2)
        Each candidate image load's (``image_load`` first, then ``image_loads``).
    pick : ndarray of int64, shape (n_channels,)
        The candidate each channel's ``H`` holds.
    resid : ndarray, shape (n_channels, 3, n_loads)
        Each candidate's smoothed loss of the blocks' votes, the kernel's scratch, and the
        candidate with a finger to come back to after a lift-off.
    contact : ndarray, shape (n_channels, n_tones, 3)
        Per tone, for the kernel's force test: the candidate without a finger (-1: none), the
        least impedance the others put on the tip, squared (N^2/m^2), and the free beam's tip per
        drive volt, squared (m^2/V^2).
    prefilter : ndarray, shape (n_channels,)
        Each channel's low-pass cutoff, Hz (0: none).
    prefilter_gain : ndarray, shape (n_channels, n_tones), complex
        Its response at each tone (1: none).
    prefilter_memory : ndarray of int64, shape (n_channels,)
        Samples its impulse response takes to fall for good to :data:`PREFILTER_DECAY` of its peak
        (0: none): what a window must wait for beyond its own length to hold nothing older.
    lag : ndarray, shape (n_channels,)
        The votes' smoothing per block: ``block`` over half the channel's window, or over
        :data:`LOAD_LAG_S`, whichever is longer.
    cond : ndarray, shape (n_channels, n_tones)
        Condition number per slot (NaN unused).
    est : ndarray, shape (n_channels, n_tones, rows, 2)
        Latest estimates (real, imaginary), the first ``rows`` of ``EST_NAMES``.
    u_out : ndarray, shape (n_channels, n_tones, 2)
        The drive's amplitude (peak, V) and phase (rad) per tone slot over the same window (NaN
        for an unused slot); its phasor's window sum is ``lock_u.acc[S_R:S_I + 1, c * n_tones + k]``
        (times ``scale[c]``).
    wave : ndarray, shape (n_channels, block)
        Latest rebuilt tip deflection, m.

    Examples
    --------
    >>> from rtctl.plant.materials import BUILTIN
    >>> from rtctl.selfsense.tmm import TMMBeam, laminate_of
    >>> pzt = BUILTIN["PZT-5A"]
    >>> beam = TMMBeam(laminate_of(1.5e-3, [(pzt, 0.3e-3), (pzt, 0.3e-3)], "parallel"),
    ...                15e-3, (0.5, 0.5), 0.01)
    >>> obs = Observer(beam, [[250.0]], 48000.0, 32)
    >>> obs.window, obs.est.shape
    (192, (1, 1, 9, 2))
    """

    def __init__(self, beam, freqs, fs, block, frontend=None, window=None, image_load=None,
                 max_cond=MAX_COND, wave=None, hop=None, lstsq=False, image_loads=(), prefilter=None, steps=True,
                 rows=N_EST):
        if isinstance(rows, bool) or not isinstance(rows, (int, np.integer)) or not 1 <= rows <= N_EST:
            raise ModelError(f"rows must be an integer in 1 ... {N_EST} (the leading rows of {EST_NAMES}); "
                             f"got {rows!r}")
        f = np.atleast_2d(np.asarray(freqs, dtype=float))
        f = np.where(np.isfinite(f), f, 0.0)
        if np.any(f < 0) or np.any(f >= fs / 2):
            raise ModelError(f"observer tones must lie in 0 < f < fs/2 = {fs / 2:g} Hz (0 unused)")
        self.beam, self.fs, self.block, self.frontend = beam, float(fs), int(block), frontend
        self.freqs = f
        n_ch, n_t = f.shape
        n_seg = beam.n_seg
        self.n_channels, self.n_tones, self.n_seg = n_ch, n_t, n_seg
        if window is None:
            window, grid_hop = block_window(f, fs, self.block)
            hop = grid_hop if hop is None else hop
        w = np.broadcast_to(np.asarray(window), (n_ch,)) if np.ndim(window) == 0 else np.asarray(window)
        if w.shape != (n_ch,) or not np.issubdtype(w.dtype, np.integer) or np.any(w < 1):
            raise ModelError(f"window must be an integer >= 1 or one per channel, shape ({n_ch},); got {window!r}")
        self.windows = np.array(w, dtype=np.int64)
        self.window = int(self.windows.max())
        self.hop = self.block if hop is None else int(hop)
        if not (1 <= self.hop <= self.block and self.block % self.hop == 0):
            raise ModelError(f"hop = {hop} must divide block = {self.block}")
        for c, wc in enumerate(self.windows):
            if wc % self.hop:
                name = "window" if np.ndim(window) == 0 else f"window[{c}]"
                raise ModelError(f"{name} = {wc} must be a multiple of hop = {self.hop}")
        self.lstsq = np.broadcast_to(np.asarray(lstsq, dtype=bool), (n_ch,)).copy()
        self.scale = 2.0 / self.windows
        self.image_loads = [image_load, *image_loads]
        # without images (an ideal front end) every load reads the same: one candidate
        loads = self.image_loads if frontend is not None else self.image_loads[:1]
        self.Hc = np.zeros((n_ch, n_t, len(loads), N_EST, 1 + n_seg, 2))
        self.H = np.zeros((n_ch, n_t, N_EST, 1 + n_seg, 2))
        self.pick = np.zeros(n_ch, dtype=np.int64)
        self.resid = np.zeros((n_ch, 3, len(loads)))
        self.lag = np.minimum(1.0, self.block / np.maximum(0.5 * self.windows, LOAD_LAG_S * self.fs))
        self.cond = np.full((n_ch, n_t), np.nan)
        # one design per distinct frequency and load, their images solved in one batch (channels
        # on the same tones share a design)
        tones = [fk for fk in f.ravel().tolist() if fk > 0.0]
        for q, load in enumerate(loads):
            cache = design_many(beam, tones, frontend, image_load=load, max_cond=max_cond)
            for c in range(n_ch):
                for k in range(n_t):
                    fk = float(f[c, k])
                    if fk <= 0.0:
                        continue
                    ob = cache[fk]
                    self.Hc[c, k, q, :, :, 0] = ob.H.real
                    self.Hc[c, k, q, :, :, 1] = ob.H.imag
                    if q == 0:
                        self.cond[c, k] = ob.cond
            if q == 0:
                self.designs = cache
        # the images enter with the drive: the loads' designs share the currents' columns, which
        # the load's choice (``_pick_load``) sums once for all of them
        if not np.array_equal(self.Hc[:, :, :, :, 1:], np.repeat(self.Hc[:, :, :1, :, 1:], len(loads), axis=2)):
            raise ModelError("observer designs for other image loads differ in the currents' columns")
        self._prefilter_design(prefilter)
        self.H[...] = self.Hc[:, :, 0]
        # the free candidate's force test (``_kernels._pick_load``): at each tone, which candidate
        # has no finger, the least squared impedance the others put on the tip, and the squared
        # tip per drive volt of the free beam
        self.contact = np.zeros((n_ch, n_t, _kernels.N_CONTACT))
        self.contact[:, :, _kernels.C_FREE] = -1.0
        free = [q for q, load in enumerate(loads) if load is None]
        touch = [load for load in loads if load is not None]
        if free and touch:
            for fk in set(tones):
                w = 2.0 * np.pi * fk
                z2 = min(abs(_load_stiffness(load, w)) for load in touch) ** 2
                g2 = abs(beam.response([fk], None)["tip"][0] * (frontend.voltage(fk) if frontend else 1.0)) ** 2
                at = f == fk
                self.contact[at, _kernels.C_FREE] = free[0]
                self.contact[at, _kernels.C_Z2] = z2
                self.contact[at, _kernels.C_G2] = g2
            # the force test weighs the window's drive, read through the low-pass
            self.contact[:, :, _kernels.C_G2] /= np.abs(self.prefilter_gain) ** 2
        try:
            self.lock_u = LockIn(n_ch, f, fs, self.windows, hop=self.hop, lstsq=self.lstsq)
            self.lock_i = LockIn(n_ch * n_seg, np.repeat(f, n_seg, axis=0), fs, np.repeat(self.windows, n_seg),
                                 hop=self.hop, lstsq=np.repeat(self.lstsq, n_seg))
        except ValueError as e:
            raise ModelError(f"observer lock-in: {e}") from None
        # the kernel computes the rows ``est`` has, and only those
        self.est = np.zeros((n_ch, n_t, int(rows), 2))
        if wave is None:
            wave = np.zeros((n_ch, self.block))
        elif wave.shape != (n_ch, self.block) or wave.dtype != np.float64 or not wave.flags.c_contiguous:
            raise ModelError(f"wave must be C-contiguous float64 of shape {(n_ch, self.block)}")
        self.wave = wave
        self.wave[...] = 0.0
        self.u_out = np.zeros((n_ch, n_t, 2))
        self._back = np.zeros((4 + self.block, n_ch * n_t))  # the waveform rebuild's scratch
        self._steps_design(bool(steps))

    def _prefilter_design(self, prefilter) -> None:
        """The low-pass of each channel's drive and currents (second-order Butterworth at
        ``prefilter`` Hz, 0: none), and its response ``G`` at each tone taken out of ``Hc`` and of
        the drive's amplitude and phase: in steady state, estimates and drive read as without it.
        Drive and currents go through the same filter, so that a window over a drive step sees
        both as late (the estimate cancels a large drive term against the currents')."""
        n_ch, n_seg, n_t = self.n_channels, self.n_seg, self.n_tones
        fc = np.zeros(n_ch) if prefilter is None else np.asarray(prefilter, dtype=float)
        if fc.ndim == 0:
            fc = np.full(n_ch, float(fc))
        if fc.shape != (n_ch,) or not np.all(np.isfinite(fc)) or np.any(fc < 0) or np.any(fc >= self.fs / 2):
            raise ModelError(f"prefilter must be cutoffs in 0 <= fc < fs/2 = {self.fs / 2:g} Hz (0: none), "
                             f"one for all or one per channel ({n_ch}); got {prefilter!r}")
        self.prefilter = fc
        self.prefilter_memory = np.zeros(n_ch, dtype=np.int64)
        # an observer without a low-passed channel keeps no rows: its block step reads drive and
        # currents as they are, copying nothing
        rows = n_ch * (1 + n_seg) if np.any(fc > 0) else 0
        self._pf = np.zeros((rows, 5))
        self._pf[:, 0] = 1.0
        self._pf_z = np.zeros((rows, 2))
        self._pf_x = np.zeros((rows, self.block))
        self._pf_g = np.zeros((n_ch, n_t, 2))
        self._pf_g[:, :, 0] = 1.0
        self.prefilter_gain = np.ones((n_ch, n_t), dtype=complex)
        for c in np.flatnonzero(fc > 0):
            b, a = scipy.signal.butter(2, fc[c], fs=self.fs)
            coef = (b[0], b[1], b[2], a[1], a[2])
            self._pf[c] = coef
            self._pf[n_ch + c * n_seg:n_ch + (c + 1) * n_seg] = coef
            # its impulse response, past where its envelope exp(-wc t / sqrt 2) is far below the decay
            h = np.abs(scipy.signal.lfilter(b, a, np.r_[1.0, np.zeros(int(self.fs / fc[c] * 2.0) + 8)]))
            self.prefilter_memory[c] = np.flatnonzero(h > PREFILTER_DECAY * h.max())[-1] + 1
            for k in np.flatnonzero(self.freqs[c] > 0):
                g = scipy.signal.freqz(b, a, worN=[self.freqs[c, k]], fs=self.fs)[1][0]
                self.prefilter_gain[c, k] = g
                self._pf_g[c, k] = (1.0 / abs(g), np.angle(g))
                h = (self.Hc[c, k, ..., 0] + 1j * self.Hc[c, k, ..., 1]) / g
                self.Hc[c, k, ..., 0] = h.real
                self.Hc[c, k, ..., 1] = h.imag

    def _steps_design(self, steps: bool) -> None:
        """What a drive step puts in a window's currents, and how to take it out (``steps``).

        A segment's current is mostly the charge the drive itself puts on it (its capacitance, and
        the bending the drive causes, which follows the drive at tones below the beam's modes):
        ``i = C dv/dt``. Over a window whose drive changed, the currents' phasor is then not
        ``j w C`` times the drive's: the lock-in of a derivative differs from ``j w`` times that of
        the signal by a boundary term, ``C (v(end) - v(start))`` rotated, which a steady tone over
        whole periods does not have. The observer cancels a drive term against the currents' that
        is tens of times the tip's share at low tones, so such a window read the tip at up to 4-5
        times its true amplitude. The lock-in of the drive's first difference over the same
        windows (``D``, formed from the drive's own window sums and the drive samples at its
        hops' edges: ``lockin_process_edges``) gives ``D / J - U`` (``J = 1 - exp(-j w / fs)``,
        exactly 0 for a steady tone over any window): that boundary term in drive volts. ``Kc``
        (each candidate load's segment readings per drive volt at the tone, the drive
        staircase's folded images included, through the observer's current columns) is what it
        puts in each estimate row, which the kernel takes out. What is left is the tip's own
        transient (the beam's ring): a window over a step then reads the tip as a lock-in of the
        true tip over it does, within 1-2 % at 10-40 Hz, 8 % at 250 Hz and 13 % at 1 kHz, where
        it was off by 65-190 % (tests/test_observer_steps.py)."""
        n_ch, n_t, n_q = self.n_channels, self.n_tones, self.Hc.shape[2]
        self.steps = steps
        self._d_acc = np.zeros_like(self.lock_u.acc)
        self._d_edge = np.zeros_like(self.lock_u.ring)
        self._reset_steps()
        self.invJ = np.zeros((n_ch, n_t, 2))
        self.Kc = np.zeros((n_ch if steps else 0, n_t, n_q, N_EST, 2))
        if not steps:
            return
        per_volt = self.readings_per_volt
        for c in range(n_ch):
            for k in np.flatnonzero(self.freqs[c] > 0.0):
                fk = float(self.freqs[c, k])
                j = 1.0 - np.exp(-2j * np.pi * fk / self.fs)
                self.invJ[c, k] = ((1.0 / j).real, (1.0 / j).imag)
                for q in range(n_q):
                    h = self.Hc[c, k, q, :, 1:, 0] + 1j * self.Hc[c, k, q, :, 1:, 1]
                    kq = h @ per_volt[fk][q]
                    self.Kc[c, k, q, :, 0] = kq.real
                    self.Kc[c, k, q, :, 1] = kq.imag

    @functools.cached_property
    def readings_per_volt(self) -> dict:
        """Each candidate load's sensed segment currents per drive volt at each tone (A/V, complex,
        shape (n_seg,), candidates in ``Hc``'s order): ``{freq: [per candidate]}``, solved once
        (the drive's correction and the lift-off test both read them; the tones are the build's).
        The drive staircase's images fold back onto the tone: about -13 % of a segment's reading,
        nearly all of it capacitive."""
        loads = self.image_loads if self.frontend is not None else self.image_loads[:1]
        fe = self.frontend
        tones = sorted({float(x) for x in self.freqs.ravel() if x > 0.0})
        per_volt = {fk: [] for fk in tones}
        for load in loads:
            images = {fk: 0.0 for fk in tones}
            if fe is not None and tones:
                om = np.concatenate([fe.image_omegas(fk) for fk in tones])
                table = dict(zip(om.tolist(), self.beam.currents(om, [_load_stiffness(load, w) for w in om])))
                images = {fk: fe.images(fk, table.__getitem__) for fk in tones}
            for fk in tones:
                g = 1.0 if fe is None else fe.voltage(fk) * fe.aa(fk)
                per_volt[fk].append(self.beam.response([fk], load)["current"][0] * g + images[fk])
        return per_volt

    def _reset_steps(self) -> None:
        """The first difference's sums empty, laid out as the drive's lock-in's."""
        self._d_acc[:] = 0.0
        for row in (_dk.HOP, _dk.NHOP, _dk.LSQ):
            self._d_acc[row] = self.lock_u.acc[row]
        self._d_edge[:] = 0.0

    @property
    def args(self) -> tuple:
        """Kernel arguments: ``observer_process(*args, drive, sensed)``."""
        return (*self.lock_u.args, *self.lock_i.args, self.u_out, self._back, self.H, self.Hc,
                self.pick, self.resid, self.contact, self.lag, self.scale, self.est, self.wave,
                self._pf, self._pf_z, self._pf_x, self._pf_g, self._d_acc, self._d_edge, self.invJ,
                self.Kc)

    def process(self, drive, sensed) -> int:
        """Advance by one block.

        Parameters
        ----------
        drive : ndarray, shape (n_channels, block), float64, C-contiguous
            Volts written to the DAC.
        sensed : ndarray, shape (n_channels * n_seg, block), float64, C-contiguous
            Current readings, A.

        Returns
        -------
        int
            0, or ``STATUS_NONFINITE``.
        """
        for name, a, rows in (("drive", drive, self.n_channels), ("sensed", sensed, self.n_channels * self.n_seg)):
            if a.shape != (rows, self.block) or a.dtype != np.float64 or not a.flags.c_contiguous:
                raise ModelError(f"{name} must be C-contiguous float64 of shape {(rows, self.block)}, "
                                 f"got {a.dtype} {a.shape}")
        return observer_process(*self.args, drive, sensed)

    def reset(self) -> None:
        """Empty windows, references at phase 0, every channel back on the first image load."""
        self.lock_u.reset()
        self.lock_i.reset()
        self._reset_steps()
        self._pf_z[:] = 0.0
        if self.Hc.shape[2] > 1:
            self.H[...] = self.Hc[:, :, 0]
            self.pick[:] = 0
            self.resid[:] = 0.0
        self.est[:] = 0.0
        self.wave[:] = 0.0

    def phasors(self, name="tip_m") -> np.ndarray:
        """Latest estimate of one ``EST_NAMES`` row, shape (n_channels, n_tones), complex."""
        row = EST_NAMES.index(name)
        if row >= self.est.shape[2]:
            raise ModelError(f"this observer computes only {', '.join(EST_NAMES[:self.est.shape[2]])} "
                             f"(rows={self.est.shape[2]}); build it with rows > {row} to read {name}")
        e = self.est[:, :, row]
        return e[..., 0] + 1j * e[..., 1]

    @property
    def amplitude(self) -> np.ndarray:
        """Tip deflection amplitude per tone, m (peak), shape (n_channels, n_tones)."""
        return np.abs(self.phasors())

    @property
    def phase(self) -> np.ndarray:
        """Tip deflection phase per tone against the drive's reference, rad."""
        return np.angle(self.phasors())

    def impedance(self) -> np.ndarray:
        """Online finger impedance per tone, tip force over tip velocity, N s/m (complex)."""
        return self.phasors("tip_force_n") / self.phasors("tip_velocity_m_s")

    def noise_floor(self, current_rms: float) -> np.ndarray:
        """Per channel and tone slot, the rms (m) of the error white noise of ``current_rms`` (A
        per sample, each segment's own, as an ADC's noise and step leave it) puts in the tip
        estimate: ``sqrt(g sum_j |H_j|^2) current_rms``, with ``g`` the lock-in's noise gain, the
        mean square of a window's phasor per unit of noise (``4 / N`` over ``N`` samples; for a
        channel read by least squares the diagonal of ``(A^T A)^-1`` over its tones' cos and sin
        columns), and ``H_j`` the segments' terms of the tip row, the largest over the candidate
        loads. Drive and currents pass the same low-pass, divided out at the tone, so it leaves
        the noise there as it was. 0 for an unused slot. A tip of amplitude ``y`` then reads
        about ``y (1 + (floor / y)^2 / 4)`` on average (the mean of a Rician magnitude): the
        magnitude of a noisy phasor is biased high."""
        n_ch, n_t = self.freqs.shape
        out = np.zeros((n_ch, n_t))
        h2 = np.max(np.sum(self.Hc[:, :, :, 0, 1:, :] ** 2, axis=(3, 4)), axis=2)  # (n_ch, n_t)
        for c in range(n_ch):
            used = np.flatnonzero(self.freqs[c] > 0.0)
            if not used.size:
                continue
            n = int(self.windows[c])
            if self.lstsq[c]:
                t = 2.0 * np.pi * np.arange(n)[:, None] * self.freqs[c, used][None, :] / self.fs
                a = np.empty((n, 2 * used.size))
                a[:, 0::2], a[:, 1::2] = np.cos(t), np.sin(t)
                d = np.diag(np.linalg.inv(a.T @ a))
                g = d[0::2] + d[1::2]
            else:
                g = np.full(used.size, 4.0 / n)
            out[c, used] = np.sqrt(g * h2[c, used]) * float(current_rms)
        return out


class ObserverRows:
    """Channels ``c0 .. c1 - 1`` of an :class:`Observer`: what a per-channel consumer (a
    controller, a report) reads of them, without an observer (and a kernel call) of their own.

    Every array is a view of the observer's own (rows along the first axis of a C-contiguous
    array, so itself C-contiguous: a stage argument as good as the whole), indexed by channel
    *within these rows*; ``u_acc`` is the whole drive lock-in's accumulator (its columns
    interleave channels and tones), read at column ``(first + c) * n_tones + slot``.

    Attributes
    ----------
    observer : Observer
        The observer that computes them.
    first, n_channels : int
        ``c0`` and ``c1 - c0``.
    freqs, windows, scale, H, Hc, pick, resid, contact, lag, cond, est, wave, u_out
        The observer's, rows ``c0:c1`` (``u_out``: the drive's amplitude (peak, V) and phase (rad)
        per tone slot, shape (n_channels, n_tones, 2)).
    prefilter, prefilter_gain, prefilter_memory
        The observer's low-pass, rows ``c0:c1``.
    window : int
        The longest of these channels' windows, samples.
    """

    def __init__(self, observer: Observer, c0: int, c1: int):
        if not 0 <= c0 < c1 <= observer.n_channels:
            raise ModelError(f"rows {c0}:{c1} of an observer of {observer.n_channels} channels")
        rows = slice(c0, c1)
        self.observer, self.first, self.n_channels = observer, int(c0), int(c1 - c0)
        for name in ("beam", "fs", "block", "frontend", "designs", "n_tones", "n_seg", "image_loads"):
            setattr(self, name, getattr(observer, name))
        for name in ("freqs", "windows", "scale", "H", "Hc", "pick", "resid", "contact", "lag", "cond", "est",
                     "wave", "prefilter", "prefilter_gain", "prefilter_memory"):
            setattr(self, name, getattr(observer, name)[rows])
        self.u_out = observer.u_out[rows]
        self.u_acc = observer.lock_u.acc
        self.window = int(self.windows.max())

    def noise_floor(self, current_rms: float) -> np.ndarray:
        """:meth:`Observer.noise_floor` of these rows."""
        return self.observer.noise_floor(current_rms)[self.first:self.first + self.n_channels]
