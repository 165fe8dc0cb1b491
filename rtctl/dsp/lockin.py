"""Lock-in demodulation at known frequencies over a sliding rectangular window."""

from fractions import Fraction

import numpy as np

from rtctl.dsp import _kernels as _k
from rtctl.dsp.oscillator import _check_block, _check_fs, _check_int

__all__ = ["LockIn", "MAX_LSQ_COND", "beat_window", "lsq_gram", "window_leakage"]

#: Largest condition number of a least-squares row (:func:`lsq_gram`, normalized to 1 for
#: orthogonal tones) that :class:`LockIn` accepts: noise in the estimate grows by up to this
#: factor. One beat period of a pair gives 1.07 (235 + 265 Hz at 48 kHz), 0.8 of it 1.7, 0.6 of it
#: 3.1.
MAX_LSQ_COND = 2.0


def window_leakage(df, window, fs):
    """Relative leakage of a tone ``df`` Hz away into a lock-in estimate with a W-sample window.

    ``|D_W(df)| = |sin(pi df W / fs) / (W sin(pi df / fs))|``: the magnitude (relative to the
    tone's own amplitude) that a tone at ``f + df`` adds to the estimate at ``f``. It is zero
    when ``df W / fs`` is a non-zero integer and bounded by ``fs / (pi |df| W)`` for
    ``|df| << fs``. Each real tone at ``f'`` leaks through ``df = f' - f`` and its mirror
    ``df = f' + f``.

    Parameters
    ----------
    df : float or array_like
        Frequency offset, Hz.
    window : int
        Window length W, samples.
    fs : float
        Sample rate, Hz.

    Returns
    -------
    float or ndarray
        Leakage, 1 at ``df = 0``.

    Examples
    --------
    >>> float(window_leakage(10.0, 4800, 48000.0)) < 1e-15   # one beat period: no leakage
    True
    >>> round(float(window_leakage(10.0, 4000, 48000.0)), 3)
    0.191
    """
    x = np.pi * np.asarray(df, dtype=np.float64) / fs
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.abs(np.sin(window * x) / (window * np.sin(x)))
    return np.where(np.sin(x) == 0.0, 1.0, d)


def lsq_gram(freqs, window, fs):
    """The fixed matrix of least-squares demodulation at ``freqs`` over a ``window``-sample window.

    With references ``z_l[n] = exp(i theta_l[n])`` at steady frequencies and ``z_l`` their value
    on the sample after the window, a signal ``x = sum_l Re(X_l z_l[n])`` has lock-in sums
    ``S_k = sum_n x[n] conj(z_k[n])`` that obey ``T = M Y`` with ``T_k = S_k z_k`` and
    ``Y_l = X_l z_l`` (real and imaginary parts interleaved): the window's Gram matrix, turned by
    the references' phases, is this fixed one. Entry by entry, with ``c = sum_{p=1..W}
    exp(-i (w_l - w_k) p)`` (the neighbour) and ``d = sum_{p=1..W} exp(i (w_l + w_k) p)`` (the
    mirror), ``w = 2 pi f / fs``::

        M[2k, 2l]   = (Re c + Re d) / 2     M[2k, 2l+1]   = (Im d - Im c) / 2
        M[2k+1, 2l] = (Im c + Im d) / 2     M[2k+1, 2l+1] = (Re c - Re d) / 2

    Over whole periods of every tone ``M = W / 2`` times the identity (plain lock-in).

    Parameters
    ----------
    freqs : array_like, shape (K,)
        Tone frequencies, Hz, ``0 < f < fs / 2``.
    window : int
        Samples.
    fs : float
        Hz.

    Returns
    -------
    ndarray, shape (2K, 2K)

    Examples
    --------
    >>> m = lsq_gram([235.0, 265.0], 1600, 48000.0) / 800
    >>> round(float(np.linalg.cond(m)), 3)   # one beat period: only the mirrors couple
    1.069
    """
    w = 2.0 * np.pi * np.asarray(freqs, dtype=np.float64).ravel() / fs
    p = np.arange(1, int(window) + 1, dtype=np.float64)
    k_ = w.size
    m = np.empty((2 * k_, 2 * k_))
    for k in range(k_):
        for l in range(k_):
            c = np.exp(-1j * (w[l] - w[k]) * p).sum()
            d = np.exp(1j * (w[l] + w[k]) * p).sum()
            m[2 * k, 2 * l] = 0.5 * (c.real + d.real)
            m[2 * k, 2 * l + 1] = 0.5 * (d.imag - c.imag)
            m[2 * k + 1, 2 * l] = 0.5 * (c.imag + d.imag)
            m[2 * k + 1, 2 * l + 1] = 0.5 * (c.real - d.real)
    return m


def beat_window(fs, beat, periods=1):
    """Shortest window of at least ``periods`` beat periods that is a whole number of samples.

    Over ``W = m fs / f_b`` samples the two tones of a beat pair (``f_c -+ f_b / 2``) are
    orthogonal, so each lock-in estimate is free of the other tone (:func:`window_leakage`).

    Parameters
    ----------
    fs : float
        Sample rate, Hz.
    beat : float
        Beat frequency f_b > 0, Hz.
    periods : int
        Minimum number of beat periods.

    Returns
    -------
    int
        W, samples. If no multiple of the period up to 1000 periods is a whole number of
        samples, the nearest integer to ``periods fs / f_b`` (then check the leakage).

    Examples
    --------
    >>> beat_window(48000.0, 10.0)
    4800
    >>> beat_window(48000.0, 7.0)          # 48000 / 7 samples is not whole; 7 periods are
    48000
    """
    fs = _check_fs(fs)
    beat = float(beat)
    if not (np.isfinite(beat) and beat > 0.0):
        raise ValueError(f"beat = {beat} Hz is out of range: allowed 0 < beat < inf")
    periods = _check_int("periods", periods, 1)
    ratio = Fraction(fs) / Fraction(beat)
    q = ratio.limit_denominator(1000)
    if q == ratio or abs(float(q) - float(ratio)) <= 1e-12 * float(ratio):
        m = -(-periods // q.denominator) * q.denominator
        return int(q * m)
    return int(round(periods * float(ratio)))


class LockIn:
    """Amplitude and phase of known tones in each channel, over a sliding window.

    Parameters
    ----------
    n_channels : int
        Rows of the input blocks.
    freq : array_like, shape (n_channels, n_freq) or (n_channels,)
        Reference frequencies, Hz, ``0 < f <= fs / 2``; NaN or 0 marks an unused slot (its
        estimates read NaN).
    fs : float
        Sample rate, Hz.
    window : int or array_like of int, shape (n_channels,)
        Window length W, samples, a multiple of ``hop``: one for every row, or one per row (a
        row's slots then sum over its own last ``W[row]`` samples, e.g. whole periods of that
        channel's tones only, so a fast channel need not wait for a slow one). Use
        :func:`beat_window` for beat pairs.
    hop : int, optional
        The window slides in hops of this many samples. Default: the largest divisor of
        every window not above 32 (one block of the loop).
    ramp : int
        Samples over which a reference frequency change is ramped, as in the oscillator bank;
        use the bank's ramp so that a demodulated tone keeps reading the bank's phase across
        frequency changes.
    lstsq : bool or array_like of bool, shape (n_channels,)
        Rows (or every row) whose tones are demodulated by least squares: each estimate free of
        the row's other tones and of every mirror over any window, not only over whole periods
        (see "Least squares"). Their reference frequencies are fixed (:meth:`set_freq` refuses).
    max_cond : float
        A least-squares row whose matrix (:func:`lsq_gram`, over ``W / 2``) has a larger
        condition number is refused (``ValueError``): its tones are too close for its window.

    Notes
    -----
    **Convention.** Each slot has a reference oscillator ``exp(i theta(t))`` with
    ``theta = 0`` at construction / :meth:`reset`, advancing at the slot's frequency and
    phase-continuous across changes (the same machinery as :class:`OscillatorBank`). With
    ``S = sum over the window of x[n] exp(-i theta[n])``, the estimate is the phasor
    ``X = 2 S / W = A exp(i phi)`` for ``x = A cos(theta + phi)``: amplitude ``A`` (peak),
    phase ``phi`` (rad, in (-pi, pi]). A bank tone ``a cos(phase)`` started with phase ``phi``
    at the same sample and frequency is read back as ``(a, phi)``.

    **Update.** Products are accumulated every sample; every ``hop`` samples (on the sample
    clock since reset, independent of call lengths) the hop's partial sum enters a ring of
    ``W / hop`` hops. ``process`` returns the estimate over the ``W`` samples ending at the
    last completed hop (with ``hop`` = the block and blocks aligned, exactly the last ``W``
    samples); amplitude and phase (``hypot``, ``atan2``) are computed once at the end of a call
    in which a hop closed. Until ``W`` samples have been seen the window is zero-filled and the
    amplitude reads low. A reference frequency change mixes old and new products in the window
    for ``W`` samples. With a window per row every statement holds per row, with its own ``W``;
    the ring is sized for the longest and a row uses its first ``W[row] / hop`` entries.

    **No drift.** The window sum is updated by adding the new hop and subtracting the oldest,
    which alone would let round-off random-walk over hours; each time the ring wraps, the sum is
    replaced by a fresh sum of exactly the hops it holds (accumulated alongside), so the error
    stays at a few ulp of one window, forever.

    **Leakage.** A rectangular window leaks a tone ``df`` Hz away with relative magnitude
    :func:`window_leakage` ``= |sin(pi df W / fs) / (W sin(pi df / fs))|``, zero when
    ``df W / fs`` is an integer. For a beat pair ``f_c -+ f_b / 2`` the tones are ``f_b`` apart
    and their mirrors ``2 f_c`` and ``2 f_c -+ f_b`` away. At fs = 48 kHz, f_c = 250 Hz,
    f_b = 10 Hz (245 / 255 Hz):

    ===========  ============  ==================  =====================
    W, samples   beat periods  neighbour (10 Hz)   mirrors (490-510 Hz)
    ===========  ============  ==================  =====================
    2400         0.5           0.64                0.013
    4000         0.83          0.19                0.0066
    4800         1             < 1e-15             < 1e-15
    7200         1.5           0.21                0.0043
    9600         2             < 1e-15             < 1e-15
    47000        9.79          0.020               0.0006
    48000        10            < 1e-15             < 1e-15
    ===========  ============  ==================  =====================

    so use ``W = m fs / f_b`` (:func:`beat_window`); with ``f_c / f_b`` a multiple of 1/2 the
    mirrors vanish too, otherwise they stay below ``fs / (pi (2 f_c - f_b) W)`` (the mirror of the
    lower tone sits at ``2 f_c - f_b`` away).

    **Least squares.** A row with ``lstsq`` set fits its tones jointly: the estimates are the
    least-squares amplitudes and phases of ``sum_l Re(X_l z_l[n])`` over the window, exact for a
    signal made of those tones over any window of at least about one period of their closest
    spacing (one beat period of a pair: 1600 samples for 235 + 265 Hz at 48 kHz, where whole
    periods of both take 9600). The normal equations ``S_k = sum_l (X_l c_lk + conj(X_l) d_lk) / 2``
    relate the plain window sums ``S`` to the phasors through the window's Gram matrix, which for
    steady references is a fixed matrix (:func:`lsq_gram`) turned by the references' phases at the
    window's end. Its inverse is taken once, at construction; per call, each slot costs one row of
    it (``2 * n_freq`` products) on top of the plain estimate. With ``m`` the matrix over
    ``W / 2``, noise in the estimate grows by at most ``cond(m)`` (reported as :attr:`cond`);
    rows above ``max_cond`` are refused.

    For the loop: ``lockin_process(*lockin.args, x, out)`` with
    ``lockin.args == (ref, pending, chan, acc, ring, solve)``.

    Attributes
    ----------
    window : int
        The longest window, samples (the only one unless given per row).
    windows : ndarray of int64, shape (n_channels,)
        Each row's window, samples.
    lstsq : ndarray of bool, shape (n_channels,)
        Rows solved by least squares.
    cond : ndarray, shape (n_channels,)
        Condition number of each least-squares row's matrix over ``W / 2`` (1 for one tone over
        whole periods); NaN for plain rows.

    Examples
    --------
    >>> from rtctl.dsp import OscillatorBank
    >>> fs = 48000.0
    >>> bank = OscillatorBank.beat_pairs(1, [0], fs, 250.0, 10.0, 2.0)
    >>> lock = LockIn(1, [[245.0, 255.0]], fs, window=beat_window(fs, 10.0))
    >>> x = np.zeros((1, 4800))
    >>> bank.process(x)
    >>> est = lock.process(x)
    >>> np.round(est[0, :, 0], 9)                 # amplitude of each tone
    array([1., 1.])
    """

    def __init__(self, n_channels, freq, fs, window, hop=None, ramp=32, lstsq=False, max_cond=MAX_LSQ_COND):
        self.n_channels = _check_int("n_channels", n_channels, 1)
        self.fs = _check_fs(fs)
        if np.ndim(window) == 0:
            w = [_check_int("window", window, 1)] * self.n_channels
            names = ["window"] * self.n_channels
        else:
            if np.shape(window) != (self.n_channels,):
                raise ValueError(f"window has shape {np.shape(window)}: expected an int or ({self.n_channels},)")
            names = [f"window[{r}]" for r in range(self.n_channels)]
            w = [_check_int(nm, x, 1) for nm, x in zip(names, window)]
        self.windows = np.array(w, dtype=np.int64)
        self.window = int(self.windows.max())
        if hop is None:
            hop = max(d for d in range(1, min(32, int(self.windows.min())) + 1) if not np.any(self.windows % d))
        self.hop = _check_int("hop", hop, 1, int(self.windows.min()))
        for nm, x in zip(names, w):
            if x % self.hop:
                raise ValueError(f"{nm} = {x} is not a multiple of hop = {self.hop}: choose hop dividing window")
        self.ramp = _check_int("ramp", ramp, 1, _k.MAX_RAMP)
        f = np.asarray(freq, dtype=np.float64)
        if f.ndim == 1:
            f = f[:, None]
        if f.ndim != 2 or f.shape[0] != self.n_channels or f.shape[1] < 1:
            raise ValueError(f"freq has shape {np.shape(freq)}: expected ({self.n_channels}, n_freq)")
        self.n_freq = f.shape[1]
        self._freq0 = self._checked(f)
        ns = self.n_channels * self.n_freq
        self.ref = np.zeros((_k.N_OSC, ns))
        self.pending = np.zeros((_k.N_PEND, ns))
        self.chan = np.repeat(np.arange(self.n_channels, dtype=np.int64), self.n_freq)
        self.acc = np.zeros((_k.N_ACC, ns))
        self._n_hops = np.repeat(self.windows // self.hop, self.n_freq).astype(np.float64)
        self.ring = np.zeros((self.window // self.hop, 2, ns))
        self.lstsq = np.broadcast_to(np.asarray(lstsq, dtype=bool), (self.n_channels,)).copy()
        self.cond = np.full(self.n_channels, np.nan)
        self.solve = np.zeros((ns, 2, 2 * self.n_freq))
        self._lsq = np.zeros(ns)
        for r in np.nonzero(self.lstsq)[0]:
            used = np.nonzero(self._freq0[r] > 0.0)[0]
            w = int(self.windows[r])
            m = lsq_gram(self._freq0[r, used], w, self.fs)
            self.cond[r] = np.linalg.cond(m / (0.5 * w))
            if not self.cond[r] <= max_cond:
                raise ValueError(f"row {r}: least squares over {w} samples at {self._freq0[r, used].tolist()} Hz is "
                                 f"ill-conditioned (condition {self.cond[r]:.3g} > {max_cond:g}): lengthen the window")
            # the plain sum's scale 2 / W turns a solved sum (W / 2) Y into the phasor Y
            inv = (0.5 * w) * np.linalg.inv(m)
            cols = np.ravel(np.column_stack([2 * used, 2 * used + 1]))
            for i, k in enumerate(used):
                s = r * self.n_freq + k
                self.solve[s][:, cols] = inv[2 * i:2 * i + 2]
                self._lsq[s] = 1.0
        self.reset()

    @property
    def args(self):
        """Arrays in kernel order: ``lockin_process(*lockin.args, x, out)``."""
        return (self.ref, self.pending, self.chan, self.acc, self.ring, self.solve)

    def process(self, x, out=None):
        """Demodulate the block ``x``; return the estimates at the last completed hop.

        Parameters
        ----------
        x : ndarray, shape (n_channels, n), float64, C-contiguous
            Input block.
        out : ndarray, shape (n_channels, n_freq, 2), float64, optional
            Receives amplitude (peak) and phase (rad); NaN for unused slots. Allocated if None.

        Returns
        -------
        out : ndarray, shape (n_channels, n_freq, 2)
        """
        _check_block("x", x, self.n_channels)
        shape = (self.n_channels, self.n_freq, 2)
        if out is None:
            out = np.empty(shape)
        elif not isinstance(out, np.ndarray) or out.shape != shape or out.dtype != np.float64:
            raise ValueError(f"out must be a float64 array of shape {shape}, got {getattr(out, 'shape', out)!r}")
        _k.lockin_process(self.ref, self.pending, self.chan, self.acc, self.ring, self.solve, x, out)
        return out

    def reset(self):
        """Empty window, references back to phase 0 at the constructor's frequencies."""
        flat = self._freq0.reshape(-1)
        used = flat > 0.0
        _k.osc_init(self.ref, self.pending, flat, used * 1.0, np.zeros_like(flat), self.fs, float(self.ramp))
        self.acc[:] = 0.0
        self.acc[_k.HOP] = self.hop
        self.acc[_k.NHOP] = self._n_hops
        self.acc[_k.LSQ] = self._lsq
        self.acc[_k.Z_R] = self.ref[_k.ZR]
        self.acc[_k.Z_I] = self.ref[_k.ZI]
        self.acc[_k.EST_A] = np.where(used, 0.0, np.nan)
        self.acc[_k.EST_P] = np.where(used, 0.0, np.nan)
        self.ring[:] = 0.0

    def set_freq(self, freq, ramp=None):
        """New reference frequencies, shape (n_channels, n_freq) (NaN or 0: unused), from the next call."""
        if self.lstsq.any():
            raise ValueError("set_freq: least-squares rows are solved for the frequencies they were built with")
        f = np.asarray(freq, dtype=np.float64)
        if f.ndim == 1 and self.n_freq == 1:
            f = f[:, None]
        if f.shape != (self.n_channels, self.n_freq):
            raise ValueError(f"freq has shape {f.shape}: expected ({self.n_channels}, {self.n_freq})")
        self.pending[_k.P_FREQ] = self._checked(f).reshape(-1)
        self.pending[_k.P_RAMP] = self.ramp if ramp is None else _check_int("ramp", ramp, 1, _k.MAX_RAMP)
        self.pending[_k.P_FLAG] = 1.0

    @property
    def phasor(self):
        """ndarray, shape (n_channels, n_freq), complex: ``A exp(i phi)`` at the last hop (NaN unused)."""
        scale = np.repeat(2.0 / self.windows, self.n_freq)
        x = scale * (self.acc[_k.X_R] + 1j * self.acc[_k.X_I])
        x[~(self.ref[_k.INC1] > 0.0)] = np.nan
        return x.reshape(self.n_channels, self.n_freq)

    @property
    def amplitude(self):
        """ndarray, shape (n_channels, n_freq): amplitude (peak) at the last hop."""
        return self.acc[_k.EST_A].reshape(self.n_channels, self.n_freq).copy()

    @property
    def phase(self):
        """ndarray, shape (n_channels, n_freq): phase (rad) relative to the reference, at the last hop."""
        return self.acc[_k.EST_P].reshape(self.n_channels, self.n_freq).copy()

    def _checked(self, f):
        f = np.where(np.isnan(f), 0.0, f)
        bad = ~((f >= 0.0) & (f <= self.fs / 2))
        if bad.any():
            c, j = np.argwhere(bad)[0]
            raise ValueError(f"freq[{c}, {j}] = {f[c, j]} Hz is out of range: "
                             f"allowed 0 <= freq <= fs / 2 = {self.fs / 2} Hz (NaN or 0: unused)")
        return np.ascontiguousarray(f, dtype=np.float64)
