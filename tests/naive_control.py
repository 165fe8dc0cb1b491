"""Naive twin of rtctl.control._kernels.amplitude_control: the same rules, written plainly."""

import cmath
import math

import numpy as np

from rtctl.control._kernels import (
    A0,
    AGREE,
    ALL,
    AMAX,
    ANCHOR,
    ANCHOR_RATE,
    BANK,
    BEFORE,
    BIG_STEP,
    CHANGED,
    CHANNEL,
    CMD,
    DEADBAND,
    ENABLE,
    EST,
    EXT_GAIN,
    FAR,
    FF,
    FITY,
    FROZEN,
    FSWING,
    GAIN,
    GHAT,
    GLIVE,
    GMAX,
    GTOP,
    HIGH,
    HIST,
    HOLD,
    HOLD0,
    HOLDMAX,
    JNOISE,
    LASTDIR,
    LATB,
    LIFTED,
    LIMSEEN,
    LIVE_DRIVE,
    LOW,
    LOWN,
    MAX_STEP,
    NALL,
    NH,
    NOISE,
    NOISE_Z,
    NPULSE,
    NREL,
    NSTR,
    NWATCH,
    OBS_CH,
    OBS_SLOT,
    ON,
    OUT,
    P1I,
    P1R,
    P1V,
    P2I,
    P2R,
    PATIENCE,
    PREVY,
    PULSE,
    PULSE_DEPTH,
    PULSE_LONG,
    PULSE_MIN,
    PULSE_NEAR,
    PULSE_RES,
    PULSE_TURN,
    PULSED,
    PULSES,
    REF,
    REFV,
    RELEASE,
    RELEASE_AFTER,
    RELEASE_RUN,
    RELNOW,
    REVERSAL,
    REVS,
    RING_K,
    RING_MOVE,
    RING_NOISE,
    RING_RES,
    RING_RHO,
    RINGED,
    RIPPLE,
    RIPPLE_DECAY,
    RIPPLE_K,
    RISE,
    RISEK,
    RMI,
    RMR,
    ROT,
    RPI,
    RPR,
    RREF,
    RRUN,
    RSAME,
    RSI,
    RSR,
    RSUM,
    RUN,
    SAT,
    SCATTER,
    SLOW,
    SPREV,
    SQ,
    START,
    STEPPED,
    STILL,
    SUM,
    SUMI,
    SUMR,
    TARGET,
    TPREV,
    TRIES,
    TURN,
    TURNS,
    W_MAX,
    WAIT,
    WAMP,
    WARM,
    WINS,
)
from rtctl.dsp._kernels import P_AMP, P_FLAG, P_RAMP
from rtctl.safety import CONTROL_FLOOR, CONTROL_FROZEN, CONTROL_SATURATED


def _pace_anew(col):
    col[HOLD], col[LASTDIR], col[REVS] = col[HOLD0], 0.0, 0.0


def _watch_anew(col):
    col[REF] = col[SUM] = col[SQ] = col[RUN] = col[TRIES] = col[ALL] = col[NALL] = 0.0
    col[SUMR] = col[SUMI] = col[NSTR] = col[SPREV] = col[ANCHOR] = col[PREVY] = col[NWATCH] = col[HIGH] = 0.0
    col[NH] = col[FITY] = col[RINGED] = col[NPULSE] = 0.0


def _let_go(col, y, r, a, waiting=False):
    """The release rule: a rise of the estimate above the anchor (the first on-target estimate,
    moved a little towards each later one), or while waiting
    out a correction's window (and after it, until an estimate comes on target) above what the
    correction explains."""
    if not (0 < y < math.inf and r > 0) or col[JNOISE] < 0:
        return False
    if col[LIFTED] != 0 and not waiting and a * col[GMAX] > (1 + RELEASE) * r:  # the test saw the free beam ring
        col[HIGH], col[PREVY] = RELEASE_RUN, y
        return True
    rip = col[RIPPLE]
    base = col[ANCHOR] if col[ANCHOR] > 0 and not waiting else col[BEFORE]
    col[NWATCH] += 1
    high = (col[NWATCH] >= RELEASE_AFTER and base > 0
            and y - base > RELEASE * r + col[JNOISE] + RIPPLE_K * rip and a * col[GMAX] > (1 + RELEASE) * r)
    col[HIGH] = col[HIGH] + 1 if high else 0.0
    if not high and not waiting:
        if col[PREVY] > 0:
            col[RIPPLE] = max(col[PREVY] - y, RIPPLE_DECAY * rip)
        if abs(y / r - 1) <= AGREE:
            # the first on target is the anchor; later ones move it by ANCHOR_RATE / WARM of the way
            col[ANCHOR] = y if col[ANCHOR] <= 0 else col[ANCHOR] + min(1.0, ANCHOR_RATE / col[WARM]) * (y - col[ANCHOR])
        elif y < r and a >= col[AMAX]:  # saturated under the target: a rise counts from the target
            col[ANCHOR] = r
    col[PREVY] = y
    return col[HIGH] >= RELEASE_RUN


def _release(col, y, r):
    """The finger let go: the drive for the most responsive load, a new command's watch."""
    col[EST], col[GHAT] = y, col[GMAX]
    col[GLIVE] = col[RSUM] = col[RRUN] = col[RREF] = 0.0
    col[NREL] += 1
    _watch_anew(col)
    _pace_anew(col)
    col[WAIT], col[BEFORE], col[RELNOW] = col[WARM], 0.0, 1.0
    return r / col[GMAX]


def _others_let_go(state, index, target, pending, ramp, stepped):
    """Where a tone released, every other playing tone of its channel whose drive overshoots on
    the lifted beam releases too, in the same block."""
    for i in np.flatnonzero(state[RELNOW]):
        for k in range(state.shape[1]):
            col, r = state[:, k], target[TARGET, k]
            if (k == i or index[OBS_CH, k] != index[OBS_CH, i] or not col[ON] or col[RELNOW] or col[JNOISE] < 0
                    or not r > 0 or col[CMD] * col[GMAX] <= (1 + RELEASE) * r):
                continue
            a = min(_release(col, col[EST], r), col[AMAX])
            col[RISEK], col[SAT], col[CMD] = col[RISE], 0.0, a
            if abs(a - col[OUT]) > AGREE * col[OUT]:
                stepped[k] = abs(a - col[OUT]) / col[OUT] if col[OUT] > 0 else 1.0
            col[OUT], col[PULSE] = a, 0.0
            b = index[BANK, k]
            pending[P_AMP, b], pending[P_RAMP, b], pending[P_FLAG, b] = a, ramp, 1.0


def _others_wait(state, index, stepped):
    """Every other playing tone read on the channel of a tone whose drive stepped (``stepped``:
    by how much, relative) waits a window afresh, watched against its own level and that step
    again."""
    for i in np.flatnonzero(stepped):
        for k in range(state.shape[1]):
            if k != i and index[OBS_CH, k] == index[OBS_CH, i] and state[ON, k]:
                state[BEFORE, k] = max(state[BEFORE, k] if state[WAIT, k] > 0 else 0.0,
                                       state[EST, k] * (1 + stepped[i]))
                state[WAIT, k] = max(state[WAIT, k], state[WARM, k])
                _watch_anew(state[:, k])


def _ring_end(p1, p2, a, v1, v2, v3):
    """Aitken's delta-squared on three complex stretch means, or -1 (no clear decaying ring)."""
    d1, d2 = p2 - p1, a - p2
    if abs(d1) > NOISE_Z * math.sqrt(v2 + v1) and abs(d2) > NOISE_Z * math.sqrt(v3 + v2) and abs(d2) <= W_MAX * abs(d1):
        w = d2 / d1
        if abs(w / (1 - w)) <= EXT_GAIN and abs(math.sin(cmath.phase(w))) >= TURN:
            return abs(a + w * d2 / (1 - w))
    return -1.0


def _ring_fit(col):
    """The last RING_K fresh estimates as a steady phasor and one real mode's ring: after turning
    the first differences back by the tone's own turn per block, each is a real combination of
    the two before it (least squares over real and imaginary parts); the steady phasor is what
    that recursion leaves fixed. Returns its amplitude, or -1."""
    k = int(col[NH]) % RING_K
    w = np.roll(col[HIST:HIST + 2 * RING_K:2] + 1j * col[HIST + 1:HIST + 2 * RING_K:2], -k)  # oldest first
    if not np.abs(w - w[-1]).max() > max(0.5 * STILL * abs(w[-1]), RING_NOISE * col[NOISE]):
        return -1.0  # estimates that barely move, or move by their noise, hold no ring worth fitting
    d = np.diff(w)
    x = d * np.exp(1j * col[ROT] * np.arange(d.size))
    m = np.column_stack([x[1:-1], x[:-2]])
    m, rhs = np.vstack([m.real, m.imag]), np.r_[x[2:].real, x[2:].imag]
    g = m.T @ m
    if not np.linalg.det(g) > 1e-9 * g[0, 0] * g[1, 1]:
        return -1.0
    coef = np.linalg.solve(g, m.T @ rhs)
    if not np.sum((m @ coef - rhs) ** 2) <= RING_RES ** 2 * np.sum(np.abs(d) ** 2):
        return -1.0
    roots = np.roots([1.0, -coef[0], -coef[1]]) * np.exp(-1j * col[ROT])
    if not (np.abs(roots).max() <= RING_RHO and np.abs(1.0 - roots).min() >= RING_MOVE):
        return -1.0
    c1, c2 = coef[0] * np.exp(-1j * col[ROT]), coef[1] * np.exp(-2j * col[ROT])
    steady = np.mean(w[2:] - c1 * w[1:-1] - c2 * w[:-2]) / (1.0 - c1 - c2)
    col[FSWING] = np.abs(w - steady).max()
    if not (col[FSWING] > STILL * abs(steady) and abs(steady) < math.inf):
        return -1.0
    # the ring's two halves at the last two estimates: the one turning least (the mode's own) now
    main, other = sorted(roots, key=lambda p: abs(cmath.phase(p)))
    if main != other:
        now = np.linalg.solve(np.array([[1.0, 1.0], [1.0 / main, 1.0 / other]]), w[-1:-3:-1] - steady)[0]
    else:
        now = 0j
    # the same ring as the block before's fit, carried one block on?
    was = complex(col[RMR], col[RMI]) * complex(col[RPR], col[RPI])
    col[RSAME] = float(col[FITY] > 0 and abs(now - was) <= PULSE_RES * abs(now))
    col[RMR], col[RMI], col[RPR], col[RPI], col[RSR], col[RSI] = now.real, now.imag, main.real, main.imag, \
        steady.real, steady.imag
    return abs(steady)


def _pulse(col, block):
    """The pulse that cancels the fitted ring: the ring now (through the window's own sum of its
    turning, carried on to the step's block), and of every pulse length within a quarter and
    three quarters of its period, the one whose real step leaves least of it. Returns (d, h), h = 0:
    none."""
    p, steady = complex(col[RPR], col[RPI]), complex(col[RSR], col[RSI])
    phi = cmath.phase(p)
    if not (0 < abs(phi) <= min(PULSE_TURN, 2 * math.pi * PULSE_NEAR * col[TURNS]) and abs(steady) > 0):
        return 0.0, 0
    seen = np.mean(np.exp(-1j * phi / block * np.arange(int(col[WINS]))))  # the window, sample by sample
    if not abs(seen) >= 0.5:
        return 0.0, 0
    lead = col[LATB] - 0.5
    x = complex(col[RMR], col[RMI]) / seen * abs(p) ** lead * cmath.exp(1j * phi * lead) / steady
    shown = abs(np.mean(np.exp(-1j * phi / block * np.arange(int(col[WAMP])))))  # in the tone's amplitude
    if not (abs(x) * shown >= PULSE_MIN and col[RSAME]):
        return 0.0, 0
    period = 2 * math.pi / abs(phi)
    best = None
    for h in range(max(1, math.ceil(period / 4)), min(PULSE_LONG, math.floor(3 * period / 4)) + 1):
        q = 1 - p ** -h
        d = (x * q.conjugate()).real / abs(q) ** 2
        if abs(d) <= PULSE_DEPTH and (best is None or abs(x - d * q) <= best[0]):
            best = (abs(x - d * q), d, h)
    if best is None or best[0] > PULSE_RES * abs(x):
        return 0.0, 0
    return best[1], best[2]


def amplitude_control(est, drive_est, index, target, state, pending, lim_counts, ramp):
    status = 0
    stepped = np.zeros(state.shape[1])
    state[RELNOW] = 0.0
    for i in range(state.shape[1]):
        b = index[BANK, i]
        col = state[:, i]
        if target[ENABLE, i] == 0:
            col[LOW] = 0.0
            if col[ON]:
                stepped[i] = 1.0
                col[ON] = col[CMD] = col[OUT] = col[PULSE] = 0.0
                pending[P_AMP, b], pending[P_RAMP, b], pending[P_FLAG, b] = 0.0, ramp, 1.0
            continue
        r = target[TARGET, i]
        pulse = None  # (step, blocks) of a ring-cancelling pulse made in this block
        lim = float(lim_counts[:, index[CHANNEL, i]].sum())
        limited, col[LIMSEEN] = lim != col[LIMSEEN], lim
        a = col[CMD]
        c, j = index[OBS_CH, i], index[OBS_SLOT, i]
        rising = col[RISEK] < col[RISE]
        if col[ON] and not rising:
            u, y = drive_est[c, j, 0], math.hypot(*est[c, j, 0])
            if u >= LIVE_DRIVE * a and u > 0 and 0 < y < math.inf:
                col[RSUM] += y / u
                col[RRUN] += 1
                if col[RRUN] >= col[HOLD]:
                    m = col[RSUM] / col[RRUN]
                    if col[RREF] > 0 and abs(m / col[RREF] - 1) <= AGREE:
                        col[GLIVE] = m
                    col[RREF], col[RSUM], col[RRUN] = m, 0.0, 0.0
        starting = not col[ON]
        if not starting and r != col[TPREV] and col[GLIVE] > 0:
            a = r / col[GLIVE]
            col[TPREV], col[WAIT], col[BEFORE] = r, col[WARM] + max(0.0, col[RISE] - col[RISEK] - 1), 0.0
            _watch_anew(col)
            _pace_anew(col)
        elif starting or r != col[TPREV]:
            a = r / col[GHAT] if col[GHAT] > 0 else START * r * col[FF]
            if starting:
                col[RISEK], col[A0], rising = 0.0, 0.0, col[RISE] > 0
            col[ON], col[TPREV], col[WAIT] = 1.0, r, col[WARM] + max(0.0, col[RISE] - col[RISEK] - 1)
            col[BEFORE] = 0.0
            _watch_anew(col)
            _pace_anew(col)
        elif col[WAIT] > 0:
            col[WAIT] -= 1
            back = col[PULSE] > 0 and col[PULSE] == 1  # a pulse's last block: the drive returns
            col[PULSE] = max(col[PULSE] - 1, 0.0)
            if col[BEFORE] > 0 and _let_go(col, math.hypot(*est[c, j, 0]), r, a, waiting=True):
                a = _release(col, math.hypot(*est[c, j, 0]), r)
                if rising:
                    col[RISEK], rising = col[RISE], False
            else:
                if col[WAIT] == 0:
                    col[NWATCH] = col[PREVY] = col[HIGH] = 0.0
                if not rising and not back:
                    continue
        elif _let_go(col, math.hypot(*est[c, j, 0]), r, a):
            a = _release(col, math.hypot(*est[c, j, 0]), r)
        else:
            y = math.hypot(*est[c, j, 0])
            col[EST] = y
            if not (0 < y < math.inf and r > 0):
                col[FROZEN] = 1.0
                col[REF] = col[SUM] = col[SQ] = col[RUN] = col[ALL] = col[NALL] = 0.0
                col[SUMR] = col[SUMI] = col[NSTR] = col[SPREV] = 0.0
                col[ANCHOR] = col[PREVY] = col[NWATCH] = col[HIGH] = col[NH] = col[FITY] = 0.0
                status |= CONTROL_FROZEN
                continue
            col[FROZEN] = 0.0
            col[GHAT] = y / a
            col[TRIES] += 1
            fit = -1.0
            if col[ROT] >= 0:
                k = int(col[NH]) % RING_K
                col[HIST + 2 * k], col[HIST + 2 * k + 1] = est[c, j, 0]
                col[NH] += 1
                if col[NH] >= RING_K:
                    fit = _ring_fit(col)
            fit_before, col[FITY] = col[FITY], max(fit, 0.0)
            if fit > 0:  # a ring: the stretches wait, the fit's end is corrected on once it holds
                col[RINGED] = 1.0
                col[REF] = col[ALL] = col[NALL] = col[SUM] = col[SQ] = col[RUN] = 0.0
                col[SUMR] = col[SUMI] = col[NSTR] = col[SPREV] = 0.0
                if not (fit_before > 0 and abs(fit / fit_before - 1) <= STILL):
                    continue
                mean, g = fit, col[GAIN]
            else:
                col[SUM] += y
                col[SQ] += y * y
                col[SUMR] += est[c, j, 0, 0]
                col[SUMI] += est[c, j, 0, 1]
                col[RUN] += 1
                col[ALL] += y
                col[NALL] += 1
                if col[RUN] < col[HOLD]:
                    continue
                mean, prev, prev_var = col[SUM] / col[RUN], col[REF], col[REFV]
                var = max(col[SQ] / col[RUN] - mean * mean, 0.0) / col[RUN]
                phasor = complex(col[SUMR], col[SUMI]) / col[RUN]
                p1, p2 = complex(col[P1R], col[P1I]), complex(col[P2R], col[P2I])
                end, moving = -1.0, False
                if col[SLOW] and not col[RINGED]:
                    end = _ring_end(p1, p2, phasor, col[P1V], prev_var, var) if col[NSTR] >= 2 else -1.0
                    moving = (col[NSTR] >= 1
                              and abs(phasor - p2) > max(STILL * mean, NOISE_Z * math.sqrt(var + prev_var)))
                young, end_before = col[NSTR] < 2, col[SPREV]
                col[SPREV] = max(end, 0.0)
                col[P1R], col[P1I], col[P1V], col[P2R], col[P2I] = p2.real, p2.imag, prev_var, phasor.real, phasor.imag
                col[NSTR] += 1
                col[SUMR] = col[SUMI] = 0.0
                if prev > 0 and abs(mean / prev - 1) > CHANGED:
                    _pace_anew(col)
                col[REF], col[REFV], col[SUM], col[SQ], col[RUN] = mean, var, 0.0, 0.0, 0.0
                agree = prev > 0 and abs(mean / prev - 1) <= AGREE
                far_agree = (col[SCATTER] != 0 and abs(r / mean - 1) > FAR
                             and abs(mean - prev) <= NOISE_Z * math.sqrt(var + prev_var))
                if agree and moving and end < 0 and young:
                    continue
                if agree and moving and end > 0:
                    mean, g = end, col[GAIN]
                elif end > 0 and end_before > 0 and abs(end / end_before - 1) <= AGREE:
                    mean, g = end, col[GAIN]
                elif agree or (prev > 0 and far_agree):
                    if abs(r / mean - 1) <= AGREE and not moving:
                        mean = col[ALL] / col[NALL]
                    g = col[GAIN]
                elif col[TRIES] >= PATIENCE * (col[WARM] + 2 * col[HOLD]):
                    g = 0.5 * col[GAIN]
                else:
                    continue
            step = (r / mean) ** g
            if abs(step - 1) <= DEADBAND:
                col[TRIES] = 0.0
                _pace_anew(col)
                d, h = _pulse(col, ramp) if fit > 0 and col[NPULSE] < PULSES else (0.0, 0)
                if not (h > 0 and r / col[GTOP] <= a * (1 + d) <= col[AMAX]) or (limited and d > 0):
                    continue
                pulses = col[NPULSE] + 1
                _watch_anew(col)
                col[NPULSE], col[WAIT], col[BEFORE] = pulses, h + col[WARM], mean * (1 + abs(d)) + col[FSWING]
                col[PULSED] += 1
                pulse = (d, h)
            if pulse is None:  # off target: correct
                step = min(max(step, 1 / MAX_STEP), MAX_STEP)
                if limited and step > 1:
                    step = 1.0
                if (step > 1 and a >= col[AMAX]) or step == 1.0:  # nothing to change: watch on
                    col[TRIES] = 0.0
                    continue
                up = 1.0 if step > 1 else -1.0
                if not 1 / REVERSAL < step < REVERSAL:
                    _pace_anew(col)
                    col[LASTDIR] = up
                elif abs(step - 1) > AGREE:
                    if up == -col[LASTDIR]:
                        col[REVS] += 1
                        if col[REVS] >= 2:
                            col[HOLD] = min(2 * col[HOLD], col[HOLDMAX])
                    else:
                        col[REVS] = 0.0
                    col[LASTDIR] = up
                a *= step
                _watch_anew(col)
                col[WAIT], col[BEFORE] = col[WARM], mean * (max(1.0, step) + abs(step - 1))
                if fit > 0:
                    col[BEFORE] += col[FSWING]
                if not 1 / BIG_STEP <= step <= BIG_STEP and col[RISE] > 1:
                    col[A0], col[RISEK], rising = col[OUT], 0.0, True
                    col[WAIT] += col[RISE] - 1
        floor = r / col[GTOP]
        col[LOW] = float(a < floor < col[AMAX])
        a = max(a, floor)
        if a >= col[AMAX]:
            a = col[AMAX]
            col[SAT] = 1.0 if (col[EST] < r or col[WAIT] > 0) else 0.0
        else:
            col[SAT] = 0.0
        if col[SAT]:
            status |= CONTROL_SATURATED
        col[CMD] = a
        if rising:
            col[RISEK] += 1
            a = col[A0] + (a - col[A0]) * (1 - math.cos(math.pi * col[RISEK] / col[RISE])) / 2
        if pulse is not None:
            a *= 1 + pulse[0]
        if abs(a - col[OUT]) > AGREE * col[OUT]:
            stepped[i] = abs(a - col[OUT]) / col[OUT] if col[OUT] > 0 else 1.0
        col[OUT], col[PULSE] = a, 0.0 if pulse is None else pulse[1]
        pending[P_AMP, b], pending[P_RAMP, b], pending[P_FLAG, b] = a, ramp, 1.0
    _others_let_go(state, index, target, pending, ramp, stepped)
    _others_wait(state, index, stepped)
    state[STEPPED] = stepped
    state[LOWN] += state[LOW] != 0
    if np.any(state[LOW]):
        status |= CONTROL_FLOOR
    return status
