"""Phase-continuous oscillator banks and beat pairs.

Phase convention (shared with :class:`rtctl.dsp.LockIn`): tone ``i`` contributes
``amp_i * cos(phase_i)`` where ``phase_i`` (rad) starts at the ``phase`` given to the
constructor (or at ``reset``) and advances by ``2 pi freq_i / fs`` per sample. A lock-in whose
reference starts at the same sample reads that tone back with the same phase.
"""

import numpy as np

from rtctl.dsp import _kernels as _k
from rtctl.dsp._routed import Routed

__all__ = ["OscillatorBank", "beat_tones"]


# ---- argument checks shared by the dsp wrappers (ValueError naming argument, value, range) ----
def _check_int(name, value, lo, hi=None):
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} = {value!r} must be an integer >= {lo}")
    if value < lo or (hi is not None and value > hi):
        allowed = f"{lo} <= {name}" + (f" <= {hi}" if hi is not None else "")
        raise ValueError(f"{name} = {value} is out of range: allowed {allowed}")
    return int(value)


def _check_fs(fs):
    fs = float(fs)
    if not (np.isfinite(fs) and fs > 0.0):
        raise ValueError(f"fs = {fs} Hz is out of range: allowed 0 < fs < inf")
    return fs


def _vector(name, value, n, lo=-np.inf, hi=np.inf, unit="", nan_ok=False, hi_label=None):
    """``value`` broadcast to a float64 vector of length ``n``, every element in [lo, hi]."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim > 1 or (arr.ndim == 1 and arr.shape[0] != n):
        raise ValueError(f"{name} has shape {arr.shape}: expected a scalar or shape ({n},)")
    arr = np.ascontiguousarray(np.broadcast_to(arr, (n,)), dtype=np.float64).copy()
    ok = (arr >= lo) & (arr <= hi)
    if nan_ok:
        ok |= np.isnan(arr)
    if not ok.all():
        i = int(np.flatnonzero(~ok)[0])
        label = name if np.ndim(value) == 0 else f"{name}[{i}]"
        unit = f" {unit}" if unit else ""
        hi_label = hi if hi_label is None else hi_label
        raise ValueError(f"{label} = {arr[i]}{unit} is out of range: allowed {lo} <= {name} <= {hi_label}{unit}")
    return arr


def _check_block(name, out, n_rows):
    """``out`` must be a C-contiguous float64 array of shape (n_rows, n)."""
    if not isinstance(out, np.ndarray) or out.dtype != np.float64 or out.ndim != 2:
        got = getattr(out, "dtype", type(out).__name__), getattr(out, "shape", None)
        raise ValueError(f"{name} must be a float64 array of shape ({n_rows}, n), got {got}")
    if out.shape[0] != n_rows:
        raise ValueError(f"{name} has {out.shape[0]} rows: expected {n_rows} (one per channel)")
    if not out.flags.c_contiguous:
        raise ValueError(f"{name} must be C-contiguous (use np.ascontiguousarray)")
    return out


def beat_tones(carrier, beat, amp):
    """Frequencies and amplitudes of the two tones of a beat pair.

    Parameters
    ----------
    carrier : float
        Carrier frequency f_c, Hz.
    beat : float
        Beat frequency f_b >= 0, Hz (the envelope repeats every 1 / f_b).
    amp : float
        Pair amplitude (peak of the envelope).

    Returns
    -------
    freq : ndarray, shape (2,)
        ``f_c - f_b / 2`` and ``f_c + f_b / 2``, Hz.
    amp : ndarray, shape (2,)
        ``amp / 2`` each: two cosines of equal phase add to
        ``amp cos(2 pi f_c t) cos(pi f_b t)``, whose envelope peaks at ``amp``.

    Examples
    --------
    >>> beat_tones(250.0, 10.0, 1.0)
    (array([245., 255.]), array([0.5, 0.5]))
    """
    carrier, beat, amp = float(carrier), float(beat), float(amp)
    if not (np.isfinite(beat) and beat >= 0.0):
        raise ValueError(f"beat = {beat} Hz is out of range: allowed 0 <= beat < inf")
    if not (np.isfinite(carrier) and carrier >= beat / 2):
        raise ValueError(f"carrier = {carrier} Hz is out of range: allowed beat / 2 = {beat / 2} <= carrier")
    if not (np.isfinite(amp) and amp >= 0.0):
        raise ValueError(f"amp = {amp} is out of range: allowed 0 <= amp < inf")
    return np.array([carrier - beat / 2, carrier + beat / 2]), np.array([amp / 2, amp / 2])


class OscillatorBank(Routed):
    """A bank of phase-continuous cosine tones added into the rows of a block.

    Parameters
    ----------
    n_channels : int
        Rows of the blocks this bank adds into.
    tone_channel : array_like of int, shape (n_tones,)
        Row of each tone; several tones may share a row (they add).
    fs : float
        Sample rate, Hz.
    freq : float or array_like, shape (n_tones,)
        Initial frequencies, Hz, ``0 <= freq <= fs / 2``.
    amp : float or array_like, shape (n_tones,)
        Initial amplitudes (peak), ``>= 0``.
    phase : float or array_like, shape (n_tones,)
        Initial phases, rad: tone ``i`` is ``amp_i cos(phase_i)`` on the first sample.
    ramp : int
        Samples over which a change written by :meth:`set` is ramped (the loop uses the block),
        ``1 <= ramp <= 2**20``.

    Notes
    -----
    A change written with :meth:`set` / :meth:`set_all` is applied at the start of the next
    :meth:`process` call and ramped over ``ramp`` samples, which may span several calls of any
    length: the instantaneous frequency moves linearly from its current value to the target
    (the phase stays continuous, only its derivative ramps) and the amplitude moves linearly (no
    step); both reach the target on the last sample of the ramp. Only a parameter whose target
    changed starts a new ramp, from wherever it had got to; the other carries on (so the
    controller's amplitude updates every block never disturb a frequency ramp, and cost no
    ``sin``/``cos``).

    Phases are exact over long runs: each tone's phase is recomputed every 256 samples from its
    value at the last change plus ``inc * k`` with an integer sample count ``k``, the product
    reduced mod 1 in integer arithmetic (``_kernels._frac_mul``), so after an hour at 48 kHz it
    is off by ~1e-15 cycles rather than by the ~1e-7 a float accumulator would collect. Between
    those anchors a complex rotation advances each tone (no ``sin`` per sample).

    For the loop's own ``@njit`` block step: ``osc_bank_process(*bank.args, out)`` with
    ``bank.args == (state, pending, chan)``; write targets into ``pending`` rows ``P_FREQ``
    (Hz), ``P_AMP`` and set ``P_FLAG`` to 1 (see :mod:`rtctl.dsp._kernels`).

    Examples
    --------
    >>> bank = OscillatorBank(2, [0, 1], fs=48000.0, freq=[250.0, 40.0], amp=[1.0, 0.5])
    >>> out = np.zeros((2, 32))
    >>> bank.process(out)
    >>> round(float(out[0, 0]), 12)
    1.0
    >>> bank.set(1, freq=80.0, amp=0.0)   # ramped over the next 32 samples
    """


    def __init__(self, n_channels, tone_channel, fs, freq, amp, phase=0.0, ramp=32):
        self.n_channels = _check_int("n_channels", n_channels, 1)
        self.fs = _check_fs(fs)
        chan = np.asarray(tone_channel)
        if chan.ndim != 1 or chan.shape[0] < 1 or not np.issubdtype(chan.dtype, np.integer):
            raise ValueError(f"tone_channel must be a non-empty 1-D integer array, got {tone_channel!r}")
        bad = (chan < 0) | (chan >= self.n_channels)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"tone_channel[{i}] = {chan[i]} is out of range: "
                f"allowed 0 <= tone_channel < n_channels = {self.n_channels}"
            )
        self.n_tones = chan.shape[0]
        self.chan = np.ascontiguousarray(chan, dtype=np.int64)
        self.ramp = _check_int("ramp", ramp, 1, _k.MAX_RAMP)
        self._freq0 = self._freq(freq)
        self._amp0 = _vector("amp", amp, self.n_tones, 0.0, np.inf)
        self._phase0 = _vector("phase", phase, self.n_tones, -np.inf, np.inf, "rad")
        if not np.isfinite(self._phase0).all():
            raise ValueError("phase must be finite (rad)")
        self.state = np.zeros((_k.N_OSC, self.n_tones))
        self.pending = np.zeros((_k.N_PEND, self.n_tones))
        self._read = np.zeros((3, self.n_tones))
        self.reset()

    @classmethod
    def beat_pairs(cls, n_channels, pair_channels, fs, carrier, beat, amp, phase=0.0, ramp=32):
        """A bank of beat pairs: pair ``p`` is tones ``2 p`` (lower) and ``2 p + 1`` (upper).

        Parameters
        ----------
        n_channels : int
            Rows of the output block.
        pair_channels : array_like of int, shape (n_pairs,) or (n_pairs, 2)
            Row of both tones of each pair, or the rows of the lower and upper tone (e.g.
            neighbouring PVDF cells, one tone each).
        fs : float
            Sample rate, Hz.
        carrier, beat, amp : float or array_like, shape (n_pairs,)
            Carrier f_c (Hz), beat f_b (Hz) and pair amplitude (envelope peak) of each pair.
        phase : float or array_like, shape (n_pairs,)
            Initial phase of both tones, rad (equal phases put an envelope peak at t = 0).
        ramp : int
            As for the constructor.

        Returns
        -------
        OscillatorBank
            With ``2 n_pairs`` tones.

        Examples
        --------
        >>> bank = OscillatorBank.beat_pairs(2, [[0, 1]], 48000.0, 250.0, 10.0, 1.0)
        >>> bank.freq
        array([245., 255.])
        >>> bank.set_beat((0, 1), beat=20.0)   # both tones ramp, no phase jump
        """
        pc = np.asarray(pair_channels)
        if pc.ndim == 1:
            pc = np.stack([pc, pc], axis=1)
        if pc.ndim != 2 or pc.shape[1] != 2:
            raise ValueError(f"pair_channels has shape {pc.shape}: expected (n_pairs,) or (n_pairs, 2)")
        n_pairs = pc.shape[0]
        carrier = _vector("carrier", carrier, n_pairs, 0.0, np.inf, "Hz")
        beat = _vector("beat", beat, n_pairs, 0.0, np.inf, "Hz")
        amp = _vector("amp", amp, n_pairs, 0.0, np.inf)
        phase = _vector("phase", phase, n_pairs, -np.inf, np.inf, "rad")
        pairs = [beat_tones(c, b, a) for c, b, a in zip(carrier, beat, amp)]
        freqs = np.concatenate([f for f, _ in pairs]) if pairs else []
        amps = np.concatenate([a for _, a in pairs]) if pairs else []
        return cls(n_channels, pc.reshape(-1), fs, freqs, amps, np.repeat(phase, 2), ramp)

    # ---- loop interface ----------------------------------------------------------------------
    @property
    def args(self):
        """Arrays in kernel order: ``osc_bank_process(*bank.args, out)``."""
        return (self.state, self.pending, self.chan)

    def process(self, out):
        """Add the next ``out.shape[1]`` samples of every tone into ``out``.

        Parameters
        ----------
        out : ndarray, shape (n_channels, n), float64, C-contiguous
            Accumulated into; the caller zeroes it.
        """
        _check_block("out", out, self.n_channels)
        _k.osc_bank_process(self.state, self.pending, self.chan, out)

    def reset(self):
        """Back to the constructor's frequencies, amplitudes and phases; no pending change."""
        _k.osc_init(
            self.state,
            self.pending,
            self._freq0,
            self._amp0,
            self._phase0 / (2 * np.pi),
            self.fs,
            float(self.ramp),
        )

    # ---- targets -----------------------------------------------------------------------------
    def set(self, i, freq=None, amp=None, ramp=None):
        """Ramp tone ``i`` to ``freq`` (Hz) and/or ``amp`` from the start of the next call.

        ``None`` keeps that target; ``ramp`` (samples) overrides the bank's ramp for this change.
        """
        i = _check_int("i", i, 0, self.n_tones - 1)
        if freq is not None:
            self._write(_k.P_FREQ, i, self._freq(freq, 1)[0])
        if amp is not None:
            self._write(_k.P_AMP, i, _vector("amp", amp, 1, 0.0, np.inf)[0])
        self._write(_k.P_RAMP, i, self._ramp(ramp))
        self._write(_k.P_FLAG, i, 1.0)

    def check_many(self, idx, freq, amp, ramp):
        """Changes of several tones, each once, checked as :meth:`set` checks one (a ValueError
        naming the first bad value): tone ``idx[j]`` to ``freq[j]`` (Hz) and ``amp[j]`` over
        ``ramp[j]`` samples. Returns them as ``(int64, float64, float64, float64)`` arrays, or
        None when ``idx`` is empty. For a schedule written into ``pending`` by a kernel
        (:func:`rtctl.dsp._kernels.osc_schedule`)."""
        idx = np.asarray(idx)
        n = idx.size
        if n == 0:
            return None
        if idx.ndim != 1 or idx.dtype.kind not in "iu":
            raise ValueError(f"idx must be a 1-D integer array, got {idx.dtype} of shape {idx.shape}")
        if idx.min() < 0 or idx.max() >= self.n_tones:
            bad = int(idx[(idx < 0) | (idx >= self.n_tones)][0])
            raise ValueError(f"i = {bad} is out of range: allowed 0 <= i <= {self.n_tones - 1}")
        if np.unique(idx).size != n:
            raise ValueError("idx lists a tone more than once: set each tone once")
        f = self._freq(freq, n)
        a = _vector("amp", amp, n, 0.0, np.inf)
        r = np.asarray(ramp)
        if r.shape != (n,) or r.dtype.kind not in "iu" or r.min() < 1 or r.max() > _k.MAX_RAMP:
            raise ValueError(f"ramp must be {n} integers in 1 ... {_k.MAX_RAMP} samples, got {r!r}")
        return idx.astype(np.int64), f, a, r.astype(np.float64)

    def set_all(self, freq=None, amp=None, ramp=None):
        """Vectorized :meth:`set`: ``freq``, ``amp`` scalars or shape (n_tones,); ``None`` keeps."""
        if freq is not None:
            freq = self._freq(freq)
        if amp is not None:
            amp = _vector("amp", amp, self.n_tones, 0.0, np.inf)
        r = self._ramp(ramp)
        if freq is not None:
            self._write(_k.P_FREQ, slice(None), freq)
        if amp is not None:
            self._write(_k.P_AMP, slice(None), amp)
        self._write(_k.P_RAMP, slice(None), r)
        self._write(_k.P_FLAG, slice(None), 1.0)

    def set_beat(self, tones, carrier=None, beat=None, amp=None, ramp=None):
        """Re-target the beat pair made of tones ``tones = (lower, upper)``.

        ``None`` keeps the pair's current target carrier ``(f_lo + f_hi) / 2``, beat
        ``f_hi - f_lo`` or amplitude ``a_lo + a_hi``. Both tones ramp together with no phase jump.
        """
        lo = _check_int("tones[0]", tones[0], 0, self.n_tones - 1)
        hi = _check_int("tones[1]", tones[1], 0, self.n_tones - 1)
        f_lo, f_hi = self.pending[_k.P_FREQ, lo], self.pending[_k.P_FREQ, hi]
        carrier = (f_lo + f_hi) / 2 if carrier is None else carrier
        beat = f_hi - f_lo if beat is None else beat
        amp = self.pending[_k.P_AMP, lo] + self.pending[_k.P_AMP, hi] if amp is None else amp
        freqs, amps = beat_tones(carrier, beat, amp)
        self._freq(freqs, 2)  # check both before touching either
        self.set(lo, freqs[0], amps[0], ramp)
        self.set(hi, freqs[1], amps[1], ramp)

    # ---- accessors ---------------------------------------------------------------------------
    @property
    def phase(self):
        """ndarray, shape (n_tones,): phase of the next sample, rad in [0, 2 pi)."""
        _k.osc_read(self.state, self._read)
        return self._read[0].copy()

    @property
    def freq(self):
        """ndarray, shape (n_tones,): current instantaneous frequency, Hz."""
        _k.osc_read(self.state, self._read)
        return self._read[1].copy()

    @property
    def amp(self):
        """ndarray, shape (n_tones,): amplitude of the last sample (peak)."""
        _k.osc_read(self.state, self._read)
        return self._read[2].copy()

    @property
    def target_freq(self):
        """ndarray, shape (n_tones,): frequencies the tones are (or will be) ramping to, Hz."""
        return self.pending[_k.P_FREQ].copy()

    @property
    def target_amp(self):
        """ndarray, shape (n_tones,): amplitudes the tones are (or will be) ramping to."""
        return self.pending[_k.P_AMP].copy()

    def _freq(self, freq, n=None):
        n = self.n_tones if n is None else n
        return _vector("freq", freq, n, 0.0, self.fs / 2, "Hz", hi_label=f"fs / 2 = {self.fs / 2}")

    def _ramp(self, ramp):
        return float(self.ramp if ramp is None else _check_int("ramp", ramp, 1, _k.MAX_RAMP))
