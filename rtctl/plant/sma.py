"""SMA antagonistic taxel (seed 002): two NiTi helical springs pulling a pin up and down.

Continuous model of one taxel (input: signed voltage ``u``, V; external finger force ``F_e``
pressing the pin down, N). Spring ``j`` = ``u`` (raise, above the pin) or ``l`` (lower)::

    m c T_j'   = P_j - h A (T_j - T_amb),     P_u = u^2/R if u > 0,  P_l = u^2/R if u < 0
    gam_i      = s_i kappa delta_j,  kappa = d / (pi D^2 N)          shear strain of shell i
    g_i'       = (clip(g_i, lo_i, hi_i) - g_i) / t_relax             transformation strain
    lo_i       = max(0, gam_i - tau_L(T_j)/G(T_j)),  hi_i = max(0, gam_i - tau_U(T_j)/G(T_j))
    P_j        = (pi d^3 / 2D) sum_i w_i s_i^2 G(T_j) (gam_i - g_i)  spring force (Gauss in r)
    0          = P_u(delta0 - x) - P_l(delta0 + x) - F_e             massless pin, x in stops

``tau_L(T) = max(tau_cr, c_M (T - M_s))`` (loading: reorientation plateau, then Tobushi-Tanaka's
line), ``tau_U(T) = c_A (T - A_s)`` (unloading), ``G`` ramps from ``G_M`` to ``G_A`` between the
DSC temperatures ``A_s`` and ``A_f``. Under monotone loading from the memorized shape the shells
reproduce Tobushi & Tanaka's Eq. (1) of seed 002 (elastic core, transformed rim); on unloading
and reheating they give the hysteresis and the shape-memory recovery that make the taxel
bistable. ``t_relax`` (2 ms) is a viscoplastic regularization of the rate-independent law: it
makes the model an ODE a scipy integrator can run and is far below the thermal time constants
(0.4 .. 3 s). Derivation, parameter sources and the calibration: ``docs/plants/sma.md``.
"""

from __future__ import annotations

import math

import numpy as np

from rtctl.errors import ModelError
from rtctl.plant import _sma_kernels as _k
from rtctl.plant._checks import positive

__all__ = ["SmaTaxel", "SmaGroup", "sma_group_process", "TRUTH_NAMES"]

TRUTH_NAMES = ("pin_m", "pin_velocity_m_s", "finger_force_n", "voltage_v")

#: Real-time kernel of :class:`SmaGroup`: ``sma_group_process(*group.args, drive, sensed, truth)``.
sma_group_process = _k.sma_group_process

COOLING = ("still", "forced")


def _positive(name, v):
    return positive("SMA taxel:", name, v)


class SmaTaxel:
    """Continuous-time model of one antagonistic SMA taxel (seed 002, Figs. 5-7, 9, 11).

    Parameters (SI; temperatures in degC; defaults are the seed's values or the calibration of
    ``docs/plants/sma.md``)
    ----------
    wire_diameter, coil_diameter : float
        Wire diameter ``d`` (200 um) and *mean* coil diameter ``D`` (1.5 mm outer - d), m.
    n_coils : int
        Active coils ``N`` (12).
    prestrain : float
        Installation deflection ``delta0`` of both springs, m (2.3 mm); pin height 0 there.
    g_austenite, g_martensite : float
        Shear moduli ``G_A``, ``G_M``, Pa (28.2 GPa, 10.5 GPa; Tobushi & Tanaka).
    tau_cr : float
        Low-temperature loading stress (R/M reorientation plateau), Pa. Fitted: 180 mN at 10 mm,
        20 degC (seed Fig. 4a).
    c_m, m_s : float
        Loading line ``c_M (T - M_s)``, Pa/K and degC. Fitted to 410 mN at 85 degC and 720 mN at
        105 degC (seed Fig. 4a): 4.85 MPa/K, 58.75 degC (the DSC R_s is 59 degC).
    c_a, a_s : float
        Unloading line ``c_A (T - A_s)``: c_A = 4.9 MPa/K (seed); A_s = 65 degC (the DSC A_f;
        with the DSC A_s of 28 degC the unloading stress would exceed the loading one).
    ramp_start, ramp_end : float
        Temperatures over which ``G`` goes from ``G_M`` to ``G_A``: DSC A_s and A_f (28, 65).
    density, specific_heat, resistivity : float
        Flexinol: 6450 kg/m^3, 837 J/(kg K), 1.0e-6 ohm m (austenite).
    resistance : float or None
        Circuit resistance of one spring, ohm; default: the active wire's, ``rho_e L / a``.
    h_still, h_forced : float
        Convection coefficients, W/(m^2 K), fitted to the seed's bandwidths (Fig. 11).
    cooling : {"still", "forced"}
        Which coefficient applies (forced = the mini-fan).
    t_ambient : float
        Ambient temperature, degC (20, the seed's room-temperature test).
    t_max : float
        Over-temperature limit of a spring, degC (status bit 4 of the group kernel).
    t_cut : float
        The driver's thermal cutoff, degC (default ``inf``: none): a spring at or above it gets
        no current until it cools below. SMA drivers sense the wire (its resistance) and do
        this; it lets one drive level serve forced air (which needs it) and still air (where
        it would otherwise overheat) without ending the run at ``t_max``.
    relax_time : float
        Viscoplastic regularization time ``t_relax`` of the transformation, s.
    stop_down, stop_up : float or None
        Pin travel from height 0 to the end stops, m; default ``prestrain`` (a spring at its
        memorized, closed-coil length cannot shorten further).
    n_shells : int
        Gauss-Legendre radii across the wire.

    Attributes
    ----------
    n_states : int
        ``2 + 2 n_shells``: ``[T_u, T_l, g_u (n_shells), g_l (n_shells)]``.
    wire_length, mass, area, k_martensite, k_austenite, h, thermal_time_constant : float
        Active wire length (m), mass (kg), surface (m^2), elastic spring rates (N/m), the
        convection coefficient in use and ``m c / (h A)`` (s).

    Examples
    --------
    >>> from rtctl.plant.sma import SmaTaxel
    >>> taxel = SmaTaxel(cooling="forced")
    >>> round(taxel.load_curve(10e-3, 20.0), 3)      # N at 10 mm, 20 degC (seed: 180 mN)
    0.18
    >>> round(taxel.resistance, 2), round(taxel.k_martensite, 1)
    (1.56, 79.7)
    """

    def __init__(self, *, wire_diameter=200e-6, coil_diameter=1.3e-3, n_coils=12,
                 prestrain=2.3e-3, g_austenite=28.2e9, g_martensite=10.5e9, tau_cr=55.93e6,
                 c_m=4.851e6, m_s=58.75, c_a=4.9e6, a_s=65.0, ramp_start=28.0, ramp_end=65.0,
                 density=6450.0, specific_heat=837.0, resistivity=1.0e-6, resistance=None,
                 h_still=97.8, h_forced=607.0, cooling="forced", t_ambient=20.0, t_max=130.0, t_cut=math.inf,
                 relax_time=2e-3, stop_down=None, stop_up=None, n_shells=8):
        self.d = _positive("wire_diameter", wire_diameter)
        self.D = _positive("coil_diameter", coil_diameter)
        if self.D <= self.d:
            raise ModelError(f"SMA taxel: coil_diameter ({self.D!r} m, mean) must exceed "
                             f"wire_diameter ({self.d!r} m)")
        if int(n_coils) != n_coils or n_coils < 1:
            raise ModelError(f"SMA taxel: n_coils must be a positive integer, got {n_coils!r}")
        self.N = int(n_coils)
        self.delta0 = _positive("prestrain", prestrain)
        self.g_a = _positive("g_austenite", g_austenite)
        self.g_m = _positive("g_martensite", g_martensite)
        self.tau_cr = _positive("tau_cr", tau_cr)
        self.c_m = _positive("c_m", c_m)
        self.c_a = _positive("c_a", c_a)
        self.m_s, self.a_s = float(m_s), float(a_s)
        self.ramp = (float(ramp_start), float(ramp_end))
        if not self.ramp[1] > self.ramp[0]:
            raise ModelError(f"SMA taxel: ramp_end ({ramp_end!r}) must exceed ramp_start "
                             f"({ramp_start!r}) degC")
        self.t_ambient = float(t_ambient)
        self.t_max = float(t_max)
        self.t_cut = float(t_cut)
        if not self.t_cut > self.t_ambient:
            raise ModelError(f"SMA taxel: t_cut ({t_cut!r} degC) must exceed t_ambient "
                             f"({t_ambient!r} degC), or no spring could ever be heated")
        if not self.t_max > self.t_ambient:
            raise ModelError(f"SMA taxel: t_max ({t_max!r} degC) must exceed t_ambient "
                             f"({t_ambient!r} degC)")
        # Unloading must stay below loading wherever the taxel can go (to t_max + 50 K).
        t_hi = self.t_max + 50.0
        if self.c_a * (t_hi - self.a_s) > max(self.tau_cr, self.c_m * (t_hi - self.m_s)):
            raise ModelError(f"SMA taxel: the unloading stress c_a (T - a_s) exceeds the loading "
                             f"stress at {t_hi:.0f} degC; raise a_s or lower c_a")
        if cooling not in COOLING:
            raise ModelError(f"SMA taxel: cooling must be one of {COOLING}, got {cooling!r}")
        self.cooling = cooling
        self.h_still = _positive("h_still", h_still)
        self.h_forced = _positive("h_forced", h_forced)
        self.h = self.h_still if cooling == "still" else self.h_forced
        self.relax_time = float(relax_time)
        if not (math.isfinite(self.relax_time) and self.relax_time >= 0.0):
            raise ModelError(f"SMA taxel: relax_time must be >= 0 s, got {relax_time!r}")
        self.stop_down = self.delta0 if stop_down is None else _positive("stop_down", stop_down)
        self.stop_up = self.delta0 if stop_up is None else _positive("stop_up", stop_up)
        if max(self.stop_down, self.stop_up) > self.delta0:
            raise ModelError("SMA taxel: an end stop beyond prestrain would compress a spring "
                             "below its closed-coil length; use stops <= prestrain")
        if int(n_shells) != n_shells or not 2 <= n_shells <= 64:
            raise ModelError(f"SMA taxel: n_shells must be an integer in [2, 64], got {n_shells!r}")
        self.n_shells = int(n_shells)

        self.wire_length = math.pi * self.D * self.N
        a_cs = math.pi * self.d**2 / 4.0
        self.mass = _positive("density", density) * a_cs * self.wire_length
        self.heat_capacity = self.mass * _positive("specific_heat", specific_heat)
        self.area = math.pi * self.d * self.wire_length
        self.resistance = (_positive("resistivity", resistivity) * self.wire_length / a_cs
                           if resistance is None else _positive("resistance", resistance))
        self.thermal_time_constant = self.heat_capacity / (self.h * self.area)
        self.kappa = self.d / (math.pi * self.D**2 * self.N)
        node, wt = np.polynomial.legendre.leggauss(self.n_shells)
        self.s = 0.5 * (node + 1.0)
        # P = (pi d^3 / 2D) int_0^1 tau(s) s^2 ds; Gauss weights on [0, 1] are wt / 2.
        self.wq = math.pi * self.d**3 / (2.0 * self.D) * 0.5 * wt * self.s**2
        spring_rate = self.d**4 / (8.0 * self.N * self.D**3)
        self.k_martensite = self.g_m * spring_rate
        self.k_austenite = self.g_a * spring_rate
        self.n_states = 2 + 2 * self.n_shells

    # -- material law ---------------------------------------------------------------------
    def shear_modulus(self, t):
        """``G(T)``, Pa (array-like ``t`` in degC)."""
        f = np.clip((np.asarray(t, float) - self.ramp[0]) / (self.ramp[1] - self.ramp[0]), 0, 1)
        return self.g_m + (self.g_a - self.g_m) * f

    def tau_load(self, t):
        """Loading shear stress ``max(tau_cr, c_M (T - M_s))``, Pa."""
        return np.maximum(self.tau_cr, self.c_m * (np.asarray(t, float) - self.m_s))

    def tau_unload(self, t):
        """Unloading shear stress ``c_A (T - A_s)`` (capped at the loading stress), Pa."""
        return np.minimum(self.c_a * (np.asarray(t, float) - self.a_s), self.tau_load(t))

    def load_curve(self, delta, t):
        """Tobushi-Tanaka load-deflection for monotone loading at constant ``t`` (seed Eq. 1).

        Parameters
        ----------
        delta : array_like
            Deflection from the memorized shape, m (>= 0).
        t : float
            Temperature, degC.

        Returns
        -------
        ndarray or float
            Axial load, N.
        """
        delta = np.asarray(delta, float)
        g = float(self.shear_modulus(t))
        tau = float(self.tau_load(t))
        de = math.pi * self.D**2 * self.N * tau / (g * self.d)
        el = g * self.d**4 * delta / (8 * self.N * self.D**3)
        with np.errstate(divide="ignore", invalid="ignore"):
            pl = math.pi * tau * self.d**3 / (6 * self.D) * (1 - 0.25 * (de / delta)**3)
        out = np.where(delta < de, el, pl)
        return float(out) if out.ndim == 0 else out

    # -- thermal ------------------------------------------------------------------------
    def voltage_for(self, t_steady):
        """Drive voltage whose continuous heating settles a spring at ``t_steady`` degC, V."""
        dt = float(t_steady) - self.t_ambient
        if not dt > 0.0:
            raise ModelError(f"t_steady ({t_steady!r} degC) must exceed t_ambient "
                             f"({self.t_ambient} degC)")
        return math.sqrt(dt * self.h * self.area * self.resistance)

    # -- state ------------------------------------------------------------------------
    def installed_strains(self):
        """Transformation strains after stretching a virgin spring to ``prestrain`` at ambient.

        Slow (rate-independent) monotone loading: ``g_i = max(0, gam_i - tau_L / G_M)``.
        """
        g = float(self.shear_modulus(self.t_ambient))
        gam = self.s * self.kappa * self.delta0
        return np.maximum(0.0, gam - float(self.tau_load(self.t_ambient)) / g)

    @property
    def y0(self):
        """Installed state: both springs at ambient, prestrained, pin at height 0."""
        gi = self.installed_strains()
        return np.concatenate([[self.t_ambient, self.t_ambient], gi, gi])

    def _forces(self, y, x):
        """Elastic spring forces ``(P_u, P_l)`` at pin height ``x`` with frozen strains."""
        n = self.n_shells
        gu, gl = self.shear_modulus(y[0]), self.shear_modulus(y[1])
        su = self.s * self.kappa * (self.delta0 - x)
        sl = self.s * self.kappa * (self.delta0 + x)
        return (float(gu * self.wq @ (su - y[2:2 + n])),
                float(gl * self.wq @ (sl - y[2 + n:2 + 2 * n])))

    def pin(self, y, f_ext=0.0):
        """Pin height (m) from the force balance at state ``y``, clipped to the stops.

        With the transformation strains as states the balance is linear in ``x``:
        ``x = (G_u (K d0 - q_u) - G_l (K d0 - q_l) - F_e) / (K (G_u + G_l))``.
        """
        n = self.n_shells
        K = self.kappa * float(self.wq @ self.s)
        gu, gl = float(self.shear_modulus(y[0])), float(self.shear_modulus(y[1]))
        qu, ql = float(self.wq @ y[2:2 + n]), float(self.wq @ y[2 + n:2 + 2 * n])
        fe = max(float(f_ext), 0.0)
        x = (gu * (K * self.delta0 - qu) - gl * (K * self.delta0 - ql) - fe) / (K * (gu + gl))
        return min(max(x, -self.stop_down), self.stop_up)

    def rhs(self, t, y, u, f_ext=0.0):
        """Time derivative of the state, for ``scipy.integrate.solve_ivp``.

        Parameters
        ----------
        t : float
            Time, s (unused: the model is autonomous for constant inputs).
        y : ndarray, shape (n_states,)
        u : float
            Signed drive voltage, V (> 0 heats the raise spring).
        f_ext : float
            Finger force pressing the pin down, N.

        Returns
        -------
        ndarray, shape (n_states,)
        """
        if self.relax_time <= 0.0:
            raise ModelError("rhs needs relax_time > 0 (the rate-independent law is no ODE)")
        n = self.n_shells
        x = self.pin(y, f_ext)
        dy = np.empty_like(np.asarray(y, float))
        p = u * u / self.resistance
        hA = self.h * self.area
        dy[0] = ((p if u > 0 and y[0] < self.t_cut else 0.0) - hA * (y[0] - self.t_ambient)) / self.heat_capacity
        dy[1] = ((p if u < 0 and y[1] < self.t_cut else 0.0) - hA * (y[1] - self.t_ambient)) / self.heat_capacity
        for j, delta in ((0, self.delta0 - x), (1, self.delta0 + x)):
            g = float(self.shear_modulus(y[j]))
            gam = self.s * self.kappa * delta
            lo = np.maximum(0.0, gam - float(self.tau_load(y[j])) / g)
            hi = np.maximum(0.0, gam - float(self.tau_unload(y[j])) / g)
            gt = y[2 + j * n:2 + (j + 1) * n]
            dy[2 + j * n:2 + (j + 1) * n] = (np.clip(gt, lo, hi) - gt) / self.relax_time
        return dy

    def outputs(self, y, u, f_ext=0.0):
        """Truth rows for state ``y``: pin height (m), velocity (m/s), finger force (N), volts.

        The velocity is ``dx/dt`` of the algebraic pin height along ``rhs`` (0 at a stop).
        At the lower stop the finger also rests on the stop and feels only the springs' net
        push (``min(F_e, P_u - P_l)``, >= 0).
        """
        fe = max(float(f_ext), 0.0)
        x = self.pin(y, fe)
        pu, pl = self._forces(y, x)
        at_stop = x <= -self.stop_down or x >= self.stop_up
        vel = 0.0
        if not at_stop:
            # x(y) is smooth between stops: a central difference along the flow is exact to
            # O(eps^2) and needs no hand-written Jacobian.
            dy = self.rhs(0.0, y, u, fe)
            eps = 1e-6 / max(1e-12, float(np.max(np.abs(dy[:2]))) + 1e-3)
            vel = (self.pin(y + eps * dy, fe) - self.pin(y - eps * dy, fe)) / (2 * eps)
        force = fe if x > -self.stop_down else min(fe, max(pu - pl, 0.0))
        return np.array([x, vel, force, float(u)])

    def kernel_params(self, fs, k_mech):
        """Float parameter vector of :func:`sma_group_process` for sample rate ``fs``."""
        dt = 1.0 / fs
        r = self.heat_capacity / (self.h * self.area)
        alpha = math.exp(-dt / r)
        om = -math.expm1(-dt / r)
        h_mech = k_mech * dt
        w = 1.0 if self.relax_time == 0.0 else h_mech / (h_mech + self.relax_time)
        fp = np.zeros(_k.N_FP)
        fp[:] = (self.kappa, self.delta0, self.g_m, self.g_a, self.ramp[0], self.ramp[1],
                 self.tau_cr, self.c_m, self.m_s, self.c_a, self.a_s, alpha,
                 om * self.t_ambient, om / (self.resistance * self.h * self.area),
                 1.0 / self.resistance, w, self.stop_down, self.stop_up, self.t_max, fs / k_mech,
                 self.t_cut)
        return fp


class SmaGroup:
    """``n_channels`` simulated SMA taxels advanced block by block (the sim-group contract).

    Temperatures advance exactly every sample (exponential of the linear thermal ODE under a
    sample-and-hold drive); the pin force balance is solved every ``fs / mech_fs`` samples by
    implicit Euler (see :mod:`rtctl.plant._sma_kernels`) and the pin height is interpolated
    linearly between the last two solutions, so truth row 0 at sample ``n`` is the pin height
    at time ``(n - lag_samples) / fs``.

    Parameters
    ----------
    plant : SmaTaxel
    fs : float
        Sample rate, Hz.
    n_channels : int
        Taxels, row-major over the crossbar grid (channel ``r * n_cols + c``).
    max_block : int
        Probe length; longer calls work, the probe then holds their first ``max_block`` samples.
    mech_fs : float
        Rate of the mechanical solve, Hz (rounded to a divisor step of ``fs``); the knob of the
        cost/error trade-off.
    crossbar : bool
        Row-scanned crossbar drive (seed Fig. 15): one row line at V at a time, for
        ``slot`` seconds each; in that slot each taxel of the row gets its requested voltage
        on the spring its sign selects (raise or lower column line), every other taxel gets
        nothing. Duty cycle ``1 / n_rows``.
    rows : int or None
        Crossbar rows (default: square grid).
    slot : float
        Crossbar slot length, s (rounded to samples, >= 1).
    substeps : int or None
        Samples per mechanical solve (overrides ``mech_fs`` with ``fs / substeps``); the name
        the numerics report uses for the cost/error knob.

    Attributes
    ----------
    kernel : callable
        :func:`sma_group_process`.
    args : tuple of ndarray
        ``(ip, fp, s, wq, temp, gt, xs, clock, f_ext, probe)``.
    temperatures : ndarray, shape (n_channels, 2)
        View of the spring temperatures, degC (raise, lower).
    f_ext : ndarray, shape (n_channels,)
        Finger force per taxel pressing the pin down, N: write between blocks.
    probe : ndarray, shape (2, max_block)
        Hottest spring temperature (degC) and total electrical power (W) per sample.
    probe_names, n_sensed, sensed_labels, capacitance, lag_samples, k_mech

    Examples
    --------
    >>> import numpy as np
    >>> from rtctl.plant.sma import SmaTaxel, SmaGroup
    >>> group = SmaGroup(SmaTaxel(cooling="forced"), fs=48000.0, n_channels=64)
    >>> drive = np.zeros((64, 32)); sensed = np.zeros((0, 32)); truth = np.zeros((64, 4, 32))
    >>> group.f_ext[:] = 0.05
    >>> group.process(drive, sensed, truth)
    0
    >>> bool(np.all(truth[:, 2] == 0.05)), group.temperatures.shape
    (True, (64, 2))
    """

    n_sensed = 0
    sensed_labels = ()
    probe_names = (("spring_temp_max", "degC"), ("power", "W"))
    capacitance = 0.0

    def __init__(self, plant: SmaTaxel, fs: float, n_channels: int, max_block: int = 64,
                 mech_fs: float = 1000.0, crossbar: bool = False, rows: int | None = None,
                 slot: float = 1e-3, substeps: int | None = None):
        if not isinstance(plant, SmaTaxel):
            raise ModelError("SmaGroup needs an SmaTaxel plant")
        fs = float(fs)
        if not (fs > 0.0 and math.isfinite(fs)):
            raise ModelError(f"fs must be a positive sample rate in Hz, got {fs!r}")
        nc = int(n_channels)
        if nc < 1 or nc != n_channels:
            raise ModelError(f"n_channels must be a positive integer, got {n_channels!r}")
        mb = int(max_block)
        if mb < 1:
            raise ModelError(f"max_block must be >= 1, got {max_block!r}")
        if substeps is not None:
            if int(substeps) != substeps or substeps < 1:
                raise ModelError(f"substeps must be a positive integer, got {substeps!r}")
            mech_fs = fs / int(substeps)
        mech_fs = float(mech_fs)
        if not (0.0 < mech_fs <= fs):
            raise ModelError(f"mech_fs must be in (0, fs = {fs:g}] Hz, got {mech_fs!r}")
        k = max(1, int(round(fs / mech_fs)))
        if rows is None:
            rows = int(round(math.sqrt(nc))) if crossbar else 1
        rows = int(rows)
        if rows < 1 or nc % rows:
            raise ModelError(f"rows ({rows!r}) must divide n_channels ({nc}); give rows= for a "
                             f"non-square crossbar grid")
        slot_n = max(1, int(round(float(slot) * fs)))
        self.plant, self.fs, self.n_channels, self.k_mech = plant, fs, nc, k
        self.lag_samples = k - 1
        self.rows, self.cols, self.slot_samples, self.crossbar = rows, nc // rows, slot_n, bool(crossbar)
        ip = np.array([k, int(bool(crossbar)), slot_n, rows, nc // rows, plant.n_shells],
                      dtype=np.int64)
        self.args = (
            ip,
            plant.kernel_params(fs, k),
            np.ascontiguousarray(plant.s),
            np.ascontiguousarray(plant.wq),
            np.zeros((nc, 2)),                    # temperatures, degC
            np.zeros((nc, 2, plant.n_shells)),    # transformation strains
            np.zeros((nc, 3)),                    # x_prev, x_cur (m), net force at x_cur (N)
            np.zeros(2, dtype=np.int64),          # mech counter, crossbar scan counter
            np.zeros(nc),                         # finger force, N
            np.zeros((2, mb)),                    # probe
        )
        self.kernel = sma_group_process
        self.reset()

    @property
    def temperatures(self) -> np.ndarray:
        return self.args[4]

    @property
    def f_ext(self) -> np.ndarray:
        return self.args[8]

    @property
    def probe(self) -> np.ndarray:
        return self.args[9]

    @property
    def strains(self) -> np.ndarray:
        """Transformation strains, shape (n_channels, 2, n_shells) (a view)."""
        return self.args[5]

    def state(self, ch: int) -> np.ndarray:
        """Channel ``ch``'s state in :meth:`SmaTaxel.rhs` layout (a copy)."""
        return np.concatenate([self.args[4][ch], self.args[5][ch, 0], self.args[5][ch, 1]])

    def reset(self) -> None:
        """Installed state (:attr:`SmaTaxel.y0`) in every channel; clocks to 0; ``f_ext`` kept."""
        self.args[4][:] = self.plant.t_ambient
        self.args[5][:] = self.plant.installed_strains()
        self.args[6][:] = 0.0
        self.args[7][:] = 0
        self.args[9][:] = 0.0

    def process(self, drive, sensed, truth) -> int:
        """Advance every taxel by one block.

        Parameters
        ----------
        drive : ndarray, shape (n_channels, n), float64, C-contiguous
            Signed spring voltage, V (> 0 heats the raise spring, < 0 the lower one).
        sensed : ndarray, shape (0, n)
        truth : ndarray, shape (n_channels, 4, n)
            Written: pin height (m), velocity (m/s), force on the finger (N), applied volts.

        Returns
        -------
        int
            Bit value 2: a state is NaN/Inf (stays until :meth:`reset`); bit value 4: a spring
            exceeded ``t_max`` during this block.
        """
        n = drive.shape[-1]
        for name, arr, shape in (("drive", drive, (self.n_channels, n)),
                                 ("sensed", sensed, (0, n)),
                                 ("truth", truth, (self.n_channels, len(TRUTH_NAMES), n))):
            if arr.shape != shape or arr.dtype != np.float64 or not arr.flags.c_contiguous:
                raise ModelError(f"{name} must be C-contiguous float64 of shape {shape}, got "
                                 f"{arr.dtype} {arr.shape}")
        return sma_group_process(*self.args, drive, sensed, truth)
