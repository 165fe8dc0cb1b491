"""The final limiter: the last stage of every block, which no controller bug can bypass.

Per channel and sample, in this order:

1. a non-finite request (NaN/Inf from any upstream bug) becomes 0 V and raises ``NONFINITE``;
2. during a fault's shutdown the request is ignored and replaced by a linear fade of the last
   output to zero (so a fault brings every output to 0 V within the fade length, one block by
   default); during a requested stop's (end of run, Ctrl-C) the request is multiplied by a
   raised-cosine release ``(1 + cos(pi k / N)) / 2`` over ``timing.stop_fade`` (tens of ms: the
   stimulus fades out instead of ending in a tap), and every later step still applies;
3. the voltage is clipped to +-``max_voltage`` (``LIMIT_VOLTAGE``);
4. the change per sample is clipped to ``min(slew, current / C) / fs`` (``LIMIT_SLEW``): a piezo is a
   capacitor, so the drive current is ``C dV/dt`` and limiting the slope limits the current;
5. a running mean, updated once per block, is kept within a bound by lowering the block's
   ceiling (``LIMIT_DC``: a piezo's mean voltage, ``|m| <= dc_offset``, against depolarisation
   and creep from a DC component; ``LIMIT_DUTY``: an SMA spring's heating duty, the mean of
   ``(v / V_max)^2`` of one polarity, ``<= duty``, against a spring held powered);
6. a lumped thermal model integrates the dielectric loss: for a sine of amplitude V at angular
   frequency w the loss is ``tan(delta) w C V^2 / 2``, which is exactly the cycle mean of
   ``(pi/2) tan(delta) C |v dv/dt|``, the instantaneous form used here (approximate for several
   tones). ``T' = (T_amb + R_th P - T) / tau_th``; above ``temperature`` it raises ``OVERTEMP``.

Coil actuators (electromagnetic, solenoid, Dot, SMA wires) are resistive, not capacitive: a
channel built with ``capacitance = 0`` and a ``resistance`` R instead has its current bounded by
a voltage bound ``|v| <= current * R`` (the steady-state coil current V/R never exceeds the limit;
the inductance only delays it), only the slew bound on the slope, and Joule heating ``v^2 / R``
in the thermal model.

The motional part of the current is not included in 4: for the demo bimorph it adds 6-10 % to the
capacitive current below 100 Hz, 14 % at 500 Hz and up to a third near the first resonance, so
``current`` should be set with that margin.
"""

from __future__ import annotations

import math

import numpy as np

from ._numba import kernel

LIMIT_VOLTAGE = 1
LIMIT_SLEW = 2
NONFINITE = 4
OVERTEMP = 8
SENSOR_SATURATED = 16
PLANT_NONFINITE = 32
DEADLINE_MISSED = 64
DEVICE_LOST = 128
IO_XRUN = 256
ESTIMATE_NONFINITE = 512
LIMIT_DC = 1024
LIMIT_DUTY = 2048
XRUN_BURST = 4096
CONTROL_SATURATED = 8192
CONTROL_FROZEN = 16384
TRACE_DROPPED = 32768  # a trace placeholder: the loop dropped this block's record (ring full)
CONTROL_FLOOR = 65536

#: Status bits that end a run (outputs fade to zero first).
FAULTS = NONFINITE | OVERTEMP | PLANT_NONFINITE | DEVICE_LOST | XRUN_BURST

STATUS_NAMES = {
    LIMIT_VOLTAGE: "voltage limited",
    LIMIT_SLEW: "slew/current limited",
    NONFINITE: "non-finite drive request (NaN/Inf) replaced by 0 V",
    OVERTEMP: "actuator over temperature",
    SENSOR_SATURATED: "current sensor saturated",
    PLANT_NONFINITE: "simulated plant state became non-finite",
    DEADLINE_MISSED: "block deadline missed",
    DEVICE_LOST: "I/O device lost (unplugged, stalled or not answering)",
    IO_XRUN: "audio under/overflow (xrun)",
    ESTIMATE_NONFINITE: "self-sensing estimate non-finite (a sensed reading was NaN/Inf)",
    LIMIT_DC: "DC offset limited (a piezo's running mean voltage held at limits.dc_offset)",
    LIMIT_DUTY: "duty limited (an SMA spring's running heating duty held at limits.duty)",
    XRUN_BURST: "audio xrun burst (more than io.xrun_limit under/overflows within io.xrun_window)",
    CONTROL_SATURATED: "amplitude control saturated (a target needs more than the channel's max_voltage)",
    CONTROL_FROZEN: "amplitude control frozen (no usable estimate: drive held, never raised)",
    TRACE_DROPPED: "trace record dropped (the trace ring was full; the block itself ran)",
    CONTROL_FLOOR: ("amplitude control held at its floor (the estimate asked for less drive than any load the "
                    "model knows needs for the target: for a moment, a ring after an event; for long, an estimate "
                    "that does not follow the tip, e.g. a target under the self-sensing noise floor; see floor_s)"),
}

#: Shapes of a shutdown fade (``fade[2]``): linear (a fault: the shortest fade the slew bound
#: allows) or raised cosine (a requested stop: zero slope at both ends, felt as a smooth release).
FADE_LINEAR, FADE_COSINE = 0, 1

# limiter state rows: last output V, temperature, fade start V, running means (see below)
_V, _T, _FADE_FROM, _MEAN_P, _MEAN_N = range(5)
# limiter parameter rows
(_VMAX, _DVMAX, _HEAT, _RTH, _ALPHA, _TAMB, _TMAX, _JOULE,
 _MKIND, _MBOUND, _MALPHA, _MSCALE, _MCMD) = range(13)
#: kinds of running-mean bound (``_MKIND``): none, a piezo's DC offset, an SMA spring's duty
#: (heating power), an SMA spring's duty behind a pin controller (commanded time)
MEAN_OFF, MEAN_DC, MEAN_DUTY, MEAN_DUTY_CMD = 0, 1, 2, 3
#: :func:`_mean_stage`'s private bit: it rewrote the block (the caller sums it again)
_ROW_LOWERED = 1 << 30
_MAX_ROOT_STEPS = 200  # of the ceiling's root search; 25 bisections alone reach its tolerance


@kernel
def _capped_measure(row, v0, dv, h, sign, kind, h_cmd):
    """The block's measure after a ceiling ``h`` on ``sign * row`` that is approached from the
    previous output ``v0`` no faster than the slope bound ``dv`` (so the ceiling never makes a
    step the slew clamp forbade): the mean of ``sign * v`` (``MEAN_DC``) or the mean of
    ``max(sign * v, 0)**2`` (``MEAN_DUTY``, times ``_MSCALE`` by the caller) or the fraction of
    samples above the command threshold ``h_cmd`` (``MEAN_DUTY_CMD``)."""
    n = row.shape[0]
    s = 0.0
    sv0 = sign * v0
    for i in range(n):
        u = min(sign * row[i], max(h, sv0 - (i + 1) * dv))
        if kind == MEAN_DC:
            s += u
        elif kind == MEAN_DUTY:
            p = max(u, 0.0)
            s += p * p
        else:
            s += u > h_cmd
    return s / n


@kernel
def _bound_mean(row, v0, dv, vmax, sign, kind, scale, h_cmd, target):
    """Lower a ceiling on ``sign * row`` until the block's measure is at most ``target``; apply
    it in place and return the number of samples lowered (by more than rounding).

    The measure is continuous, non-decreasing and piecewise linear in the ceiling, so regula
    falsi (the Illinois variant, with a bisection step whenever it stalls) lands on the root
    exactly once both ends lie on the root's linear piece: a few evaluations instead of a
    bisection's 64. The end kept is the lower one, whose measure is at most the target. A pin
    command (``MEAN_DUTY_CMD``) is on or off, its measure a step: the block's commands of that
    polarity are switched off (ceiling 0), which holds the commanded time to the bound block by
    block. If even the lowest ceiling (``-vmax`` for a DC bound, 0 for a duty bound) exceeds the target,
    because the slope bound forbids leaving the previous output fast enough, the lowest is used.
    """
    lo = -vmax if kind == MEAN_DC else 0.0
    hi = lo
    for i in range(row.shape[0]):
        hi = max(hi, sign * row[i])
    if kind == MEAN_DUTY_CMD:
        hi = lo
    f_lo = scale * _capped_measure(row, v0, dv, lo, sign, kind, h_cmd) - target
    f_hi = scale * _capped_measure(row, v0, dv, hi, sign, kind, h_cmd) - target
    if f_hi <= 0.0:  # the block meets the target already (the caller's test rounded the other way)
        lo = hi
    elif f_lo < 0.0:
        tol = 1e-13 * vmax
        side = 0
        for it in range(_MAX_ROOT_STEPS):
            if hi - lo <= tol:
                break
            h = (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
            if not (lo < h < hi) or it % 8 == 7:  # a bisection now and then bounds the worst case
                h = 0.5 * (lo + hi)
            f = scale * _capped_measure(row, v0, dv, h, sign, kind, h_cmd) - target
            if f <= 0.0:
                lo, f_lo = h, f
                if f == 0.0:
                    break
                if side < 0:
                    f_hi *= 0.5
                side = -1
            else:
                hi, f_hi = h, f
                if side > 0:
                    f_lo *= 0.5
                side = 1
    changed = 0
    sv0 = sign * v0
    ulps = 1e-12 * vmax  # a slew-clamped sample and the ceiling's slope may differ by rounding only
    for i in range(row.shape[0]):
        u = sign * row[i]
        c = min(u, max(lo, sv0 - (i + 1) * dv))
        changed += u - c > ulps
        row[i] = sign * c
    return changed


@kernel
def limit_block(x, state, params, fade, counts):
    """Limit ``x`` (n_channels, n) in place; return the OR of status bits raised.

    ``state`` (5, n_channels): last output V, temperature degC, fade start V, running means
    (``MEAN_DC``: the mean voltage; ``MEAN_DUTY``: the duty of the positive and the negative
    polarity).
    ``params`` (13, n_channels): see the row constants (``_ALPHA`` holds 1 / (fs tau_th),
    ``_JOULE`` 1 / R for a coil, 0 for a piezo; ``_MKIND`` the kind of mean bound, ``_MBOUND``
    its bound (V or a fraction), ``_MALPHA`` 1 / (fs tau_mean), ``_MSCALE`` 1 / V_max^2 for duty,
    ``_MCMD`` the pin-command threshold for ``MEAN_DUTY_CMD``).
    ``fade`` int64 (3,): samples done and length of a shutdown fade (length 0 = running), and its
    shape (``FADE_LINEAR`` or ``FADE_COSINE``).
    ``counts`` int64 (3, n_channels): samples voltage-limited, slew-limited and mean-limited.

    Per channel, passes over the contiguous row: (1) NaN/Inf -> 0 or the fade, voltage clip;
    (2) the largest step, which needs no recursion; only if it exceeds the slew bound does
    (3) the sequential slew clamp run. Requests that respect the slew bound, the normal case,
    thus cost no dependency chain. (4) The running mean, updated once per block from the block's
    mean: only if the update would leave the bound is the block lowered (:func:`_bound_mean`).
    The heat of the block is integrated once per block: the thermal time constant (seconds) is
    far longer than a block (under a millisecond).
    """
    n_ch, n = x.shape
    fading = fade[1] > 0
    hard = fading and fade[2] == FADE_LINEAR
    status = 0
    # One-pole factors 1 - exp(-n alpha): channels usually share alpha, so each is computed
    # again only when alpha differs from the previous channel's (same input, same value).
    al_th = math.nan
    a_th = 0.0
    al_m = math.nan
    a_m = 0.0
    for c in range(n_ch):
        row = x[c]
        vmax = params[_VMAX, c]
        dvmax = params[_DVMAX, c]
        v0 = state[_V, c]
        if hard:  # the request is ignored: fade from the last output to zero
            f0 = state[_FADE_FROM, c]
            for i in range(n):
                k = fade[0] + i + 1
                row[i] = f0 * (1.0 - k / fade[1]) if k < fade[1] else 0.0
        else:
            # v * 0 is 0 for finite v and NaN for NaN/Inf: one vectorizable probe instead of a
            # branch per sample (a per-sample isfinite stops LLVM vectorizing the loop).
            # Four accumulators: each term is 0 or NaN, so any order gives the same verdict,
            # and four short chains instead of one of n dependent adds (latency-bound).
            p0 = 0.0
            p1 = 0.0
            p2 = 0.0
            p3 = 0.0
            i = 0
            while i + 4 <= n:
                p0 += row[i] * 0.0
                p1 += row[i + 1] * 0.0
                p2 += row[i + 2] * 0.0
                p3 += row[i + 3] * 0.0
                i += 4
            while i < n:
                p0 += row[i] * 0.0
                i += 1
            probe = (p0 + p1) + (p2 + p3)
            if probe != 0.0:
                status |= NONFINITE
                for i in range(n):
                    if not math.isfinite(row[i]):
                        row[i] = 0.0
            if fading:  # a requested stop: the request under a raised-cosine release
                w = math.pi / fade[1]
                for i in range(n):
                    k = fade[0] + i + 1
                    row[i] *= 0.5 * (1.0 + math.cos(w * k)) if k < fade[1] else 0.0
        # Voltage clip and the largest step in one pass; the maximum is exact in any order, so
        # even and odd samples keep a running maximum each (two chains of n / 2).
        n_v = 0
        s0 = 0.0
        s1 = 0.0
        prev = v0
        i = 0
        while i + 2 <= n:
            v = row[i]
            w = row[i + 1]
            n_v += (v > vmax) | (v < -vmax)
            n_v += (w > vmax) | (w < -vmax)
            cv = min(max(v, -vmax), vmax)
            cw = min(max(w, -vmax), vmax)
            row[i] = cv
            row[i + 1] = cw
            s0 = max(s0, abs(cv - prev))
            s1 = max(s1, abs(cw - cv))
            prev = cw
            i += 2
        if i < n:
            v = row[i]
            n_v += (v > vmax) | (v < -vmax)
            cv = min(max(v, -vmax), vmax)
            row[i] = cv
            s0 = max(s0, abs(cv - prev))
        if n_v:
            counts[0, c] += n_v
            status |= LIMIT_VOLTAGE
        step = max(s0, s1)
        if step > dvmax:
            n_s = 0
            prev = v0
            for i in range(n):
                v = row[i]
                lo = prev - dvmax
                hi = prev + dvmax
                n_s += (v > hi) | (v < lo)
                prev = min(max(v, lo), hi)
                row[i] = prev
            if n_s:
                counts[1, c] += n_s
                status |= LIMIT_SLEW
        # The block's sum (for a DC bound), heat and Joule sums in one pass: three independent
        # chains, each summed in sample order as before. Recomputed only if the mean stage
        # lowered the block.
        kind = params[_MKIND, c]
        bsum = row[0]
        heat = abs(row[0] * (row[0] - v0))
        joule = row[0] * row[0]
        for i in range(1, n):
            bsum += row[i]
            heat += abs(row[i] * (row[i] - row[i - 1]))
            joule += row[i] * row[i]
        if kind != MEAN_OFF:
            if params[_MALPHA, c] != al_m:
                al_m = params[_MALPHA, c]
                a_m = -math.expm1(-n * al_m)
            ms = 0
            if kind == MEAN_DC:  # the usual case, the mean within its bound, without a call
                m = state[_MEAN_P, c]
                new = m + a_m * (bsum / n - m)
                if abs(new) > params[_MBOUND, c] and not hard:
                    ms = _mean_stage(row, state, params, counts, c, v0, dvmax, vmax, kind, hard, bsum, a_m)
                else:
                    state[_MEAN_P, c] = new
            else:
                ms = _mean_stage(row, state, params, counts, c, v0, dvmax, vmax, kind, hard, bsum, a_m)
            if ms & _ROW_LOWERED:
                heat = abs(row[0] * (row[0] - v0))
                joule = row[0] * row[0]
                for i in range(1, n):
                    heat += abs(row[i] * (row[i] - row[i - 1]))
                    joule += row[i] * row[i]
            status |= ms & ~_ROW_LOWERED
        power = (params[_HEAT, c] * heat + params[_JOULE, c] * joule) / n
        if params[_ALPHA, c] != al_th:
            al_th = params[_ALPHA, c]
            a_th = -math.expm1(-n * al_th)
        t = state[_T, c]
        t += a_th * (params[_TAMB, c] + params[_RTH, c] * power - t)
        state[_T, c] = t
        state[_V, c] = row[n - 1]
        if t > params[_TMAX, c]:
            status |= OVERTEMP
    if fading:
        fade[0] += n
    return status


@kernel
def _mean_stage(row, state, params, counts, c, v0, dvmax, vmax, kind, fading, bsum, a):
    """Step (4) of :func:`limit_block` for channel ``c``: ``m <- m + A (b - m)`` with ``b`` the
    block's measure and ``A = 1 - exp(-n / (fs tau))`` (the exact one-pole over a block whose
    measure is held), kept within the bound: a block that would carry ``m`` past it is lowered
    to the measure ``g + (D - g) / A`` that puts ``m`` exactly on it. A shutdown fade is never
    changed (the fade goes to 0 V, which only ever brings a mean back); its blocks still count."""
    n = row.shape[0]  # ``a`` = -expm1(-n params[_MALPHA, c]), from the caller
    bound = params[_MBOUND, c]
    scale = params[_MSCALE, c]
    status = 0
    if kind == MEAN_DC:
        b = bsum / n  # the caller's sum of the row (0.0 + row[0] + ... in that order)
        m = state[_MEAN_P, c]
        new = m + a * (b - m)
        if abs(new) > bound and not fading:
            sign = 1.0 if new > 0.0 else -1.0
            g = sign * m
            changed = _bound_mean(row, v0, dvmax, vmax, sign, kind, 1.0, 0.0, g + (bound - g) / a)
            status |= _ROW_LOWERED
            if changed:
                counts[2, c] += changed
                status |= LIMIT_DC
            b = 0.0
            for i in range(n):
                b += row[i]
            new = m + a * (b / n - m)
        state[_MEAN_P, c] = new
        return status
    h_cmd = params[_MCMD, c]
    # both polarities' measures before either is lowered: a ceiling on one leaves the other be
    bp = 0.0
    bn = 0.0
    if kind == MEAN_DUTY:
        for i in range(n):
            p = max(row[i], 0.0)
            q = min(row[i], 0.0)
            bp += p * p
            bn += q * q
        bp *= scale / n
        bn *= scale / n
    else:
        for i in range(n):
            bp += row[i] > h_cmd
            bn += row[i] < -h_cmd
        bp /= n
        bn /= n
    for r in range(2):
        g = state[_MEAN_P + r, c]
        b = bp if r == 0 else bn
        new = g + a * (b - g)
        if new > bound and not fading:
            sign = 1.0 if r == 0 else -1.0
            changed = _bound_mean(row, v0, dvmax, vmax, sign, kind, scale, h_cmd, g + (bound - g) / a)
            status |= _ROW_LOWERED
            if changed:
                counts[2, c] += changed
                status |= LIMIT_DUTY
            b = scale * _capped_measure(row, v0, dvmax, math.inf, sign, kind, h_cmd)
            new = g + a * (b - g)
        state[_MEAN_P + r, c] = new
    return status


@kernel
def fade_length(state, params):
    """Shortest linear shutdown fade, samples, that the slew bound lets reach 0 V from the last
    outputs (see :meth:`Limiter.shutdown`); callable from a device thread."""
    need = 0.0
    for c in range(state.shape[1]):
        if params[_DVMAX, c] > 0.0:
            need = max(need, abs(state[_V, c]) / params[_DVMAX, c])
    return int(math.floor(need)) + 1


class Limiter:
    """Per-channel limits and state of the final limiter.

    Parameters
    ----------
    fs : float
        Sample rate, Hz.
    max_voltage, slew, current, capacitance, temperature, ambient, loss_tangent,
    thermal_resistance, thermal_tau : array_like, shape (n_channels,)
        V, V/s, A, F, degC, degC, -, K/W, s (broadcast from scalars).
    resistance : array_like
        Ohm, for coil channels (capacitance 0).
    dc_offset, dc_tau : array_like
        Bound (V) on a piezo channel's running mean voltage and the mean's time constant (s);
        inf: no bound. Piezo channels only.
    duty, duty_tau : array_like
        Bound (fraction of full power ``max_voltage^2 / R``, each polarity on its own) on a coil
        channel's running heating duty and its time constant (s); inf: no bound. Meant for
        SMA springs (an antagonistic pair: + heats one spring, - the other).

    Examples
    --------
    >>> lim = Limiter(48000.0, max_voltage=[10.0], slew=[1e9], current=[1.0], capacitance=[1e-9],
    ...               temperature=[80.0], ambient=[25.0], loss_tangent=[0.02],
    ...               thermal_resistance=[100.0], thermal_tau=[10.0])
    >>> x = np.array([[5.0, 50.0, np.nan]])
    >>> status = lim.process(x)
    >>> x.tolist(), bool(status & LIMIT_VOLTAGE), bool(status & NONFINITE)
    ([[5.0, 10.0, 0.0]], True, True)
    """

    def __init__(self, fs, *, max_voltage, slew, current, capacitance, temperature, ambient,
                 loss_tangent, thermal_resistance, thermal_tau, resistance=0.0,
                 dc_offset=np.inf, dc_tau=10.0, duty=np.inf, duty_tau=2.0):
        vmax = np.atleast_1d(np.asarray(max_voltage, dtype=float))
        n = vmax.size
        b = lambda a: np.broadcast_to(np.asarray(a, dtype=float), (n,))  # noqa: E731
        cap, res = b(capacitance), b(resistance)
        if not (np.all(np.isfinite(vmax)) and np.all(vmax > 0)):
            raise ValueError(f"max_voltage must be finite and > 0, got {vmax}")
        coil = cap == 0.0
        if not np.all((cap > 0) | (coil & (res > 0))):
            raise ValueError(f"each channel needs capacitance > 0 F (piezo) or capacitance 0 and "
                             f"resistance > 0 ohm (coil), got C = {cap}, R = {res}")
        dc, dcy = b(dc_offset), b(duty)
        if np.any(np.isfinite(dc) & coil) or np.any(np.isfinite(dcy) & ~coil):
            raise ValueError("dc_offset bounds piezo channels (capacitance > 0) and duty coil "
                             f"channels (SMA springs); got dc_offset = {dc}, duty = {dcy} for C = {cap}")
        if np.any(dc <= 0) or np.any((dcy <= 0) | (dcy > 1) & np.isfinite(dcy)):
            raise ValueError(f"dc_offset must be > 0 V and duty in (0, 1], got {dc}, {dcy}")
        if np.any(b(dc_tau) <= 0) or np.any(b(duty_tau) <= 0):
            raise ValueError(f"dc_tau and duty_tau must be > 0 s, got {dc_tau}, {duty_tau}")
        # The current limit is a slope limit on a capacitor: |dV/dt| <= I_max / C; on a coil it
        # is a voltage bound |V| <= I_max R.
        with np.errstate(divide="ignore"):
            slope = np.where(coil, b(slew), np.minimum(b(slew), b(current) / np.where(coil, 1.0, cap)))
            vmax = np.where(coil, np.minimum(vmax, b(current) * np.where(coil, res, 1.0)), vmax)
        self.fs = float(fs)
        self.params = np.empty((13, n))
        self.params[_VMAX] = vmax
        self.params[_JOULE] = np.where(coil, 1.0 / np.where(coil, res, 1.0), 0.0)
        self.params[_DVMAX] = slope / self.fs
        self.params[_HEAT] = 0.5 * np.pi * b(loss_tangent) * cap * self.fs
        self.params[_RTH] = b(thermal_resistance)
        self.params[_ALPHA] = 1.0 / (self.fs * b(thermal_tau))
        self.params[_TAMB] = b(ambient)
        self.params[_TMAX] = b(temperature)
        # Running-mean bounds: a piezo's DC offset in V; an SMA spring's duty as a fraction of
        # full power (max_voltage^2 / R: for on/off drive at max_voltage, the fraction of time on).
        on_dc, on_duty = np.isfinite(dc), np.isfinite(dcy)
        self.params[_MKIND] = np.where(on_dc, MEAN_DC, np.where(on_duty, MEAN_DUTY, MEAN_OFF))
        self.params[_MBOUND] = np.where(on_dc, dc, np.where(on_duty, dcy, np.inf))
        self.params[_MALPHA] = 1.0 / (self.fs * np.where(on_dc, b(dc_tau), b(duty_tau)))
        self.params[_MSCALE] = 1.0 / vmax**2
        self.params[_MCMD] = np.inf  # pin-command threshold (commands_only)
        self.state = np.zeros((5, n))
        self.fade = np.zeros(3, dtype=np.int64)
        self.counts = np.zeros((3, n), dtype=np.int64)
        self.reset()

    @property
    def args(self):
        """Arrays in :func:`limit_block` order, after ``x``."""
        return (self.state, self.params, self.fade, self.counts)

    def process(self, x: np.ndarray) -> int:
        """Limit ``x`` (n_channels, n) in place; return the status bits."""
        return limit_block(x, *self.args)

    def shutdown(self, n_samples: int, smooth: bool = False) -> int:
        """Fade every output to 0 V; return the fade length.

        A fault's fade ignores the request and ramps the last output linearly to zero over
        ``n_samples``, or longer where the slew bound needs it: a linear fade from ``v`` over
        ``N`` samples steps ``v / N`` per sample, so ``N >= |v| / dV_max`` keeps the slew clamp
        from stopping it short of zero (one sample more, so rounding never makes the fade's step
        exceed the bound). A requested stop's (``smooth``) multiplies the request by a raised
        cosine ``(1 + cos(pi k / N)) / 2`` over ``N = n_samples`` (its slope zero at both ends),
        then 0; the slew clamp and the other bounds still act on the product. A fault during a
        smooth fade starts a fault's fade from the outputs it reached.
        """
        need = 1 if smooth else fade_length(self.state, self.params)
        self.state[_FADE_FROM] = self.state[_V]
        self.fade[0] = 0
        self.fade[1] = max(int(n_samples), need, 1)
        self.fade[2] = FADE_COSINE if smooth else FADE_LINEAR
        return int(self.fade[1])

    @property
    def smooth_stop(self) -> bool:
        """A requested stop's raised-cosine fade is running or done (not a fault's)."""
        return bool(self.fade[1] > 0 and self.fade[2] == FADE_COSINE)

    @property
    def done(self) -> bool:
        """A shutdown fade has run its length and every output is at 0 V."""
        return bool(self.fade[1] > 0 and self.fade[0] >= self.fade[1] and not np.any(self.state[_V]))

    def commands_only(self, threshold=None) -> None:
        """The outputs are pin commands to a controller whose firmware pulses the coils (Dot: a
        3 ms pulse per change) and guards them (SMA: its thermal cutoff), not coil voltages: no
        Joule heating from a held level. The voltage bound stays. A duty bound then counts
        commanded time: a sample beyond +-``threshold`` (V, per channel; the controller's
        up/down threshold) is a spring heated at the firmware's full power."""
        self.params[_JOULE] = 0.0
        duty = self.params[_MKIND] == MEAN_DUTY
        if np.any(duty):
            if threshold is None:
                raise ValueError("commands_only needs the pin-command threshold for duty-bounded channels")
            self.params[_MCMD] = np.where(duty, np.broadcast_to(threshold, duty.shape), np.inf)
            self.params[_MSCALE] = np.where(duty, 1.0, self.params[_MSCALE])
            self.params[_MKIND] = np.where(duty, MEAN_DUTY_CMD, self.params[_MKIND])

    def bounds(self) -> dict:
        """What this limiter promises, per channel, as plain lists (a trace's ``meta.limits``, which
        :mod:`rtctl.check` verifies sample by sample): ``max_voltage`` (V), ``max_step`` (V per
        sample), the running-mean bound (``mean_kind``, ``mean_bound``, ``mean_alpha`` per sample,
        ``mean_scale``, ``mean_threshold``) and ``temperature`` (degC)."""
        p = self.params
        return {"fs": self.fs, "max_voltage": p[_VMAX].tolist(), "max_step": p[_DVMAX].tolist(),
                "mean_kind": p[_MKIND].astype(int).tolist(), "mean_bound": p[_MBOUND].tolist(),
                "mean_alpha": p[_MALPHA].tolist(), "mean_scale": p[_MSCALE].tolist(),
                "mean_threshold": p[_MCMD].tolist(), "temperature": p[_TMAX].tolist()}

    @property
    def temperature(self) -> np.ndarray:
        return self.state[_T]

    @property
    def mean_kind(self) -> np.ndarray:
        """Per channel, the running-mean bound it has: ``MEAN_OFF``, ``MEAN_DC``, ``MEAN_DUTY``
        or ``MEAN_DUTY_CMD``."""
        return self.params[_MKIND]

    @property
    def mean(self) -> np.ndarray:
        """Running means (2, n_channels): a piezo's DC offset (V) in row 0; an SMA spring's duty
        in rows 0 (positive drive) and 1 (negative); 0 where no bound applies."""
        return self.state[_MEAN_P:_MEAN_N + 1]

    @property
    def last(self) -> np.ndarray:
        return self.state[_V]

    def reset(self) -> None:
        self.state[:] = 0.0
        self.state[_T] = self.params[_TAMB]
        self.fade[:] = 0
        self.counts[:] = 0


def describe(status: int) -> list[str]:
    """Human names of the bits set in ``status``."""
    return [name for bit, name in STATUS_NAMES.items() if status & bit]
