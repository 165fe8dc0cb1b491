"""Calibrating a bimorph's model on its device: segment currents per volt with the finger lifted.

A bimorph with its finger lifted is driven with a set of tones (:func:`lines`); each segment's
current per commanded volt at each line (:func:`phasors` of the drive and of the sensed currents)
is fitted by the model's relative factors (:func:`fit`): the transfer-matrix beam of
:func:`rtctl.selfsense.identify.response` seen through the front end the currents pass on their
way to the ADC (:class:`rtctl.selfsense.frontend.FrontEnd`: amplifier, zero-order hold, anti-alias
filter, the folded images of the drive).

What the fit can find is what :mod:`rtctl.selfsense.identify` says the currents show with the
finger lifted: ``E``, ``d31``, ``eps33T`` and the damping (condition 35-112 on :func:`lines`).
Geometry and density are taken as given: along the invisible directions
(:data:`~rtctl.selfsense.identify.THICKNESS_DIRECTION`,
:data:`~rtctl.selfsense.identify.DENSITY_DIRECTION`) the currents stay and the tip per volt moves
by ``s^-0.5``. A measured beam mass anchors that scale (:func:`anchored`); without one the tip
amplitude is uncertain by about half the modal mass's uncertainty (:func:`scale_uncertainty_pct`).

Nothing here knows a scene, an engine or a simulated device: the caller hands in the nominal
:class:`~rtctl.selfsense.identify.BeamParams`, the front end and the measured currents.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rtctl.errors import ModelError

from .frontend import FrontEnd
from .identify import DENSITY_DIRECTION, BeamParams, response

__all__ = ["FIT_NAMES", "NEAR_RESONANCE", "Currents", "Fit", "anchored", "beam_mass", "blocked", "fit", "images",
           "lines", "phasors", "scale_uncertainty_pct", "sensed_per_volt"]

#: The factors the currents determine with the finger lifted (docs/selfsense.md, Sec. 6).
FIT_NAMES = ("E", "d31", "eps33T", "damping")

#: Lines around the nominal free first resonance, as fractions of it: the damping shows only
#: there, and +-15 % still holds the resonance of a modulus 30 % off.
NEAR_RESONANCE = (0.85, 0.9, 0.94, 0.97, 1.0, 1.03, 1.06, 1.1, 1.15)


def lines(f1_hz: float, resolution_hz: float, f_lo: float = 20.0, f_hi: float = 3000.0, n_log: int = 24,
          near=NEAR_RESONANCE) -> np.ndarray:
    """The excitation's frequencies, Hz: ``n_log`` log-spaced lines from ``f_lo`` to ``f_hi`` and
    the lines ``near`` the nominal free first resonance ``f1_hz``, each rounded to a multiple of
    ``resolution_hz`` (so a window of ``1 / resolution_hz`` holds whole periods of every line and
    they are orthogonal there), without repeats, ascending."""
    if not (resolution_hz > 0 and f_lo >= resolution_hz and f_hi > f_lo):
        raise ModelError(f"lines: need 0 < resolution ({resolution_hz:g} Hz) <= f_lo ({f_lo:g}) < f_hi ({f_hi:g})")
    f = np.concatenate([np.geomspace(f_lo, f_hi, n_log), f1_hz * np.asarray(near, dtype=float)])
    k = np.unique(np.maximum(1, np.round(f / resolution_hz)).astype(np.int64))
    return k * float(resolution_hz)


def phasors(x: np.ndarray, fs: float, freqs) -> np.ndarray:
    """Complex amplitudes at ``freqs`` of ``x`` (..., n), whole periods of every line in the
    ``n`` samples: ``x = Re(X exp(j 2 pi f t))``, ``t = i / fs`` from the first sample.

    Every line must be a multiple of ``fs / n``: then the lines are exactly orthogonal over the
    window and this is the discrete Fourier transform's bin (a lock-in over whole periods)."""
    x = np.asarray(x, dtype=float)
    n = x.shape[-1]
    k = np.asarray(freqs, dtype=float) * n / fs
    if np.any(np.abs(k - np.round(k)) > 1e-6):
        raise ModelError(f"phasors: every line must be a multiple of fs / n = {fs / n:g} Hz")
    spec = np.fft.rfft(x, axis=-1)
    return 2.0 * spec[..., np.round(k).astype(np.int64)] / n


def images(params: BeamParams, front: FrontEnd, freqs, factors: dict | None = None) -> np.ndarray:
    """The folded images of the drive in each segment's sensed current per commanded volt,
    shape (n, n_seg) (:meth:`FrontEnd.images` with the field solve of the scaled beam, finger
    lifted: at tens of kHz the currents are nearly all capacitive)."""
    beam = params.scaled(factors or {}).beam()
    return np.array([front.images(f, lambda om: beam.solve(om)["current"]) for f in np.atleast_1d(freqs)])


def warps_with_E(support) -> bool:
    """Whether ``E`` x ``a`` is the nominal beam at ``f / sqrt(a)`` on this root (see
    :class:`Currents`): no mass on it, and each spring rigid or absent."""
    return (support.mass == 0.0 and support.inertia == 0.0
            and all(v in (0.0, math.inf) for v in (support.k, support.k_rot)))


class Currents:
    """Segment currents per actuator volt of ``params`` scaled by factors, finger lifted: what
    :func:`rtctl.selfsense.identify.response` gives, without building a beam per call.

    Building a transfer-matrix beam is mostly solving for its natural frequencies, and a fit calls
    the model hundreds of times. Two exact relations avoid that for ``E``, ``d31``, ``eps33T`` and
    the damping (any other factor takes ``response`` itself):

    * the mechanics depend on ``E`` (bending stiffness), the density and the support; a volt
      acts through the moment per volt ``m_p ~ d31 E`` only, and each segment's charge is
      ``Cp V - m_p (psi_end - psi_start)``: the motional charge goes as ``m_p^2``, ``eps33T``
      reaches only the blocked ``Cp``;
    * ``E`` x ``a`` gives the currents of ``d31`` x ``sqrt(a)`` and density x ``1/a``
      (:data:`~rtctl.selfsense.identify.DENSITY_DIRECTION`), and density x ``1/a`` at ``f`` is
      the nominal beam at ``f / sqrt(a)`` (``rho A w^2 / EI`` is all the field sees; the damping
      goes with the modes' frequencies) -- on a clamped (or free) root only: springs at the root
      would have to go x ``1/a`` as well (the root's shear and moment are ``EI`` times the
      deflection's derivatives, and the springs' forces are not), and a root mass sees the
      frequency;

    so ``I(f) = j w (Cp(E, d31, eps33T) + a b^2 Q(f / sqrt(a)))`` with ``Q`` the nominal beam's
    motional charge per volt at the fitted damping (:meth:`TMMBeam.with_damping`: its modes are
    the nominal beam's), ``a``, ``b`` the ``E`` and ``d31`` factors. A root on springs or with
    a mass takes ``Q_a(f)`` of the beam built with ``E`` x ``a`` instead (``b^2`` and the
    damping still apply to it as above), kept for the few ``E`` values a fit's step visits.
    """

    def __init__(self, params: BeamParams):
        self.params = params
        self.base = params.beam()
        self.exact_shortcut = warps_with_E(params.support)
        self._stiffened = {}  # E factor -> the beam built with it (a root the shortcut misses)

    def _beam_with_E(self, a: float):
        beam = self._stiffened.get(a)
        if beam is None:
            if len(self._stiffened) >= 8:  # a fit visits a few values per step; keep memory flat
                self._stiffened.clear()
            beam = self._stiffened[a] = self.params.scaled({"E": a}).beam()
        return beam

    def __call__(self, freqs, factors: dict | None = None) -> np.ndarray:
        """A/V, shape (n, n_seg)."""
        f = np.atleast_1d(np.asarray(freqs, dtype=float))
        fac = dict(factors or {})
        if set(fac) - set(FIT_NAMES):
            return response(self.params, None, f, fac)[0]
        a, b = fac.get("E", 1.0), fac.get("d31", 1.0)
        if self.exact_shortcut:
            beam, fp, stiff = self.base, f / math.sqrt(a), a
        else:
            beam, fp, stiff = self._beam_with_E(a), f, 1.0
        beam = beam.with_damping(beam.zeta * fac.get("damping", 1.0))
        q = beam.response(fp)["current"] / (2j * math.pi * fp)[:, None] - beam.cp[None, :]
        return 2j * math.pi * f[:, None] * (blocked(self.params, fac)[None, :] + stiff * b * b * q)

    def cond(self, freqs, factors: dict, names=FIT_NAMES, h: float = 1e-5):
        """Condition number and singular values of ``d log I / d log p`` (real parts, then
        imaginary), by central differences, as :func:`rtctl.selfsense.identify.sensitivity`
        defines them."""
        cols = []
        for k in names:
            up, dn = dict(factors), dict(factors)
            up[k] = up.get(k, 1.0) * math.exp(h)
            dn[k] = dn.get(k, 1.0) * math.exp(-h)
            d = np.log(self(freqs, up) / self(freqs, dn)) / (2.0 * h)
            cols.append(np.concatenate([d.real.ravel(), d.imag.ravel()]))
        sv = np.linalg.svd(np.array(cols).T, compute_uv=False)
        return float(sv[0] / sv[-1]), tuple(float(v) for v in sv)


def sensed_per_volt(params: BeamParams, front: FrontEnd, freqs, factors: dict | None = None,
                    image: np.ndarray | None = None) -> np.ndarray:
    """What the ADC reads of each segment's current per commanded volt, finger lifted, shape
    (n, n_seg): ``H_aa A P Y`` at each line plus its folded images (computed here unless
    ``image`` gives them)."""
    f = np.atleast_1d(np.asarray(freqs, dtype=float))
    cur, _ = response(params, None, f, factors)
    if image is None:
        image = images(params, front, f, factors)
    return cur * _line(front, f)[:, None] + image


def _line(front: FrontEnd, f) -> np.ndarray:
    """``H_aa A P`` at each line: the path of the line itself from the drive to the ADC."""
    return np.array([front.aa(fi) * front.voltage(fi) for fi in f])


@dataclass(frozen=True)
class Fit:
    """What :func:`fit` returns.

    Attributes
    ----------
    factors : dict
        The fitted relative factors (keys of ``names``).
    sd : dict
        Their relative standard deviations from the residual (the Jacobian's covariance); None
        when the Jacobian is singular.
    residual_pct : float
        rms of ``|model / measured - 1|`` over every line, segment and channel, %.
    residual_each : tuple
        The same per leading index of ``measured`` (per channel), %.
    cond : float
        Condition number of ``d log I / d log p`` at the fit (as
        :func:`rtctl.selfsense.identify.sensitivity` defines it).
    singular_values : tuple
    evaluations : int
        Model evaluations the fit took.
    """

    factors: dict
    sd: dict
    residual_pct: float
    residual_each: tuple
    cond: float
    singular_values: tuple
    evaluations: int


def fit(params: BeamParams, front: FrontEnd, freqs, measured, names=FIT_NAMES, tol: float = 1e-3,
        max_outer: int = 5) -> Fit:
    """Fit relative factors ``names`` so that :func:`sensed_per_volt` matches ``measured``.

    Parameters
    ----------
    params : BeamParams
        The nominal beam (geometry and density taken as given).
    front : FrontEnd
        The drive and sense chain the measured currents passed.
    freqs : array_like, shape (n,)
        Hz.
    measured : array_like, shape (..., n, n_seg), complex
        Sensed current per commanded volt; leading axes (channels of one group) share the fit.
    names : sequence of str
        Keys of :data:`rtctl.selfsense.identify.FACTORS`.
    tol : float
        Stop after a round in which no log factor moved more than this. A round leaves about
        1e-3 of the previous round's change (the images' share of the motional current), so
        the default stops after the second round, within 1e-6 of the converged factors.

    Notes
    -----
    Log factors by ``scipy.optimize.least_squares`` (Levenberg-Marquardt) on the relative complex
    residuals ``(model - measured) / |measured|``, real and imaginary parts, every reading weighted
    alike (smooth everywhere, unlike the log's phase, which wraps when a line sits between a
    mistaken resonance and the true one). The images (about a tenth of a reading, nearly all
    capacitive) take 80 field solves per line: they are computed at the start of each round and
    scaled with the segments' blocked capacitance inside it, and the rounds repeat until the
    factors settle.
    """
    from scipy.optimize import least_squares

    f = np.atleast_1d(np.asarray(freqs, dtype=float))
    meas = np.asarray(measured, dtype=complex)
    if meas.ndim < 2 or meas.shape[-2] != f.size:
        raise ModelError(f"measured currents have shape {meas.shape}, expected (..., {f.size}, n_seg)")
    if not np.all(np.isfinite(meas)) or np.any(meas == 0):
        raise ModelError("measured currents must be finite and nonzero at every line")
    names = tuple(names)
    model = Currents(params)
    scale = np.abs(meas)
    line = _line(front, f)[:, None]
    count = [0]

    def factors_of(x):
        return {k: math.exp(v) for k, v in zip(names, x)}

    def residuals(x, image, cp0):
        count[0] += 1
        fac = factors_of(x)
        r = ((model(f, fac) * line + image * (blocked(params, fac) / cp0)) - meas) / scale
        return np.concatenate([r.real.ravel(), r.imag.ravel()])

    x = np.zeros(len(names))
    if "E" in names:
        # Start at the stiffness whose first resonance sits where the currents put it: from the
        # nominal one, a resonance a few % off and sharpened by a low damping leaves the steepest
        # descent pointing the wrong way (d31 and the damping run to 0). A scan of E alone
        # (x0.74 ... x1.35 in steps of 1 %, a half-power width of a beam with 0.5 % damping)
        # lands within reach of the minimum.
        k = names.index("E")
        image, cp0 = images(params, front, f, {}), blocked(params, {})
        grid = np.linspace(-0.3, 0.3, 61)
        costs = []
        for e in grid:
            x[k] = e
            r = residuals(x, image, cp0)
            costs.append(float(r @ r))
        x[k] = grid[int(np.argmin(costs))]
    for _ in range(max_outer):
        image, cp0 = images(params, front, f, factors_of(x)), blocked(params, factors_of(x))
        res = least_squares(residuals, x, args=(image, cp0), method="lm", diff_step=1e-6, xtol=1e-9, ftol=1e-10)
        moved = float(np.max(np.abs(res.x - x)))
        x = res.x
        if moved < tol:
            break
    r = res.fun
    p = len(names)
    s2 = float(r @ r) / max(r.size - p, 1)
    try:
        cov = s2 * np.linalg.inv(res.jac.T @ res.jac)
        sd = {k: float(math.sqrt(max(cov[i, i], 0.0))) for i, k in enumerate(names)}
    except np.linalg.LinAlgError:  # a direction the lines do not see at all: no spread to give
        sd = {k: None for k in names}
    half = r.size // 2
    rel2 = (r[:half] ** 2 + r[half:] ** 2).reshape(meas.shape)
    each = np.sqrt(rel2.reshape(-1, f.size * meas.shape[-1]).mean(axis=1)) * 100.0
    fitted = factors_of(x)
    cond, sv = model.cond(f, fitted, names)
    return Fit(fitted, sd, float(100.0 * np.sqrt(np.mean(rel2))), tuple(float(v) for v in each), cond, sv,
               count[0])


def blocked(params: BeamParams, factors: dict | None = None) -> np.ndarray:
    """Each segment's blocked capacitance of the scaled beam, F (the laminate alone: no solve)."""
    from .tmm import laminate_of

    p = params.scaled(factors or {})
    return laminate_of(p.width, p.layers, p.connection).cp * np.asarray(p.segments) * p.length


def beam_mass(params: BeamParams, factors: dict | None = None) -> float:
    """Mass of the beam's free length, kg: ``width length sum rho_i t_i`` (of the scaled beam)."""
    p = params.scaled(factors or {})
    return float(p.width * p.length * sum(m.rho * t for m, t in p.layers))


def anchored(factors: dict, s: float) -> dict:
    """``factors`` moved along :data:`DENSITY_DIRECTION` by ``s`` (density x ``s``, ``E`` x ``s``,
    ``d31`` x ``s^-0.5``): the segment currents stay, the tip per volt goes x ``s^-0.5``. With ``s``
    the measured over the nominal beam mass this puts the modal mass where the scale reading says
    it is (the finger is left alone: it is not part of a lifted calibration)."""
    if not (s > 0 and math.isfinite(s)):
        raise ModelError(f"mass scale must be finite and > 0, got {s!r}")
    out = dict(factors)
    for k, e in DENSITY_DIRECTION.items():
        if k.startswith("finger"):
            continue
        out[k] = out.get(k, 1.0) * s ** e
    return out


def scale_uncertainty_pct(tolerance: float, mass_tolerance: float | None = None) -> float:
    """How far the tip amplitude of a calibrated model may be off, %, from what the currents
    cannot see (the modal mass).

    Without a mass (``mass_tolerance`` None): thickness and density each within ``tolerance``
    (relative bounds). Along either invisible direction the tip goes as ``s^-0.5`` while the
    modal mass goes as ``s``, and the two multiply: the mass lies within ``(1 -+ tol)^2``, the
    tip within ``(1 -+ tol)^-1``, so the bound is ``tol / (1 - tol)`` (2.04 % for 2 %). They are
    added as bounds (both at their limit in the same direction), not in quadrature (1.4 % for
    2 %): a tolerance is a bound, not a standard deviation.

    With a mass weighed within ``mass_tolerance``: the tip within ``(1 -+ mtol)^-0.5``, so
    ``(1 - mtol)^-0.5 - 1`` (0.25 % for 0.5 %). The geometry's tolerance then no longer matters
    as long as the errors are uniform along the beam (the mass and the modal mass scale alike).
    """
    if mass_tolerance is None:
        t = float(tolerance)
        return 100.0 * t / (1.0 - t)
    return 100.0 * ((1.0 - float(mass_tolerance)) ** -0.5 - 1.0)
