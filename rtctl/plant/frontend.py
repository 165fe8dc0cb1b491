"""Drive and sense electronics of a simulated piezo channel: amplifier, shunt, AA filter, ADC.

Signal path of one channel::

    commanded V --[Amplifier: 1st-order low-pass]--> actuator V --> piezo segments
    segment current --[shunt R_s]--> V = R_s I --[Butterworth AA]--> ADC (noise, quantize, clip)

The shunt's voltage drop on the piezo is neglected: it is ``R_s I = R_s C dV/dt``, i.e. a pole at
``1 / (2 pi R_s Cp)``, which must lie far above the sample rate (``R_s Cp fs << 1``; checked
where both are known, in :class:`rtctl.plant.bimorph.SimGroup`). The analog parts (amplifier, AA
filter) are continuous-time and discretized exactly with the rest of the plant; only the ADC acts
on samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rtctl.errors import ModelError
from rtctl.plant.lti import StateSpace

__all__ = ["Amplifier", "CurrentSense", "NOISE_TABLE_LENGTHS"]

#: Noise table lengths: two primes, so any number of interleaved streams S < 2^20 - 5 is coprime
#: with both and the pair repeats only after len1 * len2 ~ 1.1e12 samples.
NOISE_TABLE_LENGTHS = (1048573, 1048571)  # 2^20 - 3, 2^20 - 5, both prime


def _positive(owner, name, value):
    v = float(value)
    if not (v > 0.0 and math.isfinite(v)):
        raise ModelError(f"{owner}.{name} must be finite and > 0, got {value!r}")
    return v


@dataclass(frozen=True)
class Amplifier:
    """Unity-gain voltage amplifier with a first-order bandwidth.

    ``V' = w_a (u - V)``, ``w_a = 2 pi bandwidth_hz``: ``V`` is the actuator voltage (V), ``u``
    the commanded voltage (V). Its state equation also gives ``dV/dt`` without differentiating
    anything, which the capacitive current needs.

    Parameters
    ----------
    bandwidth_hz : float
        -3 dB bandwidth, Hz.

    Examples
    --------
    >>> from rtctl.plant.frontend import Amplifier
    >>> amp = Amplifier(bandwidth_hz=20e3)
    >>> round(float(abs(amp.state_space().frequency_response([20e3])[0, 0, 0])), 4)
    0.7071
    """

    bandwidth_hz: float

    def __post_init__(self):
        object.__setattr__(self, "bandwidth_hz", _positive("Amplifier", "bandwidth_hz",
                                                           self.bandwidth_hz))

    @property
    def omega(self) -> float:
        """Corner angular frequency, rad/s."""
        return 2.0 * math.pi * self.bandwidth_hz

    def state_space(self) -> StateSpace:
        """One state (actuator voltage, V), input commanded voltage (V), output actuator V."""
        w = self.omega
        return StateSpace([[-w]], [[w]], [[1.0]], [[0.0]], state_names=("voltage_v",),
                          input_names=("command_v",), output_names=("voltage_v",))


@dataclass(frozen=True)
class CurrentSense:
    """Shunt current sense with a Butterworth anti-alias filter and an ADC.

    Parameters
    ----------
    shunt_ohm : float
        Shunt resistance, ohm; the ADC sees ``R_s I``.
    aa_cutoff_hz : float
        Anti-alias filter -3 dB frequency, Hz (continuous time, part of the plant).
    aa_order : int
        Butterworth order (>= 1).
    bits : int
        ADC resolution over ``[-full_scale_v, +full_scale_v)``; LSB ``2 full_scale_v / 2^bits``.
    full_scale_v : float
        ADC input range, V peak. Beyond it the reading clips and a status bit is set.
    noise_rms_v : float
        White Gaussian noise at the ADC input, V rms (>= 0).
    seed : int
        Seed of the noise tables and positions (reproducible runs).

    Notes
    -----
    Noise comes from two tables of standard normals, of prime lengths ``NOISE_TABLE_LENGTHS``,
    each shifted and scaled to exactly zero mean and unit variance, stored as float32. Stream
    ``j`` (of ``S`` interleaved streams) at sample ``t`` reads entry ``p + t S + j`` of each
    (modulo its length) and adds ``noise_rms_v / sqrt(2)`` times their sum. Statistics over a
    full table period: mean 0, variance ``noise_rms_v^2``; the autocorrelation of one stream is
    0 at lags below the table length (~1e6 samples, ~22 s at 48 kHz; the sample estimate from the
    finite tables is ~1e-3), 0.5 at multiples of one table length (one table repeats, the other
    does not); distinct streams read distinct entries at equal times (cross-correlation ~1e-3).
    The pair repeats after ``len1 * len2 ~ 1.1e12`` samples. Drawing normals at run time would
    cost ~40 % of the real-time budget.

    Examples
    --------
    >>> from rtctl.plant.frontend import CurrentSense
    >>> cs = CurrentSense(shunt_ohm=100.0, aa_cutoff_hz=15e3, bits=24, full_scale_v=2.5)
    >>> cs.aa_filter().n_states
    2
    >>> cs.lsb_v == 5.0 / 2**24
    True
    """

    shunt_ohm: float
    aa_cutoff_hz: float
    aa_order: int = 2
    bits: int = 24
    full_scale_v: float = 2.5
    noise_rms_v: float = 1e-5
    seed: int = 0

    def __post_init__(self):
        set_ = object.__setattr__
        for name in ("shunt_ohm", "aa_cutoff_hz", "full_scale_v"):
            set_(self, name, _positive("CurrentSense", name, getattr(self, name)))
        if int(self.aa_order) != self.aa_order or not 1 <= int(self.aa_order) <= 8:
            raise ModelError(f"CurrentSense.aa_order must be an integer 1..8, got "
                             f"{self.aa_order!r}")
        if int(self.bits) != self.bits or not 2 <= int(self.bits) <= 32:
            raise ModelError(f"CurrentSense.bits must be an integer 2..32, got {self.bits!r}")
        nr = float(self.noise_rms_v)
        if not (nr >= 0.0 and math.isfinite(nr)):
            raise ModelError(f"CurrentSense.noise_rms_v must be finite and >= 0, got {nr!r}")
        set_(self, "aa_order", int(self.aa_order))
        set_(self, "bits", int(self.bits))
        set_(self, "noise_rms_v", nr)
        set_(self, "seed", int(self.seed))

    @property
    def lsb_v(self) -> float:
        """ADC step, V."""
        return 2.0 * self.full_scale_v / 2.0 ** self.bits

    @property
    def code_range(self) -> tuple:
        """Lowest and highest output code, ``(-2^(bits-1), 2^(bits-1) - 1)``."""
        return -(2.0 ** (self.bits - 1)), 2.0 ** (self.bits - 1) - 1.0

    def same_analog(self, other: CurrentSense) -> bool:
        """True if ``other`` has the same shunt and AA filter (the parts inside the plant)."""
        return (self.shunt_ohm, self.aa_cutoff_hz, self.aa_order) == \
            (other.shunt_ohm, other.aa_cutoff_hz, other.aa_order)

    def aa_filter(self) -> StateSpace:
        """Butterworth low-pass, unity DC gain, current in (A) to filtered current out (A).

        Realized as a cascade of sections with states ``[y, y'/w_c]`` (both in the unit of the
        signal, so the states are equally scaled): a second-order section
        ``y'' + (w/Q) y' + w^2 y = w^2 u`` per pole pair, ``Q = 1 / (2 sin((2k + 1) pi / 2n))``,
        and ``y' = w (u - y)`` for an odd order.
        """
        n = self.aa_order
        w = 2.0 * math.pi * self.aa_cutoff_hz
        A = np.zeros((n, n))
        B = np.zeros((n, 1))
        C = np.zeros((1, n))
        i = 0
        prev = None  # index of the previous section's output state
        for k in range(n // 2):
            q = 1.0 / (2.0 * math.sin((2 * k + 1) * math.pi / (2 * n)))
            A[i, i + 1] = w
            A[i + 1, i] = -w
            A[i + 1, i + 1] = -w / q
            if prev is None:
                B[i + 1, 0] = w
            else:
                A[i + 1, prev] += w
            prev = i
            i += 2
        if n % 2:
            A[i, i] = -w
            if prev is None:
                B[i, 0] = w
            else:
                A[i, prev] += w
            prev = i
        C[0, prev] = 1.0
        return StateSpace(A, B, C, np.zeros((1, 1)),
                          state_names=tuple(f"aa{j}" for j in range(n)),
                          input_names=("current_a",), output_names=("aa_current_a",))

    def noise_tables(self):
        """The two seeded noise tables (float32, zero mean, unit variance), unpadded."""
        rng = np.random.default_rng(self.seed)
        out = []
        for n in NOISE_TABLE_LENGTHS:
            t = rng.standard_normal(n)
            t = (t - t.mean()) / t.std()
            out.append(t.astype(np.float32))
        return out[0], out[1]

    def noise_start(self, seed=None):
        """Seeded start positions ``(p1, p2)`` in the two tables."""
        rng = np.random.default_rng([self.seed if seed is None else int(seed), 1])
        return np.array([rng.integers(0, n) for n in NOISE_TABLE_LENGTHS], dtype=np.int64)
