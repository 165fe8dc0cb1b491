"""The amplitude controller's block kernel (see :class:`rtctl.control.AmplitudeController`)."""

import cmath
import math

from .._numba import kernel
from ..dsp._kernels import P_AMP, P_FLAG, P_RAMP
from ..safety import CONTROL_FLOOR, CONTROL_FROZEN, CONTROL_SATURATED

# state rows, one column per controlled tone
(CMD,     # commanded amplitude, V peak (what the oscillator ramps to)
 FF,      # feedforward gain of the model, V per m of tip amplitude
 AMAX,    # the tone's share of the channel's max_voltage, V
 GAIN,    # correction exponent (1: the whole ratio r / y at once)
 WAIT,    # blocks left before the estimate answers the latest command
 WARM,    # blocks from a command to an estimate that holds nothing older (latency + window + 1)
 ON,      # 1 while the tone plays under control
 TPREV,   # the target the command was last set for, m
 SAT,     # 1: saturated at AMAX with the target out of reach
 FROZEN,  # 1: the last estimate was unusable; the command is held
 EST,     # the last estimate used, m
 LIMSEEN,  # the channel's limiter count when last seen (float copy)
 GHAT,    # tip per volt the last fresh estimate showed, m/V (0: none yet)
 REF,     # the mean of the last complete stretch of fresh estimates, m (0: none yet)
 RUN,     # fresh estimates in the present stretch
 HOLD,    # fresh estimates per stretch
 SUM,     # sum of the present stretch's estimates, m
 TRIES,   # fresh estimates since the last correction or the last on-target stretch
 ALL,     # sum of every fresh estimate of the present command, m
 NALL,    # how many
 GLIVE,   # tip per volt, the mean of the last stretch of windows that agreed with the one before, m/V
 RSUM,    # sum of the present stretch's tip per volt of each window (tip over the drive's lock-in)
 RRUN,    # windows in it
 RREF,    # the mean of the stretch before, m/V (0: none yet)
 RISE,    # blocks a start (or a big correction) rises over (raised cosine; 0 or 1: within one block)
 RISEK,   # blocks of the present rise done
 A0,      # the drive the present rise started from, V
 OUT,     # the drive last written, V
 SQ,      # sum of the squares of the present stretch's estimates, m^2
 REFV,    # the variance of the mean of the last complete stretch, m^2
 SCATTER,  # 1: a stretch spans at least one window (the spread of its estimates is their noise)
 HOLD0,   # the designed stretch, which HOLD returns to (HOLD grows while corrections hunt)
 HOLDMAX,  # the longest stretch HOLD may grow to
 LASTDIR,  # the direction of the last correction: +1 up, -1 down, 0 none since the pace was reset
 REVS,    # small corrections in a row, each reversing the one before
 SUMR,    # sums of the present stretch's estimates as phasors (real, imaginary part), m
 SUMI,
 P1R,     # the phasor mean of the stretch before the last one, m
 P1I,
 P2R,     # the phasor mean of the last complete stretch, m
 P2I,
 P1V,     # the variance of the mean of the stretch before the last one, m^2
 NSTR,    # complete stretches of the present command
 SPREV,   # the steady amplitude the last stretch extrapolated, m (0: none)
 SLOW,    # 1: a loaded mode rings beside the tone, turning less than half a beat per stretch
 STEPPED,  # the drive's relative change in this block where over AGREE, 1 from or to 0 (0: none; its
           # channel's other tones wait)
 GTOP,    # the most tip per volt a device may have at the tone, m/V (inf: no floor; see LOW)
 LOW,     # 1: the command is held at the floor, target / GTOP (the estimate asked for less)
 LOWN,    # blocks the command has been held at the floor since the controller's reset
 GMAX,    # the most tip per volt a device may have at the tone, m/V (GTOP without its margin)
 JNOISE,  # the release rule's noise allowance on a rise of the estimate, m (< 0: no release rule)
 ANCHOR,  # what a rise counts from: the first fresh estimate of this command within AGREE of the
          # target, moved towards each later one by ANCHOR_RATE / WARM (the target itself while
          # saturated under it), m (0: none)
 NREL,    # releases since the controller's reset
 PREVY,   # the previous watched block's fresh estimate, m (0: none since the last command)
 RIPPLE,  # how far fresh estimates fell from block to block of late, m (a decaying peak)
 NWATCH,  # blocks watched since the last command
 HIGH,    # fresh estimates in a row that rose as a release does
 BEFORE,  # while waiting out a correction's window: the most the estimate reads there on an unchanged
          # plant, the level corrected on times the step where it rose, and the step's size again
          # for the ring it may leave (0: not watched meanwhile), m
 RELNOW,  # 1: released in this block (its channel's other tones are released with it)
 ROT,     # the tone's own turn per block, rad (< 0: no ring fit for this tone)
 NH,      # fresh estimates of the present command pushed into the ring history
 FITY,    # the steady amplitude the ring fit found in the block before, m (0: none)
 FSWING,  # the largest distance of the fitted estimates from that steady phasor, m
 RINGED,  # 1: a ring fit stood for the present command (its stretches extrapolate no ring)
 NOISE,   # the rms noise of the tone's estimate, m (the sense chain's, 0: none known)
 WINS,    # the tone's observer window, samples
 LATB,    # blocks from a drive block to the currents answering it (the observer's latency)
 PULSE,   # blocks left until a ring-cancelling pulse's drive returns to CMD (0: no pulse)
 NPULSE,  # pulses since the present command's watch began
 RMR,     # the fitted ring's half nearest the tone at the latest estimate (real, imaginary), m
 RMI,
 RPR,     # its root per block (real, imaginary)
 RPI,
 RSR,     # the fit's steady phasor (real, imaginary), m
 RSI,
 RSAME,   # 1: the ring fitted in this block is the one of the block before, carried on by its root
 WAMP,    # samples a tone's amplitude is fitted over (``report.fit_window``: a ring it shows)
 TURNS,   # the tone's own turns per block, unwrapped (ROT is their fraction, in rad)
 PULSED,  # ring-cancelling pulses since the controller's reset
 LIFTED,  # 1: the block of currents read in this block showed the finger lift off (written by the
          # group's lift-off test, ``rtctl.selfsense.lift``, before this stage; 0: not, or no test)
 HIST,    # RING_K phasors (real, imaginary part), the latest fresh estimates, a circular buffer
 ) = range(81)

# target rows (written through the engine's parameter queue)
TARGET, ENABLE = 0, 1
N_TARGET = 2

# index rows
OBS_CH, OBS_SLOT, BANK, CHANNEL, SIBLING = 0, 1, 2, 3, 4
N_INDEX = 5

#: largest factor one correction may change a command by, either way (a wild estimate moves the
#: drive by at most this): a finger landing cuts a 1 kHz tip 12-14 fold and a lift-off multiplies
#: it 5-20 fold, which one correction then follows (with up to 4x, two or three corrections took
#: 52-96 ms, each waiting for its rise, the window and two stretches). That took 1 kHz windows
#: that reject the event's ring (the observer's ``MIN_PERIODS``): over 2 periods the ring biased
#: the estimates, the step of x1.66 that followed a x7 one rang +11.6 % over the target, and the
#: lift-offs settled slower (the corrections after a 16-fold drop chased the free beam's ring)
MAX_STEP = 16.0
#: two successive stretches of fresh estimates whose means agree within this say the plant is
#: steady (a window sliding over a change of the plant moves its estimate for a whole window;
#: correcting on it would chase it). The loaded beam's ripple after a finger lands or a command
#: steps (several % for tens of ms) mostly averages out within a stretch; what is left of it
#: makes a tighter bound wait stretch after stretch for no gain in accuracy: the correction
#: made on a mean within this is refined by the next one.
AGREE = 0.05
#: how many (wait + 2 stretches) may pass without two agreeing stretches before a correction is
#: made anyway, at half strength (a plant that keeps drifting is still followed)
PATIENCE = 4
#: the first command of a tone aims at this share of its target by the model: the model's finger
#: is a guess (a softer finger than it says lets a beam near its loaded resonance move up to 2x
#: more), so the tip starts below the target and feedback brings it there without overshoot
START = 0.7
#: the tip per volt of a window (tip estimate over the drive's lock-in over the same window) is
#: learned only while that drive is at least this share of the command: a window still filling
#: with a starting tone, or holding little drive, gives a ratio dominated by noise
LIVE_DRIVE = 0.25
#: a correction that changes the command by more than this factor (either way) rises to it as a
#: start does (``RISE``): its step of drive rings in a loaded mode beside the tone as a start's
#: does (a finger landing cuts a 1 kHz tip 20-fold; the corrections by 4x that follow rang up to
#: +11 % over the target). Smaller steps go in one block: the rise's wait would add to every
#: fine correction (the 120 Hz start's second command came 4-8 ms too late).
BIG_STEP = 2.0
#: far from the target (by more than this share) two stretches also agree when their means differ
#: by no more than NOISE_Z standard errors of that difference (from the spread within each, as if
#: the estimates were independent): after a finger lands at 1 kHz the tip is a tenth of its
#: target, its estimates scatter by +-50 %, and two stretches seldom agree within AGREE. A window
#: sliding over a change still moves the mean by more than sqrt(12) such errors between stretches,
#: so the loop still waits for it to pass. Near the target only AGREE counts (agreement within
#: noise would correct on noise). Only where a stretch spans a whole window (``SCATTER``): the
#: estimates of overlapping windows spread by what the plant did (a ring, the other sine of a beat
#: pair), not by noise. Figures: docs/control.md, "Stretches far from the target".
FAR = 0.1
NOISE_Z = 2.0
#: an error smaller than this is left alone: a correction blinds the loop for a window, and the
#: loop then answers a change of the plant a window later
DEADBAND = 0.002
#: hunting: two corrections in a row by more than AGREE and less than this factor (either way),
#: each reversing the one before, mean that two stretches agreed on the extremes of a beat of
#: the tone with a loaded mode (a mode 70 Hz away beats with a 500 Hz tone every 15 ms;
#: stretches of 4 blocks see its swing, not its mean), and each such correction rings the mode
#: again. From then on every such correction doubles the stretch (up to ``HOLDMAX``, half the
#: model's ring time), until the stretches average the beat out. Finer corrections (the last
#: percent or two of a noise-bound tone) neither count nor break the count. An on-target
#: stretch, a start or target step, a bigger correction and two stretches ``CHANGED`` apart (the
#: plant changed: an event) set the stretch back. Figures: docs/control.md, "Hunting beside a
#: loaded mode".
REVERSAL = 1.3
#: two successive stretches further apart than this share say the plant changed: the stretch
#: goes back to its designed length, so an event is answered at the designed pace
CHANGED = 4.0 * AGREE
#: a ring: two successive stretches whose phasor means differ by more than this share (and by
#: more than their noise) hold a plant still moving, even where their amplitudes agree within
#: AGREE. Beside a lightly damped loaded mode a step of drive rings for several of its time
#: constants; the tip's envelope beats slowly with the tone and moves a few % per stretch, so two
#: stretches agree on a point of the ring, not on the steady amplitude
STILL = 0.01
#: three successive stretch means of one command, P1, P2, A, that move as one decaying ring
#: (``A - P2 = w (P2 - P1)``, ``|w|`` at most this) extrapolate to its end: the steady phasor
#: ``A + w (A - P2) / (1 - w)`` (Aitken's delta-squared on complex means: exact for one mode's
#: ring, whatever its frequency and decay)
W_MAX = 0.95
#: and only where the rest of the ring, ``w / (1 - w)`` of the last step, is at most this many
#: steps: a window sliding over a change moves its estimate along a line that stops within a
#: stretch, and three means across that stop look like a ring that barely turns, with ``w`` near
#: 1 (up to 0.95: 19 steps more). A ring beside a loaded mode turns: 14 Hz from a 500 Hz tone,
#: with a 25 ms time constant, ``|w| = 0.87`` and 0.3 rad per 3.3 ms stretch, 2.9 steps more
EXT_GAIN = 4.0
#: and only where the three means turn, by at least this (sine of the angle of ``w``): a window
#: sliding over a change of the plant moves its estimate along a straight line, from the old
#: phasor to the new, and three means across the line's end have a ``w`` without a turn (up to
#: 0.8 within EXT_GAIN). A ring beside a loaded mode turns by its beat (0.3 rad per stretch
#: above); one exactly on its mode's frequency does not, and is left to the other rules
TURN = 0.1
#: a release: a fresh estimate that rises more than this share of the target (and more than its
#: noise, ``JNOISE``) above the on-target estimates of an unchanged command (``ANCHOR``, which
#: follows them slowly: ``ANCHOR_RATE``) says the finger
#: let go (lifts off, or presses lighter). Where the rule is on (a long window, and the lifted
#: beam the most responsive load the model knows: ``GMAX``), the drive drops at once to what puts
#: the target on that load, which no device the model allows overshoots with, and the loop
#: watches anew from there. Waiting for a window of the new load (100 ms at 10 Hz, 33 ms for a
#: 250 / 30 Hz beat pair) let a lifted tip swing at up to 3.7x its target; the window's first
#: blocks already show the rise. Figures: docs/control.md, "A finger that lets go".
RELEASE = 0.02
#: ... and by more than this many times what the estimate fell from one block to the next of
#: late (``RIPPLE``: the largest fall, decaying by ``RIPPLE_DECAY`` per watched block). After a
#: finger lands on a half-damped beam with a soft finger, the low-passed 80 Hz reading still
#: wobbles by a few % per block; each wobble read as a release dropped the drive, the loop raised
#: it again, and the tone was held 27 % low for a second. A wobble falls as far as it rises, so
#: its falls measure it; a finger letting go lifts the estimate block after block, and its own
#: rises, counted as well, had raised the bar the rise had to clear (the 40 Hz tone at its cap
#: released 21 blocks after the lift-off, +54 % over the target, median over the devices; on its
#: falls, +26 %)
RIPPLE_K = 2.0
RIPPLE_DECAY = 0.9
#: ... and not before this many fresh estimates of the command have been watched (two moves from
#: block to block seen: the ring a correction or an event leaves has shown its size)
RELEASE_AFTER = 3
#: ... in this many fresh estimates in a row. A finger pressing harder also lifts the first
#: estimate after it, by its static step (+4 % at 80 Hz on a 20 mm beam, and the next one 6 %
#: under the target); a lift-off keeps rising. On one estimate the drive had dropped 5x under the
#: pressing finger
RELEASE_RUN = 2
# While a correction's window slides past (``WAIT``), the estimate moves from the level the
# correction was made on to that times the step, no further on an unchanged plant but for the
# ring the step leaves (a window over a drive step reads as the tip's own lock-in does:
# docs/selfsense.md), so a finger letting go then shows as a rise over that (``BEFORE``) by the
# release's margins. Without this watch a lift-off in that window went unanswered until it passed
# (a 25 Hz tone on a 20 mm beam corrected 55 blocks before the lift-off released 60 blocks after
# it, its tip 5x its target).
#: The anchor a rise counts from: the first estimate of a command within AGREE of the target, and
#: each later one moves it this many WARMs (a window and its latency) of the way per block: a
#: finger's slow relaxation is followed, a lift-off's rise (the window filling with the lighter
#: load over WARM blocks) outruns it. When each estimate within AGREE became the anchor, a rise
#: that started slowly (a lift-off near the tip's zero crossing) carried it along and had to clear
#: 2 % above up to 1.05 of the target (10 Hz lift-offs +16 / +12 % over the target, worst / median
#: over the control sweep's devices; +12 / +6 % now)
ANCHOR_RATE = 4.0
#: the ring fit: the last RING_K fresh phasor estimates of one command, as a steady phasor and one
#: real mode's decaying ring. A mode at ``f_m`` rings in the tone's phasor at ``f_m - f`` and,
#: through the real signal's other half, at ``-(f_m + f)``: two roots per block of one size whose
#: angles add up to ``-2`` times the tone's own turn per block (``ROT``). Turned back by that turn
#: (``x[n] = d[n] exp(j ROT n)``, ``d`` the first differences, which leave the steady phasor out),
#: such a ring obeys ``x[n+2] = al x[n+1] + be x[n]`` with ``al`` and ``be`` real, fitted by least
#: squares over the real and imaginary parts; the steady phasor is what that recursion leaves
#: fixed, ``c0 / (1 - c1 - c2)`` (``c1 = al exp(-j ROT)``, ``c2 = be exp(-2j ROT)``, ``c0`` the
#: mean of ``w[n+2] - c1 w[n+1] - c2 w[n]``): exact for one real mode, whatever its frequency,
#: decay and the window's share of its other half. Beside a loaded mode 95 Hz from a 500 Hz tone
#: (half the damping, a soft finger) the estimates swing by +-30 % for 40 ms after a finger
#: presses, stretch means of half a beat alternate around the steady level, and the loop had
#: corrected only after 57 ms, or on two stretches that agreed on a point of the ring (-20 %,
#: wrong); the fit holds the steady level within 0.3 % from 9 ms after the press. Over 8
#: estimates instead of 10 it took a finger's slow relaxation for the steady level (500 Hz
#: presses on the control sweep's devices with damping x2 and a soft finger settled in 92-112 ms
#: against 40-42). Figures: docs/control.md, "A ring fitted".
RING_K = 10
N_STATE = HIST + 2 * RING_K
#: estimates that all lie within half of STILL of the latest, or within this many times the
#: estimate's noise (``NOISE``), are not fitted: most blocks, where the fit would find no ring
#: (a ring passes RING_RES only where its steps are some 20 times the noise's), and skipping them
#: keeps the fit's cost (0.16 us a tone) off steady tones
RING_NOISE = 10.0
#: the fit stands only where its prediction's residual is at most this share of the differences
#: (a window sliding over a change, noise or two modes leave more: 0.1-0.9 against 0.002-0.02 on
#: one mode's ring)
RING_RES = 0.05
#: ... both roots inside RING_RHO (a ring that decays) and at least RING_MOVE from 1 (a window
#: sliding over a change moves its estimate along a line: a root at 1)
RING_RHO = 0.995
RING_MOVE = 0.1
#: ... and the fitted estimates swing by more than STILL around the steady phasor (less is left
#: to the stretches: without this bound the control sweep's full grid missed 487 clauses, 477
#: with it). Two successive blocks' fits within STILL of each other are corrected on; while a
#: ring is fitted no stretch is (its means are points of the ring), and once one was, the
#: stretches of that command extrapolate no ring (``SLOW``): what the fit leaves of it is too
#: small, and three such means had read a ring's end 5 % off

#: A ring fitted on target (its steady level within DEADBAND) is cancelled by a pulse of drive:
#: a step of ``d`` of the drive, and back ``h`` blocks later. A step of drive leaves a ring of
#: minus the step it makes in the steady phasor (the tip cannot jump: measured within 1 % and
#: 0.02 rad beside a loaded mode 68 Hz from a 500 Hz tone), and the ring turns by ``P`` per
#: block, so the pulse leaves ``-d (1 - P^-h)`` of the steady phasor, which cancels a ring of
#: ``x`` (at the first step, relative to the steady phasor) for ``d = x / (1 - P^-h)``; ``d`` is
#: real (the drive's amplitude), so ``h`` is the one that leaves the least of ``x``. Only rings
#: fitted alike in two successive blocks (the one before carried on by its root, within
#: PULSE_RES), that the tone's amplitude (fitted over ``WAMP``) shows at PULSE_MIN of the steady
#: level or more (what would leave the 5 % band: a faster beat averages out of it), that turn by at most
#: PULSE_TURN per block (a beat the block rate resolves, whose window response and latency can be
#: undone), pulses of at most PULSE_DEPTH of the drive and PULSE_LONG blocks that leave at most
#: PULSE_RES of the ring, and PULSES of them per command's watch. Figures: docs/control.md, "A ring
#: cancelled".
PULSE_MIN = AGREE
PULSE_TURN = 0.5 * math.pi
#: ... and only a ring within this share of the tone's frequency from it: the observer reads the
#: tip through matrices designed at the tone, and a ring further off through other weights of its
#: currents than the tip's (after a lift-off at 250 Hz a mode 104 Hz off read 2-4 times its true
#: swing, and pulses against that doubled a settle time; a mode 68 Hz from 500 Hz read true)
PULSE_NEAR = 0.15
PULSE_DEPTH = 0.5
PULSE_LONG = 2 * RING_K
PULSE_RES = 0.3
PULSES = 2


@kernel
def _watch_anew(state, i):
    """A new command: no stretch of its fresh estimates yet."""
    state[REF, i] = 0.0
    state[SUM, i] = 0.0
    state[SQ, i] = 0.0
    state[RUN, i] = 0.0
    state[TRIES, i] = 0.0
    state[ALL, i] = 0.0
    state[NALL, i] = 0.0
    state[SUMR, i] = 0.0
    state[SUMI, i] = 0.0
    state[NSTR, i] = 0.0
    state[SPREV, i] = 0.0
    state[ANCHOR, i] = 0.0
    state[PREVY, i] = 0.0
    state[NWATCH, i] = 0.0
    state[HIGH, i] = 0.0
    state[NH, i] = 0.0
    state[FITY, i] = 0.0
    state[RINGED, i] = 0.0
    state[NPULSE, i] = 0.0


@kernel
def _hist(state, i, n):
    """The ``n``-th oldest phasor of tone ``i``'s ring history."""
    k = (int(state[NH, i]) + n) % RING_K
    return complex(state[HIST + 2 * k, i], state[HIST + 2 * k + 1, i])


@kernel
def _ring_fit(state, i):
    """The steady amplitude of tone ``i``'s last RING_K fresh estimates, fitted as a steady
    phasor and one real mode's decaying ring (``RING_K``), or -1 where they are not that; keeps
    the fitted ring's largest distance from the steady phasor in ``FSWING``. One pass over the
    history gathers every sum the fit needs (it runs in every fresh block of a tone that has
    the fit)."""
    k = int(state[NH, i]) % RING_K
    j = k - 1 if k > 0 else RING_K - 1  # the latest
    lr, li = state[HIST + 2 * j, i], state[HIST + 2 * j + 1, i]
    gate = max(0.5 * STILL * math.hypot(lr, li), RING_NOISE * state[NOISE, i]) ** 2
    for n in range(RING_K):  # squared distances first: most blocks end here
        dr = state[HIST + 2 * n, i] - lr
        di = state[HIST + 2 * n + 1, i] - li
        if dr * dr + di * di > gate:
            break
    else:
        return -1.0  # (a steady estimate, or noise: as most blocks, no ring the fit would find)
    last = complex(lr, li)
    turn = cmath.exp(1j * state[ROT, i])
    g11 = g22 = g12 = b1 = b2 = cc = dd = 0.0
    total = 0j
    first = second = before = w1 = x0 = x1 = 0j
    z = 1.0 + 0j
    for n in range(RING_K):
        w = complex(state[HIST + 2 * k, i], state[HIST + 2 * k + 1, i])
        k = k + 1 if k + 1 < RING_K else 0
        total += w
        if n == 1:
            second = w
        elif n == RING_K - 2:
            before = w
        if n == 0:
            first = w
        else:
            x = (w - w1) * z  # x[n-1]: the difference turned back by the tone's own turn n-1 times
            z *= turn
            dd += x.real * x.real + x.imag * x.imag
            if n >= 3:  # x = al x1 + be x0, al and be real
                g11 += x1.real * x1.real + x1.imag * x1.imag
                g22 += x0.real * x0.real + x0.imag * x0.imag
                g12 += x1.real * x0.real + x1.imag * x0.imag
                b1 += x1.real * x.real + x1.imag * x.imag
                b2 += x0.real * x.real + x0.imag * x.imag
                cc += x.real * x.real + x.imag * x.imag
            x0, x1 = x1, x
        w1 = w
    det = g11 * g22 - g12 * g12
    if not det > 1e-9 * g11 * g22:
        return -1.0
    al = (b1 * g22 - g12 * b2) / det
    be = (g11 * b2 - g12 * b1) / det
    # the least-squares residual, from the same sums: what the fit leaves of the right-hand side
    if not cc - al * b1 - be * b2 <= RING_RES * RING_RES * dd:
        return -1.0
    disc = cmath.sqrt(al * al + 4.0 * be + 0j)
    p1 = 0.5 * (al + disc) / turn
    p2 = 0.5 * (al - disc) / turn
    if not (max(abs(p1), abs(p2)) <= RING_RHO and min(abs(1.0 - p1), abs(1.0 - p2)) >= RING_MOVE):
        return -1.0
    c1 = al / turn
    c2 = be / (turn * turn)
    # the mean of w[n+2] - c1 w[n+1] - c2 w[n], n = 0 ... RING_K - 3, from the sum of every w
    c0 = (total - first - second) - c1 * (total - first - last) - c2 * (total - before - last)
    a = c0 / ((RING_K - 2) * (1.0 - c1 - c2))
    y = abs(a)
    swing = 0.0
    for n in range(RING_K):
        swing = max(swing, abs(_hist(state, i, n) - a))
    state[FSWING, i] = swing
    if not (swing > STILL * y and y < math.inf):
        return -1.0
    # the ring's half nearest the tone (the mode's own; the other is its image) at the latest
    # estimate, from the last two: what a pulse cancels (``_pulse``)
    if abs(cmath.phase(p1)) <= abs(cmath.phase(p2)):
        pm, po = p1, p2
    else:
        pm, po = p2, p1
    cm = 0j
    if pm != po:
        cm = ((last - a) - po * (before - a)) * pm / (pm - po)
    # the block before's ring (where a fit stood there), one block on
    was = complex(state[RMR, i], state[RMI, i]) * complex(state[RPR, i], state[RPI, i])
    state[RSAME, i] = 1.0 if state[FITY, i] > 0.0 and abs(cm - was) <= PULSE_RES * abs(cm) else 0.0
    state[RMR, i] = cm.real
    state[RMI, i] = cm.imag
    state[RPR, i] = pm.real
    state[RPI, i] = pm.imag
    state[RSR, i] = a.real
    state[RSI, i] = a.imag
    return y


@kernel
def _pulse(state, i, block):
    """The pulse that cancels tone ``i``'s fitted ring (``PULSE_MIN``): the drive's relative
    step ``d`` and the blocks ``h`` until it returns, or ``h = 0`` (none). The ring's half at the
    latest estimate is read through its window (samples ``WINS``: a component turning by ``psi``
    per sample reads ``exp(-j psi (W - 1) / 2) sin(psi W / 2) / (W sin(psi / 2))`` of itself at the
    window's end) and carried on by its root to the middle of the block the step ramps over
    (``LATB - 1/2`` blocks after that end)."""
    pm = complex(state[RPR, i], state[RPI, i])
    a = complex(state[RSR, i], state[RSI, i])
    phi = cmath.phase(pm)
    if not (abs(phi) > 0.0 and abs(phi) <= PULSE_TURN and abs(phi) <= 2.0 * math.pi * PULSE_NEAR * state[TURNS, i]
            and abs(pm) > 0.0 and abs(a) > 0.0):
        return 0.0, 0
    w = state[WINS, i]
    psi = phi / block
    hw = cmath.exp(-0.5j * psi * (w - 1.0)) * (math.sin(0.5 * psi * w) / (w * math.sin(0.5 * psi)))
    if not abs(hw) >= 0.5:
        return 0.0, 0  # a window this blurred does not tell the ring's phase
    lead = state[LATB, i] - 0.5
    x = complex(state[RMR, i], state[RMI, i]) / hw * cmath.exp(lead * cmath.log(pm)) / a
    wa = state[WAMP, i]  # ... and as much of it as the tone's amplitude shows
    seen = abs(math.sin(0.5 * psi * wa) / (wa * math.sin(0.5 * psi)))
    if not (abs(x) * seen >= PULSE_MIN and state[RSAME, i] != 0.0):
        return 0.0, 0
    period = 2.0 * math.pi / abs(phi)
    h0 = max(1, int(math.ceil(0.25 * period)))
    h1 = min(PULSE_LONG, int(math.floor(0.75 * period)))
    best, d_best, h_best = PULSE_RES * abs(x), 0.0, 0
    back = 1.0 + 0j
    inv = 1.0 / pm
    for h in range(1, h1 + 1):
        back *= inv  # P^-h
        if h < h0:
            continue
        q = 1.0 - back
        d = (x.real * q.real + x.imag * q.imag) / (q.real * q.real + q.imag * q.imag)
        left = abs(x - d * q)
        if left <= best and abs(d) <= PULSE_DEPTH:
            best, d_best, h_best = left, d, h
    return d_best, h_best


@kernel
def _released(state, i, y, r, a, waiting):
    """Whether tone ``i``'s estimate ``y`` (m; target ``r``, command ``a``) shows a release
    (``RELEASE``, ``RELEASE_RUN`` estimates in a row) over ``ANCHOR``, or while ``waiting`` out a
    correction's window over ``BEFORE``; keeps ``ANCHOR``, ``RIPPLE``, ``HIGH`` (waiting: neither
    the anchor nor the ripple moves, the window's slide being the loop's own)."""
    if not (y > 0.0 and y < math.inf and r > 0.0) or state[JNOISE, i] < 0.0:
        return False
    if state[LIFTED, i] != 0.0 and not waiting and a * state[GMAX, i] > (1.0 + RELEASE) * r:
        # the currents read in this block showed the free beam ring: a release now, before any
        # window's estimate can rise (they show a lift-off a window's share at a time). Not while
        # waiting out a command's window: the test's premise is a plant that was steady under the
        # finger (after a landing's correction a finger stiffer than the model's read as no finger)
        state[HIGH, i] = RELEASE_RUN
        state[PREVY, i] = y
        return True
    rip = state[RIPPLE, i]
    # (after a wait, until an estimate comes on target, what the wait was watched against)
    base = state[BEFORE, i] if waiting or state[ANCHOR, i] <= 0.0 else state[ANCHOR, i]
    state[NWATCH, i] += 1.0
    high = (state[NWATCH, i] >= RELEASE_AFTER and base > 0.0
            and y - base > RELEASE * r + state[JNOISE, i] + RIPPLE_K * rip
            and a * state[GMAX, i] > (1.0 + RELEASE) * r)
    if high:  # (a rise in progress neither moves the anchor nor counts as ripple)
        state[HIGH, i] += 1.0
    elif waiting:
        state[HIGH, i] = 0.0
    else:
        state[HIGH, i] = 0.0
        if state[PREVY, i] > 0.0:
            state[RIPPLE, i] = max(state[PREVY, i] - y, RIPPLE_DECAY * rip)
        if abs(y / r - 1.0) <= AGREE:
            if state[ANCHOR, i] > 0.0:
                state[ANCHOR, i] += min(1.0, ANCHOR_RATE / state[WARM, i]) * (y - state[ANCHOR, i])
            else:
                state[ANCHOR, i] = y
        elif y < r and a >= state[AMAX, i]:
            # saturated under the target: a rise is measured from the target, which the tip
            # cannot pass unless the plant changed (a 40 Hz tone at its cap under 200 g rose to
            # 1.5-2x the target when the finger lifted, with no on-target estimate to rise from)
            state[ANCHOR, i] = r
    state[PREVY, i] = y
    return state[HIGH, i] >= RELEASE_RUN


@kernel
def _let_go(state, i, y, r):
    """The finger let go (estimate ``y``, target ``r``): the drive for the most responsive load
    at once, in one block (a rise would hold the swing for its length), and a new command's
    watch. Returns that drive."""
    state[EST, i] = y
    state[GHAT, i] = state[GMAX, i]  # what a start or target step now aims by
    state[GLIVE, i] = 0.0
    state[RSUM, i] = 0.0
    state[RRUN, i] = 0.0
    state[RREF, i] = 0.0
    state[NREL, i] += 1.0
    _watch_anew(state, i)
    _pace_anew(state, i)
    state[WAIT, i] = state[WARM, i]
    state[BEFORE, i] = 0.0
    state[RELNOW, i] = 1.0
    return r / state[GMAX, i]


@kernel
def _extrapolate(state, i, ar, ai, v, pv):
    """The steady amplitude three stretch means of one ring end at (P1, P2 and the present one,
    ``ar + 1j ai``, whose means' variances are ``P1V``, ``pv`` and ``v``), or -1 where they do not
    move as one decaying ring beyond their noise."""
    if state[NSTR, i] < 2.0:
        return -1.0
    d1r = state[P2R, i] - state[P1R, i]
    d1i = state[P2I, i] - state[P1I, i]
    d2r = ar - state[P2R, i]
    d2i = ai - state[P2I, i]
    n1 = math.hypot(d1r, d1i)
    n2 = math.hypot(d2r, d2i)
    if not (n1 > NOISE_Z * math.sqrt(pv + state[P1V, i]) and n2 > NOISE_Z * math.sqrt(v + pv)
            and n2 <= W_MAX * n1):
        return -1.0
    den = d1r * d1r + d1i * d1i
    wr = (d2r * d1r + d2i * d1i) / den
    wi = (d2i * d1r - d2r * d1i) / den
    nr = wr * d2r - wi * d2i  # w (A - P2)
    ni = wr * d2i + wi * d2r
    qr = 1.0 - wr
    qi = -wi
    qq = qr * qr + qi * qi
    if wr * wr + wi * wi > EXT_GAIN * EXT_GAIN * qq:
        return -1.0  # barely turning, barely decaying: a drift, or a window sliding to a stop
    if wi * wi < TURN * TURN * (wr * wr + wi * wi):
        return -1.0  # three means on a line: a window sliding over a change, not a ring
    return math.hypot(ar + (nr * qr + ni * qi) / qq, ai + (ni * qr - nr * qi) / qq)


@kernel
def _siblings_wait(state, index):
    """After every tone's block: where a tone's drive stepped, every other tone of its channel
    is read from the same currents, and a window that holds the step holds it in their
    estimates too (a beat pair's two sines, read jointly, each see the other's step), so they
    wait for a window without it. (A tone that stepped in the same block has just begun that
    wait for its own step: this changes nothing for it. After the loop, not within it, so that
    a tone later in the loop still makes the correction it was due in this block.)"""
    for i in range(state.shape[1]):
        if state[STEPPED, i] == 0.0:
            continue
        k = index[SIBLING, i]
        while k != i:
            if state[ON, k] != 0.0:
                # its own command unchanged, it reads on at its level meanwhile, give or take
                # what the other's step may ring (the step's size again)
                state[BEFORE, k] = max(state[BEFORE, k] if state[WAIT, k] > 0.0 else 0.0,
                                       state[EST, k] * (1.0 + state[STEPPED, i]))
                state[WAIT, k] = max(state[WAIT, k], state[WARM, k])
                _watch_anew(state, k)
            k = index[SIBLING, k]


@kernel
def _send(state, i, a, pending, b, ramp):
    """Tone ``i``'s drive for the next block, ``a`` volts, to its oscillator ``b`` (ramped over
    ``ramp`` samples); ``STEPPED`` where it moved by more than AGREE."""
    if abs(a - state[OUT, i]) > AGREE * state[OUT, i]:
        state[STEPPED, i] = abs(a - state[OUT, i]) / state[OUT, i] if state[OUT, i] > 0.0 else 1.0
    state[OUT, i] = a
    state[PULSE, i] = 0.0  # (a new command ends a pulse; a pulse's own step sets it after)
    pending[P_AMP, b] = a
    pending[P_RAMP, b] = ramp
    pending[P_FLAG, b] = 1.0


@kernel
def _siblings_let_go(state, index, target, pending, ramp):
    """Where a tone released, the other tones of its channel that would overshoot on the lifted
    beam drop with it, in the same block: the finger let go of the beam, not of one tone."""
    for i in range(state.shape[1]):
        if state[RELNOW, i] == 0.0:
            continue
        k = index[SIBLING, i]
        while k != i:
            r = target[TARGET, k]
            if (state[ON, k] != 0.0 and state[RELNOW, k] == 0.0 and state[JNOISE, k] >= 0.0 and r > 0.0
                    and state[CMD, k] * state[GMAX, k] > (1.0 + RELEASE) * r):
                a = min(_let_go(state, k, state[EST, k], r), state[AMAX, k])
                state[RISEK, k] = state[RISE, k]
                state[SAT, k] = 0.0
                state[CMD, k] = a
                _send(state, k, a, pending, index[BANK, k], ramp)
            k = index[SIBLING, k]


@kernel
def _pace_anew(state, i):
    """The designed stretch again, and no hunting counted."""
    state[HOLD, i] = state[HOLD0, i]
    state[LASTDIR, i] = 0.0
    state[REVS, i] = 0.0


@kernel
def amplitude_control(est, drive_est, index, target, state, pending, lim_counts, ramp):
    """Set the next block's amplitude of every controlled tone; returns status bits.

    Parameters
    ----------
    est : ndarray, shape (n_ch, n_slots, N_EST, 2)
        The observer's latest estimates (row 0: tip deflection phasor, m).
    drive_est : ndarray, shape (n_ch, n_slots, 2)
        The observer's lock-in of the drive over the same window (amplitude V, phase rad).
    index : ndarray int64, shape (N_INDEX, n)
        Per controlled tone: the observer channel and slot of its estimate, its oscillator in the
        bank, its drive channel (the limiter's column), and the next tone read on the same
        observer channel (a cycle through them; the tone itself where it is alone).
    target : ndarray, shape (N_TARGET, n)
        Target tip amplitude (m) and enable flag per tone.
    state : ndarray, shape (N_STATE, n)
    pending : ndarray, shape (N_PEND, n_bank_tones)
        The oscillator bank's pending parameters (written: amplitude, ramp, flag).
    lim_counts : ndarray int64, shape (3, n_channels)
        The limiter's per-channel counts of limited samples.
    ramp : float
        Samples each amplitude change ramps over (one block).
    """
    status = 0
    n = state.shape[1]
    for i in range(n):
        state[STEPPED, i] = 0.0
        state[RELNOW, i] = 0.0
        b = index[BANK, i]
        if target[ENABLE, i] == 0.0:
            state[LOW, i] = 0.0
            if state[ON, i] != 0.0:  # switched off: ramp to silence
                state[STEPPED, i] = 1.0
                state[PULSE, i] = 0.0
                state[ON, i] = 0.0
                state[CMD, i] = 0.0
                state[OUT, i] = 0.0
                pending[P_AMP, b] = 0.0
                pending[P_RAMP, b] = ramp
                pending[P_FLAG, b] = 1.0
            continue
        r = target[TARGET, i]
        ch = index[CHANNEL, i]
        lim = float(lim_counts[0, ch] + lim_counts[1, ch] + lim_counts[2, ch])
        limited = lim != state[LIMSEEN, i]
        state[LIMSEEN, i] = lim
        a = state[CMD, i]
        c, j = index[OBS_CH, i], index[OBS_SLOT, i]
        y_now = math.hypot(est[c, j, 0, 0], est[c, j, 0, 1])  # the latest estimate's amplitude
        rising = state[RISEK, i] < state[RISE, i]
        pulse = 0.0  # a ring-cancelling pulse's relative step in this block, and its length
        h = 0
        if state[ON, i] != 0.0 and not rising:
            # the plant's tip per volt over the latest window, whatever the drive did in it (a
            # target that moves every block never gives a window of one command)
            u = drive_est[c, j, 0]
            y = y_now
            if u >= LIVE_DRIVE * a and u > 0.0 and y > 0.0 and y < math.inf:
                # followed in stretches as the estimate is: a swell's windows lag their drive
                # (the tip rings up behind it), and a gain taken from every window at once would
                # feed that lag back into the drive
                state[RSUM, i] += y / u
                state[RRUN, i] += 1.0
                if state[RRUN, i] >= state[HOLD, i]:
                    m = state[RSUM, i] / state[RRUN, i]
                    if state[RREF, i] > 0.0 and abs(m / state[RREF, i] - 1.0) <= AGREE:
                        state[GLIVE, i] = m
                    state[RREF, i] = m
                    state[RSUM, i] = 0.0
                    state[RRUN, i] = 0.0
        if state[ON, i] != 0.0 and r != state[TPREV, i] and state[GLIVE, i] > 0.0:
            # a target step while playing: the drive for it from the latest window's tip per volt
            a = r / state[GLIVE, i]
            state[TPREV, i] = r
            state[WAIT, i] = state[WARM, i] + max(0.0, state[RISE, i] - state[RISEK, i] - 1.0)
            state[BEFORE, i] = 0.0
            _watch_anew(state, i)
            _pace_anew(state, i)
        elif state[ON, i] == 0.0 or r != state[TPREV, i]:
            # a start or a target step: the drive for the new target from the tip per volt the
            # last fresh estimate showed (what feedback learned), else from the model's
            if state[GHAT, i] > 0.0:
                a = r / state[GHAT, i]
            else:  # the model's drive, aimed low: its finger is a guess, feedback brings it up
                a = START * r * state[FF, i]
            if state[ON, i] == 0.0:
                state[RISEK, i] = 0.0
                state[A0, i] = 0.0
                rising = state[RISE, i] > 0.0
            _pace_anew(state, i)
            state[ON, i] = 1.0
            state[TPREV, i] = r
            # the estimate answers the command once the rise has reached it and a window has passed
            state[WAIT, i] = state[WARM, i] + max(0.0, state[RISE, i] - state[RISEK, i] - 1.0)
            state[BEFORE, i] = 0.0
            _watch_anew(state, i)
        elif state[WAIT, i] > 0.0:
            state[WAIT, i] -= 1.0
            back = False  # a pulse's drive returns to the command in this block
            if state[PULSE, i] > 0.0:
                state[PULSE, i] -= 1.0
                back = state[PULSE, i] == 0.0
            if state[BEFORE, i] > 0.0 and _released(state, i, y_now, r, a, True):
                a = _let_go(state, i, y_now, r)
                if rising:  # a release drops the drive in one block, whatever rise was under way
                    state[RISEK, i] = state[RISE, i]
                    rising = False
            else:
                if state[WAIT, i] == 0.0:  # the watch after the wait starts as it did without one
                    state[NWATCH, i] = 0.0
                    state[PREVY, i] = 0.0
                    state[HIGH, i] = 0.0
                if not (rising or back):
                    continue
        elif _released(state, i, y_now, r, a, False):
            a = _let_go(state, i, y_now, r)
        else:
            # every block from here on the estimate holds nothing but the present command: watch
            # it until it has been steady for HOLD blocks, then correct on the run's mean
            y = y_now
            state[EST, i] = y
            if not (y > 0.0 and y < math.inf and r > 0.0):
                state[FROZEN, i] = 1.0  # hold the drive: never raise it on a bad estimate
                state[REF, i] = 0.0
                state[SUM, i] = 0.0
                state[SQ, i] = 0.0
                state[RUN, i] = 0.0
                state[ALL, i] = 0.0
                state[NALL, i] = 0.0
                state[SUMR, i] = 0.0
                state[SUMI, i] = 0.0
                state[NSTR, i] = 0.0
                state[SPREV, i] = 0.0
                state[ANCHOR, i] = 0.0
                state[PREVY, i] = 0.0
                state[NWATCH, i] = 0.0
                state[HIGH, i] = 0.0
                state[NH, i] = 0.0  # (the ring fit needs estimates of consecutive blocks)
                state[FITY, i] = 0.0
                status |= CONTROL_FROZEN
                continue
            state[FROZEN, i] = 0.0
            state[GHAT, i] = y / a
            state[TRIES, i] += 1.0
            fit = -1.0
            if state[ROT, i] >= 0.0:
                k = int(state[NH, i]) % RING_K
                state[HIST + 2 * k, i] = est[c, j, 0, 0]
                state[HIST + 2 * k + 1, i] = est[c, j, 0, 1]
                state[NH, i] += 1.0
                if state[NH, i] >= RING_K:
                    fit = _ring_fit(state, i)
            before = state[FITY, i]
            state[FITY, i] = max(fit, 0.0)
            if fit > 0.0:
                # a ring: its stretch means are points of it, and the fit is its end
                state[RINGED, i] = 1.0
                state[REF, i] = 0.0
                state[ALL, i] = 0.0
                state[NALL, i] = 0.0
                state[SUM, i] = 0.0
                state[SQ, i] = 0.0
                state[RUN, i] = 0.0
                state[SUMR, i] = 0.0
                state[SUMI, i] = 0.0
                state[NSTR, i] = 0.0
                state[SPREV, i] = 0.0
                if not (before > 0.0 and abs(fit / before - 1.0) <= STILL):
                    continue
                y = fit
                g = state[GAIN, i]
            if fit < 0.0:  # no ring fitted: stretches
                # steady: the means of two successive stretches of HOLD fresh estimates agree (a
                # ripple averages out within a stretch, a drift or a window sliding over a change
                # shows between them)
                state[SUM, i] += y
                state[SQ, i] += y * y
                state[SUMR, i] += est[c, j, 0, 0]
                state[SUMI, i] += est[c, j, 0, 1]
                state[RUN, i] += 1.0
                state[ALL, i] += y
                state[NALL, i] += 1.0
                if state[RUN, i] < state[HOLD, i]:
                    continue
                n_run = state[RUN, i]
                m = state[SUM, i] / n_run
                v = max(state[SQ, i] / n_run - m * m, 0.0) / n_run  # the mean's variance, as if independent
                prev, pv = state[REF, i], state[REFV, i]
                ar = state[SUMR, i] / n_run
                ai = state[SUMI, i] / n_run
                ext = -1.0
                moving = False
                if state[SLOW, i] != 0.0 and state[RINGED, i] == 0.0:
                    # (elsewhere a ring turns or decays within a stretch; and once a ring fit
                    # stood, what it leaves of the ring is too small to extrapolate)
                    ext = _extrapolate(state, i, ar, ai, v, pv)
                    moving = state[NSTR, i] >= 1.0 and (math.hypot(ar - state[P2R, i], ai - state[P2I, i])
                                                        > max(STILL * m, NOISE_Z * math.sqrt(v + pv)))
                young = state[NSTR, i] < 2.0
                sprev = state[SPREV, i]
                state[SPREV, i] = max(ext, 0.0)
                state[P1R, i], state[P1I, i], state[P1V, i] = state[P2R, i], state[P2I, i], pv
                state[P2R, i], state[P2I, i] = ar, ai
                state[NSTR, i] += 1.0
                state[SUMR, i] = 0.0
                state[SUMI, i] = 0.0
                if prev > 0.0 and abs(m / prev - 1.0) > CHANGED:
                    _pace_anew(state, i)
                state[REF, i] = m
                state[REFV, i] = v
                state[SUM, i] = 0.0
                state[SQ, i] = 0.0
                state[RUN, i] = 0.0
                if prev > 0.0 and abs(m / prev - 1.0) <= AGREE and moving and ext < 0.0 and young:
                    continue  # amplitudes agree on a point of a slow ring: a third stretch tells its end
                if prev > 0.0 and abs(m / prev - 1.0) <= AGREE and moving and ext > 0.0:
                    y = ext
                    g = state[GAIN, i]
                elif ext > 0.0 and sprev > 0.0 and abs(ext / sprev - 1.0) <= AGREE:
                    y = ext  # two successive stretches extrapolate the ring to one end
                    g = state[GAIN, i]
                elif prev > 0.0 and (abs(m / prev - 1.0) <= AGREE
                                     or (state[SCATTER, i] != 0.0 and abs(r / m - 1.0) > FAR
                                         and abs(m - prev) <= NOISE_Z * math.sqrt(v + pv))):
                    y = m
                    if abs(r / m - 1.0) <= AGREE and not moving:
                        # near the target the steady plant is best seen in the mean of every fresh
                        # estimate of this command (the last correction's fine tuning)
                        y = state[ALL, i] / state[NALL, i]
                    g = state[GAIN, i]
                elif state[TRIES, i] >= PATIENCE * (state[WARM, i] + 2.0 * state[HOLD, i]):
                    y = m
                    g = 0.5 * state[GAIN, i]  # never steady: follow the drift at half strength
                else:
                    continue
            step = (r / y) ** g
            if abs(step - 1.0) <= DEADBAND:
                state[TRIES, i] = 0.0  # on target: keep watching (this stretch compares with the next)
                _pace_anew(state, i)
                if not (fit > 0.0 and state[NPULSE, i] < PULSES):
                    continue
                # on target, but ringing: a pulse of drive that cancels the ring (``PULSE_MIN``)
                d, h = _pulse(state, i, ramp)
                # (within the floor and the cap, and never up while the limiter holds the channel)
                if not (h > 0 and r / state[GTOP, i] <= a * (1.0 + d) <= state[AMAX, i] and not (limited and d > 0.0)):
                    continue
                n_p = state[NPULSE, i]
                _watch_anew(state, i)
                state[NPULSE, i] = n_p + 1.0
                state[PULSED, i] += 1.0
                state[WAIT, i] = h + state[WARM, i]  # and then a window of nothing but the command
                state[BEFORE, i] = y * (1.0 + abs(d)) + state[FSWING, i]
                pulse = d
            else:  # off target: correct
                step = min(max(step, 1.0 / MAX_STEP), MAX_STEP)
                if limited and step > 1.0:
                    step = 1.0  # the limiter holds this channel: no windup
                if (step > 1.0 and a >= state[AMAX, i]) or step == 1.0:
                    # no change to make (at the cap, or held by the limiter): keep watching, not blind
                    # for a window after a command that is the one before (a finger letting go of a
                    # saturated tone must find the watch running)
                    state[TRIES, i] = 0.0
                    continue
                d = 1.0 if step > 1.0 else -1.0
                if not (step < REVERSAL and step * REVERSAL > 1.0):
                    _pace_anew(state, i)
                    state[LASTDIR, i] = d
                elif abs(step - 1.0) > AGREE:  # (finer corrections tune, they do not hunt)
                    if d == -state[LASTDIR, i]:
                        state[REVS, i] += 1.0
                        if state[REVS, i] >= 2.0:
                            state[HOLD, i] = min(2.0 * state[HOLD, i], state[HOLDMAX, i])
                    else:
                        state[REVS, i] = 0.0
                    state[LASTDIR, i] = d
                a = a * step
                _watch_anew(state, i)
                state[WAIT, i] = state[WARM, i]  # judge this command only once the estimate is all of it
                # a step of drive may ring the plant by up to the step again (a loaded mode beside
                # the tone beats with it: a 10 Hz tone under a stiff finger pressing, stepped x1.7,
                # read 7 % over its new level)
                state[BEFORE, i] = y * (max(1.0, step) + abs(step - 1.0))
                if fit > 0.0:  # and the ring corrected across goes on meanwhile
                    state[BEFORE, i] += state[FSWING, i]
                if (step > BIG_STEP or step * BIG_STEP < 1.0) and state[RISE, i] > 1.0:
                    state[A0, i] = state[OUT, i]  # from the drive now, not from 0
                    state[RISEK, i] = 0.0
                    state[WAIT, i] += state[RISE, i] - 1.0
                    rising = True
        # the floor: no device the model allows needs less drive for the target than this. An
        # estimate that still reads the tip above the target there does not see the tip (current
        # noise over a tip below what the observer resolves reads as a tip that stays put while
        # every correction divides the drive: without the floor the drive fell to 1e-16 V)
        floor = r / state[GTOP, i]
        state[LOW, i] = 0.0
        if a < floor:
            a = floor
            # (a floor over AMAX: no load reaches the target, and the command saturates below)
            state[LOW, i] = 1.0 if floor < state[AMAX, i] else 0.0
        if a >= state[AMAX, i]:
            a = state[AMAX, i]
            state[SAT, i] = 1.0 if (state[EST, i] < r or state[WAIT, i] > 0.0) else 0.0
        else:
            state[SAT, i] = 0.0
        if state[SAT, i] != 0.0:
            status |= CONTROL_SATURATED
        state[CMD, i] = a
        if rising:  # block by block along a raised cosine from the last drive to the command
            state[RISEK, i] += 1.0
            a = state[A0, i] + (a - state[A0, i]) * 0.5 * (1.0 - math.cos(math.pi * state[RISEK, i] / state[RISE, i]))
        _send(state, i, a * (1.0 + pulse), pending, b, ramp)
        if pulse != 0.0:
            state[PULSE, i] = h
    _siblings_let_go(state, index, target, pending, ramp)
    _siblings_wait(state, index)
    for i in range(n):  # every block a tone is held at its floor, waiting or not
        if state[LOW, i] != 0.0:
            state[LOWN, i] += 1.0
            status |= CONTROL_FLOOR
    return status
