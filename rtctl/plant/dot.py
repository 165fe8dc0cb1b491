"""Latching Dot Braille pin (seed 001: a 4 x 4 fingertip matrix of Dot Braille cells).

Seed 001 builds a 4 x 4 display from two 2 x 4 Dot Braille cells (2.6 mm pitch, 5 V supply).
Every pin has a solenoid, goes up or down with the direction of its current (one MX1508
H-bridge channel per pin, driven by an Arduino) and has a locking mechanism that keeps it up
or down with the power off. The seed gives no transition time, force or height; the defaults
below are stated and justified in ``docs/plants/dot.md``.

Continuous model of one pin (drive: the H-bridge command ``u``, V; per-channel parameter:
finger preload ``F_p``, N)::

    V_c      = +V_s if u > V_s/2,  -V_s if u < -V_s/2,  else 0      H-bridge (0: both low, brake)
    L i'     = V_c - R i - K x'                                      coil, back-EMF K x'
    m x''    = K i - c x' + F_l + F_bot - F_top - F_c
    F_l      = +F_h if x > h/2 else -F_h                             latch: to the nearer end
    F_bot, F_top = stiff penalty stops at 0 and h (push only)
    F_c      = skin contact (rtctl.plant.contact), >= 0

``x`` is the pin height (m, 0 = down, ``h`` = up, into the finger). The latch is modelled as a
constant holding force ``F_h`` toward whichever end the pin is nearer (a bistable magnetic
detent flattened to its mean): with the coil off the pin stays where it is, a current pulse has
to beat ``F_h`` (and the finger) to move it, and a pulse cut before the pin passes mid-travel
lets the latch pull it back. A finger that presses an up pin with more than ``F_h`` pushes it
off its top stop to where the finger's force equals ``F_h``; if that is below mid-travel the
latch pulls it down: the pin *flips down and stays down* until the next up command (the probe
``up_share`` shows it). With the default finger (``k0`` = 300 N/m) that takes a preload above
``F_h - k0 h`` = 0.25 N to give way and above ``F_h - k0 h / 2`` = 0.325 N to flip.

Truth rows (:data:`~rtctl.plant.hybrid.TRUTH_NAMES`): pin height (m), velocity (m/s), force on
the finger (N, >= 0), coil voltage ``V_c`` (V). No sensed rows (the H-bridge has no current
sense).
"""

from __future__ import annotations

import math

import numpy as np

from rtctl.errors import ModelError
from rtctl.plant._checks import positive
from rtctl.plant.contact import PinReference, SkinContact, add_skin
from rtctl.plant.finger import MaxwellLoad
from rtctl.plant.hybrid import TRUTH_NAMES, HybridBuilder, HybridGroup, Lin, unilateral
from rtctl.plant.solenoid import DEFAULT_FINGER

__all__ = ["DotPin", "DotGroup", "PITCH", "GRID"]

#: Pin centre to pin centre, m (seed 001).
PITCH = 2.6e-3
#: Rows and columns of seed 001's fingertip matrix (two 2 x 4 cells).
GRID = (4, 4)


def _pos(name, v, zero_ok=False):
    return positive("DotPin", name, v, zero_ok)


class DotPin(PinReference):
    """Continuous switched-linear model of one latching Dot pin with the finger on top.

    Parameters
    ----------
    supply : float
        H-bridge supply V_s, V (seed 001: 5 V). Commands above ``V_s / 2`` drive up, below
        ``-V_s / 2`` down, anything between leaves the coil shorted (no drive).
    travel : float
        Pin travel h, m. Default 0.5 mm: a Braille dot (0.48 mm in the US Library of Congress
        specification, 0.5 mm Marburg medium; seed 001 gives no number).
    resistance : float
        Coil resistance R, ohm. Default 8 (0.63 A at 5 V, within the MX1508's 1.5 A).
    inductance : float
        Coil inductance L, H. Default 10 mH (a wound micro-solenoid with an iron yoke): L/R =
        1.25 ms sets the transition time.
    force_constant : float
        K, N/A (= back-EMF constant, V s/m). Default 2.0: 1.25 N at 5 V.
    mass : float
        Moving mass of pin and plunger, kg. Default 30 mg.
    damping : float
        Viscous friction of the plunger in its sleeve, N s/m. Default 1.0: the pin then crosses
        its travel at < 1 m/s (0.9 m/s peak under the finger) and the up transition takes ~2
        ms; the back-EMF adds K^2/R = 0.5 N s/m while the bridge conducts or brakes.
    latch_force : float
        Holding force F_h of the latch at either end, N. Default 0.4: above what the default
        finger puts on an up pin (0.18 N at 0.03 N preload), below the coil's 1.25 N.
    stop_stiffness : float
        Penalty stiffness of the two end stops, N/m. Default 1e7 (F_h indents it 40 nm).
    stop_damping : float or None
        N s/m; None: damping ratio 1.5 on the pin mass, ``3 sqrt(k_e m)`` (16.4 N s/m): a dead
        stop, the pin does not rebound. It also keeps the stop modes non-oscillatory, which
        the hybrid engine steps in whole substeps; at ratio 0.5 a pin resting on a stop costs
        16 pieces per substep (2-3x the run time).
    finger : MaxwellLoad or None
        Normal finger load on the pin (mass > 0); None: no finger.
    k_contact, c_contact, surface : float
        Pin-skin penalty contact (:class:`~rtctl.plant.contact.SkinContact`).
    preload : float
        Finger force on this pin at rest, N (a per-channel parameter). Default 0.03: seed 000's
        50 g preload shared by 16 pins.

    Attributes
    ----------
    model : HybridModel
        Inputs ``(command_v, preload_n)``; outputs the 4 truth rows then ``coil_current_a``.
        States ``(coil_a, pin_m, pin_velocity_m_s[, skin_m, skin_velocity_m_s, branches])``.
    y0 : ndarray, shape (n_states,)
        Rest state down (latched at 0) at zero drive and ``preload``.
    y0_up : ndarray, shape (n_states,)
        Rest state up (latched at ``travel``).
    up_bits, contact_bits, top_bits, bottom_bits : tuple of int
        Switch bits that are all on while the pin is in its upper half / touches the skin /
        rests on a stop.

    Examples
    --------
    >>> from rtctl.plant.dot import DotPin
    >>> pin = DotPin()
    >>> round(float(pin.outputs(pin.y0_up, 0.0)[0]) * 1e3, 4)      # latched up, mm
    0.5
    >>> round(float(pin.outputs(pin.y0_up, 0.0)[2]), 3)            # finger force on it, N
    0.18
    >>> [float(pin.outputs(pin.y0, u)[3]) for u in (-5.0, -1.0, 0.0, 3.0)]   # H-bridge, V
    [-5.0, 0.0, 0.0, 5.0]
    """

    def __init__(self, supply=5.0, travel=0.5e-3, resistance=8.0, inductance=10e-3,
                 force_constant=2.0, mass=30e-6, damping=1.0, latch_force=0.4,
                 stop_stiffness=1e7, stop_damping=None, finger: MaxwellLoad | None = DEFAULT_FINGER,
                 k_contact=1e6, c_contact=None, surface=0.0, preload=0.03):
        self.supply = _pos("supply", supply)
        self.travel = _pos("travel", travel)
        self.resistance = _pos("resistance", resistance)
        self.inductance = _pos("inductance", inductance)
        self.force_constant = _pos("force_constant", force_constant)
        self.mass = _pos("mass", mass)
        self.damping = _pos("damping", damping, zero_ok=True)
        self.latch_force = _pos("latch_force", latch_force)
        self.stop_stiffness = _pos("stop_stiffness", stop_stiffness)
        self.stop_damping = (3.0 * math.sqrt(self.stop_stiffness * self.mass)
                             if stop_damping is None
                             else _pos("stop_damping", stop_damping, zero_ok=True))
        self.preload = _pos("preload", preload, zero_ok=True)
        if finger is None and self.preload != 0.0:
            raise ModelError(f"a preload ({preload!r} N) needs a finger; pass finger=... or "
                             "preload=0")
        self.finger = finger
        self.skin = None if finger is None else SkinContact(finger, k_contact, c_contact, surface)
        if self.latch_force >= self.force_constant * self.supply / self.resistance:
            raise ModelError(f"the coil's {self.force_constant * self.supply / self.resistance:.3g}"
                             f" N at {self.supply:g} V cannot beat the latch's "
                             f"{self.latch_force:.3g} N; raise force_constant or supply, or lower "
                             "latch_force")
        self.model = self._build()
        self.n_states = self.model.n_states
        rest_up = self._mask(self.up_bits + self.top_bits + self.contact_bits)
        rest_down = self._mask(self.bottom_bits + self.contact_bits)
        self.y0, _ = self.model.equilibrium([0.0, self.preload], prefer=rest_down)
        self.y0_up, mode = self.model.equilibrium([0.0, self.preload], prefer=rest_up)
        if (mode & rest_up) != rest_up:
            raise ModelError(f"the latch ({self.latch_force:g} N) cannot hold the pin up "
                             f"against the finger's "
                             f"{self.skin.rest_force(self.preload, self.travel):.3g} N at "
                             f"{self.preload:g} N preload; lower the preload or raise latch_force")

    @staticmethod
    def _mask(bits) -> int:
        return int(sum(1 << b for b in bits))

    def _build(self):
        R, L, K, m, h = self.resistance, self.inductance, self.force_constant, self.mass, \
            self.travel
        b = HybridBuilder(["command_v", "preload_n"])
        i, x, v = b.add_state("coil_a"), b.add_state("pin_m"), b.add_state("pin_velocity_m_s")
        # The H-bridge is a comparator on the command: its output is a constant of each mode.
        half = 0.5 * self.supply
        fwd = b.add_switch("bridge_up", Lin.u(0) - half)
        rev = b.add_switch("bridge_down", -Lin.u(0) - half)
        b.derivative(i, (-Lin.x(i, R) - Lin.x(v, K)) * (1.0 / L))
        b.derivative(i, Lin.const(self.supply / L), when=(fwd,))
        b.derivative(i, Lin.const(-self.supply / L), when=(rev,))
        b.derivative(x, Lin.x(v))
        b.derivative(v, (Lin.x(i, K) - Lin.x(v, self.damping)) * (1.0 / m))
        # Latch: -F_h in the lower half, +F_h in the upper half (written as -F_h + 2 F_h).
        up = b.add_switch("latch_up", Lin.x(x) - 0.5 * h)
        b.derivative(v, Lin.const(-self.latch_force / m))
        b.derivative(v, Lin.const(2.0 * self.latch_force / m), when=(up,))
        self.up_bits = (up,)
        rows = [b.output(TRUTH_NAMES[0], Lin.x(x)), b.output(TRUTH_NAMES[1], Lin.x(v)),
                b.output(TRUTH_NAMES[2], Lin()), b.output(TRUTH_NAMES[3], Lin()),
                b.output("coil_current_a", Lin.x(i))]
        b.add_to_output(rows[3], Lin.const(self.supply), when=(fwd,))
        b.add_to_output(rows[3], Lin.const(-self.supply), when=(rev,))
        inv_m = 1.0 / m
        self.bottom_bits, _ = unilateral(b, "bottom", -Lin.x(x), -Lin.x(v), self.stop_stiffness,
                                         self.stop_damping, [(v, inv_m)])
        self.top_bits, _ = unilateral(b, "top", Lin.x(x) - h, Lin.x(v), self.stop_stiffness,
                                      self.stop_damping, [(v, -inv_m)])
        self.contact_bits = ()
        if self.skin is not None:
            st = add_skin(b, self.skin, Lin.x(x), Lin.x(v), Lin.u(1), [(v, -inv_m)],
                          force_row=rows[2])
            self.contact_bits = st.when
        return b.build()


class DotGroup(HybridGroup):
    """``n_channels`` latching Dot pins (default the 4 x 4 matrix of seed 001).

    Per-channel parameter: ``params[:, 0]``, the finger preload on each pin, N (may be written
    between blocks). Probes: ``up_share`` (share of pins in the upper half of their travel,
    i.e. latched or moving up) and, with a finger, ``contact_share``. No sensed rows.

    Parameters
    ----------
    plant : DotPin
    fs : float
        Sample rate, Hz.
    n_channels : int
        Default 16.
    up : bool or array_like of bool, shape (n_channels,)
        Pins that start (and :meth:`reset` to) latched up; default all down.
    max_block : int
    substeps : int
        Exact steps per sample (default 1: every mode is exact at any step; only switching
        times need resolving, which ``levels`` does at a cost only when something switches).
    levels : int
        Switch localization to ``1 / (fs substeps 2^levels)`` (default 16: 0.3 ns; costs only
        when something switches). Against Radau through an up transition, max error / peak:
        height 1.6e-6, velocity 3.2e-4, force 3.5e-4 at (1, 16); 2.6e-5, 8.6e-3, 7.1e-3 at
        (1, 12); 2.8e-4, 0.12, 0.55 at (1, 8) (the top-stop impact needs it).
    max_events : int
        Localized switches per substep.

    Attributes
    ----------
    resistance : float
        Coil resistance, ohm (the limiter's coil bound ``|V| <= I_max R``).
    capacitance : float
        0.0 (a coil).

    Examples
    --------
    >>> import numpy as np
    >>> from rtctl.plant.dot import DotPin, DotGroup
    >>> group = DotGroup(DotPin(), fs=48000.0, n_channels=2)
    >>> drive = np.zeros((2, 960)); drive[0, :480] = 5.0   # pin 0: a 10 ms up pulse
    >>> truth = np.empty((2, 4, 960))
    >>> group.process(drive, np.empty((0, 960)), truth)
    0
    >>> [round(float(h) * 1e3, 3) for h in truth[:, 0, -1]]   # mm, 20 ms later: up, down
    [0.5, -0.0]
    """

    def __init__(self, plant: DotPin, fs: float, n_channels: int = 16, up=False,
                 max_block: int = 64, substeps: int = 1, levels: int = 16, max_events: int = 4):
        if not isinstance(plant, DotPin):
            raise ModelError("DotGroup needs a DotPin")
        mask = plant._mask
        probes = [("up_share", "", mask(plant.up_bits))]
        if plant.contact_bits:
            probes.append(("contact_share", "", mask(plant.contact_bits)))
        self.plant = plant
        self.resistance = plant.resistance
        super().__init__(plant.model, fs, n_channels, plant.y0, params=[plant.preload],
                         sensed=(), probes=probes, substeps=substeps, levels=levels,
                         max_events=max_events, max_block=max_block, capacitance=0.0)
        up = np.broadcast_to(np.asarray(up, dtype=bool), (self.n_channels,)).copy()
        self._up0 = up
        self.reset()

    def reset(self) -> None:
        """Every pin back to rest, latched up where ``up`` said, down elsewhere."""
        super().reset()
        up = getattr(self, "_up0", None)
        if up is not None:
            self.state[up] = self.plant.y0_up
