"""Solenoid pin between hard end stops, with the finger on top (seed 003: 3x3 pins, 200 um stroke,
pulse drive 0-340 Hz).

Continuous model of one pin (drive: coil voltage ``V``; per-channel parameter: finger preload
``F_p``)::

    L i'     = V - R i - K v                               coil, back-EMF K v
    x'       = v
    m v'     = K i - F_s - k_r x - c v + F_bot - F_top - F_c
    F_bot    = k_e d + c_e d',  d = -x          (d > 0 and F_bot > 0)   bottom stop at 0
    F_top    = k_e d + c_e d',  d = x - stroke  (d > 0 and F_top > 0)   top stop at stroke
    F_c      = skin contact (rtctl.plant.contact), >= 0

``x`` is the pin height (m, up into the finger, 0 on the bottom stop), ``i`` the coil current (A).
The return spring ``k_r`` is preloaded by ``F_s`` (which also carries the pin's weight, ~1 mN,
so gravity is not a separate term): at rest the pin sits on its bottom stop.

**Force constant (the linearization).** ``F = K i`` and back-EMF ``K v`` with one constant ``K``
(N/A = V s/m, so electrical power ``K i v`` equals mechanical power) describe a *polarized*
(moving-magnet or magnet-biased) solenoid whose permanent-magnet flux dominates the coil's: the
force is then linear in current and both directions work. It holds while ``|i|`` stays well below
the current that saturates the iron or opposes the magnet, and while the stroke (200 um) is
small against the magnetic gap, so that ``K`` and ``L`` do not change with ``x``. A plain
(unpolarized) reluctance solenoid pulls with ``F = i^2 dL/dx / 2``, quadratic in ``i`` and
growing as the gap closes; that plant is nonlinear and not modelled here. Eddy currents and
hysteresis in the iron are neglected (a constant ``L``).

**End stops** are a deliberately stiff case: ``k_e = 1e8 N/m`` on a 0.1 g pin is a 160 kHz
contact mode, 3x the 48 kHz sample rate, critically damped (coefficient of restitution
``e^-2 = 0.14``: the damper lets go when ``k_e d + c_e d'`` reaches 0). Explicit integration at
the sample rate would explode; the exact per-mode discretization of :mod:`rtctl.plant.hybrid`
is stable for any ``k_e``, and switch localization keeps the stop from adding energy on impact.
Critical damping also keeps the stop from swinging out and back within one substep, where a
switch check at the end of the substep would miss the release (an underdamped stop is still
handled correctly, at the cost of finer pieces while on it: ``HybridModel.piece_levels``).

**Parameters** other than the stroke and the 0-340 Hz range are not in seed 003 (which gives
neither coil nor spring data); the defaults are plausible values for a 3 mm polarized
micro-solenoid, chosen so that 5 V pulses give the full 200 um stroke at low pulse rates (a
net upward force of ~0.1 N at the top with the finger on it) and the stroke rolls off toward
340 Hz. Scenes can override every one of them.
"""

from __future__ import annotations

import math

from rtctl.errors import ModelError
from rtctl.plant._checks import positive
from rtctl.plant.contact import PinReference, SkinContact, add_skin
from rtctl.plant.finger import MaxwellLoad
from rtctl.plant.hybrid import TRUTH_NAMES, HybridBuilder, HybridGroup, Lin, unilateral

__all__ = ["SolenoidPin", "SolenoidGroup", "DEFAULT_FINGER"]

#: Normal finger load under a pin when a scene gives none (three relaxation times 4 ms, 70 ms,
#: 1.4 s, Pawluk & Howe 1999, docs/references.md; stiffnesses as the bundled scenes).
DEFAULT_FINGER = MaxwellLoad(1e-4, 300.0, ((300.0, 0.004), (150.0, 0.07), (80.0, 1.4)))


def _pos(name, v, zero_ok=False):
    return positive("solenoid", name, v, zero_ok)


class SolenoidPin(PinReference):
    """Continuous switched-linear model of one solenoid pin with end stops and the finger.

    Parameters
    ----------
    resistance : float
        Coil resistance R, ohm.
    inductance : float
        Coil inductance L, H.
    force_constant : float
        K, N/A (= back-EMF constant, V s/m).
    mass : float
        Moving mass of pin and plunger, kg.
    spring : float
        Return spring stiffness k_r, N/m.
    spring_preload : float
        Return spring force at x = 0 (pin weight included), N, pulling the pin down.
    damping : float
        Viscous damping of the pin (guide friction, air), N s/m.
    stroke : float
        Height of the top stop, m (seed 003: 200 um).
    stop_stiffness : float
        Penalty stiffness of both end stops, N/m.
    stop_damping_ratio : float
        Damping of both end stops as a ratio of critical on the pin mass
        (``c_e = 2 zeta sqrt(k_e m)``); 1 (default) is critical.
    finger : MaxwellLoad or None
        Normal finger load under the pin (mass > 0); None: no finger (no skin states).
    k_contact, c_contact, surface : float
        Pin-skin penalty contact (:class:`~rtctl.plant.contact.SkinContact`).
    preload : float
        Finger force on this pin at rest, N (a per-channel parameter of the group).

    Attributes
    ----------
    model : HybridModel
        Inputs ``(coil_v, preload_n)``; outputs the 4 truth rows then ``coil_current_a``.
    y0 : ndarray, shape (n_states,)
        Rest state at zero drive and ``preload``.
    contact_bits, top_bits, bottom_bits : tuple of int
        Switch bits that are all on while the pin touches the skin / the top / the bottom stop.

    Examples
    --------
    >>> from rtctl.plant.solenoid import SolenoidPin
    >>> pin = SolenoidPin()
    >>> pin.model.state_names[:3]
    ('pin_m', 'pin_velocity_m_s', 'coil_a')
    >>> round(float(pin.outputs(pin.y0, 0.0)[2]), 4)        # the finger's 20 mN rest on the pin
    0.02
    >>> round(pin.static_height(5.0) * 1e6, 1)              # held at 5 V: on the top stop, um
    200.0
    """

    def __init__(self, resistance=20.0, inductance=20e-3, force_constant=1.5, mass=1e-4,
                 spring=200.0, spring_preload=0.02, damping=0.02, stroke=200e-6,
                 stop_stiffness=1e8, stop_damping_ratio=1.0, finger=DEFAULT_FINGER,
                 k_contact=1e6, c_contact=None, surface=0.0, preload=0.02):
        self.R = _pos("resistance", resistance)
        self.L = _pos("inductance", inductance)
        self.K = _pos("force_constant", force_constant)
        self.m = _pos("mass", mass)
        self.k_r = _pos("spring", spring, zero_ok=True)
        self.F_s = float(spring_preload)
        if not math.isfinite(self.F_s):
            raise ModelError(f"spring_preload must be finite, got {spring_preload!r}")
        self.c = _pos("damping", damping, zero_ok=True)
        self.stroke = _pos("stroke", stroke)
        self.k_e = _pos("stop_stiffness", stop_stiffness)
        self.c_e = 2.0 * _pos("stop_damping_ratio", stop_damping_ratio, zero_ok=True) \
            * math.sqrt(self.k_e * self.m)
        self.preload = _pos("preload", preload, zero_ok=True)
        self.skin = None if finger is None else SkinContact(finger, k_contact, c_contact, surface)

        b = HybridBuilder(["coil_v", "preload_n"])
        x, v, i = b.add_state("pin_m"), b.add_state("pin_velocity_m_s"), b.add_state("coil_a")
        b.derivative(x, Lin.x(v))
        b.derivative(i, (Lin.u(0) - Lin.x(i, self.R) - Lin.x(v, self.K)) * (1.0 / self.L))
        b.derivative(v, (Lin.x(i, self.K) - self.F_s - Lin.x(x, self.k_r) - Lin.x(v, self.c))
                     * (1.0 / self.m))
        rows = [b.output(TRUTH_NAMES[0], Lin.x(x)), b.output(TRUTH_NAMES[1], Lin.x(v)),
                b.output(TRUTH_NAMES[2], Lin()), b.output(TRUTH_NAMES[3], Lin.u(0)),
                b.output("coil_current_a", Lin.x(i))]
        inv_m = 1.0 / self.m
        self.bottom_bits, _ = unilateral(b, "bottom", -Lin.x(x), -Lin.x(v), self.k_e, self.c_e,
                                         [(v, inv_m)])
        self.top_bits, _ = unilateral(b, "top", Lin.x(x) - self.stroke, Lin.x(v), self.k_e,
                                      self.c_e, [(v, -inv_m)])
        self.contact_bits = ()
        if self.skin is not None:
            st = add_skin(b, self.skin, Lin.x(x), Lin.x(v), Lin.u(1), [(v, -inv_m)],
                          force_row=rows[2])
            self.contact_bits = st.when
        self.model = b.build()
        self.y0, _ = self.model.equilibrium([0.0, self.preload])

    @property
    def n_states(self) -> int:
        return self.model.n_states

    @property
    def time_constant(self) -> float:
        """Electrical time constant L / R, s."""
        return self.L / self.R

    def static_height(self, volts: float) -> float:
        """Rest height under a constant coil voltage, m."""
        x, _ = self.model.equilibrium(self._u(volts))
        return float(x[0])


class SolenoidGroup(HybridGroup):
    """``n_channels`` solenoid pins (e.g. the 3x3 array of seed 003) under the group contract.

    Sensed row per channel: the coil current (``"coil_a"``) through an ideal shunt amplifier
    and an ADC (``adc_bits`` over +-``current_full_scale``; clipping sets status bit 1).
    Per-channel parameter: ``params[:, 0]``, the finger preload on each pin, N (may be written
    between blocks). Probes: the share of pins touching the finger, on the top stop and on the
    bottom stop, per sample.

    Parameters
    ----------
    plant : SolenoidPin
    fs : float
        Sample rate, Hz.
    n_channels : int
    max_block : int
    substeps : int
        Exact steps per sample (default 1). Inside a mode every step is exact, so the error is
        set by the switching-time resolution ``1 / (fs substeps 2^levels)``, not by the
        substep (docs/plants/solenoid.md has the table).
    levels : int
        Switch localization to ``substep / 2^levels`` (default 16: 0.3 ns at 48 kHz).
    max_events : int
        Localized switches per substep (default 8).
    adc_bits : int
        0 for an ideal reading.
    current_full_scale : float
        A.

    Examples
    --------
    >>> import numpy as np
    >>> from rtctl.plant.solenoid import SolenoidPin, SolenoidGroup
    >>> group = SolenoidGroup(SolenoidPin(), fs=48000.0, n_channels=9)
    >>> drive = np.full((9, 32), 5.0)
    >>> sensed, truth = np.empty((9, 32)), np.empty((9, 4, 32))
    >>> group.process(drive, sensed, truth), group.sensed_labels, group.capacitance
    (0, ('coil_a',), 0.0)
    """

    def __init__(self, plant: SolenoidPin, fs: float, n_channels: int, max_block: int = 64,
                 substeps: int = 1, levels: int = 16, max_events: int = 8, adc_bits: int = 12,
                 current_full_scale: float = 0.5):
        if not isinstance(plant, SolenoidPin):
            raise ModelError("SolenoidGroup needs a SolenoidPin")
        fsc = _pos("current_full_scale", current_full_scale)
        if int(adc_bits) != adc_bits or not 0 <= int(adc_bits) <= 32:
            raise ModelError(f"adc_bits must be an integer in 0..32, got {adc_bits!r}")
        lsb = 2.0 * fsc / 2 ** int(adc_bits) if adc_bits else 0.0
        mask = lambda bits: sum(1 << b for b in bits)  # noqa: E731
        probes = [("top_stop_share", "", mask(plant.top_bits)),
                  ("bottom_stop_share", "", mask(plant.bottom_bits))]
        if plant.contact_bits:
            probes.insert(0, ("contact_share", "", mask(plant.contact_bits)))
        self.plant = plant
        super().__init__(plant.model, fs, n_channels, plant.y0, params=[plant.preload],
                         sensed=[("coil_a", 4, lsb, fsc)], probes=probes, substeps=substeps,
                         levels=levels, max_events=max_events, max_block=max_block,
                         capacitance=0.0)
