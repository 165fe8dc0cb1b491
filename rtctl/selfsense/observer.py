"""Segmented-electrode observers (seed 000, Eq. 2): mechanical state from currents and voltage.

Each electrode segment ``j`` of a beam driven by one voltage ``V`` carries the charge
``Cp_j V - m_p (psi_end - psi_start)``, so every current is affine in a few unknown loads or
states ``u`` and in ``V``::

    I_j / (j w) - b_j V = a_j . u          (one row per segment)

* **two segments, known support** (clamped or given springs): ``u = [P, T]``, the external force
  and moment at the tip, a 2x2 system. ``a_j`` and ``b_j`` come from the port receptance of the
  unloaded beam (:meth:`TMMBeam.port_receptance`), which has the plant's modal damping: modal
  damping is not a local law, so it cannot sit in field matrices, but it is exact in a
  receptance. The tip force pushed into the finger is ``Q(L) = -P``; ``T`` should read ~0.
* **four segments, support unknown**: ``u = [w_c, psi_c, M_c, Q_c]``, the root state, carried
  through the segments by the field matrices (4x4; Kelvin-Voigt damping, since the modes that
  modal damping refers to depend on the support being identified). The support's dynamic
  stiffnesses follow as ``k - m w^2 = -Q_c / w_c`` and ``k_rot - J w^2 = M_c / psi_c``.

With ``u`` known, the model gives the tip: deflection, velocity, slope, moment and the force
``Q(L)`` pushed into the finger (skin inertia included), hence the finger impedance ``Q(L) / v``.
Everything is linear in the measured phasors, so per frequency the observer is one complex
matrix ``H`` with ``estimate = H @ [D, S_0, ..., S_{n-1}]``, ``D`` the drive phasor and ``S_j``
the sensed current phasors; :class:`FrontEnd` turns sensed into true currents (AA filter, aliased
images of the DAC staircase) and the drive into the actuator voltage (amplifier, zero-order hold).

Conditioning
------------
The motional current is a small share of each reading (6-8 % for the bundled beam: the rest is
capacitive), so a relative error ``e`` in a reading becomes ``~e / 0.07`` in the mechanics before
the inversion adds its own condition number. The tip force is the small difference between what
the voltage alone would do and what the currents say the beam did, so its relative error grows
further as the finger gets softer (``|K_f| / k_beam``: 0.4 at 50 g, 0.12 at 2 g).
:attr:`ObserverMatrix.cond` is the 2-norm condition number of the scaled system (unknowns in
units of the beam's ``L``, ``EI/L``, ``EI/L^2``; rows per segment charge scale);
:attr:`ObserverMatrix.gain` the relative tip-displacement error per relative current error.
Designs beyond ``max_cond`` raise :class:`~rtctl.errors.ModelError`. Identifying a support needs
more: :func:`estimate` returns the sensitivity of ``k`` and ``k_rot`` to the currents.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rtctl.errors import ModelError
from rtctl.selfsense.frontend import FrontEnd
from rtctl.selfsense.tmm import _load_stiffness

__all__ = ["EST_NAMES", "MAX_COND", "MAX_COND_SUPPORT", "ObserverMatrix", "design", "design_many", "estimate"]

#: Rows of an estimate: tip deflection (m), tip velocity (m/s), tip slope (rad), tip moment
#: (N m), tip force into the load (N), root deflection (m), root slope (rad), root moment
#: (N m), root shear (N). Phasors.
EST_NAMES = ("tip_m", "tip_velocity_m_s", "tip_slope_rad", "tip_moment_nm", "tip_force_n",
             "root_m", "root_slope_rad", "root_moment_nm", "root_shear_n")
N_EST = len(EST_NAMES)

#: Default refusal threshold of the scaled condition number (known support).
MAX_COND = 1e6
#: Default refusal threshold when the support is identified (four segments). A rigid root
#: motion strains nothing, so below the first resonance the root state reaches the currents
#: only through the beam's inertia and cond grows like (f_1 / f)^2: 8300 at 100 Hz, 530 at
#: 400 Hz, 150 at 1 kHz for the bundled beam. Measured on the FE plant: k is off by > 50 % at
#: cond >= 350, and within 1 % at 1-1.5 kHz (docs/selfsense.md, Sec. 3).
MAX_COND_SUPPORT = 300.0


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


def design_many(beam, freqs_hz, frontend: FrontEnd | None = None, unknown_support=None,
                image_load=None, max_cond=None) -> dict:
    """:func:`design` at each distinct frequency of ``freqs_hz`` (Hz, > 0), as a dict frequency
    -> :class:`ObserverMatrix`; the same matrices :func:`design` gives one by one, bitwise, but
    the aliased images of every frequency (``2 n_images`` beam solves each, most of the work) are
    solved in one batch (:meth:`~rtctl.selfsense.tmm.TMMBeam.currents`)."""
    freqs = list(dict.fromkeys(float(f) for f in np.ravel(freqs_hz)))
    currents = None
    if frontend is not None and freqs:
        om = np.concatenate([frontend.image_omegas(f) for f in freqs])
        loads = [_load_stiffness(image_load, w) for w in om]
        table = dict(zip(om.tolist(), beam.currents(om, loads)))

        def currents(omega):
            return table[float(omega)]
    return {f: design(beam, f, frontend, unknown_support, image_load, max_cond, image_currents=currents)
            for f in freqs}


def design(beam, freq_hz, frontend: FrontEnd | None = None, unknown_support=None,
           image_load=None, max_cond=None, image_currents=None) -> ObserverMatrix:
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
    max_cond : float, optional
        Refuse designs whose scaled condition number exceeds this (default ``MAX_COND``, or
        ``MAX_COND_SUPPORT`` when the support is identified).
    image_currents : callable, optional
        ``omega -> ndarray (n_seg,)``: the beam's segment currents per volt under ``image_load``
        at the images' frequencies (:meth:`FrontEnd.image_omegas`), solved beforehand (what
        :func:`design_many` does); default each solved here.

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
    ((9, 3), 5.01)
    >>> r = beam.response([250.0])                  # the beam's own response at 1 V
    >>> est = estimate(obs, 1.0, r["current"][0])
    >>> bool(abs(est["tip_m"] / r["tip"][0] - 1) < 1e-9), bool(abs(est["tip_force_n"]) < 1e-12)
    (True, True)
    """
    f = float(freq_hz)
    if not (f > 0.0 and math.isfinite(f)):
        raise ModelError(f"observer frequency must be > 0 Hz, got {freq_hz!r}")
    w = 2.0 * math.pi * f
    n = beam.n_seg
    if unknown_support is None:
        unknown_support = n >= 4
    n_u = 4 if unknown_support else 2
    if n < n_u:
        raise ModelError(f"{n} electrode segment(s) cannot observe {n_u} unknowns; "
                         f"use {n_u} segments (seed 000: two with a known support, four to "
                         "identify it)")
    if max_cond is None:
        max_cond = MAX_COND_SUPPORT if unknown_support else MAX_COND
    if unknown_support:
        A, b, Tu, tv, Ru, rv, unit = _root_form(beam, w)
    else:
        A, b, Tu, tv, Ru, rv, unit = _port_form(beam, w)
    # Scaled conditioning: unknowns in units of the beam's own scales, rows per charge scale.
    As = A * unit[None, :]
    As = As / np.linalg.norm(As, axis=1, keepdims=True)
    cond = float(np.linalg.cond(As))
    if not (cond <= max_cond):
        what = ("identifying the support needs the beam's inertia (cond ~ (f_1/f)^2): use a "
                "frequency near or above the first resonance" if unknown_support else
                "move the electrode split or use another frequency")
        raise ModelError(f"observer at {f:g} Hz is ill-conditioned (scaled cond {cond:.3g} > "
                         f"{max_cond:.3g}): {what}")
    Ainv = np.linalg.pinv(A)
    fe = frontend
    vfac = 1.0 if fe is None else fe.voltage(f)       # actuator V per drive volt
    aa = 1.0 if fe is None else fe.aa(f)
    img = np.zeros(n, dtype=complex)
    if fe is not None:
        img = fe.images(f, image_currents or (lambda om: beam.solve(om, _load_stiffness(image_load, om))["current"]))
    # q_j = I_j / (j w) - b_j V with I_j = (S_j - img_j D) / aa, V = vfac D.
    # u = Ainv q = Ainv [diag(1/(j w aa)) S - (img/(j w aa) + b vfac) D].
    Hu = np.empty((n_u, 1 + n), dtype=complex)
    Hu[:, 1:] = Ainv / (1j * w * aa)
    Hu[:, 0] = -Ainv @ (img / (1j * w * aa) + b * vfac)
    # Tip [w, psi, M, Q] and root [w, psi, M, Q] are affine in (u, V).
    Htip = Tu @ Hu
    Htip[:, 0] += tv * vfac
    Hroot = Ru @ Hu
    Hroot[:, 0] += rv * vfac
    H = np.empty((N_EST, 1 + n), dtype=complex)
    H[0] = Htip[0]
    H[1] = 1j * w * Htip[0]
    H[2] = Htip[1]
    H[3] = Htip[2]
    H[4] = Htip[3]
    H[5:9] = Hroot
    # Gain: relative tip error per relative current error at the nominal load.
    cur = beam.response([f], image_load)["current"][0]
    S = cur * vfac * aa + img
    tip = H[0] @ np.concatenate(([1.0], S))
    gain = float(np.linalg.norm(H[0, 1:] * S) / max(abs(tip), 1e-300))
    return ObserverMatrix(f, H, cond, gain, bool(unknown_support))


def _port_form(beam, w):
    """Known support: the unknowns are the tip's external force ``P`` and moment ``T`` on the
    unloaded beam, whose port receptance carries the plant's modal damping exactly.

    Returns ``A`` (n_seg, 2) and ``b`` (n_seg,) with motional charge ``= A u`` and charge
    ``q = I / (j w) = A u + b V``; the tip state ``Tu u + tv V`` and the root state
    ``Ru u + rv V`` (4 rows each: w, psi, M, Q); the unknowns' unit sizes.
    """
    n = beam.n_seg
    G, Y0 = beam.port_receptance(w, root=True)
    gV = G[:, :n].sum(axis=1)                  # all segments on the one drive
    A = G[:n, n:n + 2]
    b = gV[:n] + beam.cp
    Tu = np.zeros((4, 2), dtype=complex)
    Tu[:2] = G[n:n + 2, n:n + 2]
    Tu[2, 1] = 1.0                             # M(L) = T
    Tu[3, 0] = -1.0                            # Q(L) = -P: the force pushed into the load
    tv = np.zeros(4, dtype=complex)
    tv[:2] = gV[n:n + 2]
    Ru, rv = Y0[:, n:n + 2], Y0[:, :n].sum(axis=1)
    L, EI = beam.length, beam.lam.EI
    return A, b, Tu, tv, Ru, rv, np.array([EI / L**2, EI / L])


def _root_form(beam, w):
    """Unknown support: the unknowns are the root state ``[w, psi, M, Q]``, carried through the
    segments by the field matrices (Kelvin-Voigt damping; the modes, hence the modal damping,
    depend on the support being identified). Same returns as :func:`_port_form`."""
    n = beam.n_seg
    Yu, yv = np.eye(4, dtype=complex), np.zeros(4, dtype=complex)
    A = np.empty((n, 4), dtype=complex)
    b = np.empty(n, dtype=complex)
    for j in range(n):
        T, t, c = beam.segment_matrix(j, w)
        A[j] = c[:4] @ Yu
        b[j] = c[:4] @ yv + c[4]
        Yu, yv = T @ Yu, T @ yv + t
    L, EI = beam.length, beam.lam.EI
    return (A, b, Yu, yv, np.eye(4, dtype=complex), np.zeros(4, dtype=complex),
            np.array([L, 1.0, EI / L, EI / L**2]))


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
        and, for an unknown support, ``support_k_n_m`` (``-Q_c / w_c``: ``k - m w^2``),
        ``support_k_rot_nm_rad`` (``M_c / psi_c``) and their sensitivities
        ``support_k_sensitivity``, ``support_k_rot_sensitivity``: the relative error of each
        per relative error of the sensed currents (2-norm over the segments, to first order).
        A stiff support barely moves, so its ``w_c`` and ``psi_c`` are small differences: a
        sensitivity of 1e4 with currents known to 1e-5 means ~10 % (flag such estimates).
    """
    S = np.asarray(sensed, dtype=complex)
    z = obs.H @ np.concatenate(([complex(drive)], S))
    out = dict(zip(EST_NAMES, z))
    out["impedance_n_s_m"] = z[4] / z[1]
    if obs.unknown_support:
        out["support_k_n_m"] = -z[8] / z[5]
        out["support_k_rot_nm_rad"] = z[7] / z[6]
        # d(ratio)/ratio = d(num)/num - d(den)/den, each linear in the sensed phasors.
        out["support_k_sensitivity"] = float(np.linalg.norm(
            (obs.H[8, 1:] / z[8] - obs.H[5, 1:] / z[5]) * S))
        out["support_k_rot_sensitivity"] = float(np.linalg.norm(
            (obs.H[7, 1:] / z[7] - obs.H[6, 1:] / z[6]) * S))
    return out
