"""What the segment currents can and cannot tell about a bimorph (identifiability).

A calibration from electrical data alone fits the model's parameters to measured segment currents
per volt. This module asks which parameters such a fit can determine, using the transfer-matrix
model's currents (:meth:`rtctl.selfsense.tmm.TMMBeam.response`), with or without a finger.

**One direction is invisible.** Every layer thickness x ``s``, every ``E`` x ``s^-2``, ``d31`` x
``s^1.5``, ``eps33T`` x ``s``, and the finger's stiffnesses and mass x ``s`` leave every segment
current unchanged while the tip per volt scales by ``s^-0.5`` (:data:`THICKNESS_DIRECTION`). In
the equivalent circuit of a mode (modal mass ``m``, stiffness ``k``, transformer ratio ``N``
from volts to force), the motional branch seen from the electrodes is an inductance ``m/N^2`` and
a capacitance ``N^2/k``: scaling ``m`` and ``k`` by ``s`` and ``N`` by ``sqrt(s)`` changes
neither, nor the blocked capacitance, but moves the tip per volt ``N/k`` by ``s^-0.5``. The
density is the same direction seen from the mass (:data:`DENSITY_DIRECTION`). The currents
therefore fix the displacement scale only up to half the relative uncertainty of the modal mass
(thickness x density): it must be anchored on a mechanical fact.

**The rest** is measured by :func:`sensitivity`: the Jacobian of the log segment currents with
respect to log parameters, and its singular values (docs/selfsense.md, "What the currents cannot
tell").

Parameters are the relative factors of :data:`FACTORS` (the names the scene's simulated device
uses for its own departures from the model), applied to a :class:`BeamParams` and a finger.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from rtctl.errors import ModelError

from .tmm import Support, TMMBeam, laminate_of

__all__ = ["DENSITY_DIRECTION", "FACTORS", "THICKNESS_DIRECTION", "BeamParams", "Sensitivity", "grid",
           "invisible_scaling", "response", "scaled_load", "sensitivity"]

#: Relative factors a parameter set can be scaled by: the bimorph's (every layer, every material)
#: and the finger's.
FACTORS = ("thickness", "E", "d31", "eps33T", "rho", "damping", "finger_k0", "finger_mass", "finger_branches")

_FINGER = {"finger_k0": 1.0, "finger_mass": 1.0, "finger_branches": 1.0}

#: Exponents of ``s`` that leave every segment current unchanged: bending stiffness and mass per
#: length x ``s`` (``E t^3`` and ``rho t``), moment per volt x ``sqrt(s)`` (``d31 E t``), blocked
#: capacitance and coupling unchanged (``eps33T / t``, ``d31^2 E / eps33T``), finger x ``s``.
THICKNESS_DIRECTION = {"thickness": 1.0, "E": -2.0, "d31": 1.5, "eps33T": 1.0, **_FINGER}

#: The same invisible scaling reached through the density: ``rho E`` x ``s`` (mass and stiffness),
#: ``d31`` x ``s^-0.5`` (moment per volt ``d31 E`` x ``sqrt(s)``).
DENSITY_DIRECTION = {"rho": 1.0, "E": 1.0, "d31": -0.5, **_FINGER}


@dataclass(frozen=True)
class BeamParams:
    """The ingredients of a bimorph's transfer-matrix model, in the units the model takes.

    Attributes
    ----------
    width, length : float
        m.
    layers : tuple of (Material, float)
        Bottom face up: a material (``E``, ``d31``, ``eps33T``, ``rho``; see
        :mod:`rtctl.plant.materials`) and its thickness, m.
    connection : {"parallel", "series"}
    segments : tuple of float
        Electrode split, fractions of the length from the root.
    zeta : float
        Modal damping ratio.
    support : Support
    """

    width: float
    length: float
    layers: tuple
    connection: str
    segments: tuple
    zeta: float
    support: Support = field(default_factory=Support)

    @classmethod
    def from_fe(cls, fe) -> BeamParams:
        """The ingredients of a :class:`~rtctl.plant.beam.BeamFE` (its spec and support)."""
        s, sup = fe.spec, fe.support
        return cls(s.width, s.length, tuple((l.material, l.thickness) for l in s.layers), s.connection,
                   tuple(s.segments), s.damping, Support(sup.k, sup.k_rot, sup.mass, sup.inertia))

    def scaled(self, factors: dict) -> BeamParams:
        """Every layer's thickness and material constants, and the damping, times ``factors``
        (keys of :data:`FACTORS`; the finger's are ignored here, see :func:`scaled_load`)."""
        f = _check(factors)
        layers = tuple((replace(m, E=m.E * f["E"], d31=m.d31 * f["d31"], eps33T=m.eps33T * f["eps33T"],
                                rho=m.rho * f["rho"]), t * f["thickness"]) for m, t in self.layers)
        return replace(self, layers=layers, zeta=self.zeta * f["damping"])

    def beam(self) -> TMMBeam:
        return TMMBeam(laminate_of(self.width, self.layers, self.connection), self.length, self.segments,
                       self.zeta, self.support)


def _check(factors) -> dict:
    f = {k: float(v) for k, v in (factors or {}).items()}
    unknown = sorted(set(f) - set(FACTORS))
    if unknown:
        raise ModelError(f"unknown factors {unknown}; allowed: {', '.join(FACTORS)}")
    bad = [k for k, v in f.items() if not (math.isfinite(v) and v > 0.0)]
    if bad:
        raise ModelError(f"factors {bad} must be finite and > 0")
    return {k: f.get(k, 1.0) for k in FACTORS}


def scaled_load(load, factors: dict):
    """A Maxwell finger (``mass``, ``k0``, ``branches`` of ``(k, tau)``) with its mass, static
    stiffness and branch stiffnesses times ``factors``; None stays None."""
    if load is None:
        return None
    f = _check(factors)
    return replace(load, mass=load.mass * f["finger_mass"], k0=load.k0 * f["finger_k0"],
                   branches=tuple((k * f["finger_branches"], tau) for k, tau in load.branches))


def response(params: BeamParams, load, freqs, factors: dict | None = None):
    """Segment currents and tip deflection per volt (electrodes driven together) of the beam and
    finger scaled by ``factors``.

    Returns
    -------
    current : ndarray, shape (n, n_seg), complex
        A/V.
    tip : ndarray, shape (n,), complex
        m/V.
    """
    f = factors or {}
    r = params.scaled(f).beam().response(freqs, scaled_load(load, f))
    return r["current"], r["tip"]


def grid(params: BeamParams, n: int = 30, f_lo: float = 20.0, f_hi: float = 3000.0) -> np.ndarray:
    """The measurement frequencies of the analysis, Hz: ``n`` equally spaced lines from ``f_lo``
    to ``f_hi`` (a periodic multisine's lines are) and the first natural frequency of the beam
    without finger, sorted."""
    f1 = params.beam().natural_frequencies(1)[0]
    return np.sort(np.r_[np.linspace(f_lo, f_hi, n), f1])


def invisible_scaling(params: BeamParams, load, freqs, s: float, direction: dict = THICKNESS_DIRECTION) -> dict:
    """Scale the parameters by ``s ** direction[name]`` and compare with the unscaled ones.

    Returns
    -------
    dict
        ``current_change``: the largest ``|I_scaled / I - 1|`` over frequencies and segments;
        ``tip_ratio``: ``tip_scaled / tip`` per frequency (complex; the scaling predicts
        ``s^-0.5``); ``tip_ratio_error``: the largest ``|tip_ratio - s^-0.5|``.
    """
    i0, w0 = response(params, load, freqs)
    i1, w1 = response(params, load, freqs, {k: s ** e for k, e in direction.items()})
    ratio = w1 / w0
    return {"current_change": float(np.max(np.abs(i1 / i0 - 1.0))), "tip_ratio": ratio,
            "tip_ratio_error": float(np.max(np.abs(ratio - s ** -0.5)))}


@dataclass(frozen=True)
class Sensitivity:
    """What :func:`sensitivity` returns.

    Attributes
    ----------
    names : tuple of str
        The parameters (columns of ``jacobian``).
    jacobian : ndarray, shape (2 n n_seg, n_params)
        ``d log I / d log p``: real parts (log amplitude) of every frequency and segment, then
        imaginary parts (phase, rad).
    singular_values : ndarray
        Descending.
    vt : ndarray, shape (n_params, n_params)
        Right singular vectors (rows), in the order of ``singular_values``.
    """

    names: tuple
    jacobian: np.ndarray
    singular_values: np.ndarray
    vt: np.ndarray

    @property
    def cond(self) -> float:
        """Largest over smallest singular value."""
        return float(self.singular_values[0] / self.singular_values[-1])

    @property
    def null(self) -> dict:
        """The least determined direction in log parameters (unit vector, its largest component
        positive), by name."""
        v = self.vt[-1]
        v = v * np.sign(v[np.argmax(np.abs(v))])
        return dict(zip(self.names, v.tolist()))


def sensitivity(params: BeamParams, load, freqs, names, h: float = 1e-5) -> Sensitivity:
    """Jacobian of the log segment currents in log parameters by central differences, and its SVD.

    Parameters
    ----------
    params : BeamParams
    load : Maxwell finger or None
    freqs : array_like
        Hz.
    names : sequence of str
        Keys of :data:`FACTORS`.
    h : float
        Step in log parameter. The truncation error is O(h^2) times the third derivative, largest
        at a resonance (about ``1 / (2 zeta)`` per unit log stiffness, cubed); the rounding error
        about ``1e-13 / h``. 1e-5 keeps both below 1e-6 for the bundled beam.
    """
    names = tuple(names)
    _check({k: 1.0 for k in names})
    cols = []
    for k in names:
        ip, _ = response(params, load, freqs, {k: math.exp(h)})
        im, _ = response(params, load, freqs, {k: math.exp(-h)})
        d = np.log(ip / im) / (2.0 * h)  # a ratio near 1: no branch cut of the phase
        cols.append(np.concatenate([d.real.ravel(), d.imag.ravel()]))
    J = np.array(cols).T
    _, sv, vt = np.linalg.svd(J, full_matrices=False)
    return Sensitivity(names, J, sv, vt)
