"""Numba kernels of ``rtctl.dsp``: they allocate nothing, raise nothing and hold no policy.

Every kernel works on preallocated arrays owned by a wrapper (``OscillatorBank``, ``LockIn``,
``PulseTrain``, ``Ramp``, ``Fade``) and can be called directly from the loop's own ``@njit``
block step with ``kernel(*obj.args, out)``. Array layouts are structure-of-arrays: one row per
field, one column per tone / channel / slot, so the innermost loops run over contiguous memory.

Phase is kept in **cycles** internally (``[0, 1)``); wrappers convert to radians.

Oscillator segments
-------------------
Each oscillator's phase is in a *segment*: either steady (constant increment ``INC0``
cycles/sample) or a frequency ramp of ``R = K + LEFT`` samples started by a pending change of
the target frequency. With ``k`` samples done in the segment, ``PH0`` the phase at its start
and ``DINC = (inc1 - inc0) / R``::

    phase[k]  = PH0 + INC0 k + DINC k (k + 1) / 2      (exact closed form, used at anchors)
    inc[k]    = INC0 + DINC (k + 1)                     (phase[k + 1] - phase[k])

so frequency moves linearly with no phase jump and reaches the target on sample ``R - 1``.
Amplitude ramps run on their own counter (``AK`` done, ``ALEFT`` left):
``amp[k] = A0 + DAMP (k + 1)``; an amplitude-only change (the loop's controller, every block)
leaves the phase segment alone and costs no ``sin``/``cos``.

The phasor ``exp(2 pi i phase)`` is advanced by a complex rotation ``W`` (itself rotated by
``D`` during a frequency ramp): no ``sin``/``cos`` per sample. A frequency change updates the
exact closed-form phase (``PH0``) and steps ``W`` by rotation (one ``sin``/``cos`` pair); every
``ANCHOR`` samples of the global clock the phasor, and any rotation obtained by rotating, is
recomputed from the closed form, so round-off never accumulates past ``ANCHOR`` steps (~1e-13).
Anchors sit on the global sample clock and ramps on call starts, so any split of the same
samples into calls gives bitwise identical output.
"""

import math

import numpy as np

from rtctl._numba import TINY, kernel, kernel_exact

# Samples between exact re-anchoring of every phasor (a multiple of 8; see module docstring).
ANCHOR = 256
# Longest ramp: keeps k (k + 1) / 2 exact in float64 and the quadratic phase term's rounding
# below R * 2**-55 cycles (3e-11 cycles at the limit, 1e-15 at R = 32).
MAX_RAMP = 1 << 20
# Steady segments are re-based before their sample count reaches this, so that the integer
# product in _frac_mul stays below 2**63 (see there).
_FOLD = float(1 << 30)

TWO32 = 4294967296.0
INV_TWO32 = 1.0 / TWO32
_MASK32 = (1 << 32) - 1
TWO_PI = 2.0 * math.pi

# ---- oscillator state rows, shape (N_OSC, n_tones) -------------------------------------------
ZR, ZI = 0, 1  # phasor exp(2 pi i phase) of the next sample
WR, WI = 2, 3  # rotation from the next sample to the one after: exp(2 pi i inc[k])
DR, DI = 4, 5  # rotation of the rotation during a frequency ramp: exp(2 pi i DINC); (1, 0) else
AMP = 6  # amplitude of the next sample
DAMP = 7  # amplitude step per sample (0 when not ramping)
PH0 = 8  # phase at the segment start, cycles in [0, 1)
INC0 = 9  # increment at the segment start, cycles/sample
DINC = 10  # increment step per sample during a frequency ramp (0 when steady)
A0 = 11  # amplitude at the start of the amplitude ramp
A1 = 12  # target amplitude
INC1 = 13  # target increment, cycles/sample
K = 14  # samples done in the phase segment (integer-valued)
LEFT = 15  # samples left in the frequency ramp (0: steady)
AK = 16  # samples done in the amplitude ramp
ALEFT = 17  # samples left in the amplitude ramp (0: none)
FS = 18  # sample rate, Hz (constant)
CLOCK = 19  # samples since reset (same in every column; anchors use column 0)
Y = 20  # scratch: this sample's output of each tone
STALE = 21  # 1: W was obtained by rotation; the next anchor recomputes it exactly
N_OSC = 22

# ---- pending rows, shape (N_PEND, n_tones): written between blocks, applied at the next call --
P_FREQ, P_AMP, P_RAMP, P_FLAG = 0, 1, 2, 3
N_PEND = 4


@kernel_exact
def _flush(v):
    """``v`` with magnitudes below TINY set to 0.0 (branch-free; NaN and Inf pass through)."""
    return v * (abs(v) >= TINY)


@kernel_exact
def _frac_mul(x, k):
    """``frac(x * k)`` for ``0 <= x < 1`` and integer ``0 <= k < 2**31``, to ~1 ulp of 1.

    ``x * k`` itself can reach 1e9 cycles after an hour, where a float64 product keeps only
    ~1e-7 cycles of fraction. Split ``x = hi + lo`` with ``hi`` on a 2**-32 grid: ``hi * k`` is
    done in int64 (exact, < 2**63) and reduced mod 1 by masking, and ``lo * k < 0.5`` is a
    plain product with an error ~1e-17 cycles.
    """
    hi = np.floor(x * TWO32)
    lo = x - hi * INV_TWO32  # exact: hi * 2**-32 is x truncated to 32 fraction bits
    m = (np.int64(hi) * np.int64(k)) & _MASK32
    f = m * INV_TWO32 + lo * k
    return f - np.floor(f)


@kernel_exact
def _phase_at(ph0, inc0, dinc, k):
    """Phase in cycles ``[0, 1)`` after ``k`` samples of a segment (closed form, see top)."""
    q = dinc * (k * (k + 1.0) * 0.5)  # k (k + 1) / 2 < 2**40 is exact
    f = ph0 + _frac_mul(inc0, k) + (q - np.floor(q))
    return f - np.floor(f)


# cos / sin of the eight octant angles k pi / 4, and Taylor coefficients for |x| <= pi / 8
_OCT_C = np.array([math.cos(k * math.pi / 4) for k in range(8)])
_OCT_S = np.array([math.sin(k * math.pi / 4) for k in range(8)])
_OCT_C[2] = _OCT_C[6] = _OCT_S[0] = _OCT_S[4] = 0.0  # exact zeros, not 6e-17


@kernel_exact
def _cis(cycles):
    """``(cos, sin)`` of ``2 pi cycles`` to ~2 ulp, without libm.

    ``cycles`` is reduced exactly to the nearest octant ``n / 8`` plus ``|r| <= 1/16``: Taylor
    series of degree 14/15 for ``x = 2 pi r`` (|x| <= pi / 8, truncation < 1e-19) rotated by the
    octant's (cos, sin). A third of the cost of libm's ``cos`` + ``sin``, and no call: it runs at
    every anchor and frequency change.
    """
    c = cycles - np.floor(cycles + 0.5)  # [-1/2, 1/2]: small arguments keep full relative precision
    n = np.floor(c * 8.0 + 0.5)
    x = TWO_PI * (c - n * 0.125)  # c - n / 8 is exact (Sterbenz)
    x2 = x * x
    sn = x * (1.0 + x2 * (-1.0 / 6 + x2 * (1.0 / 120 + x2 * (-1.0 / 5040 + x2 * (
        1.0 / 362880 + x2 * (-1.0 / 39916800 + x2 * (1.0 / 6227020800 + x2 * (-1.0 / 1307674368000))))))))
    cs = 1.0 + x2 * (-0.5 + x2 * (1.0 / 24 + x2 * (-1.0 / 720 + x2 * (
        1.0 / 40320 + x2 * (-1.0 / 3628800 + x2 * (1.0 / 479001600 + x2 * (-1.0 / 87178291200)))))))
    k = int(n) & 7
    oc = _OCT_C[k]
    os_ = _OCT_S[k]
    return oc * cs - os_ * sn, oc * sn + os_ * cs


# ---- linear ramp helpers: value[k] = v0 + step (k + 1), k = 0 .. R - 1 ------------------------
@kernel_exact
def ramp_step(v0, v1, r):
    """Per-sample step of a linear ramp from ``v0`` to ``v1`` over ``r >= 1`` samples."""
    return (v1 - v0) / r


@kernel_exact
def ramp_value(v0, step, k):
    """Value on sample ``k`` (0-based) of a ramp that started at ``v0``; ``k + 1 = r`` gives the end."""
    return v0 + step * (k + 1.0)


# ---- oscillator machinery (shared by the bank and the lock-in references) ---------------------
@kernel
def _osc_start_ramps(st, pend):
    """Start ramps on every tone whose pending flag is set (called at the start of a call)."""
    for i in range(st.shape[1]):
        if pend[P_FLAG, i] == 0.0:
            continue
        pend[P_FLAG, i] = 0.0
        r = min(max(1.0, np.floor(pend[P_RAMP, i])), MAX_RAMP)
        # a ramp (re)starts, from the current value, only for a target that changed
        a1 = _flush(pend[P_AMP, i])
        if a1 != st[A1, i]:
            a_now = st[A0, i] + st[DAMP, i] * st[AK, i]  # amplitude of the last sample
            damp = ramp_step(a_now, a1, r)
            st[A0, i] = a_now
            st[A1, i] = a1
            st[DAMP, i] = damp
            st[AK, i] = 0.0
            st[ALEFT, i] = r
            st[AMP, i] = _flush(ramp_value(a_now, damp, 0.0))
        inc1 = _flush(pend[P_FREQ, i] / st[FS, i])
        if inc1 == st[INC1, i]:
            continue
        k = st[K, i]
        old_dinc = st[DINC, i]
        inc_now = st[INC0, i] + old_dinc * k  # last increment applied
        dinc = ramp_step(inc_now, inc1, r)
        st[PH0, i] = _phase_at(st[PH0, i], st[INC0, i], old_dinc, k)
        st[INC0, i] = inc_now
        st[DINC, i] = dinc
        st[INC1, i] = inc1
        st[K, i] = 0.0
        st[LEFT, i] = r
        # W = exp(2 pi i inc[k]) is one D step ahead of the last applied increment: step back
        # with the old D and forward with the new one. The phasor Z carries on: it already is
        # the exact phase up to rotation round-off, and the next anchor resets it.
        dr, di = _cis(dinc)
        odr = st[DR, i]
        odi = st[DI, i]
        wr = st[WR, i] * odr + st[WI, i] * odi
        wi = st[WI, i] * odr - st[WR, i] * odi
        st[WR, i] = wr * dr - wi * di
        st[WI, i] = wr * di + wi * dr
        st[DR, i] = dr
        st[DI, i] = di
        st[STALE, i] = 1.0


@kernel
def _osc_chunk(st, m_max):
    """Samples until the next event (anchor or ramp end), at most ``m_max``, and the loop to use:
    0 all steady, 1 amplitude ramps only, 2 some frequency ramp."""
    m = min(m_max, ANCHOR - int(st[CLOCK, 0] % ANCHOR))
    mode = 0
    for i in range(st.shape[1]):
        left = st[LEFT, i]
        if left > 0.0:
            mode = 2
            m = min(m, int(left))
        aleft = st[ALEFT, i]
        if aleft > 0.0:
            mode = max(mode, 1)
            m = min(m, int(aleft))
    return m, mode


@kernel
def _osc_advance(st, m):
    """Account ``m`` processed samples, then finish ramps and re-anchor where due."""
    nt = st.shape[1]
    for i in range(nt):
        st[K, i] += m
        st[CLOCK, i] += m
        if st[ALEFT, i] > 0.0:
            st[AK, i] += m
            st[ALEFT, i] -= m
            if st[ALEFT, i] == 0.0:
                st[A0, i] = st[A1, i]
                st[AMP, i] = st[A1, i]
                st[DAMP, i] = 0.0
                st[AK, i] = 0.0
        if st[LEFT, i] > 0.0:
            st[LEFT, i] -= m
            if st[LEFT, i] == 0.0:
                _osc_end_freq_ramp(st, i)
    if st[CLOCK, 0] % ANCHOR == 0.0:
        for i in range(nt):
            _osc_anchor(st, i)


@kernel
def _osc_end_freq_ramp(st, i):
    st[PH0, i] = _phase_at(st[PH0, i], st[INC0, i], st[DINC, i], st[K, i])
    st[INC0, i] = st[INC1, i]
    st[DINC, i] = 0.0
    st[K, i] = 0.0
    # the ramp loop rotated W once past the last ramp sample: undo that step; the exact
    # W = exp(2 pi i INC1) follows at the next anchor (no sin/cos here)
    dr = st[DR, i]
    di = st[DI, i]
    wr = st[WR, i] * dr + st[WI, i] * di
    st[WI, i] = st[WI, i] * dr - st[WR, i] * di
    st[WR, i] = wr
    st[DR, i] = 1.0
    st[DI, i] = 0.0
    st[STALE, i] = 1.0


@kernel
def _osc_anchor(st, i):
    k = st[K, i]
    phi = _phase_at(st[PH0, i], st[INC0, i], st[DINC, i], k)
    st[ZR, i], st[ZI, i] = _cis(phi)
    if st[ALEFT, i] > 0.0:
        st[AMP, i] = _flush(ramp_value(st[A0, i], st[DAMP, i], st[AK, i]))
    if st[LEFT, i] > 0.0:
        st[WR, i], st[WI, i] = _cis(st[INC0, i] + st[DINC, i] * (k + 1.0))
        st[STALE, i] = 0.0
    else:
        if st[STALE, i] != 0.0:
            st[WR, i], st[WI, i] = _cis(st[INC0, i])
            st[STALE, i] = 0.0
        if k >= _FOLD:
            st[PH0, i] = phi
            st[K, i] = 0.0


@kernel
def _osc_amp_ramp_add(st, chan, out, j0, m):
    """Rotate every tone's phasor and add it into its row; amplitudes step by ``DAMP``, which is
    0 outside an amplitude ramp (so this is also the steady loop: a separate one without the add
    measured only ~0.2 ns per tone-sample faster)."""
    zr = st[ZR]
    zi = st[ZI]
    wr = st[WR]
    wi = st[WI]
    amp = st[AMP]
    damp = st[DAMP]
    y = st[Y]
    nt = zr.shape[0]
    for j in range(j0, j0 + m):
        for i in range(nt):
            y[i] = amp[i] * zr[i]
            amp[i] += damp[i]
            r = zr[i] * wr[i] - zi[i] * wi[i]
            zi[i] = zr[i] * wi[i] + zi[i] * wr[i]
            zr[i] = r
        for i in range(nt):
            out[chan[i], j] += y[i]


@kernel
def _osc_ramp_add(st, chan, out, j0, m):
    zr = st[ZR]
    zi = st[ZI]
    wr = st[WR]
    wi = st[WI]
    dr = st[DR]
    di = st[DI]
    amp = st[AMP]
    damp = st[DAMP]
    y = st[Y]
    nt = zr.shape[0]
    for j in range(j0, j0 + m):
        for i in range(nt):
            y[i] = amp[i] * zr[i]
            amp[i] += damp[i]
            r = zr[i] * wr[i] - zi[i] * wi[i]
            zi[i] = zr[i] * wi[i] + zi[i] * wr[i]
            zr[i] = r
            r = wr[i] * dr[i] - wi[i] * di[i]
            wi[i] = wr[i] * di[i] + wi[i] * dr[i]
            wr[i] = r
        for i in range(nt):
            out[chan[i], j] += y[i]


@kernel
def osc_schedule(pos, blocks, first, tone, freq, amp, ramp, pending):
    """A bank's known schedule of changes, written into ``pending`` at the start of each block
    (what :meth:`OscillatorBank.set` of each change would write), inside the block function.

    ``pos = (this block's number, next schedule entry)``, advanced here; block ``blocks[j]``
    sets tones ``tone[first[j]:first[j + 1]]`` (each once) to ``freq``, ``amp`` over ``ramp``
    samples. Returns 0 (a status)."""
    k = pos[0]
    j = pos[1]
    while j < blocks.shape[0] and blocks[j] <= k:
        if blocks[j] == k:
            for e in range(first[j], first[j + 1]):
                i = tone[e]
                pending[P_FREQ, i] = freq[e]
                pending[P_AMP, i] = amp[e]
                pending[P_RAMP, i] = ramp[e]
                pending[P_FLAG, i] = 1.0
        j += 1
    pos[0] = k + 1
    pos[1] = j
    return 0


@kernel
def osc_bank_process(state, pending, chan, out):
    """Add ``n = out.shape[1]`` samples of every tone into ``out[chan[i]]`` (see OscillatorBank).

    Parameters
    ----------
    state : ndarray, shape (N_OSC, n_tones), float64
        Oscillator state (rows ``ZR`` .. ``Y`` of this module), updated in place.
    pending : ndarray, shape (N_PEND, n_tones), float64
        Targets: ``P_FREQ`` (Hz), ``P_AMP`` (peak), ``P_RAMP`` (samples), ``P_FLAG`` (non-zero:
        start a ramp to these targets at the start of this call; cleared here).
    chan : ndarray, shape (n_tones,), int64
        Output row of each tone.
    out : ndarray, shape (n_channels, n), float64, C-contiguous
        Accumulated into (tones add; the caller zeroes it).
    """
    if state.shape[1] == 0:
        return
    n = out.shape[1]
    _osc_start_ramps(state, pending)
    t = 0
    while t < n:
        m, mode = _osc_chunk(state, n - t)
        if mode == 2:
            _osc_ramp_add(state, chan, out, t, m)
        else:
            _osc_amp_ramp_add(state, chan, out, t, m)
        _osc_advance(state, m)
        t += m


@kernel
def osc_init(state, pending, freq, amp, phase, fs, ramp):
    """Put every tone in a steady segment at ``freq`` (Hz), ``amp``, ``phase`` (cycles)."""
    for i in range(state.shape[1]):
        inc = _flush(freq[i] / fs)
        a = _flush(amp[i])
        ph = phase[i] - np.floor(phase[i])
        for r in range(N_OSC):
            state[r, i] = 0.0
        state[ZR, i], state[ZI, i] = _cis(ph)
        state[WR, i], state[WI, i] = _cis(inc)
        state[DR, i] = 1.0
        state[AMP, i] = a
        state[PH0, i] = ph
        state[INC0, i] = inc
        state[INC1, i] = inc
        state[A0, i] = a
        state[A1, i] = a
        state[FS, i] = fs
        pending[P_FREQ, i] = freq[i]
        pending[P_AMP, i] = amp[i]
        pending[P_RAMP, i] = ramp
        pending[P_FLAG, i] = 0.0


@kernel
def osc_read(state, out):
    """Current phase (rad, of the next sample), frequency (Hz, last increment) and amplitude
    (of the last sample) into ``out``, shape (3, n_tones)."""
    for i in range(state.shape[1]):
        k = state[K, i]
        out[0, i] = TWO_PI * _phase_at(state[PH0, i], state[INC0, i], state[DINC, i], k)
        out[1, i] = (state[INC0, i] + state[DINC, i] * k) * state[FS, i]
        out[2, i] = state[A0, i] + state[DAMP, i] * state[AK, i]


# ---- lock-in ---------------------------------------------------------------------------------
# accumulator rows, shape (N_ACC, n_slots); slot s = channel * n_freq + f
ACC_R, ACC_I = 0, 1  # partial sum of x conj(ref) over the current hop
S_R, S_I = 2, 3  # window sum: the slot's last NHOP complete hops
F_R, F_I = 4, 5  # fresh sum of the hops written since the ring last wrapped
EST_A, EST_P = 6, 7  # amplitude (peak) and phase (rad) at the last complete hop
HOP = 8  # samples per hop (constant)
NHOP = 9  # hops in this slot's window (constant; the ring holds the longest slot's)
Z_R, Z_I = 10, 11  # the reference of the sample after the last complete hop, exp(i theta[N])
X_R, X_I = 12, 13  # the window sum the estimate is made of: S, or S solved for the row's tones
LSQ = 14  # 1: this slot's row is solved by least squares (solve[s] holds its row of the inverse)
N_ACC = 15


@kernel
def _lockin_demod(ref, chan, acc, x, j0, m, ramping):
    zr = ref[ZR]
    zi = ref[ZI]
    wr = ref[WR]
    wi = ref[WI]
    dr = ref[DR]
    di = ref[DI]
    xs = ref[Y]
    ar = acc[ACC_R]
    ai = acc[ACC_I]
    ns = zr.shape[0]
    for j in range(j0, j0 + m):
        for s in range(ns):
            xs[s] = x[chan[s], j]
        for s in range(ns):
            v = xs[s]
            ar[s] += v * zr[s]
            ai[s] -= v * zi[s]
            r = zr[s] * wr[s] - zi[s] * wi[s]
            zi[s] = zr[s] * wi[s] + zi[s] * wr[s]
            zr[s] = r
        if ramping:
            for s in range(ns):
                r = wr[s] * dr[s] - wi[s] * di[s]
                wi[s] = wr[s] * di[s] + wi[s] * dr[s]
                wr[s] = r


@kernel
def _run_end(acc, s0):
    """One past the last slot of the run from ``s0`` whose windows are ``s0``'s."""
    s1 = s0 + 1
    while s1 < acc.shape[1] and acc[NHOP, s1] == acc[NHOP, s0]:
        s1 += 1
    return s1


@kernel
def _lockin_hop(ref, acc, ring, hop_index):
    """Close hop ``hop_index`` (count since reset, 0-based): move its partial sums into the window.

    Each slot's window holds its own ``NHOP`` hops (ring rows ``0 .. NHOP - 1``). Slots are taken
    in runs of equal ``NHOP`` (a group-wide window is one run; per-channel windows a run per
    channel), so the ring row is one per run and the inner loop stays a contiguous sweep.
    """
    ns = acc.shape[1]
    s0 = 0
    while s0 < ns:
        nh = acc[NHOP, s0]
        s1 = _run_end(acc, s0)
        n_hops = max(1, int(nh))  # >= 1 from LockIn; guarded so a zeroed acc cannot raise
        idx = hop_index % n_hops
        wrap = idx == n_hops - 1
        for s in range(s0, s1):
            pr = _flush(acc[ACC_R, s])
            pi = _flush(acc[ACC_I, s])
            acc[S_R, s] += pr - ring[idx, 0, s]
            acc[S_I, s] += pi - ring[idx, 1, s]
            acc[F_R, s] += pr
            acc[F_I, s] += pi
            ring[idx, 0, s] = pr
            ring[idx, 1, s] = pi
            acc[ACC_R, s] = 0.0
            acc[ACC_I, s] = 0.0
            acc[Z_R, s] = ref[ZR, s]
            acc[Z_I, s] = ref[ZI, s]
            if wrap:
                # the ring now holds exactly the hops added to F since the last wrap: replace the
                # add-and-subtract running sum by this fresh one, so round-off cannot drift
                acc[S_R, s] = acc[F_R, s]
                acc[S_I, s] = acc[F_I, s]
                acc[F_R, s] = 0.0
                acc[F_I, s] = 0.0
            acc[S_R, s] = _flush(acc[S_R, s])
            acc[S_I, s] = _flush(acc[S_I, s])
            acc[F_R, s] = _flush(acc[F_R, s])
            acc[F_I, s] = _flush(acc[F_I, s])
        s0 = s1


@kernel
def _lockin_solve(acc, solve, s):
    """Slot ``s``'s window sum with its row's other tones and every mirror removed (see LockIn,
    "Least squares"): with ``T_l = S_l z_l`` (``z_l`` the reference after the window) over the
    row's slots ``l``, ``Y = solve[s] T`` (real, imaginary interleaved) and ``X = Y conj(z_s)``."""
    n_freq = solve.shape[2] // 2
    b = s - s % n_freq
    yr = 0.0
    yi = 0.0
    for j in range(n_freq):
        lr = acc[S_R, b + j]
        li = acc[S_I, b + j]
        zr = acc[Z_R, b + j]
        zi = acc[Z_I, b + j]
        tr = lr * zr - li * zi
        ti = lr * zi + li * zr
        yr += solve[s, 0, 2 * j] * tr + solve[s, 0, 2 * j + 1] * ti
        yi += solve[s, 1, 2 * j] * tr + solve[s, 1, 2 * j + 1] * ti
    zr = acc[Z_R, s]
    zi = acc[Z_I, s]
    acc[X_R, s] = yr * zr + yi * zi
    acc[X_I, s] = yi * zr - yr * zi


@kernel
def _lockin_sums_out(acc, solve):
    """The window sum each slot's estimate is made of (``X``): for a slot whose row is solved by
    least squares (``LSQ``) its solved sum, for every other its plain one."""
    for s in range(acc.shape[1]):
        if acc[LSQ, s] != 0.0:
            _lockin_solve(acc, solve, s)
        else:
            acc[X_R, s] = acc[S_R, s]
            acc[X_I, s] = acc[S_I, s]


@kernel
def _lockin_edges(chan, acc, x, j, edge, ed, hop_index):
    """At hop ``hop_index``'s close (its last sample ``j`` of ``x``, the reference after it in
    ``acc[Z]``): its ``E = x[j] conj z`` into ``edge``'s ring row, and ``ed`` the window's ``E``
    less the one before the window's first hop, which that row held (see
    :func:`lockin_process_edges`; rows as :func:`_lockin_hop`'s)."""
    ns = acc.shape[1]
    s0 = 0
    while s0 < ns:
        s1 = _run_end(acc, s0)
        idx = hop_index % max(1, int(acc[NHOP, s0]))
        for s in range(s0, s1):
            v = x[chan[s], j]
            er = v * acc[Z_R, s]
            ei = -v * acc[Z_I, s]
            ed[0, s] = er - edge[idx, 0, s]
            ed[1, s] = ei - edge[idx, 1, s]
            edge[idx, 0, s] = er
            edge[idx, 1, s] = ei
        s0 = s1


@kernel
def _lockin_estimate(ref, acc):
    """Amplitude and phase of every slot from the window sum its estimate is made of
    (:func:`_lockin_sums_out`; once per call, not per hop); the scale is one per run of slots with
    equal windows, as in :func:`_lockin_hop`."""
    ns = acc.shape[1]
    s0 = 0
    while s0 < ns:
        nh = acc[NHOP, s0]
        s1 = _run_end(acc, s0)
        scale = 2.0 / (nh * acc[HOP, 0])
        for s in range(s0, s1):
            if ref[INC1, s] > 0.0:
                acc[EST_A, s] = scale * math.hypot(acc[X_R, s], acc[X_I, s])
                acc[EST_P, s] = math.atan2(acc[X_I, s], acc[X_R, s])
            else:
                acc[EST_A, s] = np.nan
                acc[EST_P, s] = np.nan
        s0 = s1


@kernel
def lockin_process(ref, pending, chan, acc, ring, solve, x, out):
    """Demodulate ``x`` at every slot's reference frequency over a sliding window (see LockIn).

    Parameters
    ----------
    ref : ndarray, shape (N_OSC, n_slots), float64
        Reference oscillators (same layout as the oscillator bank), updated in place.
    pending : ndarray, shape (N_PEND, n_slots), float64
        Reference frequency targets as for the bank (``P_FREQ`` <= 0 or NaN: slot unused).
    chan : ndarray, shape (n_slots,), int64
        Input row of each slot (``slot // n_freq``).
    acc : ndarray, shape (N_ACC, n_slots), float64
        Hop, window and fresh sums and the latest estimates, updated in place; ``acc[NHOP]``
        the hops in each slot's window (equal everywhere for a window shared by all slots).
    ring : ndarray, shape (n_hops, 2, n_slots), float64
        Partial sums of the hops in the window (real, imaginary); ``n_hops`` the longest
        slot's (a slot uses rows ``0 .. acc[NHOP, s] - 1``).
    solve : ndarray, shape (n_slots, 2, 2 * n_freq), float64
        Per slot whose ``acc[LSQ]`` is set: its rows (real, imaginary) of the least-squares
        inverse over its row's slots (see LockIn); unread for the others.
    x : ndarray, shape (n_channels, n), float64, C-contiguous
        Input block.
    out : ndarray, shape (n_channels, n_freq, 2), float64
        Amplitude (peak) and phase (rad) at the last complete hop; NaN for unused slots.
    """
    _lockin_process(ref, pending, chan, acc, ring, solve, x, out, ring, acc, False)


@kernel
def lockin_process_edges(ref, pending, chan, acc, ring, solve, x, out, edge, ed):
    """:func:`lockin_process` that also keeps what a lock-in of ``x``'s first difference needs
    beyond ``x``'s own window sums. With ``z`` the reference (rotating by ``exp(j w)`` per sample)
    and ``J = 1 - exp(-j w)``, a hop's sum of ``(x[n] - x[n-1]) conj z[n]`` is ``J`` times its sum
    of ``x[n] conj z[n]`` plus ``E - E'``, where ``E = x[b] conj z[b + 1]`` at the hop's last
    sample ``b`` and ``E'`` the hop before's (0 before the first sample); over a window the ``E``
    telescope to its two ends. ``edge`` (shaped as ``ring``) holds each hop's ``E``, ``ed[0:2]``
    the window's ``E - E'`` (real, imaginary) after the last hop closed in this call."""
    _lockin_process(ref, pending, chan, acc, ring, solve, x, out, edge, ed, True)


@kernel
def _lockin_process(ref, pending, chan, acc, ring, solve, x, out, edge, ed, edges):
    if ref.shape[1] == 0:
        return
    if _lockin_run(ref, pending, chan, acc, ring, solve, x, edge, ed, edges):
        _lockin_estimate(ref, acc)
    n_freq = out.shape[1]
    for r in range(out.shape[0]):
        for k in range(n_freq):
            out[r, k, 0] = acc[EST_A, r * n_freq + k]
            out[r, k, 1] = acc[EST_P, r * n_freq + k]


@kernel
def lockin_sums(ref, pending, chan, acc, ring, solve, x):
    """:func:`lockin_process` without amplitude and phase, for a caller that reads only the window
    sums: ``acc[X_R]``, ``acc[X_I]`` (and ``acc[Z_R]``, ``acc[Z_I]``) are updated as there,
    ``acc[EST_A]``, ``acc[EST_P]`` are left as they were (a ``hypot`` and an ``atan2`` per slot and
    call saved). Returns whether a hop closed in this call (the sums then changed)."""
    return _lockin_run(ref, pending, chan, acc, ring, solve, x, ring, acc, False)


@kernel
def _lockin_run(ref, pending, chan, acc, ring, solve, x, edge, ed, edges):
    """:func:`lockin_sums`, and where ``edges`` :func:`_lockin_edges` at every hop's close."""
    ns = ref.shape[1]
    if ns == 0:
        return False
    for s in range(ns):
        if pending[P_FLAG, s] != 0.0 and not (pending[P_FREQ, s] > 0.0):
            pending[P_FREQ, s] = 0.0  # unused: a still reference costs nothing and reads NaN
    _osc_start_ramps(ref, pending)
    hop = int(acc[HOP, 0])
    n = x.shape[1]
    t = 0
    closed = False
    while t < n:
        clock = int(ref[CLOCK, 0])
        m, mode = _osc_chunk(ref, n - t)
        m = min(m, hop - clock % hop)
        _lockin_demod(ref, chan, acc, x, t, m, mode == 2)
        _osc_advance(ref, m)
        if (clock + m) % hop == 0:
            _lockin_hop(ref, acc, ring, (clock + m) // hop - 1)
            if edges:
                _lockin_edges(chan, acc, x, t + m - 1, edge, ed, (clock + m) // hop - 1)
            closed = True
        t += m
    if closed:
        _lockin_sums_out(acc, solve)
    return closed


# ---- pulse trains ----------------------------------------------------------------------------
# Position in the cycle is an integer count of 2**-40 cycle held in a float64 (a DDS phase
# accumulator). Within a stretch of at most _PULSE_RUN samples, base + j * inc < 2**40 + 2**52
# stays an integer below 2**53, so every position is computed exactly and independently of the
# previous sample (no serial dependency: the loop vectorizes), and edges never drift.
PULSE_UNIT = float(1 << 40)
_INV_PULSE_UNIT = 1.0 / PULSE_UNIT
_PULSE_RUN = 1 << 13
POS, PINC, PDUTY, PHIGH, PLOW, PFS = 0, 1, 2, 3, 4, 5
N_PULSE = 6
Q_FREQ, Q_DUTY, Q_HIGH, Q_LOW, Q_FLAG = 0, 1, 2, 3, 4
N_QPEND = 5


@kernel_exact
def pulse_process(state, pending, out):
    """Add rectangular waves into ``out``, shape (n_channels, n) (see PulseTrain).

    Parameters
    ----------
    state : ndarray, shape (N_PULSE, n_channels), float64
        ``POS`` (cycle position, units of 2**-40 cycle), ``PINC`` (units/sample), ``PDUTY``
        (units), ``PHIGH``, ``PLOW`` (levels), ``PFS`` (Hz).
    pending : ndarray, shape (N_QPEND, n_channels), float64
        ``Q_FREQ`` (Hz), ``Q_DUTY`` (0..1), ``Q_HIGH``, ``Q_LOW``, ``Q_FLAG`` (non-zero: apply
        at the start of this call; cleared here).
    out : ndarray, shape (n_channels, n), float64
        Accumulated into: sample ``j`` gets HIGH while the position is below the duty, else LOW.
    """
    n = out.shape[1]
    for c in range(state.shape[1]):
        if pending[Q_FLAG, c] != 0.0:
            pending[Q_FLAG, c] = 0.0
            state[PINC, c] = np.floor(pending[Q_FREQ, c] / state[PFS, c] * PULSE_UNIT + 0.5)
            state[PDUTY, c] = np.floor(pending[Q_DUTY, c] * PULSE_UNIT + 0.5)
            state[PHIGH, c] = pending[Q_HIGH, c]
            state[PLOW, c] = pending[Q_LOW, c]
        pos = state[POS, c]
        inc = state[PINC, c]
        duty = state[PDUTY, c]
        hi = state[PHIGH, c]
        lo = state[PLOW, c]
        j0 = 0
        while j0 < n:
            m = min(n - j0, _PULSE_RUN)
            seg = out[c, j0 : j0 + m]  # a view indexed from 0 lets the loop vectorize
            for j in range(m):
                p = pos + j * inc
                p -= PULSE_UNIT * np.floor(p * _INV_PULSE_UNIT)
                seg[j] += hi if p < duty else lo
            pos += m * inc
            pos -= PULSE_UNIT * np.floor(pos * _INV_PULSE_UNIT)
            j0 += m
        state[POS, c] = pos


# ---- linear parameter ramps --------------------------------------------------------------------
R_VAL, R_STEP, R_V0, R_K, R_LEFT, R_TARGET = 0, 1, 2, 3, 4, 5
N_RAMP = 6
RP_TARGET, RP_RAMP, RP_FLAG = 0, 1, 2
N_RPEND = 3


@kernel
def ramp_process(state, pending, out):
    """Write ramped parameter values into ``out``, shape (n_params, n) (see Ramp).

    ``state`` rows: ``R_VAL`` (value of the last sample), ``R_STEP``, ``R_V0`` (value at the ramp
    start), ``R_K`` (samples done), ``R_LEFT`` (samples left), ``R_TARGET``. ``pending`` rows:
    ``RP_TARGET``, ``RP_RAMP`` (samples), ``RP_FLAG``.
    """
    n = out.shape[1]
    for p in range(state.shape[1]):
        if pending[RP_FLAG, p] != 0.0:
            pending[RP_FLAG, p] = 0.0
            r = max(1.0, np.floor(pending[RP_RAMP, p]))
            target = _flush(pending[RP_TARGET, p])
            state[R_V0, p] = state[R_VAL, p]
            state[R_STEP, p] = ramp_step(state[R_VAL, p], target, r)
            state[R_TARGET, p] = target
            state[R_K, p] = 0.0
            state[R_LEFT, p] = r
        v0 = state[R_V0, p]
        step = state[R_STEP, p]
        target = state[R_TARGET, p]
        k = state[R_K, p]
        left = state[R_LEFT, p]
        val = state[R_VAL, p]
        row = out[p]
        for j in range(n):
            if left > 0.0:
                left -= 1.0
                # the last sample lands exactly on the target
                val = target if left == 0.0 else ramp_value(v0, step, k)
                k += 1.0
            row[j] = val
        state[R_K, p] = k
        state[R_LEFT, p] = left
        state[R_VAL, p] = _flush(val)


# ---- raised-cosine fade --------------------------------------------------------------------------
FD_K, FD_N, FD_G0, FD_G1, FD_GAIN = 0, 1, 2, 3, 4
N_FADE = 5


@kernel
def fade_start(state, gain, length):
    """Start a fade from the current gain to ``gain`` over ``length >= 1`` samples."""
    state[FD_G0] = state[FD_GAIN]
    state[FD_G1] = gain
    state[FD_K] = 0.0
    state[FD_N] = max(1.0, np.floor(length))


@kernel
def fade_process(state, out):
    """Multiply ``out``, shape (n_channels, n), in place by a raised-cosine fade (see Fade).

    ``state``: ``FD_K`` samples done, ``FD_N`` fade length (0: idle), ``FD_G0`` / ``FD_G1`` gains
    at the start and end of the fade, ``FD_GAIN`` gain of the last sample. Sample ``k`` (1-based)
    of a fade gets ``g1 + (g0 - g1) (1 + cos(pi k / N)) / 2``: the slope is zero at both ends and
    the last sample is exactly ``g1``.
    """
    n = out.shape[1]
    nch = out.shape[0]
    for j in range(n):
        length = state[FD_N]
        if length > 0.0:
            k = state[FD_K] + 1.0
            state[FD_K] = k
            if k >= length:
                g = state[FD_G1]
                state[FD_N] = 0.0
            else:
                g1 = state[FD_G1]
                g = g1 + (state[FD_G0] - g1) * (0.5 + 0.5 * math.cos(math.pi * k / length))
            state[FD_GAIN] = g
        else:
            g = state[FD_GAIN]
        if g == 0.0:
            for ch in range(nch):
                out[ch, j] = 0.0  # faded out means silent, even where the input was NaN
        elif g != 1.0:
            for ch in range(nch):
                out[ch, j] *= g
