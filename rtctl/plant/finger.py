"""Finger load on an actuator tip: a generalized Maxwell solid with a moving skin mass.

Model (seed 000, Fig. 1 right; Pawluk & Howe 1999 for three relaxation times)::

    F = k0 x + sum_i f_i,      f_i' = k_i x' - f_i / tau_i

``x`` is the contact displacement (m, moving with the actuator tip), ``F`` the force the tissue
exerts back against that motion (N), each branch a spring ``k_i`` in series with a dashpot
``c_i = k_i tau_i``. The skin mass ``mass`` moves with the tip; in a plant it is added to the
structure's mass at the tip DOF, so it is *not* part of the tissue force ``F``.

Parameter sets belong to scenes; nothing here has defaults beyond the empty branch list.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rtctl.errors import ModelError
from rtctl.plant.lti import StateSpace

__all__ = ["MaxwellLoad"]


@dataclass(frozen=True)
class MaxwellLoad:
    """Generalized Maxwell finger load with skin mass.

    Parameters
    ----------
    mass : float
        Skin mass moving with the contact, kg (>= 0).
    k0 : float
        Equilibrium (long-term) stiffness, N/m (>= 0).
    branches : tuple of (k, tau)
        Maxwell branches: stiffness ``k`` in N/m (> 0) and relaxation time ``tau`` in s (> 0).

    Examples
    --------
    >>> from rtctl.plant.finger import MaxwellLoad
    >>> load = MaxwellLoad(mass=1e-4, k0=300.0, branches=((300.0, 0.004), (150.0, 0.07)))
    >>> round(load.relaxation(0.0), 6)    # instantaneous stiffness k0 + sum k_i, N/m
    750.0
    >>> round(float(abs(load.dynamic_stiffness(0.0))), 6)
    300.0
    """

    mass: float
    k0: float
    branches: tuple = ()

    def __post_init__(self):
        for name in ("mass", "k0"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0.0):
                raise ModelError(f"MaxwellLoad.{name} must be finite and >= 0, got {v!r}")
            object.__setattr__(self, name, v)
        br = []
        for i, b in enumerate(self.branches):
            try:
                k, tau = (float(v) for v in b)
            except (TypeError, ValueError):
                raise ModelError(f"MaxwellLoad branch {i} must be a pair (k N/m, tau s), "
                                 f"got {b!r}") from None
            if not (k > 0.0 and math.isfinite(k) and tau > 0.0 and math.isfinite(tau)):
                raise ModelError(f"MaxwellLoad branch {i}: k and tau must be finite and > 0, "
                                 f"got k={k!r}, tau={tau!r}")
            br.append((k, tau))
        object.__setattr__(self, "branches", tuple(br))

    @property
    def n_branches(self) -> int:
        return len(self.branches)

    @property
    def k(self) -> np.ndarray:
        """Branch stiffnesses, N/m, shape (n_branches,)."""
        return np.array([b[0] for b in self.branches], dtype=np.float64)

    @property
    def tau(self) -> np.ndarray:
        """Branch relaxation times, s, shape (n_branches,)."""
        return np.array([b[1] for b in self.branches], dtype=np.float64)

    def relaxation(self, t):
        """Relaxation modulus: force per unit step displacement, ``k0 + sum k_i exp(-t/tau_i)``.

        Parameters
        ----------
        t : float or ndarray
            Time since the step, s (>= 0).

        Returns
        -------
        float or ndarray
            N/m.
        """
        t = np.asarray(t, dtype=np.float64)
        g = self.k0 + sum(k * np.exp(-t / tau) for k, tau in self.branches)
        return float(g) if g.ndim == 0 else g

    def tissue_stiffness(self, omega):
        """Complex stiffness of the tissue alone, ``F / x`` without the skin mass, N/m.

        ``k0 + sum_i k_i j w tau_i / (1 + j w tau_i)``; ``omega`` in rad/s.
        """
        w = np.asarray(omega, dtype=np.float64)
        s = 1j * w
        return self.k0 + sum(k * s * tau / (1.0 + s * tau) for k, tau in self.branches)

    def dynamic_stiffness(self, omega):
        """Force needed per unit displacement of the contact, skin mass included, N/m.

        ``K(w) = -w^2 mass + tissue_stiffness(w)``: what the actuator tip feels.

        Parameters
        ----------
        omega : float or ndarray
            Angular frequency, rad/s.

        Returns
        -------
        complex or ndarray of complex
        """
        w = np.asarray(omega, dtype=np.float64)
        return -w * w * self.mass + self.tissue_stiffness(w)

    def impedance(self, omega):
        """Mechanical impedance ``F / velocity = K(w) / (j w)``, N s/m (skin mass included).

        Undefined at ``omega = 0`` (a spring has infinite impedance at DC).
        """
        w = np.asarray(omega, dtype=np.float64)
        if np.any(w == 0.0):
            raise ModelError("impedance is infinite at omega = 0; use dynamic_stiffness")
        return self.dynamic_stiffness(w) / (1j * w)

    def branch_system(self) -> StateSpace:
        """The branches alone, driven by the contact velocity.

        States ``f_i`` (N), input ``x'`` (m/s), output ``sum_i f_i`` (N):
        ``A = diag(-1/tau_i)``, ``B = k_i``, ``C = 1``. A plant adds ``k0 x`` itself.
        """
        n = self.n_branches
        return StateSpace(np.diag(-1.0 / self.tau) if n else np.zeros((0, 0)),
                          self.k.reshape(n, 1), np.ones((1, n)), np.zeros((1, 1)),
                          state_names=tuple(f"branch{i}_force_n" for i in range(n)),
                          input_names=("velocity_m_s",), output_names=("branch_force_n",))

    def state_space(self) -> StateSpace:
        """Standalone tissue model: states ``[x, f_1..f_n]``, input velocity, output ``F``.

        ``x' = v``, ``f_i' = k_i v - f_i / tau_i``, ``F = k0 x + sum f_i`` (N). The skin mass
        is not included (it belongs to whatever drives the contact).
        """
        n = self.n_branches
        A = np.zeros((n + 1, n + 1))
        A[1:, 1:] = np.diag(-1.0 / self.tau) if n else 0.0
        B = np.concatenate(([1.0], self.k)).reshape(n + 1, 1)
        C = np.concatenate(([self.k0], np.ones(n))).reshape(1, n + 1)
        return StateSpace(A, B, C, np.zeros((1, 1)),
                          state_names=("x_m",) + tuple(f"branch{i}_force_n" for i in range(n)),
                          input_names=("velocity_m_s",), output_names=("force_n",))
