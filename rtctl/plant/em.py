"""Electromagnetic perpendicular actuator of the bimodal display (seed 000, section 3.3).

Each of the 16 coupled actuators (4 x 4, 2.4 mm pitch, 2.3 mm x 2.3 mm footprint) is a
moving-magnet voice coil that lifts a pin, with a piezoelectric bimorph mounted on the moving
part for lateral excitation. The perpendicular actuator stimulates the Merkel receptors (0-30 Hz,
>= 30 um, seed 000 section 1). Seed 000 gives no electrical or mechanical numbers; the defaults
below are a design for the 2.3 mm footprint, derived in ``docs/plants/em.md``.

Continuous model of one channel (input: coil voltage ``u``, V; per-channel parameter: finger
preload ``F_p``, N)::

    L i'     = u - R i - K x'                                coil (back-EMF constant = K)
    m x''    = K i - k x - c x' - F_c                        armature + bimorph on the suspension
    m_s y''  = -k0 y - sum_j f_j - F_p + F_c                 skin surface (finger bone held still)
    f_j'     = k_j y' - f_j / tau_j                          generalized Maxwell branches
    F_c      = k_c (x - y) + c_c (x' - y')   while x > y and F_c > 0, else 0

``x`` is the pin height (m, up into the finger), ``y`` the height of the skin surface over the
pin, both 0 at the unloaded rest position. A preload ``F_p`` is the force a rigid pin at height 0
would carry once the tissue has relaxed: the bone sits ``F_p / k0`` below the free skin surface.
The contact is the stiff penalty spring-damper of :mod:`rtctl.plant.contact`, which pushes but
never pulls: the skin can lift off a pin that retracts faster than the tissue recovers, and lands
again. Every contact mode is linear and discretized exactly
(:class:`rtctl.plant.hybrid.HybridGroup`).

Truth rows (:data:`TRUTH_NAMES`): pin height (m), pin velocity (m/s), contact force on the finger
(N, >= 0), coil voltage (V). Sensed row: coil current (A, ``"coil_a"``).
"""

from __future__ import annotations

import numpy as np

from rtctl.errors import ModelError
from rtctl.plant._checks import positive
from rtctl.plant.contact import PinReference, SkinContact, add_skin
from rtctl.plant.finger import MaxwellLoad
from rtctl.plant.hybrid import TRUTH_NAMES, HybridBuilder, HybridGroup, Lin
from rtctl.plant.solenoid import DEFAULT_FINGER

__all__ = ["EMPlant", "EMGroup", "TRUTH_NAMES", "PITCH", "FOOTPRINT", "GRID"]

#: Pin centre to pin centre, m (seed 000, section 3.3).
PITCH = 2.4e-3
#: Side of one coupled actuator's square footprint, m (seed 000, section 3.3).
FOOTPRINT = 2.3e-3
#: Rows and columns of the bimodal display (seed 000, section 3.3).
GRID = (4, 4)


def _positive(name, value, allow_zero=False):
    return positive("EMPlant", name, value, allow_zero)


class EMPlant(PinReference):
    """Continuous model of one electromagnetic perpendicular actuator with a unilateral finger.

    Parameters
    ----------
    resistance : float
        Coil resistance R, ohm. Default 14: ~170 turns of 40 um copper on a 1.6/2.2 mm bobbin,
        ~1 m of wire.
    inductance : float
        Coil inductance L, H. Default 100 uH (air core ~50 uH, doubled by the magnet's iron
        return path); L/R = 7 us, far above the Merkel band.
    force_constant : float
        Force per ampere K, N/A; equal to the back-EMF constant, V s/m (energy conservation).
        Default 0.25 (B ~ 0.25 T over ~1 m of wire).
    armature_mass : float
        Magnet, pin and holder, kg. Default 35 mg (NdFeB 1.5 mm x 2 mm is 26.5 mg).
    payload_mass : float
        Mass carried in the normal direction besides the armature (the lateral bimorph), kg.
        Default 105 mg (PZT, 15 x 1.5 x 0.6 mm, the default scene's beam).
    stiffness : float
        Suspension stiffness k, N/m. Default 400 (two spiral flexures, 200 N/m each).
    damping : float
        Suspension damping c, N s/m. Default 0.02 (mechanical damping ratio ~0.04 unloaded).
    lateral_stiffness : float
        In-plane stiffness of the suspension at the bimorph's root, N/m. Default 2e5: two
        flexures 4 mm apart, each 1e5 N/m in plane (500x its axial stiffness).
    tilt_stiffness : float
        Rotational stiffness of the suspension at the bimorph's root, N m/rad. Default 0.8:
        ``k_r s^2 / 2`` with ``k_r`` = 1e5 N/m per flexure, ``s`` = 4 mm.
    armature_inertia : float
        Rotary inertia of the armature about the tilt axis, kg m^2. Default 1.9e-11 (a 35 mg
        cylinder, 1.5 mm x 2 mm).
    finger : MaxwellLoad or None
        Normal finger load on the pin (skin mass > 0); ``None``: no finger (free pin, no skin
        states, force row 0). Default :data:`rtctl.plant.solenoid.DEFAULT_FINGER`.
    k_contact, c_contact, surface : float
        Pin-skin penalty contact (:class:`~rtctl.plant.contact.SkinContact`; defaults 1e6 N/m,
        damping ratio 0.7 on the skin mass, skin surface at the pin's rest height).
    preload : float
        Finger force on this pin at rest, N (a per-channel parameter of the group). Default
        0.03: seed 000's 50 g preload (0.49 N) shared by 16 pins.

    Attributes
    ----------
    model : HybridModel
        Inputs ``("coil_v", "preload_n")``; outputs the 4 truth rows, then ``"coil_current_a"``.
        States ``(coil_a, pin_m, pin_velocity_m_s[, skin_m, skin_velocity_m_s, branches])``.
    y0 : ndarray, shape (n_states,)
        Rest state at zero drive and ``preload``.
    moving_mass : float
        ``armature_mass + payload_mass``, kg: what the coil moves in the normal direction.
    contact_bits : tuple of int
        Switch bits that are all on while the pin touches the skin (empty without a finger).
    skin : SkinContact or None

    Examples
    --------
    >>> from rtctl.plant.em import EMPlant
    >>> plant = EMPlant()
    >>> round(plant.static_deflection(1.0, with_finger=False) * 1e6, 2)   # um per volt, free
    44.64
    >>> [round(float(a) * 1e6, 1) for a in abs(plant.frequency_response([1.0, 30.0])[:, 0])]
    [22.1, 17.1]
    >>> h, _, f, _ = plant.outputs(plant.y0, 0.0)     # at rest the suspension yields:
    >>> round(float(h) * 1e6, 1), round(float(f), 4)   # F_p k / (k + k0) on the pin, N
    (-42.8, 0.0171)
    """

    def __init__(self, resistance: float = 14.0, inductance: float = 100e-6,
                 force_constant: float = 0.25, armature_mass: float = 35e-6,
                 payload_mass: float = 105e-6, stiffness: float = 400.0, damping: float = 0.02,
                 lateral_stiffness: float = 2e5, tilt_stiffness: float = 0.8,
                 armature_inertia: float = 1.9e-11, finger: MaxwellLoad | None = DEFAULT_FINGER,
                 k_contact: float = 1e6, c_contact: float | None = None, surface: float = 0.0,
                 preload: float = 0.03):
        self.resistance = _positive("resistance", resistance)
        self.inductance = _positive("inductance", inductance)
        self.force_constant = _positive("force_constant", force_constant)
        self.armature_mass = _positive("armature_mass", armature_mass)
        self.payload_mass = _positive("payload_mass", payload_mass, allow_zero=True)
        self.stiffness = _positive("stiffness", stiffness)
        self.damping = _positive("damping", damping, allow_zero=True)
        self.lateral_stiffness = _positive("lateral_stiffness", lateral_stiffness)
        self.tilt_stiffness = _positive("tilt_stiffness", tilt_stiffness)
        self.armature_inertia = _positive("armature_inertia", armature_inertia, allow_zero=True)
        self.preload = _positive("preload", preload, allow_zero=True)
        if finger is not None and not isinstance(finger, MaxwellLoad):
            raise ModelError("EMPlant finger must be a MaxwellLoad or None")
        if finger is None and self.preload != 0.0:
            raise ModelError(f"a preload ({preload!r} N) needs a finger; pass finger=... or "
                             "preload=0")
        self.finger = finger
        self.skin = None if finger is None else SkinContact(finger, k_contact, c_contact, surface)
        self.moving_mass = self.armature_mass + self.payload_mass
        self.model = self._build()
        self.n_states = self.model.n_states
        self.y0, _ = self.model.equilibrium([0.0, self.preload], prefer=self.contact_mask)

    # ------------------------------------------------------------------ model
    def _build(self):
        R, L, K = self.resistance, self.inductance, self.force_constant
        m, k, c = self.moving_mass, self.stiffness, self.damping
        b = HybridBuilder(["coil_v", "preload_n"])
        i, x, v = b.add_state("coil_a"), b.add_state("pin_m"), b.add_state("pin_velocity_m_s")
        b.derivative(i, (Lin.u(0) - Lin.x(i, R) - Lin.x(v, K)) * (1.0 / L))
        b.derivative(x, Lin.x(v))
        b.derivative(v, (Lin.x(i, K) - Lin.x(x, k) - Lin.x(v, c)) * (1.0 / m))
        rows = [b.output(TRUTH_NAMES[0], Lin.x(x)), b.output(TRUTH_NAMES[1], Lin.x(v)),
                b.output(TRUTH_NAMES[2], Lin()), b.output(TRUTH_NAMES[3], Lin.u(0)),
                b.output("coil_current_a", Lin.x(i))]
        self.contact_bits = ()
        if self.skin is not None:
            st = add_skin(b, self.skin, Lin.x(x), Lin.x(v), Lin.u(1), [(v, -1.0 / m)],
                          force_row=rows[2])
            self.contact_bits = st.when
        return b.build()

    @property
    def contact_mask(self) -> int:
        """Mode bits that are all on while the pin touches the finger (0 without a finger)."""
        return int(sum(1 << w for w in self.contact_bits))

    def static_deflection(self, volts: float, with_finger: bool = True) -> float:
        """Closed-form rise of the pin under a DC voltage, m (from its rest height).

        ``K V / (R k_eff)`` with ``k_eff = k + k0 k_c / (k0 + k_c)`` in contact (``k`` alone
        without the finger or with ``with_finger=False``); valid while the pin pushes.
        """
        k_eff = self.stiffness
        if with_finger and self.skin is not None:
            k0, kc = self.finger.k0, self.skin.k_contact
            k_eff += k0 * kc / (k0 + kc)
        return self.force_constant * float(volts) / (self.resistance * k_eff)

    def frequency_response(self, freqs_hz):
        """Closed-form response per coil volt, pin in permanent contact (or no finger).

        Parameters
        ----------
        freqs_hz : array_like, shape (n_freqs,)

        Returns
        -------
        ndarray, shape (n_freqs, 3), complex
            Pin height (m/V), contact force (N/V), coil current (A/V).

        Notes
        -----
        From impedances, not from the state matrices: the skin side has dynamic stiffness
        ``Z_s = -w^2 m_s + K_t(w)`` (:meth:`MaxwellLoad.dynamic_stiffness`), the contact
        ``Z_c = k_c + j w c_c`` in series with it, the pin ``Z_p = k - w^2 m + j w c``; then
        ``x = K i / (Z_p + Z_cs)`` and ``(R + j w L) i = u - j w K x``.
        """
        w = 2.0 * np.pi * np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
        s = 1j * w
        zp = self.stiffness - w**2 * self.moving_mass + s * self.damping
        zcs = np.zeros_like(s)
        if self.skin is not None:
            zsk = self.finger.dynamic_stiffness(w)
            zc = self.skin.k_contact + s * self.skin.c
            zcs = zc * zsk / (zc + zsk)
        K = self.force_constant
        x_per_i = K / (zp + zcs)
        i = 1.0 / (self.resistance + s * self.inductance + s * K * x_per_i)
        x = x_per_i * i
        return np.stack([x, zcs * x, i], axis=1)

    def support_spec(self):
        """The bimorph's root support: ``SupportSpec("elastic", ...)`` for :mod:`rtctl.plant.beam`.

        The root mass is the armature alone: the bimorph's own mass is in its finite elements.
        """
        from rtctl.plant.beam import SupportSpec

        return SupportSpec("elastic", k=self.lateral_stiffness, k_rot=self.tilt_stiffness,
                           mass=self.armature_mass, inertia=self.armature_inertia)


class EMGroup(HybridGroup):
    """``n_channels`` electromagnetic actuators under the simulated-group contract.

    Sensed row per channel: the coil current (``"coil_a"``) through an ideal shunt amplifier and
    an ADC (``adc_bits`` over +-``current_full_scale``; clipping sets status bit 1).
    Per-channel parameter: ``params[:, 0]``, the finger preload on each pin, N (the loop may
    write it between blocks). Probe (with a finger): ``contact_share``, the share of pins
    touching the finger, per sample.

    Parameters
    ----------
    plant : EMPlant
    fs : float
        Sample rate, Hz.
    n_channels : int
        Default 16 (the 4 x 4 display).
    max_block : int
    substeps : int
        Exact steps per sample (default 1: every mode is exact at any step; only the contact
        switching time needs resolving, which ``levels`` does at a cost only when it switches).
    levels : int
        Contact switch localization to ``1 / (fs substeps 2^levels)`` (default 10: 20 ns).
        Against Radau through a contact loss: height 2.3e-5, velocity 1.5e-4, force 4.9e-3 of
        peak at (1, 10); (1, 8) gives 2.8e-2 on the force, (4, 10) is no better than (1, 10)
        and costs 2.2x.
    max_events : int
        Localized switches per substep.
    adc_bits : int
        Current ADC resolution (default 16; 0: an ideal reading).
    current_full_scale : float
        Current sense range, A peak (default 1.0).

    Attributes
    ----------
    resistance : float
        Coil resistance, ohm (the limiter bounds ``|V| <= I_max R``).
    capacitance : float
        0.0 (a coil).

    Examples
    --------
    >>> import numpy as np
    >>> from rtctl.plant.em import EMPlant, EMGroup
    >>> group = EMGroup(EMPlant(finger=None, preload=0.0), fs=48000.0, n_channels=2)
    >>> drive = np.full((2, 4800), 1.0)
    >>> sensed, truth = np.empty((2, 4800)), np.empty((2, 4, 4800))
    >>> group.process(drive, sensed, truth), group.sensed_labels
    (0, ('coil_a',))
    >>> round(float(truth[0, 0, -1]) * 1e6, 1), round(float(sensed[0, -1]), 4)  # um, A at 0.1 s
    (44.6, 0.0714)
    """

    def __init__(self, plant: EMPlant, fs: float, n_channels: int = 16, max_block: int = 64,
                 substeps: int = 1, levels: int = 10, max_events: int = 4, adc_bits: int = 16,
                 current_full_scale: float = 1.0):
        if not isinstance(plant, EMPlant):
            raise ModelError("EMGroup needs an EMPlant")
        fsc = _positive("current_full_scale", current_full_scale)
        if int(adc_bits) != adc_bits or not 0 <= int(adc_bits) <= 32:
            raise ModelError(f"adc_bits must be an integer in 0..32, got {adc_bits!r}")
        lsb = 2.0 * fsc / 2 ** int(adc_bits) if adc_bits else 0.0
        self.plant = plant
        self.resistance = plant.resistance
        mask = plant.contact_mask
        probes = [("contact_share", "", mask)] if mask else []
        super().__init__(plant.model, fs, n_channels, plant.y0, params=[plant.preload],
                         sensed=[("coil_a", 4, lsb, fsc)], probes=probes, substeps=substeps,
                         levels=levels, max_events=max_events, max_block=max_block,
                         capacitance=0.0)
