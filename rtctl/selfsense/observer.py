"""Segmented-electrode observers (seed 000, Eq. 2): mechanical state from currents and voltage.

Each electrode segment ``j`` of a beam driven by one voltage ``V`` carries the charge
``Cp_j V - m_p (psi_end - psi_start)``; the transfer matrices carry the root state
``y_c = [w, psi, M, Q]`` through the segments, so every current is affine in the root state's
unknown entries ``u`` and in ``V``::

    I_j / (j w) - b_j V = a_j . u          (one row per segment)

* two segments, clamped root (``w = psi = 0`` known): ``u = [M_c, Q_c]``, a 2x2 system;
* four segments, support unknown: ``u = [w_c, psi_c, M_c, Q_c]``, 4x4; the support's dynamic
  stiffnesses follow as ``k - m w^2 = -Q_c / w_c`` and ``k_rot - J w^2 = M_c / psi_c``.

With ``u`` known, the transfer matrices give the tip: deflection, velocity, slope, moment and the
force ``Q(L)`` pushed into the finger (skin inertia included), hence the finger impedance
``Q(L) / v``. Everything is linear in the measured phasors, so per frequency the observer is one
complex matrix ``H`` with ``estimate = H @ [D, S_0, ..., S_{n-1}]``, ``D`` the drive phasor and
``S_j`` the sensed current phasors; :class:`FrontEnd` turns sensed into true currents
(AA filter, aliased images of the DAC staircase) and the drive into the actuator voltage
(amplifier, zero-order hold).

Conditioning
------------
The motional current is a small share of each reading (6-8 % for the bundled beam: the rest is
capacitive), so a relative error ``e`` in a reading becomes ``~e / 0.07`` in the mechanics before
the inversion adds its own condition number. :attr:`ObserverMatrix.cond` is the 2-norm condition
number of the scaled system (unknowns in units of ``L``, ``EI/L``, ``EI/L^2``; rows per segment
charge scale); :attr:`ObserverMatrix.gain` the relative tip-displacement error per relative
current error. Designs beyond ``max_cond`` raise :class:`~rtctl.errors.ModelError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rtctl.errors import ModelError
from rtctl.selfsense.frontend import FrontEnd
from rtctl.selfsense.tmm import _load_stiffness

__all__ = ["EST_NAMES", "ObserverMatrix", "design", "estimate"]

#: Rows of an estimate: tip deflection (m), tip velocity (m/s), tip slope (rad), tip moment
#: (N m), tip force into the load (N), root deflection (m), root slope (rad), root moment
#: (N m), root shear (N). Phasors.
EST_NAMES = ("tip_m", "tip_velocity_m_s", "tip_slope_rad", "tip_moment_nm", "tip_force_n",
             "root_m", "root_slope_rad", "root_moment_nm", "root_shear_n")
N_EST = len(EST_NAMES)

#: Default refusal threshold of the scaled condition number.
MAX_COND = 1e6


@dataclass(frozen=True)
class ObserverMatrix:
    """Observer at one frequency: ``estimate = H @ [D, S_0, ..., S_{n_seg-1}]``.

    Attributes
    ----------
    freq_hz : float
    H : ndarray, shape (N_EST, 1 + n_seg), complex
        Rows ``EST_NAMES``; columns: drive phasor (V), sensed current phasors (A).
    cond : float
        Condition number of the scaled inversion.
    gain : float
        Relative tip-deflection error per relative error of the sensed currents (2-norm), at
        the design's nominal load.
    unknown_support : bool
    """

    freq_hz: float
    H: np.ndarray
    cond: float
    gain: float
    unknown_support: bool


def design(beam, freq_hz, frontend: FrontEnd | None = None, unknown_support=None,
           image_load=None, max_cond=MAX_COND) -> ObserverMatrix:
    """Observer matrix at one frequency.

    Parameters
    ----------
    beam : TMMBeam
        Model of the actuator (its support is used when the support is known).
    freq_hz : float
        Hz, > 0.
    frontend : FrontEnd, optional
        Drive and sense chain; None: ideal (the phasors are the actuator voltage and the true
        currents).
    unknown_support : bool, optional
        Solve for all four root states (needs >= 4 segments). Default: True iff the beam has
        >= 4 segments.
    image_load : MaxwellLoad or callable, optional
        Load assumed when predicting the aliased images (tens of kHz, where the finger acts as
        its skin mass) and for :attr:`ObserverMatrix.gain`.
    max_cond : float
        Refuse designs whose scaled condition number exceeds this.

    Raises
    ------
    ModelError
        Too few segments, or ``cond > max_cond`` (naming the frequency and the fix).

    Examples
    --------
    >>> from rtctl.plant.materials import BUILTIN
    >>> from rtctl.selfsense.tmm import TMMBeam, laminate_of
    >>> pzt = BUILTIN["PZT-5A"]
    >>> beam = TMMBeam(laminate_of(1.5e-3, [(pzt, 0.3e-3), (pzt, 0.3e-3)], "parallel"),
    ...                15e-3, (0.5, 0.5), 0.01)
    >>> obs = design(beam, 250.0)
    >>> obs.H.shape, round(obs.cond, 2)
    ((9, 3), 4.99)
    >>> sol = beam.solve(2 * 3.141592653589793 * 250.0)         # the beam's own response at 1 V
    >>> est = estimate(obs, 1.0, sol["current"])
    >>> bool(abs(est["tip_m"] / sol["y"][-1][0] - 1) < 1e-9)
    True
    """
    f = float(freq_hz)
    if not (f > 0.0 and math.isfinite(f)):
        raise ModelError(f"observer frequency must be > 0 Hz, got {freq_hz!r}")
    w = 2.0 * math.pi * f
    n = beam.n_seg
    if unknown_support is None:
        unknown_support = n >= 4
    n_u = 4 if unknown_support else 2
    if not unknown_support and not beam.support.clamped:
        # A known elastic support: the root state is [w, psi, k_rot psi, -k w].
        ks, kr = beam.support_stiffness(w)
        N = np.zeros((4, 2), dtype=complex)
        N[0, 0], N[3, 0] = 1.0, -ks
        N[1, 1], N[2, 1] = 1.0, kr
        if math.isinf(beam.support.k):
            N[:, 0] = [0, 0, 0, 1.0]
        if math.isinf(beam.support.k_rot):
            N[:, 1] = [0, 0, 1.0, 0]
    elif unknown_support:
        N = np.eye(4, dtype=complex)
    else:
        N = np.zeros((4, 2), dtype=complex)
        N[2, 0] = N[3, 1] = 1.0
    if n < n_u:
        raise ModelError(f"{n} electrode segment(s) cannot observe {n_u} unknown root states; "
                         f"use {n_u} segments (seed 000: two with a known support, four to "
                         "identify it)")
    L, EI = beam.length, beam.lam.EI
    Dscale = np.array([L, 1.0, EI / L, EI / L**2])
    # Propagate: y = Yu @ u + yv * V at each segment boundary.
    Yu, yv = N.copy(), np.zeros(4, dtype=complex)
    A = np.empty((n, n_u), dtype=complex)
    b = np.empty(n, dtype=complex)
    for j in range(n):
        T, t, c = beam.segment_matrix(j, w)
        A[j] = c[:4] @ Yu
        b[j] = c[:4] @ yv + c[4]
        Yu, yv = T @ Yu, T @ yv + t
    # Scaled conditioning: unknowns in units of the root state scale, rows per charge scale.
    unit = np.abs(N).T @ Dscale  # a typical size of each unknown
    As = A * unit[None, :]
    As = As / np.linalg.norm(As, axis=1, keepdims=True)
    cond = float(np.linalg.cond(As))
    if not (cond <= max_cond):
        raise ModelError(f"observer at {f:g} Hz is ill-conditioned (scaled cond {cond:.3g} > "
                         f"{max_cond:.0e}): move the electrode split, use fewer unknowns or "
                         "another frequency")
    Ainv = np.linalg.pinv(A)
    fe = frontend
    vfac = 1.0 if fe is None else fe.voltage(f)       # actuator V per drive volt
    aa = 1.0 if fe is None else fe.aa(f)
    img = np.zeros(n, dtype=complex)
    if fe is not None:
        img = fe.images(f, lambda om: beam.solve(om, _load_stiffness(image_load, om))["current"])
    # q_j = I_j / (j w) - b_j V with I_j = (S_j - img_j D) / aa, V = vfac D.
    # u = Ainv q = Ainv [diag(1/(j w aa)) S - (img/(j w aa) + b vfac) D].
    Hu = np.empty((n_u, 1 + n), dtype=complex)
    Hu[:, 1:] = Ainv / (1j * w * aa)
    Hu[:, 0] = -Ainv @ (img / (1j * w * aa) + b * vfac)
    # Root and tip states are affine in (u, V).
    Hroot = np.zeros((4, 1 + n), dtype=complex)
    Hroot += N @ Hu
    Htip = Yu @ Hu
    Htip[:, 0] += yv * vfac
    H = np.empty((N_EST, 1 + n), dtype=complex)
    H[0] = Htip[0]
    H[1] = 1j * w * Htip[0]
    H[2] = Htip[1]
    H[3] = Htip[2]
    H[4] = Htip[3]
    H[5:9] = Hroot
    # Gain: relative tip error per relative current error at the nominal load.
    sol = beam.solve(w, _load_stiffness(image_load, w))
    S = sol["current"] * vfac * aa + img
    tip = H[0] @ np.concatenate(([1.0], S))
    gain = float(np.linalg.norm(H[0, 1:] * S) / max(abs(tip), 1e-300))
    return ObserverMatrix(f, H, cond, gain, bool(unknown_support))


def estimate(obs: ObserverMatrix, drive, sensed) -> dict:
    """Apply an observer to measured phasors.

    Parameters
    ----------
    obs : ObserverMatrix
    drive : complex
        Drive phasor, V.
    sensed : array_like, shape (n_seg,), complex
        Sensed current phasors, A.

    Returns
    -------
    dict
        ``EST_NAMES`` -> complex phasor, plus ``impedance_n_s_m`` (tip force over tip velocity)
        and, for an unknown support, ``support_k_n_m`` (``-Q_c / w_c``: ``k - m w^2``) and
        ``support_k_rot_nm_rad`` (``M_c / psi_c``).
    """
    z = obs.H @ np.concatenate(([complex(drive)], np.asarray(sensed, dtype=complex)))
    out = dict(zip(EST_NAMES, z))
    out["impedance_n_s_m"] = z[4] / z[1]
    if obs.unknown_support:
        out["support_k_n_m"] = -z[8] / z[5]
        out["support_k_rot_nm_rad"] = z[7] / z[6]
    return out
