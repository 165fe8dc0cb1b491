"""Unilateral normal contact of a pin with the finger: pushes, never pulls.

The skin under a pin is a moving mass on the generalized Maxwell tissue (seed 000, Fig. 1;
:class:`~rtctl.plant.finger.MaxwellLoad`), in pin coordinates (height, positive up into the
finger)::

    x_s' = v_s
    m_s v_s' = F_c - k0 (x_s - surface) - sum_i f_i - F_p
    f_i' = k_i v_s - f_i / tau_i
    F_c = k_c d + c_c d'   while d = x_pin - x_s > 0 and k_c d + c_c d' > 0, else 0

``F_c`` (N, >= 0) is the force the pin puts on the finger. Contact is a stiff penalty
Kelvin-Voigt element (:func:`rtctl.plant.hybrid.unilateral`): ``k_c`` (default 1e6 N/m, 1000x the
tissue) only keeps the pin out of the skin; ``c_c`` (default damping ratio 0.7 on the skin mass)
damps the contact rattle. It acts only while the pin indents the skin *and* the force would be
positive, so the skin is never pulled: when the pin retracts faster than the skin can follow
(its mass on the tissue springs), contact is lost, ``F_c = 0``, and the skin flies free until the
pin catches up with it again.

**Preload.** The finger's static force ``F_p`` (N) presses the skin toward the pin through the
tissue's long-term spring: without the pin the skin would rest ``F_p / k0`` below ``surface``
(its unloaded height, pin coordinates; 0 = the pin's rest height). A pin resting at the surface
therefore indents the preloaded skin by ``F_p / k0`` and carries the whole preload, up to the
penalty's share: at rest ``F_c = (F_p + k0 (x_pin - surface)) / (1 + k0 / k_c)``. All branch
forces are zero at rest (relaxed). ``F_p = 0`` is a skin just touching a pin at the surface.
``F_p`` is an input of the model, so a group can change it between blocks. With ``k0 = 0`` the
preload still holds the skin on the pin, but a skin that loses contact has no rest position
(the model then has no equilibrium without contact).

The skin mass must be > 0: a massless skin would follow any retraction instantly, and contact
loss, the point of this model, would not exist.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rtctl.errors import ModelError
from rtctl.plant.finger import MaxwellLoad
from rtctl.plant.hybrid import TRUTH_NAMES, HybridBuilder, HybridModel, Lin, unilateral

__all__ = ["SkinContact", "SkinStates", "add_skin", "kinematic_pin_model"]


@dataclass(frozen=True)
class SkinContact:
    """The finger under one pin, with its penalty contact.

    Parameters
    ----------
    finger : MaxwellLoad
        Skin mass (kg, > 0), long-term stiffness ``k0`` (N/m) and Maxwell branches.
    k_contact : float
        Penalty stiffness of the pin-skin contact, N/m (> 0).
    c_contact : float or None
        Penalty damping, N s/m (>= 0); None: ``2 * 0.7 * sqrt(k_contact * mass)``.
    surface : float
        Unloaded skin surface height in pin coordinates, m (0 = the pin's rest height;
        positive leaves an air gap).

    Examples
    --------
    >>> from rtctl.plant.finger import MaxwellLoad
    >>> from rtctl.plant.contact import SkinContact
    >>> skin = SkinContact(MaxwellLoad(1e-4, 300.0, ((300.0, 0.004),)))
    >>> round(skin.c, 3), round(skin.rest_force(0.2, 0.0) / 0.2, 4)
    (14.0, 0.9997)
    """

    finger: MaxwellLoad
    k_contact: float = 1e6
    c_contact: float | None = None
    surface: float = 0.0

    def __post_init__(self):
        if not isinstance(self.finger, MaxwellLoad):
            raise ModelError("SkinContact.finger must be a MaxwellLoad")
        if not self.finger.mass > 0.0:
            raise ModelError("the skin under a pin needs a mass > 0 (finger.normal.mass): a "
                             "massless skin can never lose contact")
        k = float(self.k_contact)
        if not (k > 0.0 and math.isfinite(k)):
            raise ModelError(f"k_contact must be finite and > 0 N/m, got {self.k_contact!r}")
        c = 1.4 * math.sqrt(k * self.finger.mass) if self.c_contact is None \
            else float(self.c_contact)
        if not (c >= 0.0 and math.isfinite(c)):
            raise ModelError(f"c_contact must be finite and >= 0 N s/m, got {self.c_contact!r}")
        s = float(self.surface)
        if not math.isfinite(s):
            raise ModelError(f"surface must be a finite height in m, got {self.surface!r}")
        object.__setattr__(self, "k_contact", k)
        object.__setattr__(self, "c_contact", c)
        object.__setattr__(self, "surface", s)

    @property
    def c(self) -> float:
        """Contact damping in use, N s/m."""
        return float(self.c_contact)

    def rest_force(self, preload: float, pin_height: float) -> float:
        """Contact force at rest with the pin held at ``pin_height`` (m), N (>= 0)."""
        k0, kc = self.finger.k0, self.k_contact
        f = (float(preload) + k0 * (float(pin_height) - self.surface)) / (1.0 + k0 / kc)
        return max(f, 0.0)


@dataclass(frozen=True)
class SkinStates:
    """Where :func:`add_skin` put the skin in a model.

    Attributes
    ----------
    x, v : int
        State indices of the skin height (m) and velocity (m/s).
    branches : tuple of int
        State indices of the Maxwell branch forces (N).
    when : tuple of int
        Switch bits that are all on while the pin touches the skin.
    force : Lin
        Contact force (valid while ``when`` is on), N.
    """

    x: int
    v: int
    branches: tuple
    when: tuple
    force: Lin


def add_skin(builder: HybridBuilder, skin: SkinContact, pin_height: Lin, pin_velocity: Lin,
             preload: Lin, pin_rows=(), force_row: int | None = None,
             name: str = "contact") -> SkinStates:
    """Add the skin states and the unilateral contact to a pin model.

    Parameters
    ----------
    builder : HybridBuilder
    skin : SkinContact
    pin_height, pin_velocity : Lin
        The pin tip's height (m, up) and its time derivative (m/s), as forms of the states and
        inputs (a moving pin: its states; a kinematic pin: its height state and velocity input).
    preload : Lin
        Finger preload ``F_p``, N (usually an input, e.g. ``Lin.u(1)``).
    pin_rows : sequence of (int, float)
        ``(state row, gain)`` receiving ``gain * F_c``: the pin's velocity row with
        ``-1 / m_pin`` (the skin pushes the pin down).
    force_row : int, optional
        Output row that receives ``F_c`` while in contact (0 otherwise).
    name : str
        Switch name prefix.

    Returns
    -------
    SkinStates
    """
    f = skin.finger
    xs, vs = builder.add_state("skin_m"), builder.add_state("skin_velocity_m_s")
    br = tuple(builder.add_state(f"skin_branch{i}_n") for i in range(f.n_branches))
    builder.derivative(xs, Lin.x(vs))
    inv_m = 1.0 / f.mass
    tissue = Lin.x(xs, f.k0) - f.k0 * skin.surface + preload
    for j in br:
        tissue = tissue + Lin.x(j)
    builder.derivative(vs, tissue * -inv_m)
    for j, (k, tau) in zip(br, f.branches):
        builder.derivative(j, Lin.x(vs, k) - Lin.x(j, 1.0 / tau))
    when, force = unilateral(builder, name, pin_height - Lin.x(xs), pin_velocity - Lin.x(vs),
                             skin.k_contact, skin.c, [(vs, inv_m), *pin_rows], force_row)
    return SkinStates(xs, vs, br, when, force)


def kinematic_pin_model(skin: SkinContact) -> HybridModel:
    """A pin whose motion is prescribed, on the skin: for kinematic pins (latching, stepper).

    Inputs ``(pin_velocity_m_s, preload_n)``; states ``(pin_m, skin_m, skin_velocity_m_s,
    skin_branch*_n)``. The pin height is the integral of the velocity input, so a prescribed
    height ``h(t)`` enters as ``u[k] = (h[k + 1] - h[k]) * fs`` (zero-order hold): the height is
    then exact at every sample and linear between, with no staircase jumps for the stiff
    contact to ring on. Outputs are the :data:`~rtctl.plant.hybrid.TRUTH_NAMES` rows (voltage
    row 0).

    Returns
    -------
    HybridModel

    Examples
    --------
    >>> from rtctl.plant.finger import MaxwellLoad
    >>> from rtctl.plant.contact import SkinContact, kinematic_pin_model
    >>> model = kinematic_pin_model(SkinContact(MaxwellLoad(1e-4, 300.0, ((300.0, 0.004),))))
    >>> model.state_names
    ('pin_m', 'skin_m', 'skin_velocity_m_s', 'skin_branch0_n')
    >>> x, mode = model.equilibrium([0.0, 0.1], fixed={0: 0.0})   # pin held at height 0
    >>> round(float(model.outputs(x, [0.0, 0.1])[2]), 4)     # the pin carries the preload, N
    0.1
    """
    b = HybridBuilder(["pin_velocity_m_s", "preload_n"])
    xp = b.add_state("pin_m")
    b.derivative(xp, Lin.u(0))
    rows = [b.output(TRUTH_NAMES[0], Lin.x(xp)), b.output(TRUTH_NAMES[1], Lin.u(0)),
            b.output(TRUTH_NAMES[2], Lin()), b.output(TRUTH_NAMES[3], Lin())]
    add_skin(b, skin, Lin.x(xp), Lin.u(0), Lin.u(1), force_row=rows[2])
    return b.build()


class PinReference:
    """The continuous reference interface of a coil pin under the finger (``solve_ivp``'s
    ``fun`` and the truth rows), shared by the solenoid, EM and Dot plants. A subclass holds
    ``model`` (a :class:`~rtctl.plant.hybrid.HybridModel` with inputs ``(drive V, preload N)``)
    and ``preload`` (N)."""

    def _u(self, u):
        return np.array([float(u), self.preload])

    def rhs(self, t, y, u):
        """State derivative for drive voltage ``u`` (V) at the pin's preload, shape (n_states,)."""
        return self.model.rhs(t, y, self._u(u))

    def outputs(self, y, u):
        """Truth rows ``(height m, velocity m/s, finger force N, coil voltage V)``, shape (4,)."""
        return self.model.outputs(y, self._u(u))[:len(TRUTH_NAMES)]

    def mode(self, y, u) -> int:
        """The switched model's mode (bit set of active switches) at ``y``, ``u``."""
        return self.model.mode(y, self._u(u))
