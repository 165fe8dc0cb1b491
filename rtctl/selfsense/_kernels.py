"""Real-time kernel of the self-sensing observer: lock-in, observer matrices, tip waveform.

Allocates nothing, raises nothing; the wrapper is :class:`rtctl.selfsense.rt.Observer`.
"""

import numpy as np

from rtctl._numba import kernel
from rtctl.dsp import _kernels as _dk

# Status bit: an estimate is NaN/Inf (a poisoned reading or state); the sim uses 1 and 2.
STATUS_NONFINITE = 4
#: The estimate row of the tip moment (``EST_NAMES``), the residual :func:`_pick_load` compares.
ROW_MOMENT = 3
#: A block votes against the candidates whose tip-moment residual (squared) is over this many
#: times the least (twice the moment, or more): no vote where none is.
DECISIVE = 0.25
#: The estimate row of the tip force: a free tip (the finger lifted) pushes nothing.
ROW_FORCE = 4
#: The candidate without a finger reads a tip force. Over this share of the least force a finger
#: of the candidates would put on that tip (``contact``: the smallest of their impedances at the
#: tone, skin mass included), a finger is there: the free candidate loses the block's vote, whatever
#: the moments say. Under :data:`FREE`, none is: the finger's candidates lose. In between (a finger
#: whose stiffness and skin inertia nearly cancel at the tone, or a model far off) the moments vote.
#: A beam with a mode near the drive's images (20 mm of PZT-5H: its 6th mode at 47 kHz) reads its
#: tip through the images' load 14 % apart lifted or not, while its tip moments differ by less than
#: a device off its model moves them: the moments alone took the images for a free tip's under
#: the finger, and a finger's with it lifted.
TOUCH = 0.2
FREE = 0.005
#: ... and only where the free candidate's tip is one the drive explains: no more than this many
#: times the free beam's tip at that drive. A window of noise (a tone faded out, the drive at 0 V
#: while the tips settle) reads a tip and a force of noise, which would vote at random.
DRIVEN = 4.0
#: The columns of ``contact`` (per channel and tone): the candidate without a finger (-1: none),
#: the least squared impedance the others put on the tip (N^2/m^2), the free beam's squared tip
#: per drive volt (m^2/V^2).
C_FREE, C_Z2, C_G2 = 0, 1, 2
N_CONTACT = 3
#: Leaving a free tip, smoothed losses this close count as even, and the tie goes to the finger's
#: candidate in use when the finger lifted (it comes back as it left). The 50 g and 200 g sets
#: of a finger pin the tip alike, but not always alike enough: on a beam with a mode near the
#: images they read its tip 60 % apart, and which one followed a lift-off was decided by a hair.
TIE = 0.05
#: A candidate load takes over when its smoothed loss of the blocks' votes (the least tip-moment
#: residual wins) is under this share of the one in use's: two candidates that noise or the
#: finger's sets split (50 g and 200 g of skin pin the tip alike) do not alternate.
SWITCH = 0.25

_ZR, _ZI, _WR, _WI = _dk.ZR, _dk.ZI, _dk.WR, _dk.WI
_XR, _XI = _dk.X_R, _dk.X_I  # the window sums the lock-ins' estimates are made of
_SR, _SI, _AR, _AI, _ZAR, _ZAI = _dk.S_R, _dk.S_I, _dk.ACC_R, _dk.ACC_I, _dk.Z_R, _dk.Z_I
# Fewest slots for which the waveform is rebuilt with the slots innermost (as vector lanes): the
# crossover measured against one chain per slot (bench/observer.py's parts, 1-48 slots)
_LANES = 8


@kernel
def observer_process(u_ref, u_pend, u_chan, u_acc, u_ring, u_solve, i_ref, i_pend, i_chan, i_acc, i_ring,
                     i_solve, u_out, back, H, Hc, pick, resid, contact, lag, scale, est, wave, pf, pf_z,
                     pf_x, pf_g, d_acc, d_edge, invJ, Kc, drive, sensed):
    """One block: low-pass drive and currents (:func:`_prefilter`), demodulate them, take each
    channel's image load (:func:`_pick_load`), apply the observer, rebuild the tip waveform.

    Parameters
    ----------
    u_ref, u_pend, u_chan, u_acc, u_ring, u_solve : ndarray
        Lock-in of the drive (``LockIn.args``), slots ``(n_ch, n_tones)``.
    i_ref, i_pend, i_chan, i_acc, i_ring, i_solve : ndarray
        Lock-in of the sensed currents, rows ``ch * n_seg + seg``, slots ``(n_ch * n_seg, n_tones)``;
        each row's window that of its channel in the drive's lock-in. Only its window sums are
        kept (``lockin_sums``): its amplitudes and phases are not computed.
    u_out : ndarray, shape (n_ch, n_tones, 2)
        Written: the drive lock-in's amplitude/phase outputs.
    back : ndarray, shape (4 + n, n_ch * n_tones)
        Scratch of the waveform rebuild (see :func:`_rebuild`).
    H : ndarray, shape (n_ch, n_tones, n_est, 1 + n_seg, 2)
        Observer matrices (real, imaginary) in use; all zero for an unused tone slot.
    Hc : ndarray, shape (n_ch, n_tones, n_loads, n_est, 1 + n_seg, 2)
        The observer matrices of each candidate load at the images (``H`` is a copy of one).
    pick : ndarray int64, shape (n_ch,)
        The candidate each channel's ``H`` holds; updated.
    resid : ndarray, shape (n_ch, 3, n_loads)
        Each candidate's smoothed loss of the blocks' votes, scratch, and (``resid[c, 2, 0]``) the
        candidate with a finger in use when the free one took over; updated.
    contact : ndarray, shape (n_ch, n_tones, N_CONTACT)
        Per tone, for the force test of :func:`_pick_load`: the candidate without a finger (-1:
        none), the least squared impedance the others put on the tip, the free beam's squared
        tip per drive volt (``C_FREE``, ``C_Z2``, ``C_G2``).
    lag : ndarray, shape (n_ch,)
        Each channel's smoothing of the votes per block (``Observer.lag``).
    scale : ndarray, shape (n_ch,)
        ``2 / window`` of each channel: lock-in sum to phasor.
    est : ndarray, shape (n_ch, n_tones, n_est, 2)
        Written: estimate phasors (real, imaginary) over the last complete window, of the first
        ``n_est`` rows of ``H`` (a caller that reads the tip alone passes one row).
    wave : ndarray, shape (n_ch, n)
        Written: tip deflection rebuilt from the row-0 estimates on this block's samples, m.
    pf, pf_z, pf_x : ndarray, shapes (n_ch * (1 + n_seg), 5), (..., 2), (..., n)
        The low-pass of drive (rows ``0 .. n_ch - 1``) and currents (then rows ``ch * n_seg +
        seg``): coefficients, state and the filtered block (:func:`_prefilter`). The observer
        matrices take its response at each tone out of the estimates. No rows: no channel is
        low-passed, and drive and currents go to the lock-ins as they are.
    pf_g : ndarray, shape (n_ch, n_tones, 2)
        ``1 / |G|`` and ``arg G`` of that response at each tone (1 and 0 unfiltered): ``u_out``
        is the drive's, as sent.
    d_acc : ndarray, shape like ``u_acc``
        The drive's first difference (as the drive's lock-in reads the drive, after the
        low-pass) over the same windows, as a lock-in's sums: rows ``ACC_R``, ``ACC_I`` the edge
        term of each slot's window (kept every block), ``S`` its window sum ``J S_u + (E - E')``
        and ``X`` that solved as the drive's is (``lockin_process_edges``; formed only where
        ``Kc`` has rows); ``HOP``, ``NHOP``, ``LSQ`` as ``u_acc``'s.
    d_edge : ndarray, shape like ``u_ring``
        Each hop's edge term ``E`` (``lockin_process_edges``); updated.
    invJ : ndarray, shape (n_ch, n_tones, 2)
        ``1 / (1 - exp(-j w / fs))`` per slot (real, imaginary): a steady tone's first
        difference over its phasor, inverted.
    Kc : ndarray, shape (n_ch or 0, n_tones, n_loads, n_est, 2)
        Per candidate load, what a drive step's boundary term (``D J^-1 - U``, drive volts) puts
        in each estimate row through the currents (``Observer._steps_design``); taken out. No rows:
        nothing is taken out, and the first difference is not demodulated.
    drive : ndarray, shape (n_ch, n)
        Drive volts written to the DAC for this block.
    sensed : ndarray, shape (n_ch * n_seg, n)
        ADC current readings of this block, A.

    Returns
    -------
    int
        0, or ``STATUS_NONFINITE`` if any estimate is NaN/Inf.
    """
    # (the drive's lock-in keeps its hops' edge terms too: what the first difference's window sums
    # need beyond the drive's, one product per slot and hop instead of a third lock-in)
    if pf.shape[0] == 0:  # no channel low-passed: the lock-ins read the block as it came
        _dk.lockin_process_edges(u_ref, u_pend, u_chan, u_acc, u_ring, u_solve, drive, u_out, d_edge, d_acc)
        _dk.lockin_sums(i_ref, i_pend, i_chan, i_acc, i_ring, i_solve, sensed)
    else:
        n_d = drive.shape[0]
        _prefilter(pf, pf_z, drive, pf_x, 0)
        _prefilter(pf, pf_z, sensed, pf_x, n_d)
        _dk.lockin_process_edges(u_ref, u_pend, u_chan, u_acc, u_ring, u_solve, pf_x[:n_d], u_out, d_edge, d_acc)
        for c in range(u_out.shape[0]):
            for k in range(u_out.shape[1]):
                u_out[c, k, 0] *= pf_g[c, k, 0]
                u_out[c, k, 1] -= pf_g[c, k, 1]
        _dk.lockin_sums(i_ref, i_pend, i_chan, i_acc, i_ring, i_solve, pf_x[n_d:])
    steps = Kc.shape[0] > 0
    if steps:
        for s in range(u_acc.shape[1]):
            # J = 1 - exp(-j w), w the reference's step per sample
            jr = 1.0 - u_ref[_WR, s]
            ji = u_ref[_WI, s]
            sr = u_acc[_SR, s]
            si = u_acc[_SI, s]
            d_acc[_SR, s] = jr * sr - ji * si + d_acc[_AR, s]
            d_acc[_SI, s] = jr * si + ji * sr + d_acc[_AI, s]
            d_acc[_ZAR, s] = u_acc[_ZAR, s]
            d_acc[_ZAI, s] = u_acc[_ZAI, s]
        _dk._lockin_sums_out(d_acc, u_solve)
    if Hc.shape[2] > 1:
        _pick_load(u_acc, i_acc, H, Hc, pick, resid, contact, lag, scale)
    n_ch, n_t, n_est = est.shape[0], est.shape[1], est.shape[2]
    n_seg = H.shape[3] - 1
    status = 0
    for c in range(n_ch):
        sc = scale[c]
        for k in range(n_t):
            us = c * n_t + k
            dr = sc * u_acc[_XR, us]
            di = sc * u_acc[_XI, us]
            for e in range(n_est):
                hr = H[c, k, e, 0, 0]
                hi = H[c, k, e, 0, 1]
                est[c, k, e, 0] = hr * dr - hi * di
                est[c, k, e, 1] = hr * di + hi * dr
            # segment by segment, each current's phasor scaled once; every estimate still sums
            # drive, then segments in order
            for j in range(n_seg):
                js = (c * n_seg + j) * n_t + k
                sr = sc * i_acc[_XR, js]
                si = sc * i_acc[_XI, js]
                for e in range(n_est):
                    hr = H[c, k, e, 1 + j, 0]
                    hi = H[c, k, e, 1 + j, 1]
                    est[c, k, e, 0] += hr * sr - hi * si
                    est[c, k, e, 1] += hr * si + hi * sr
            if steps:
                # the boundary term of a drive step, in drive volts: what the difference's phasor
                # says the drive was, less what the drive's says; 0 for a steady tone
                qr = sc * d_acc[_XR, us]
                qi = sc * d_acc[_XI, us]
                jr = invJ[c, k, 0]
                ji = invJ[c, k, 1]
                br = qr * jr - qi * ji - dr
                bi = qr * ji + qi * jr - di
                q = pick[c]
                for e in range(n_est):
                    kr = Kc[c, k, q, e, 0]
                    ki = Kc[c, k, q, e, 1]
                    est[c, k, e, 0] -= kr * br - ki * bi
                    est[c, k, e, 1] -= kr * bi + ki * br
            for e in range(n_est):
                if not (np.isfinite(est[c, k, e, 0]) and np.isfinite(est[c, k, e, 1])):
                    status |= STATUS_NONFINITE
    _rebuild(u_ref, est, back, wave)
    return status


@kernel
def _prefilter(pf, z, x, y, r0):
    """Row ``r`` of ``x`` through biquad ``r0 + r`` into ``y[r0 + r]`` (transposed direct form
    II, as ``scipy.signal.lfilter``): ``pf[r0 + r] = (b0, b1, b2, a1, a2)``, ``a0 = 1``; ``z[r0 +
    r]`` its two states, carried from block to block. A row of ``(1, 0, 0, 0, 0)`` is copied.
    A non-finite reading goes through as one non-finite sample and clears the state (a state
    that held it would poison every later sample, where the lock-in forgets it after a window)."""
    for r in range(x.shape[0]):
        q = r0 + r
        b0, b1, b2, a1, a2 = pf[q, 0], pf[q, 1], pf[q, 2], pf[q, 3], pf[q, 4]
        if b0 == 1.0 and b1 == 0.0 and b2 == 0.0 and a1 == 0.0 and a2 == 0.0:
            for n in range(x.shape[1]):
                y[q, n] = x[r, n]
            continue
        z0, z1 = z[q, 0], z[q, 1]
        for n in range(x.shape[1]):
            xn = x[r, n]
            yn = b0 * xn + z0
            z0 = b1 * xn - a1 * yn + z1
            z1 = b2 * xn - a2 * yn
            if not (np.isfinite(z0) and np.isfinite(z1)):
                z0 = 0.0
                z1 = 0.0
            y[q, n] = yn
        z[q, 0], z[q, 1] = z0, z1


@kernel
def _pick_load(u_acc, i_acc, H, Hc, pick, resid, contact, lag, scale):
    """Per channel, the candidate load at the images whose observer reads the tip as that load
    would leave it: free of a moment, and free of a force where the candidate has no finger.

    The aliased images of the drive (2 fs +- f and beyond) see the tip's load at tens of kHz, where
    any skin in contact pins the tip and none leaves it free: a beam with a mode near an image
    band reads its currents through a different image term with the finger on or off (a 25 mm
    beam lifted, read with the finger's images, 2.6-8.2 % off). Neither load puts a moment on the
    tip, so the tip moment a candidate's observer reads is its residual (squared, summed over the
    channel's tones). A block whose least residual is under :data:`DECISIVE` of another's votes:
    every candidate that far above the least loses (``resid[c, 1]`` 1), the rest win (0: the 50 g
    and 200 g sets of a finger pin the tip nearly alike, and often neither stands out), and the
    losses are smoothed (``resid[c, 0]``, a first-order lag ``lag[c]`` per block: over half the
    channel's window, at least ``rt.LOAD_LAG_S``). A vote is scale-free: a window straddling a
    drive step (whose residuals jump 10-100 fold for every candidate alike) weighs no more than
    any other block; and where noise decides (10 Hz at 10 V, or 250 Hz at 1 V, with 1 uV of sense
    noise), or a transient that no candidate explains, no candidate stands out and nothing is
    voted. A candidate takes over when its smoothed loss is under :data:`SWITCH` of the one in
    use's; a silent or non-finite window changes nothing. The candidates' matrices differ in the
    drive's column alone (the images enter with the drive; :class:`~rtctl.selfsense.rt.Observer`
    checks it).

    Before the moments, the force: the candidate without a finger (``contact[..., C_FREE]``) reads
    a tip force ``F`` and tip ``x``; ``sum |F|^2`` over :data:`TOUCH` squared times ``sum Z^2 |x|^2``
    (``C_Z2``: the least force a finger of the candidates would push that tip with) votes against
    it, under :data:`FREE` squared times that against every other candidate, and in between the
    moments vote; only where ``sum |x|^2`` is at most :data:`DRIVEN` squared times ``sum G^2 |D|^2``
    (``C_G2``: the free beam's tip at the window's drive ``D``), a tip the drive explains.
    """
    n_ch, n_t = H.shape[0], H.shape[1]
    n_seg = H.shape[3] - 1
    n_q = Hc.shape[2]
    for c in range(n_ch):
        sc = scale[c]
        for q in range(n_q):
            resid[c, 1, q] = 0.0
        free = -1
        f2 = 0.0   # the free candidate's squared tip force, summed over the tones
        z2 = 0.0   # the least squared force a finger of the candidates would push that tip with
        x2 = 0.0   # the free candidate's squared tip
        g2 = 0.0   # the free beam's squared tip at the window's drive
        for k in range(n_t):
            # the currents' share of the moment is every candidate's (only the drive's column
            # holds the images), so it is summed once
            cr = 0.0
            ci = 0.0
            for j in range(n_seg):
                js = (c * n_seg + j) * n_t + k
                sr = sc * i_acc[_XR, js]
                si = sc * i_acc[_XI, js]
                hr = Hc[c, k, 0, ROW_MOMENT, 1 + j, 0]
                hi = Hc[c, k, 0, ROW_MOMENT, 1 + j, 1]
                cr += hr * sr - hi * si
                ci += hr * si + hi * sr
            us = c * n_t + k
            dr = sc * u_acc[_XR, us]
            di = sc * u_acc[_XI, us]
            for q in range(n_q):
                hr = Hc[c, k, q, ROW_MOMENT, 0, 0]
                hi = Hc[c, k, q, ROW_MOMENT, 0, 1]
                tr = cr + hr * dr - hi * di
                ti = ci + hr * di + hi * dr
                resid[c, 1, q] += tr * tr + ti * ti
            q = int(contact[c, k, C_FREE])
            if q >= 0:
                free = q
                fr = Hc[c, k, q, ROW_FORCE, 0, 0] * dr - Hc[c, k, q, ROW_FORCE, 0, 1] * di
                fi = Hc[c, k, q, ROW_FORCE, 0, 0] * di + Hc[c, k, q, ROW_FORCE, 0, 1] * dr
                xr = Hc[c, k, q, 0, 0, 0] * dr - Hc[c, k, q, 0, 0, 1] * di
                xi = Hc[c, k, q, 0, 0, 0] * di + Hc[c, k, q, 0, 0, 1] * dr
                for j in range(n_seg):
                    js = (c * n_seg + j) * n_t + k
                    sr = sc * i_acc[_XR, js]
                    si = sc * i_acc[_XI, js]
                    fr += Hc[c, k, q, ROW_FORCE, 1 + j, 0] * sr - Hc[c, k, q, ROW_FORCE, 1 + j, 1] * si
                    fi += Hc[c, k, q, ROW_FORCE, 1 + j, 0] * si + Hc[c, k, q, ROW_FORCE, 1 + j, 1] * sr
                    xr += Hc[c, k, q, 0, 1 + j, 0] * sr - Hc[c, k, q, 0, 1 + j, 1] * si
                    xi += Hc[c, k, q, 0, 1 + j, 0] * si + Hc[c, k, q, 0, 1 + j, 1] * sr
                f2 += fr * fr + fi * fi
                z2 += contact[c, k, C_Z2] * (xr * xr + xi * xi)
                x2 += xr * xr + xi * xi
                g2 += contact[c, k, C_G2] * (dr * dr + di * di)
        total = 0.0
        for q in range(n_q):
            total += resid[c, 1, q]
        if not (total > 0.0 and total < np.inf):
            continue
        known = free >= 0 and z2 > 0.0 and z2 < np.inf and f2 < np.inf and x2 <= DRIVEN * DRIVEN * g2
        tie = -1
        if known and f2 < FREE * FREE * z2:          # no finger: every finger's candidate loses
            for q in range(n_q):
                resid[c, 1, q] = 0.0 if q == free else 1.0
        else:
            # a finger: the free candidate loses, and the moments vote among the others
            out = free if known and f2 > TOUCH * TOUCH * z2 else -1
            win = -1
            worst = 0.0
            for q in range(n_q):
                if q != out:
                    if win < 0 or resid[c, 1, q] < resid[c, 1, win]:
                        win = q
                    worst = max(worst, resid[c, 1, q])
            least = resid[c, 1, win]
            decisive = least < DECISIVE * worst
            if out < 0 and not decisive:
                continue                               # no candidate stands out: no vote
            for q in range(n_q):
                resid[c, 1, q] = 1.0 if q == out or (decisive and least < DECISIVE * resid[c, 1, q]) else 0.0
            # leaving the free tip on a vote that leaves the finger's candidates even: the one in
            # use when the finger lifted
            if out == free and pick[c] == free and not decisive:
                last = int(resid[c, 2, 0])
                if last != free and 0 <= last < n_q:
                    tie = last
        a = lag[c]
        for q in range(n_q):
            resid[c, 0, q] += a * (resid[c, 1, q] - resid[c, 0, q])
        cur = pick[c]
        best = cur
        for q in range(n_q):
            if resid[c, 0, q] < resid[c, 0, best]:
                best = q
        if tie >= 0 and resid[c, 0, tie] <= resid[c, 0, best] + TIE:
            best = tie
        if best != cur and resid[c, 0, best] < SWITCH * resid[c, 0, cur]:
            if best == free:
                resid[c, 2, 0] = cur  # the finger's candidate to come back to
            use_load(H, Hc, pick, c, best)


@kernel
def use_load(H, Hc, pick, c, q):
    """Channel ``c`` reads through candidate ``q`` from now on: its matrices copied into ``H``."""
    for k in range(H.shape[1]):
        for e in range(H.shape[2]):
            for j in range(H.shape[3]):
                H[c, k, e, j, 0] = Hc[c, k, q, e, j, 0]
                H[c, k, e, j, 1] = Hc[c, k, q, e, j, 1]
    pick[c] = q


@kernel
def _rebuild(u_ref, est, back, wave):
    """Tip deflection on the block's samples from the row-0 estimates: ``x[m] = Re(X z[m])``, with
    ``z`` of the next sample the reference's (``ZR``, ``ZI``) and earlier samples stepping back by
    the conjugate per-sample rotation (steady tones).

    Each slot's phasor is a recursion over the samples; run with the slots innermost, the slots'
    recursions are independent lanes of one vector instead of one dependent chain each. ``back``
    holds the state: rows 0-1 the phasors, 2-3 the estimates, ``4 + m`` the sample ``m`` of every
    channel's wave (``wave`` transposed, so that the slot loop writes contiguously), copied into
    ``wave`` at the end. An estimate of exactly zero (an unused slot) adds zeros: the same wave.
    Under :data:`_LANES` slots that bookkeeping costs more than the chains (0.39 against 0.12 us
    for one slot, even at 8), and each slot runs its own chain instead: the same operations.
    """
    n_ch, n_t = est.shape[0], est.shape[1]
    n = wave.shape[1]
    if n_ch * n_t < _LANES:
        _rebuild_chains(u_ref, est, wave)
        return
    for c in range(n_ch):
        for k in range(n_t):
            us = c * n_t + k
            back[0, us] = u_ref[_ZR, us]
            back[1, us] = u_ref[_ZI, us]
            back[2, us] = est[c, k, 0, 0]
            back[3, us] = est[c, k, 0, 1]
    for m in range(n):
        for c in range(n_ch):
            back[4 + m, c] = 0.0
    for m in range(n - 1, -1, -1):
        for k in range(n_t):
            for c in range(n_ch):
                us = c * n_t + k
                zr = back[0, us]
                zi = back[1, us]
                wr = u_ref[_WR, us]
                wi = -u_ref[_WI, us]
                t = zr * wr - zi * wi
                zi = zr * wi + zi * wr
                zr = t
                back[0, us] = zr
                back[1, us] = zi
                back[4 + m, c] += back[2, us] * zr - back[3, us] * zi
    for c in range(n_ch):
        for m in range(n):
            wave[c, m] = back[4 + m, c]


@kernel
def _rebuild_chains(u_ref, est, wave):
    """:func:`_rebuild` one slot at a time, its samples one dependent chain."""
    n_ch, n_t = est.shape[0], est.shape[1]
    n = wave.shape[1]
    for c in range(n_ch):
        for m in range(n):
            wave[c, m] = 0.0
        for k in range(n_t):
            us = c * n_t + k
            xr, xi = est[c, k, 0, 0], est[c, k, 0, 1]
            zr, zi = u_ref[_ZR, us], u_ref[_ZI, us]
            wr, wi = u_ref[_WR, us], -u_ref[_WI, us]
            for m in range(n - 1, -1, -1):
                t = zr * wr - zi * wi
                zi = zr * wi + zi * wr
                zr = t
                wave[c, m] += xr * zr - xi * zi
