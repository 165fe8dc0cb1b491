"""Per-tone amplitude control from the self-sensing observer's estimates.

The plant, at a steady tone, is a gain: tip amplitude ``y = G a`` for drive amplitude ``a``, with
``G`` unknown to within the model's error and the finger's changes. The observer sees it through
its lock-in window (``M`` blocks: whole periods of the channel's tones) ``L`` blocks late (the I/O
latency), so an estimate holds nothing but the present command ``W = L + M + 1`` blocks after a
change (one block more for the oscillator's ramp). The controller therefore works in sampled
steps, per controlled tone:

* at the start and at every target step: ``a = r / G``, with ``G`` the tip per volt the last fresh
  estimate showed (what feedback learned, saturated or not), or before the first estimate the
  model's ``|G_model|`` aimed at ``START`` (70 %) of the target (its finger is a guess); a start
  rises to it along a raised cosine over ``rise`` blocks (a step of drive rings in the loaded
  beam's modes); then wait ``W`` blocks after the rise;
* then watch every fresh estimate (one that holds nothing but the present command) in stretches
  of ``H`` blocks (:func:`steady_blocks`); once the means of two successive stretches agree within
  5 % the plant is steady (a window sliding over a change of the plant, the finger pressing or
  lifting, moves its estimate for a whole window: correcting on it would chase it; the loaded
  beam's ripple averages out within a stretch). More than 10 % from the target, and where a
  stretch spans a whole window, two stretches within 2 standard errors of their difference (from
  the spread within each) agree too: at a tenth of its amplitude after a finger lands the
  estimate is noisy. If no two agree for four times (``W`` + 2 stretches), correct anyway at half
  strength;
* correct on the last stretch's mean ``y`` (within 5 % of the target, on the mean of every fresh
  estimate of the command): ``a <- a * (r / y) ** g`` (at most a factor of 4; a correction by
  more than 2x rises from the present drive as a start does), then wait ``W`` again. An error
  under 0.2 % is left alone and the watch goes on: a correction blinds the loop for ``W``, so
  skipping needless ones lets it answer a change of the plant a window sooner (``M + L + 2 H``
  blocks after the change, rather than up to ``W`` more);
* a slow ring (``beside``: the model puts a loaded mode so near the tone that its ring turns
  less than half a beat per stretch, and outlasts a stretch): two stretches whose amplitudes
  agree may agree on a point of the ring. Where their phasor means moved (by more than 1 % and
  their noise) the loop waits for a third; three stretch means of one command that move as one
  decaying, turning ring (``A - P2 = w (P2 - P1)``) are extrapolated to its end,
  ``A + w (A - P2) / (1 - w)`` (Aitken's delta-squared on the phasors, exact for one mode), and
  the correction is made on that; two successive extrapolations that agree are steady too;
* every tone read on one observer channel (a beat pair's sines) waits a fresh window when
  another's drive changes by more than 5 %: the window that holds that step holds it in every
  estimate of the channel;
* hunting: from the second correction in a row by 5-30 % (either way) that reverses the one
  before, each such correction doubles ``H``, up to half the ring time: the two stretches had
  agreed on the extremes of a beat of the tone with a loaded mode, which a longer stretch
  averages out. An on-target stretch, a start or target step, a correction by more than 30 %,
  and two stretches more than 20 % apart (an event) set ``H`` back to its design;
* a release (``release``: tones whose window is long and whose most responsive load is the
  lifted beam): a fresh estimate more than 2 % of the target above the latest one within 5 % of
  it (and beyond its noise and its latest block-to-block move, from the third estimate of a
  command) says the finger let go, and the command drops at once to the target over that load's
  tip per volt, then waits ``W``: the lifted tip would swing at up to 3.7x the target for a window;
* a ring fitted (``turn``: the last fresh estimates as a steady phasor and one real mode's ring)
  is corrected on at its end; where that end is on target but the ring, near the tone, holds the
  tip out of its 5 % band, a pulse of drive (a step and back, half a beat or so later) cancels
  it: a step leaves a ring of minus the step it makes in the steady phasor (``PULSE_MIN``).

With ``g = 1`` this is deadbeat for a static plant: one correction removes a model error up to a
factor of four (a wild estimate cannot move the drive by more), and feedback never crosses the
target (the feedforward alone is off by the model's error: calibrate the model to keep that
small); a drifting or changing plant (the finger relaxing, pressing harder) is followed step by
step. The design, done at build time, is the wait ``W`` from the tone's window and the latency
(:func:`design`), and the stretch ``H`` from the window and the model's ring time.

Saturation: the command never exceeds the tone's share of ``max_voltage`` (the state *is* the
command, so there is nothing to wind up) and does not grow while the limiter holds the channel
(slew, current, thermal, DC bounds). A non-finite or zero estimate holds the command and raises
``CONTROL_FROZEN``: the drive is never raised on a bad estimate. Recovery after a saturation or an
event is one correction step once the target is reachable. The floor: the command never falls
below the target over ``FLOOR_MARGIN`` (4) times the most tip per volt any load the model knows
allows (``gain_top``); a tone held there raises ``CONTROL_FLOOR``. For a moment that is a ring
after an event read above the steady tip; for long, an estimate that does not follow the tip (a
tip under the observer's noise floor reads as the noise, which no drop of drive moves).
"""

from __future__ import annotations

import numpy as np

from ._kernels import (
    AMAX,
    BANK,
    CHANNEL,
    ENABLE,
    FF,
    GAIN,
    GMAX,
    GTOP,
    HOLD,
    HOLD0,
    HOLDMAX,
    JNOISE,
    LATB,
    N_INDEX,
    N_STATE,
    N_TARGET,
    NOISE,
    OBS_CH,
    OBS_SLOT,
    RING_K,
    RISE,
    ROT,
    SCATTER,
    SIBLING,
    SLOW,
    TARGET,
    TURNS,
    WAMP,
    WARM,
    WINS,
)

#: a loaded mode rings "beside" a tone (``SLOW``) where its beat with the tone turns by less than
#: this many turns per stretch (and the ring outlasts a stretch): two stretches can then agree in
#: amplitude on a point of its ring. A quarter turn left out the bundled beam's 500 Hz tone under
#: a soft finger (a mode 70-90 Hz away, 0.24-0.3 turns per 4-5 block stretch), which hunted
#: there for 300 ms
SLOW_TURNS = 0.5
#: the floor of a tone's drive is its target over this many times the most tip per volt any
#: load the model knows allows (the finger lifted, its sets, each 3x softer and stiffer): room
#: for a device off its model (a mode 5 % nearer the tone, half the damping) that a closed loop
#: never needs in the sweeps, and a bound on the drive an estimate that does not follow the tip
#: can ask for (current noise over a tip below what the observer resolves: each correction
#: divided the drive again, down to 1e-16 V, while the estimate stayed on the noise)
FLOOR_MARGIN = 4.0
#: a target at least this many times its estimate's noise floor (the rms the sense chain's noise
#: leaves in it, :meth:`rtctl.selfsense.rt.Observer.noise_floor`) is held within 1 % at the
#: loop's pace; a closer one is warned of when the rig is built. Not the Rician bias alone (a noisy
#: phasor's magnitude reads high by about ``(floor / y)^2 / 4``: 1 % at 5 times): each correction
#: is made on the mean of a few windows, so the held tip follows their noise. Measured at 250 Hz
#: on the bundled beam (6 noise seeds each, 1 s): 5 times the floor, up to 4.4 % off, 3 seeds
#: never within 5 % for good; 10 times 1.8 %, 0.72-1 s to settle; 20 times 1.2 %, 60-354 ms (one
#: seed never); 40 times 0.78 % (one seed 702 ms); 50 times 0.72 % and 30-40 ms (docs/control.md)
NOISE_MARGIN = 50.0
#: the release rule's allowance for noise: this many times the estimate's noise floor (the rise
#: it looks for is between estimates of windows a few blocks apart, whose noise is mostly the
#: same: their difference's noise is a small part of the floor)
RELEASE_Z = 3.0
#: the release rule is for tones whose observer window is at least this long, s: a lift-off
#: swings there for a window before the loop's own correction. Under it (250 Hz and 1 kHz, 4 ms)
#: the correction comes soon anyway, and a drop in one block rang the lifted beam: with the rule,
#: the 250 Hz lift-off on half-damped devices came within 5 % in 52 ms, 18 ms without it
RELEASE_WINDOW = 0.008


def steady_blocks(window: int, ring: int) -> int:
    """Fresh estimates per stretch (two successive stretches whose means agree say the plant is
    steady): at least a quarter window, so that a window sliding over a change of the plant
    (its estimate moves for a whole window) shows a change of more than 4 ``AGREE`` between two
    stretches, and an eighth of the ring time, so that the loaded beam's ripple after a finger
    lands or a command steps averages out within a stretch; at least 2.

    >>> steady_blocks(75, 47), steady_blocks(6, 47), steady_blocks(6, 0)
    (19, 6, 2)
    """
    return max(2, -(-int(window) // 4), -(-int(ring) // 8))


def design(latency: int, window: int) -> tuple[float, int]:
    """The correction exponent and the wait, in blocks, between a command and an estimate that
    holds nothing older: ``L + M + 1``.

    >>> design(1, 6)
    (1.0, 8)
    """
    return 1.0, max(0, int(latency)) + max(1, int(window)) + 1


class AmplitudeController:
    """Amplitude control of ``n`` tones (the stage's state; :func:`amplitude_control` runs it).

    Parameters
    ----------
    obs_channel, obs_slot : array_like of int, shape (n,)
        Where each tone's estimate sits in the observer's ``est`` (channel, tone slot).
    bank_index : array_like of int, shape (n,)
        Each tone's oscillator in the bank.
    channel : array_like of int, shape (n,)
        Each tone's drive channel (the limiter's column).
    gain_model : array_like, shape (n,)
        The model's tip amplitude per volt at each tone's frequency under the assumed load, m/V.
    max_amplitude : array_like, shape (n,)
        Each tone's share of its channel's max_voltage, V.
    targets : array_like, shape (n,)
        Target tip amplitude per tone, m.
    latency : int
        Blocks from a drive block to the currents answering it.
    window : int or array_like of int, shape (n,)
        The observer's window in blocks: one for every tone, or each tone's own (its channel's
        window: a group's channels each have theirs, and one controller serves the group).
    block : int
        Samples per block (each amplitude change ramps over one block).
    ring : int
        Blocks the plant rings after a start or a target step (its slowest loaded mode's time
        constant, from the model): it sets the stretch (:func:`steady_blocks`, at least an
        eighth of it, and a hunting loop's stretch, at most half of it). The wait after a
        command is the window and the latency alone (``WARM``): two steady stretches are what
        keep a ring from being corrected on.
    rise : int
        Blocks a tone's start (or a correction by more than ``BIG_STEP``) rises over to its
        command, along a raised cosine (0 or 1: within one block, a ramp of ``block`` samples). A
        step of drive excites the loaded beam's modes, which beat with the tone and ring for their
        decay time; a rise of ``T`` leaves of a mode ``df`` away from the tone about
        ``|cos(pi df T) / (1 - 4 (df T)^2)|`` of what a step leaves (1/15 at ``df T = 2``), at the
        cost of ``T`` before the next estimate.
    beside : (array_like, array_like), each of shape (n,), optional
        Per tone, the loaded mode nearest to it (:meth:`~rtctl.models.Models.nearest_modes`):
        its beat with the tone in turns per block and its time constant in blocks. Where that
        ring turns by less than ``SLOW_TURNS`` (half a turn) per stretch and outlasts one, two
        stretches whose amplitudes agree but whose phasors moved wait for a third, which tells
        where the ring ends (``SLOW``). None: no such mode.
    gain_top : array_like, shape (n,), optional
        Per tone, the most tip amplitude per volt any load the model knows allows, m/V (at least
        ``gain_model``; inf: none). The drive never falls below the target over ``FLOOR_MARGIN``
        times it, and the tone raises ``CONTROL_FLOOR`` while it holds that floor (an estimate
        that reads the tip above the target there is not following the tip, or reads a ring).
        None: no floor.
    release : array_like, shape (n,), optional
        Per tone, the noise allowance (m) of the release rule (``RELEASE``: a fresh estimate that
        rises above the latest on-target one by more than ``RELEASE`` of the target and this drops
        the drive to the target over ``gain_top``), or a negative value: no release rule for
        that tone. Needs ``gain_top``. None: no release rule.
    turn : array_like, shape (n,), optional
        Per tone, its own turns per block (frequency times block over the sample rate): where
        given and the tone's window is at most ``RING_K - 4`` blocks, the last ``RING_K`` fresh
        estimates of a command are fitted as a steady phasor and one real mode's decaying ring
        (whose other half turns by ``-(f_m + f)``, and so needs the tone's own turn), and the
        loop corrects on the ring's end (``RING_K``). None: no ring fit.
    noise : array_like, shape (n,), optional
        Per tone, the rms noise of its estimate, m (:meth:`rtctl.selfsense.rt.Observer.noise_floor`):
        estimates that move by no more than ``RING_NOISE`` times it are not fitted. None: 0.
    window_samples : array_like of int, shape (n,), optional
        Per tone, its observer window in samples (default ``window`` blocks): a fitted ring that
        holds the tip out of its band on target is cancelled by a pulse of drive
        (``PULSE_MIN``), whose timing reads the ring's phase through that window.
    amplitude_window : array_like, shape (n,), optional
        Per tone, the samples its amplitude is fitted over (:func:`rtctl.engine.report.fit_window`;
        default ``window_samples``): a ring is cancelled where that amplitude shows it.

    Attributes
    ----------
    gain, warm, hold, scatter : scalars, or ndarrays of shape (n,)
        The correction exponent and the wait (:func:`design`), the stretch
        (:func:`steady_blocks`), in blocks, and whether a stretch spans a whole window (1.0: the
        spread of its estimates is their noise, and far from the target two stretches may agree
        within it): one each for one ``window``, per tone for a window per tone.
    """

    def __init__(self, obs_channel, obs_slot, bank_index, channel, gain_model, max_amplitude, targets,
                 latency: int, window, block: int, ring: int = 0, rise: int = 0, beside=None, gain_top=None,
                 release=None, turn=None, noise=None, window_samples=None, amplitude_window=None):
        n = len(bank_index)
        self.n = n
        self.index = np.zeros((N_INDEX, n), dtype=np.int64)
        self.index[OBS_CH], self.index[OBS_SLOT] = obs_channel, obs_slot
        self.index[BANK], self.index[CHANNEL] = bank_index, channel
        for c in np.unique(self.index[OBS_CH]):  # the tones of one observer channel, a cycle
            same = np.flatnonzero(self.index[OBS_CH] == c)
            self.index[SIBLING, same] = np.roll(same, -1)
        self.state = np.zeros((N_STATE, n))
        self.target = np.zeros((N_TARGET, n))
        g = np.asarray(gain_model, dtype=float)
        if np.any(~np.isfinite(g)) or np.any(g <= 0):
            raise ValueError("the model's tip amplitude per volt must be finite and > 0 for every tone")
        self._ff = 1.0 / g
        self._gtop = np.full(n, np.inf)
        if gain_top is not None:
            top = np.broadcast_to(np.asarray(gain_top, dtype=float), (n,))
            if np.any(~(top >= g)):
                raise ValueError("the most tip per volt of any load must be at least the model's, per tone "
                                 "(inf: no floor)")
            self._gtop = FLOOR_MARGIN * top
        self._gmax = self._gtop / FLOOR_MARGIN
        self._release = np.full(n, -1.0)
        if release is not None:
            rel = np.broadcast_to(np.asarray(release, dtype=float), (n,))
            if gain_top is None and np.any(rel >= 0):
                raise ValueError("the release rule drops the drive to the target over gain_top: it needs gain_top")
            if np.any(np.isnan(rel)):
                raise ValueError("release: a noise allowance (m) per tone, negative for none, not NaN")
            self._release = rel.copy()
        self._amax = np.asarray(max_amplitude, dtype=float)
        self.targets0 = np.asarray(targets, dtype=float)
        self.ring = max(0, int(ring))
        if np.ndim(window) == 0:
            self.gain, self.warm = design(latency, window)
            self.hold = steady_blocks(window, self.ring)
            self.scatter = float(self.hold >= max(1, int(window)))
        else:
            w = np.asarray(window)
            if w.shape != (n,) or not np.issubdtype(w.dtype, np.integer):
                raise ValueError(f"window must be an int or one int per tone, shape ({n},)")
            designs = [design(latency, int(x)) for x in w]
            self.gain = np.array([d[0] for d in designs])
            self.warm = np.array([d[1] for d in designs], dtype=np.int64)
            self.hold = np.array([steady_blocks(int(x), self.ring) for x in w], dtype=np.int64)
            self.scatter = (self.hold >= np.maximum(1, w)).astype(float)
        self.block = int(block)
        self.rise = max(0, int(rise))
        self.slow = np.zeros(n)
        if beside is not None:
            beat, tau = (np.broadcast_to(np.asarray(x, dtype=float), (n,)) for x in beside)
            hold = np.broadcast_to(self.hold, (n,))
            self.slow = ((beat * hold < SLOW_TURNS) & (tau > hold)).astype(float)
        self.noise = np.zeros(n) if noise is None else np.broadcast_to(np.asarray(noise, dtype=float), (n,)).copy()
        if np.any(~(self.noise >= 0)) or np.any(~np.isfinite(self.noise)):
            raise ValueError("noise: each tone's estimate noise, m rms, finite and >= 0")
        self.latency = max(0, int(latency))
        ws = np.broadcast_to(np.asarray(window), (n,)) * self.block if window_samples is None else window_samples
        self.window_samples = np.broadcast_to(np.asarray(ws, dtype=float), (n,)).copy()
        wa = self.window_samples if amplitude_window is None else amplitude_window
        self.amplitude_window = np.broadcast_to(np.asarray(wa, dtype=float), (n,)).copy()
        for name, x in (("window_samples", self.window_samples), ("amplitude_window", self.amplitude_window)):
            if np.any(~np.isfinite(x)) or np.any(x < 1):
                raise ValueError(f"{name}: per tone, samples, finite and at least 1")
        self.rot = np.full(n, -1.0)
        self.turns = np.zeros(n)
        if turn is not None:
            t = np.broadcast_to(np.asarray(turn, dtype=float), (n,))
            if np.any(~np.isfinite(t)) or np.any(t < 0):
                raise ValueError("turn: each tone's own turns per block, finite and >= 0")
            # (a window sliding over a change of the plant, read within RING_K estimates, would
            # pass for a ring where it is not short against them)
            short = np.broadcast_to(np.asarray(window), (n,)) <= RING_K - 4
            self.rot = np.where(short, 2.0 * np.pi * (t % 1.0), -1.0)
            self.turns = t.copy()
        self.reset()

    @property
    def args(self) -> dict:
        """The stage's arguments after the observer's ``est`` and ``drive_est`` and before the bank's
        pending and the limiter's counts: ``amplitude_control(est, drive_est, **args..., pending,
        lim_counts, ramp)``."""
        return {"index": self.index, "target": self.target, "state": self.state}

    def reset(self) -> None:
        """Every tone off, targets back to the scene's; nothing commanded yet."""
        self.state[...] = 0.0
        self.state[FF] = self._ff
        self.state[GTOP] = self._gtop
        self.state[GMAX] = self._gmax
        self.state[JNOISE] = self._release
        self.state[AMAX] = self._amax
        self.state[GAIN] = self.gain
        self.state[WARM] = self.warm
        self.state[HOLD] = self.state[HOLD0] = self.hold
        self.state[HOLDMAX] = np.maximum(self.hold, -(-self.ring // 2))
        self.state[SCATTER] = self.scatter
        self.state[SLOW] = self.slow
        self.state[ROT] = self.rot
        self.state[NOISE] = self.noise
        self.state[WINS] = self.window_samples
        self.state[WAMP] = self.amplitude_window
        self.state[TURNS] = self.turns
        self.state[LATB] = self.latency
        self.state[RISE] = self.rise
        self.target[TARGET] = self.targets0
        self.target[ENABLE] = 0.0

    def feedforward(self, i: int) -> float:
        """The model's drive for tone ``i``'s target, V."""
        return float(min(self.targets0[i] * self._ff[i], self._amax[i]))
