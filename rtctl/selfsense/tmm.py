"""Transfer matrices of a layered piezoelectric cantilever in the frequency domain.

Seed 000, Eq. (1): tip state = ``L_m A R_m`` root state, with the bimorph ``A`` a product of
segment field matrices, the finger load ``L_m`` and the support ``R_m`` as point matrices.

Model (Euler-Bernoulli, per electrode segment, time factor ``exp(j w t)``)
-----------------------------------------------------------------------
State ``y = [w, psi, M, Q]``: deflection (m), slope (rad), bending moment (N m), shear force (N)
with ``M = EI* w'' + m_p V`` and ``Q = M'``. The piezo acts as an induced curvature
``-m_p V / EI`` (``m_p < 0`` N m/V: a positive voltage raises the tip), so within a segment::

    w' = psi,  psi' = (M - m_p V) / EI*,  M' = Q,  Q' = rhoA w^2 w
    charge = Cp V - m_p (psi_end - psi_start),   current I = j w charge

Damping. The field (:meth:`TMMBeam.solve`, :meth:`TMMBeam.segment_matrix`) needs a local law:
``EI* = EI (1 + j w c(w))`` (Kelvin-Voigt) with ``c = 2 zeta / w_n``, ``w_n`` the unloaded
beam's natural frequency nearest to ``w`` (in log; ``c = 2 zeta / w`` above the tabulated
modes), so every resonance of the unloaded beam gets the damping ratio ``zeta``. The
finite-element plant damps each mode by its own ``2 zeta w_n`` instead, which is no local law:
between resonances, and at the resonances of a finger-loaded beam (a mix of unloaded modes),
the two differ by ``zeta``-sized shares (2-5 % of the admittance at the 2nd loaded mode; 1-12 %
of a tip force read by self-sensing). Port quantities (:meth:`TMMBeam.port_receptance`,
:meth:`TMMBeam.response`, the observers of a known support) therefore carry the modal damping
exactly: the Kelvin-Voigt receptance is stiffness-proportionally damped, so its modal terms are
``a a^T / (w_n^2 (1 + j w c) - w^2)``; they are swapped for ``a a^T / (w_n^2 - w^2 + 2 j zeta
w_n w)`` on the ``N_MODAL`` tabulated modes (participations ``a`` from the residues of the
undamped receptance) and quasi-statically on the rest (their residual flexibility).

Sign conventions (as :mod:`rtctl.plant.beam`): ``w``, a tip force and ``psi`` point "up"; an
external tip force ``P`` gives ``Q(L) = -P``, a finger of dynamic stiffness ``K_f`` gives
``Q(L) = K_f w(L)`` (so ``Q(L)`` is the force the tip pushes the finger with); at the root a
clamp reacts with ``Q(0)``, ``-M(0)``. The seed's velocity form ``[v, psi_dot, M, F, U]`` is
``diag(j w, j w, 1, 1, 1)`` of ours.

Numerics
--------
The field matrix ``T(x)`` in Krylov functions needs only ``lam = beta^4 = rhoA w^2 / EI*``:
``f_k = sum_n lam^n x^(4n+k) / (4n+k)!`` (``f0 = S``, ``f1 = T/beta``, ``f2 = U/beta^2``,
``f3 = V/beta^3``). Every segment is cut into pieces with ``|lam| l^4 <= 1``, where the series
converges in a few terms with no cancellation (the closed forms ``cosh - cos`` lose all digits
at low frequency, and products of long pieces grow like ``exp(beta L)``). Responses are then
solved as one banded boundary-value system over all piece ends (multiple shooting): every
block is O(1), partial pivoting keeps it stable at any frequency (tested to 1e-9 against the
closed-form cantilever receptance at ``beta L = 40``, where the plain product has lost ~17
digits).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.optimize

from rtctl.errors import ModelError

__all__ = ["Laminate", "laminate_of", "Support", "TMMBeam", "krylov", "piece_matrix",
           "seed_matrix", "load_point_matrix", "support_point_matrix"]

_TERMS = 12  # series terms: |lam x^4| <= 1 leaves < 1/(48)! after 12
#: Modes tabulated for the damping: exact modal damping on these, the rest quasi-static.
N_MODAL = 6
#: The undamped angular frequencies of the beams built so far (their first N_MODAL modes)
_UNDAMPED: dict = {}
#: LAPACK's banded solve with partial pivoting (stable), the routine scipy's solve_banded calls
_zgbsv = scipy.linalg.get_lapack_funcs("gbsv", (np.zeros(1, dtype=complex),))


def _band_solve(ab, rhs):
    """Solve the system of 5 bands each side in ``ab`` (gbsv's storage, 16 rows; overwritten)
    for ``rhs`` (overwritten), as scipy's solve_banded does, without its checks and copies."""
    _, _, y, info = _zgbsv(5, 5, ab, rhs, overwrite_ab=True, overwrite_b=True)
    if info > 0:
        raise np.linalg.LinAlgError("singular matrix")
    if info < 0:
        raise ValueError(f"illegal value in argument {-info} of gbsv")
    return y


@dataclass(frozen=True)
class Laminate:
    """Per-length properties of a layered piezoelectric section.

    Attributes
    ----------
    EI : float
        Bending stiffness about the E-weighted neutral axis, N m^2.
    rhoA : float
        Mass per length, kg/m.
    m_p : float
        Bending moment per port volt, N m/V (< 0: a positive voltage raises the tip).
    cp : float
        Port capacitance per length with bending blocked, F/m.
    """

    EI: float
    rhoA: float
    m_p: float
    cp: float


def laminate_of(width, layers, connection) -> Laminate:
    """Section properties of a bonded stack (derived here, independently of the FE plant).

    Parameters
    ----------
    width : float
        m.
    layers : sequence of (Material, thickness)
        Bottom face up; ``Material`` has ``E``, ``d31``, ``eps33T``, ``rho``, ``e31``,
        ``eps33S`` (see :mod:`rtctl.plant.materials`), thickness in m.
    connection : {"parallel", "series"}

    Returns
    -------
    Laminate

    Notes
    -----
    Each piezo layer, poled so that all help, gives ``-|e31| w |z_c|`` N m per volt across it
    (``z_c``: its centroid above the neutral axis) and ``e31 w`` N axial force per volt; the axial
    stretch is free (condensed), so the blocked per-length capacitance is
    ``sum eps33S w / t + (sum n_i f_i)^2 / EA``. ``parallel``: every layer sees the port volt.
    ``series``: layers share it as a capacitive divider; only stacks whose layers have equal
    moments per volt are accepted (otherwise floating electrodes add a stiffness this model
    leaves out).
    """
    mats = [m for m, _ in layers]
    t = np.array([float(th) for _, th in layers])
    E = np.array([m.E for m in mats])
    zb = np.concatenate(([0.0], np.cumsum(t)[:-1]))
    zt = zb + t
    EA = float(np.sum(E * width * t))
    zn = float(np.sum(E * t * (zb + zt) / 2.0) / np.sum(E * t))
    EI = float(np.sum(E * width * ((zt - zn) ** 3 - (zb - zn) ** 3) / 3.0))
    rhoA = float(np.sum(np.array([m.rho for m in mats]) * width * t))
    pz = [i for i, m in enumerate(mats) if m.d31 != 0.0]
    if not pz:
        raise ModelError("laminate has no piezoelectric layer (every d31 is 0)")
    zc = (zb[pz] + zt[pz]) / 2.0 - zn
    e31 = np.array([mats[i].e31 for i in pz])
    mu = -np.abs(e31) * width * np.abs(zc)
    sgn = -np.sign(zc) * np.sign(e31)
    n_ax = np.where(sgn == 0.0, 1.0, sgn) * e31 * width
    c = np.array([mats[i].eps33S for i in pz]) * width / t[pz]
    if connection == "parallel":
        f = np.ones(len(pz))
        cp = float(np.sum(c) + np.sum(n_ax) ** 2 / EA)
    elif connection == "series":
        if np.ptp(mu) > 1e-9 * np.max(np.abs(mu)):
            raise ModelError("series stack with unequal moments per volt per layer: the TMM "
                             "model leaves out the floating-electrode stiffness; use the FE "
                             "plant or a symmetric stack")
        C_l = np.diag(c) + np.outer(n_ax, n_ax) / EA
        Ci = np.linalg.solve(C_l, np.ones(len(pz)))
        f = Ci / Ci.sum()
        cp = float(1.0 / Ci.sum())
    else:
        raise ModelError(f"connection must be 'parallel' or 'series', got {connection!r}")
    return Laminate(EI, rhoA, float(np.sum(f * mu)), cp)


@dataclass(frozen=True)
class Support:
    """Root of the cantilever: clamped, elastic, or elastic with a mass (a moving support).

    Parameters
    ----------
    k : float
        Translational stiffness, N/m (``inf``: fixed).
    k_rot : float
        Rotational stiffness, N m/rad (``inf``: fixed).
    mass : float
        Mass moving with the root deflection, kg (e.g. the armature of a perpendicular
        actuator carrying the bimorph).
    inertia : float
        Rotary inertia of the root, kg m^2.

    Examples
    --------
    >>> Support().clamped, Support(k=2e4, mass=1e-4).clamped
    (True, False)
    """

    k: float = math.inf
    k_rot: float = math.inf
    mass: float = 0.0
    inertia: float = 0.0

    def __post_init__(self):
        for name in ("k", "k_rot", "mass", "inertia"):
            v = float(getattr(self, name))
            if math.isnan(v) or v < 0.0 or (name in ("mass", "inertia") and math.isinf(v)):
                raise ModelError(f"Support.{name} must be >= 0 (inf allowed for k, k_rot), got {v!r}")
            object.__setattr__(self, name, v)
        if self.k == 0.0 or self.k_rot == 0.0:
            raise ModelError("Support k = 0 or k_rot = 0 leaves a mechanism; give a stiffness or inf")

    @property
    def clamped(self) -> bool:
        return math.isinf(self.k) and math.isinf(self.k_rot)

    def stiffness(self, omega):
        """Dynamic root stiffnesses ``(k - m w^2, k_rot - J w^2)`` at ``omega`` (rad/s)."""
        return self.k - self.mass * omega**2, self.k_rot - self.inertia * omega**2


def krylov(lam, x):
    """Scaled Krylov functions ``f_k(x) = sum_n lam^n x^(4n+k) / (4n+k)!``, k = 0..3.

    ``f0 = S(beta x)``, ``f1 = T/beta``, ``f2 = U/beta^2``, ``f3 = V/beta^3`` with
    ``beta^4 = lam`` (Pestel & Leckie). Accurate for ``|lam| x^4 <= 1`` (series, no cancellation).

    Returns
    -------
    ndarray, shape (4,), complex
    """
    z = complex(lam) * x**4
    f = np.zeros(4, dtype=complex)
    term = np.array([1.0, x, x * x / 2.0, x**3 / 6.0], dtype=complex)
    for n in range(_TERMS):
        f += term
        k = 4 * n
        term = term * z / np.array([(k + 1) * (k + 2) * (k + 3) * (k + 4), (k + 2) * (k + 3) * (k + 4) * (k + 5),
                                    (k + 3) * (k + 4) * (k + 5) * (k + 6), (k + 4) * (k + 5) * (k + 6) * (k + 7)])
    return f


def piece_matrix(lam, EI, x):
    """Field matrix of a uniform piece of length ``x``: ``y(x) = T y(0)`` (``V = 0``).

    Parameters
    ----------
    lam : complex
        ``rhoA w^2 / EI*``, 1/m^4.
    EI : complex
        ``EI*``, N m^2.
    x : float
        m, with ``|lam| x^4 <= 1``.

    Returns
    -------
    ndarray, shape (4, 4), complex
    """
    f0, f1, f2, f3 = krylov(lam, x)
    return np.array([[f0, f1, f2 / EI, f3 / EI],
                     [lam * f3, f0, f1 / EI, f2 / EI],
                     [EI * lam * f2, EI * lam * f3, f0, f1],
                     [EI * lam * f1, EI * lam * f2, lam * f3, f0]])


#: Krylov series divisors ``(k+1)...(k+4)`` .. ``(k+4)...(k+7)`` of term ``n`` (``k = 4 n``)
_KRYLOV_DIV = np.array([[(k + 1) * (k + 2) * (k + 3) * (k + 4), (k + 2) * (k + 3) * (k + 4) * (k + 5),
                         (k + 3) * (k + 4) * (k + 5) * (k + 6), (k + 4) * (k + 5) * (k + 6) * (k + 7)]
                        for k in range(0, 4 * _TERMS, 4)])


def _cmul(a, b):
    """``a * b`` elementwise as a scalar complex product rounds it (Python's and numpy's scalar
    arithmetic: four products, a difference and a sum), which numpy's array loop, fusing a
    product into the sum, does not always match to the last bit."""
    a, b = np.asarray(a, dtype=complex), np.asarray(b, dtype=complex)
    return (a.real * b.real - a.imag * b.imag) + 1j * (a.real * b.imag + a.imag * b.real)


def _piece_matrices(lam, EI, x):
    """:func:`piece_matrix` of many pieces at once, bitwise the same: ``lam``, ``EI`` complex and
    ``x`` (m) of shape (n,); shape (n, 4, 4). Where :func:`piece_matrix` multiplies scalars the
    products are :func:`_cmul`'s, and the powers of ``x`` are Python's (numpy's power loop rounds
    differently)."""
    x3 = np.array([v**3 for v in x])
    x4 = np.array([v**4 for v in x])
    x = np.asarray(x, dtype=float)
    z = _cmul(lam, x4)
    f = np.zeros((x.size, 4), dtype=complex)
    term = np.stack([np.ones_like(x), x, x * x / 2.0, x3 / 6.0], axis=1).astype(complex)
    for n in range(_TERMS):
        f += term
        term = term * z[:, None] / _KRYLOV_DIV[n]  # array by scalar, as in krylov
    f0, f1, f2, f3 = f.T
    EIlam = _cmul(EI, lam)
    lf1, lf2, lf3 = _cmul(EIlam, f1), _cmul(EIlam, f2), _cmul(EIlam, f3)
    l3 = _cmul(lam, f3)
    return np.stack([np.stack([f0, f1, f2 / EI, f3 / EI], axis=1),
                     np.stack([l3, f0, f1 / EI, f2 / EI], axis=1),
                     np.stack([lf2, lf3, f0, f1], axis=1),
                     np.stack([lf1, lf2, l3, f0], axis=1)], axis=1)


def load_point_matrix(K):
    """Point matrix of a load of dynamic stiffness ``K`` (N/m) on the deflection.

    ``[w, psi, M, Q]`` beam side -> outside: ``Q+ = Q- - K w``; a free end outside
    (``M+ = Q+ = 0``) then gives ``Q(L) = K w(L)``.
    """
    P = np.eye(4, dtype=complex)
    P[3, 0] = -K
    return P


def support_point_matrix(k, k_rot):
    """Point matrix from the ground side of a spring support into the beam root.

    ``M(0) = M_g + k_rot psi``, ``Q(0) = Q_g - k w``; ``k``, ``k_rot`` may be dynamic
    (``Support.stiffness``). With a free ground side (``M_g = Q_g = 0``) only ``w, psi`` remain.
    """
    P = np.eye(4, dtype=complex)
    P[2, 1] = k_rot
    P[3, 0] = -k
    return P


def seed_matrix(T, t, c, omega):
    """A 4x4 field matrix in the seed's 5x5 velocity form (Eq. 1 and 2).

    ``[v, psi_dot, M, F, I]_end = A [v, psi_dot, M, F, U]_start``.

    Parameters
    ----------
    T : ndarray, shape (4, 4)
        Displacement-form field matrix.
    t : ndarray, shape (4,)
        Response to the segment voltage.
    c : ndarray, shape (5,)
        Charge row: charge = ``c @ [w, psi, M, Q, V]_start``.
    omega : float
        rad/s, > 0.
    """
    jw = 1j * omega
    S = np.diag([jw, jw, 1.0, 1.0])
    A = np.zeros((5, 5), dtype=complex)
    A[:4, :4] = S @ T @ np.linalg.inv(S)
    A[:4, 4] = S @ t
    A[4, :4] = jw * c[:4] @ np.linalg.inv(S)
    A[4, 4] = jw * c[4]
    return A


class TMMBeam:
    """Transfer-matrix model of a layered piezoelectric cantilever with electrode segments.

    Parameters
    ----------
    lam : Laminate
        Section properties.
    length : float
        Free length, m.
    segments : sequence of float
        Electrode split, fractions of the length from the root (sum 1).
    zeta : float
        Modal damping ratio of every mode of the unloaded beam on ``support`` (as the FE
        plant's ``damping``); see the module docstring for where it is exact.
    support : Support, optional
        Default clamped.

    Examples
    --------
    >>> from rtctl.plant.materials import BUILTIN
    >>> from rtctl.selfsense.tmm import TMMBeam, laminate_of
    >>> pzt = BUILTIN["PZT-5A"]
    >>> beam = TMMBeam(laminate_of(1.5e-3, [(pzt, 0.3e-3), (pzt, 0.3e-3)], "parallel"),
    ...                15e-3, (0.5, 0.5), 0.01)
    >>> round(beam.natural_frequencies(1)[0])
    1208
    """

    def __init__(self, lam: Laminate, length, segments, zeta=0.01, support: Support | None = None):
        self.lam = lam
        self.length = float(length)
        if not (self.length > 0.0 and math.isfinite(self.length)):
            raise ModelError(f"TMMBeam length must be > 0 m, got {length!r}")
        seg = np.asarray(segments, dtype=float)
        if seg.ndim != 1 or seg.size < 1 or np.any(seg <= 0.0) or abs(seg.sum() - 1.0) > 1e-9:
            raise ModelError(f"segments must be positive fractions summing to 1, got {segments!r}")
        self.bounds = np.concatenate(([0.0], np.cumsum(seg))) * self.length
        self.bounds[-1] = self.length
        self.n_seg = seg.size
        self.cp = lam.cp * np.diff(self.bounds)
        self.support = Support() if support is None else support
        self.zeta = float(zeta)
        if not (0.0 <= self.zeta < 1.0):
            raise ModelError(f"zeta must be in [0, 1), got {zeta!r}")
        self.c_kv = 0.0
        self._wn = np.array([1.0])
        if self.zeta > 0.0:
            # the same beam is built again and again (each observer design, each check of a
            # scene): its undamped modes are a scan of the characteristic determinant, ~0.5 s
            key = (lam, self.length, tuple(self.bounds.tolist()), self.support)
            wn = _UNDAMPED.get(key)
            if wn is None:
                if len(_UNDAMPED) >= 64:
                    _UNDAMPED.clear()
                wn = _UNDAMPED[key] = 2.0 * math.pi * self.natural_frequencies(N_MODAL)
            self._wn = wn.copy()
            self.c_kv = 2.0 * self.zeta / self._wn[0]

    def _c(self, omega):
        """Kelvin-Voigt coefficient at ``omega``: ``2 zeta / w_n`` of the tabulated mode nearest
        in log frequency, and ``2 zeta / omega`` above the last one (a constant loss factor
        ``2 zeta``), so every resonance of the unloaded beam has the damping ratio ``zeta``, also
        the high ones the aliased images of the drive hit (docs/selfsense.md, Sec. 3)."""
        if self.c_kv == 0.0:
            return 0.0
        w = abs(omega)
        if w >= self._wn[-1]:
            return 2.0 * self.zeta / w
        i = int(np.argmin(np.abs(np.log(self._wn / max(w, 1e-30)))))
        return 2.0 * self.zeta / self._wn[i]

    @classmethod
    def from_fe(cls, fe, mismatch=None) -> TMMBeam:
        """The TMM twin of a :class:`~rtctl.plant.beam.BeamFE` (its spec and support only).

        Parameters
        ----------
        fe : BeamFE
        mismatch : dict, optional
            Relative model errors, e.g. ``{"thickness": 0.05, "d31": -0.05}``: every layer
            thickness and every ``d31`` scaled by ``1 + value``.
        """
        from dataclasses import replace

        s = fe.spec
        mm = dict(mismatch or {})
        unknown = set(mm) - {"thickness", "d31"}
        if unknown:
            raise ModelError(f"mismatch keys {sorted(unknown)} unknown; allowed: thickness, d31")
        layers = [(replace(l.material, d31=l.material.d31 * (1.0 + mm.get("d31", 0.0))),
                   l.thickness * (1.0 + mm.get("thickness", 0.0))) for l in s.layers]
        sup = fe.support
        return cls(laminate_of(s.width, layers, s.connection), s.length, s.segments,
                   s.damping, Support(sup.k, sup.k_rot, sup.mass, sup.inertia))

    def with_support(self, support: Support) -> TMMBeam:
        """Same beam on another support (its modes, hence its damping, tabulated anew)."""
        return TMMBeam(self.lam, self.length, np.diff(self.bounds) / self.length, self.zeta,
                       support)

    def with_damping(self, zeta) -> TMMBeam:
        """Same beam with modal damping ratio ``zeta``. The tabulated modes and their port
        participations are the undamped beam's, so they are shared, not solved anew (the
        natural frequencies are most of the cost of building a beam)."""
        z = float(zeta)
        if not (0.0 <= z < 1.0):
            raise ModelError(f"zeta must be in [0, 1), got {zeta!r}")
        if self.c_kv == 0.0:  # no modes tabulated yet
            return TMMBeam(self.lam, self.length, np.diff(self.bounds) / self.length, z, self.support)
        out = copy.copy(self)
        out.zeta = z
        out.c_kv = 2.0 * z / self._wn[0] if z > 0.0 else 0.0
        return out

    def support_stiffness(self, omega, c=None):
        """Dynamic root stiffnesses at ``omega``: springs damped like the beam (the FE plant's
        modal damping acts on the whole stiffness, support springs included), minus inertia.
        ``c``: Kelvin-Voigt coefficient (default :meth:`_c`)."""
        damp = 1.0 + 1j * omega * (self._c(omega) if c is None else c)
        sup = self.support
        return sup.k * damp - sup.mass * omega**2, sup.k_rot * damp - sup.inertia * omega**2

    # ------------------------------------------------------------------ matrices
    def _ei_lam(self, omega, c=None):
        EI = self.lam.EI * (1.0 + 1j * omega * (self._c(omega) if c is None else c))
        return EI, self.lam.rhoA * omega**2 / EI

    def _pieces(self, lam, a, b):
        n = max(1, int(math.ceil((b - a) * abs(lam) ** 0.25)))
        return n, (b - a) / n

    def segment_matrix(self, j, omega):
        """Field matrix of electrode segment ``j`` (product of its pieces).

        Returns
        -------
        T : ndarray, shape (4, 4), complex
        t : ndarray, shape (4,), complex
            ``y_end = T y_start + t V``.
        c : ndarray, shape (5,), complex
            Charge (C) ``= c @ [y_start, V]``.

        Notes
        -----
        Fine for ``beta l_j`` up to a few (the observer's band); responses at high frequency
        use the banded solve of :meth:`solve`.
        """
        EI, lam = self._ei_lam(omega)
        n, h = self._pieces(lam, self.bounds[j], self.bounds[j + 1])
        P = piece_matrix(lam, EI, h)
        T = np.linalg.matrix_power(P, n)
        e_m = np.array([0, 0, 1.0, 0])
        t = self.lam.m_p * (e_m - T @ e_m)
        c = np.empty(5, dtype=complex)
        c[:4] = -self.lam.m_p * (T[1] - np.array([0, 1.0, 0, 0]))
        c[4] = self.cp[j] - self.lam.m_p * t[1]
        return T, t, c

    def seed_matrices(self, omega):
        """Seed Eq. (2) matrices ``A_j`` (5x5 velocity form), one per segment, root first."""
        return [seed_matrix(*self.segment_matrix(j, omega), omega) for j in range(self.n_seg)]

    # ------------------------------------------------------------------ responses
    def solve(self, omega, load=0.0, volts=None, tip_force=0.0, tip_moment=0.0):
        """Steady response at one angular frequency: banded solve over all piece ends.

        The field inside the beam needs a local constitutive law, so this solve uses the
        Kelvin-Voigt damping of :meth:`_c`; :meth:`response` and :meth:`port_receptance` give the
        port quantities with the modal damping of the finite-element plant.

        Parameters
        ----------
        omega : float
            rad/s (>= 0).
        load : complex
            Dynamic stiffness of the tip load (finger), N/m: ``MaxwellLoad.dynamic_stiffness``.
        volts : array_like, shape (n_seg,), optional
            Segment voltage phasors, V (default 1 V on all).
        tip_force, tip_moment : complex
            External force (N, up) and moment (N m, ccw) at the tip.

        Returns
        -------
        dict
            ``x`` (node positions, m), ``y`` (states at the nodes, shape (n_nodes, 4)),
            ``current`` (segment current phasors, A, shape (n_seg,)), ``seg_nodes``.
        """
        V = np.ones(self.n_seg, dtype=complex) if volts is None else np.asarray(volts, dtype=complex)
        x, seg_nodes, y = self._solve_many(omega, load, V[None, :], [tip_force], [tip_moment])
        psi = y[0, seg_nodes, 1]
        charge = self.cp * V - self.lam.m_p * np.diff(psi)
        return {"x": x, "y": y[0], "current": 1j * omega * charge, "seg_nodes": seg_nodes}

    def _solve_many(self, omega, load, volts, tip_force, tip_moment, c=None):
        """Banded solve for several right-hand sides (one factorization).

        ``volts`` shape (n_cases, n_seg), ``tip_force`` and ``tip_moment`` length n_cases; ``c``
        the Kelvin-Voigt coefficient (default :meth:`_c`). Returns node positions, segment node
        indices and the states, shape (n_cases, n_nodes, 4).
        """
        volts = np.atleast_2d(np.asarray(volts, dtype=complex))
        n_cases = volts.shape[0]
        EI, lam = self._ei_lam(omega, c)
        e_m = np.array([0, 0, 1.0, 0])
        segs, seg_nodes = [], [0]
        for j in range(self.n_seg):
            n, h = self._pieces(lam, self.bounds[j], self.bounds[j + 1])
            P = piece_matrix(lam, EI, h)
            segs.append((n, h, P, self.lam.m_p * (e_m - P @ e_m)))  # t: per volt on this segment
            seg_nodes.append(seg_nodes[-1] + n)
        N = seg_nodes[-1]
        x = np.concatenate([[0.0]] + [self.bounds[j] + h * np.arange(1, n + 1) for j, (n, h, _, _) in enumerate(segs)])
        L, EIr = self.length, self.lam.EI
        D = np.array([L, 1.0, EIr / L, EIr / L**2])  # y = D y~: dimensionless unknowns
        n_unk = 4 * (N + 1)
        # The block-bidiagonal system (5 bands each side: piece i's rows 2 + 4 i .. 5 + 4 i hold
        # -P~ on the unknowns of node i and the identity on those of node i + 1), written straight
        # into LAPACK gbsv's band storage: row 10 + r - col holds A[r, col], rows 0-4 are room for
        # the fill-in of its partial pivoting (what scipy's solve_banded hands gbsv, bitwise).
        # A dense matrix to take the bands from cost more than the solve.
        ab = np.zeros((16, n_unk), dtype=complex)
        rhs = np.zeros((n_unk, n_cases), dtype=complex)
        ks, kr = self.support_stiffness(omega, c)
        # Root rows (the ground side is free: only w, psi remain, as R_m of Eq. 1).
        if math.isinf(self.support.k):
            ab[10, 0] = 1.0
        else:   # Q(0) + k w(0) = 0
            ab[7, 3], ab[10, 0] = 1.0, ks * D[0] / D[3]
        if math.isinf(self.support.k_rot):
            ab[10, 1] = 1.0
        else:   # M(0) - k_rot psi(0) = 0
            ab[9, 2], ab[10, 1] = 1.0, -kr * D[1] / (EIr / L)
        a, b = np.divmod(np.arange(16), 4)
        i0 = 0
        for j, (n, _, P, t) in enumerate(segs):
            i = np.arange(i0, i0 + n)
            ab[(12 + a - b)[None, :], (4 * i[:, None] + b[None, :])] = (-(P * D[None, :]) / D[:, None]).ravel()
            rhs[2 + 4 * i0:2 + 4 * (i0 + n)] = np.tile((t / D)[:, None] * volts[None, :, j], (n, 1))
            i0 += n
        ab[8, 4:] = 1.0
        r = 2 + 4 * N
        c0 = 4 * N
        # Tip: M(L) = tip_moment; Q(L) - K w(L) = -tip_force.
        ab[10, c0 + 2] = 1.0
        rhs[r] = np.asarray(tip_moment, dtype=complex) / D[2]
        ab[10, c0 + 3], ab[13, c0] = 1.0, -load * D[0] / D[3]
        rhs[r + 1] = -np.asarray(tip_force, dtype=complex) / D[3]
        y = _band_solve(ab, rhs)
        y = y.T.reshape(n_cases, N + 1, 4) * D[None, None, :]
        return x, np.array(seg_nodes), y

    def currents(self, omega, load=0.0):
        """Segment currents per volt (every segment at 1 V, no tip force or moment) at each of
        many angular frequencies: ``solve(omega[i], complex(load[i]))["current"]`` for every
        ``i``, bitwise, with the numpy work of all of them done at once (an observer's aliased
        images: 80 solves per tone, far above the beam's modes, in many pieces each).

        Parameters
        ----------
        omega : array_like, shape (m,)
            rad/s (> 0).
        load : complex or array_like, shape (m,)
            Dynamic stiffness of the tip load at each, N/m.

        Returns
        -------
        ndarray, shape (m, n_seg), complex
        """
        om = np.atleast_1d(np.asarray(omega, dtype=float))
        K = np.broadcast_to(np.asarray(load, dtype=complex), om.shape)
        n = self.n_seg
        out = np.empty((om.size, n), dtype=complex)
        if om.size == 0:
            return out
        # the scalar set-up of each solve as solve() does it (Python's and numpy's scalar
        # arithmetic are not numpy's array loops to the last bit: a complex quotient differs)
        setup = []
        for w in om:
            c = self._c(w)
            EI, lam = self._ei_lam(w, c)
            setup.append((c, EI, lam, tuple(self._pieces(lam, self.bounds[j], self.bounds[j + 1])
                                            for j in range(n))))
        # solves with the same pieces per segment share one band layout
        by_layout: dict = {}
        for i, (_, _, _, pcs) in enumerate(setup):
            by_layout.setdefault(tuple(p[0] for p in pcs), []).append(i)
        L, EIr = self.length, self.lam.EI
        D = np.array([L, 1.0, EIr / L, EIr / L**2])
        e_m = np.array([0, 0, 1.0, 0])
        a, b = np.divmod(np.arange(16), 4)
        for counts, idx in by_layout.items():
            m = len(idx)
            N = sum(counts)
            n_unk = 4 * (N + 1)
            EI = np.array([setup[i][1] for i in idx])
            lam = np.array([setup[i][2] for i in idx])
            ab = np.zeros((m, 16, n_unk), dtype=complex)
            rhs = np.zeros((m, n_unk, 1), dtype=complex)
            i0 = 0
            for j, nj in enumerate(counts):
                h = [setup[i][3][j][1] for i in idx]
                P = _piece_matrices(lam, EI, h)
                t = self.lam.m_p * (e_m - P @ e_m)
                pieces = np.arange(i0, i0 + nj)
                blk = (-(P * D[None, None, :]) / D[None, :, None]).reshape(m, 1, 16)
                ab[:, (12 + a - b)[None, :], (4 * pieces[:, None] + b[None, :])] = blk
                rhs[:, 2 + 4 * i0:2 + 4 * (i0 + nj), 0] = np.tile(t / D[None, :], (1, nj))
                i0 += nj
            ab[:, 8, 4:] = 1.0
            c0 = 4 * N
            ab[:, 10, c0 + 2] = 1.0
            ab[:, 10, c0 + 3] = 1.0
            for q, i in enumerate(idx):
                w = om[i]
                ks, kr = self.support_stiffness(w, setup[i][0])
                if math.isinf(self.support.k):
                    ab[q, 10, 0] = 1.0
                else:
                    ab[q, 7, 3], ab[q, 10, 0] = 1.0, ks * D[0] / D[3]
                if math.isinf(self.support.k_rot):
                    ab[q, 10, 1] = 1.0
                else:
                    ab[q, 9, 2], ab[q, 10, 1] = 1.0, -kr * D[1] / (EIr / L)
                ab[q, 13, c0] = -complex(K[i]) * D[0] / D[3]
            seg_nodes = np.concatenate(([0], np.cumsum(counts)))
            psi = np.empty((m, n + 1), dtype=complex)
            for q in range(m):
                y = _band_solve(ab[q], rhs[q])
                psi[q] = y[4 * seg_nodes + 1, 0] * D[1]
            # j w times the charge: (0 + j w)(a + j b) is (-w b, w a) however it is rounded
            out[idx] = (1j * om[idx])[:, None] * (self.cp * (1.0 + 0j) - self.lam.m_p * np.diff(psi, axis=1))
        return out

    def _ports_kv(self, omega, c):
        """Port receptance with Kelvin-Voigt coefficient ``c`` and the root state per input.

        Returns ``G`` (n_seg + 2, n_seg + 2) as :meth:`port_receptance` and ``Y0`` (4, n_seg + 2),
        the root state ``[w, psi, M, Q]`` per unit input.
        """
        n = self.n_seg
        volts = np.zeros((n + 2, n), dtype=complex)
        volts[np.arange(n), np.arange(n)] = 1.0
        force = np.zeros(n + 2)
        moment = np.zeros(n + 2)
        force[n], moment[n + 1] = 1.0, 1.0
        _, seg_nodes, y = self._solve_many(omega, 0.0, volts, force, moment, c)
        G = np.empty((n + 2, n + 2), dtype=complex)
        G[:n] = (-self.lam.m_p * np.diff(y[:, seg_nodes, 1], axis=1)).T
        G[n] = y[:, -1, 0]
        G[n + 1] = y[:, -1, 1]
        return G, y[:, 0, :].T

    def _modal(self):
        """Tabulated modes: ``w_n`` (rad/s), port participations ``a_n`` (N_MODAL, n_seg + 2) of
        the mass-normalized shapes, and the residual flexibility ``R`` of the other modes.

        ``a_n a_n^T`` is the residue of the undamped receptance at ``w_n^2``, read from two
        solves at ``w_n^2 (1 -+ 1e-4)``: their difference is ``-2 a_n a_n^T / h`` up to
        ``O(h)`` from the smooth rest (relative error ~1e-8). The tip force is the input (a free
        tip moves in every mode). ``R = G(0) - sum a_n a_n^T / w_n^2``.
        """
        cache = self.__dict__.get("_modal_cache")
        if cache is not None:
            return cache
        n = self.n_seg
        wn = self._wn
        A = np.empty((wn.size, n + 2))
        for i, w in enumerate(wn):
            h = 1e-4 * w * w
            g = [self._ports_kv(math.sqrt(w * w + s * h), 0.0)[0][:, n] for s in (1.0, -1.0)]
            aphi = (-h / 2.0) * (g[0] - g[1]).real         # a_n * phi_n(L)
            if not aphi[n] > 0.0:
                raise ModelError(f"mode at {w / (2 * math.pi):.4g} Hz has no tip motion: cannot "
                                 "normalize it for the modal damping")
            A[i] = aphi / math.sqrt(aphi[n])
        G0 = self._ports_kv(0.0, 0.0)[0].real
        R = G0 - (A.T / wn**2) @ A
        cache = (wn.copy(), A, (R + R.T) / 2.0)
        self.__dict__["_modal_cache"] = cache
        return cache

    def port_receptance(self, omega, root=False):
        """Receptance among the beam's ports, unloaded, with the plant's modal damping.

        Ports (inputs = columns, outputs = rows, reciprocal so ``G`` is symmetric): segment
        ``j``'s voltage (V) and its motional charge (C: charge minus ``Cp_j V_j``); the tip
        force (N, up) and the tip deflection (m); the tip moment (N m, ccw) and the tip slope
        (rad). Modal damping gives mode ``n`` the term ``a_n a_n^T / (w_n^2 - w^2 + 2 j zeta
        w_n w)``; it is not a local law, so it is added to the Kelvin-Voigt solve (a
        stiffness-proportional damping, whose modal terms are ``a_n a_n^T / (w_n^2 (1 + j w c)
        - w^2)``) as the difference of the two for the ``N_MODAL`` tabulated modes, and for the
        rest quasi-statically, ``R j w c / (1 + j w c)`` (valid well below the first
        untabulated mode, ~140 kHz for the bundled beam).

        Parameters
        ----------
        omega : float
            rad/s (>= 0).
        root : bool
            Also return the root state ``[w, psi, M, Q]`` per unit input (Kelvin-Voigt),
            shape (4, n_seg + 2).

        Returns
        -------
        ndarray, shape (n_seg + 2, n_seg + 2), complex
        """
        c = self._c(omega)
        G, Y0 = self._ports_kv(omega, c)
        if self.c_kv > 0.0:
            wn, A, R = self._modal()
            w2 = omega * omega
            d = (1.0 / (wn**2 - w2 + 2j * self.zeta * wn * omega)
                 - 1.0 / (wn**2 * (1.0 + 1j * omega * c) - w2))
            G = G + (A.T * d) @ A + R * (1j * omega * c / (1.0 + 1j * omega * c))
        return (G, Y0) if root else G

    def response(self, freqs_hz, load=None, volts=None):
        """Tip response and segment currents per volt over frequency (modal damping).

        The unloaded port receptance (:meth:`port_receptance`) closed by the tip load:
        ``w_L = g_w / (1 + K G_PP)`` with ``g`` the response to the voltages.

        Parameters
        ----------
        freqs_hz : array_like, shape (n,)
            Hz, > 0.
        load : MaxwellLoad or callable or None
            Finger at the tip (``dynamic_stiffness(omega)``), or a function of omega (rad/s)
            returning N/m, or None.
        volts : array_like, shape (n_seg,), optional
            Segment voltages (default all 1 V, the electrodes driven together).

        Returns
        -------
        dict of ndarray, complex
            ``tip`` (m/V), ``velocity`` (m/s/V), ``slope`` (rad/V), ``moment`` (N m/V),
            ``force`` (N/V, ``Q(L)``: pushed into the load), each shape (n,); ``current``
            (A/V, shape (n, n_seg)); ``admittance`` (A/V, total current, shape (n,)).
        """
        f = np.atleast_1d(np.asarray(freqs_hz, dtype=float))
        n = self.n_seg
        V = np.ones(n, dtype=complex) if volts is None else np.asarray(volts, dtype=complex)
        out = {k: np.empty(f.size, dtype=complex) for k in ("tip", "slope", "moment", "force")}
        cur = np.empty((f.size, n), dtype=complex)
        for i, fi in enumerate(f):
            w = 2.0 * math.pi * fi
            K = _load_stiffness(load, w)
            G = self.port_receptance(w)
            g = G[:, :n] @ V
            wl = g[n] / (1.0 + K * G[n, n])
            o = g - G[:, n] * (K * wl)
            out["tip"][i], out["slope"][i] = wl, o[n + 1]
            out["moment"][i], out["force"][i] = 0.0, K * wl
            cur[i] = 1j * w * (self.cp * V + o[:n])
        out["velocity"] = 2j * math.pi * f * out["tip"]
        out["current"] = cur
        out["admittance"] = cur.sum(axis=1)
        return out

    # ------------------------------------------------------------------ eigenvalues
    def _char(self, s, load_fn):
        """Characteristic 2x2 determinant at complex ``s`` (Laplace variable).

        Two root states spanning the support conditions are carried to the tip piece by piece
        in dimensionless units, re-orthonormalized (QR) after each piece so nothing overflows;
        the phases of ``R``'s diagonal are kept, so the sign of a real determinant is exact.
        """
        EI = self.lam.EI * (1.0 + s * self._c(abs(s)))
        lam = -self.lam.rhoA * s * s / EI
        L, EIr = self.length, self.lam.EI
        D = np.array([L, 1.0, EIr / L, EIr / L**2])
        sup = self.support
        damp = 1.0 + s * self._c(abs(s))
        # (a rigid DOF has no spring term: inf * complex would make NaN parts)
        ks = 0.0 if math.isinf(sup.k) else sup.k * damp + sup.mass * s * s
        kr = 0.0 if math.isinf(sup.k_rot) else sup.k_rot * damp + sup.inertia * s * s
        Y = np.zeros((4, 2), dtype=complex)
        if math.isinf(sup.k):
            Y[3, 0] = 1.0                       # w = 0, Q free
        else:
            Y[0, 0], Y[3, 0] = 1.0, -ks         # Q(0) = -k w(0)
        if math.isinf(sup.k_rot):
            Y[2, 1] = 1.0                       # psi = 0, M free
        else:
            Y[1, 1], Y[2, 1] = 1.0, kr          # M(0) = k_rot psi(0)
        Y = Y / D[:, None]
        Y /= np.linalg.norm(Y, axis=0)
        n, h = self._pieces(lam, 0.0, L)
        P = (piece_matrix(lam, EI, h) * D[None, :]) / D[:, None]
        phase = 1.0 + 0j
        for _ in range(n):
            Y, r = np.linalg.qr(P @ Y)
            d = np.diag(r)
            phase *= np.prod(d / np.abs(d))
        K = load_fn(s)
        B = np.array([[0, 0, 1.0, 0], [-K * L**3 / EIr, 0, 0, 1.0]], dtype=complex)
        return np.linalg.det(B @ Y) * phase

    def natural_frequencies(self, n=4, tip_mass=0.0, tip_k=0.0):
        """Undamped natural frequencies, Hz (real roots of the characteristic determinant).

        Parameters
        ----------
        n : int
        tip_mass : float
            kg at the tip.
        tip_k : float
            N/m from the tip to ground.
        """
        saved, self.c_kv = self.c_kv, 0.0
        try:
            lf = lambda s: tip_k + tip_mass * s * s  # noqa: E731
            g = lambda f: float(np.real(self._char(2j * math.pi * f, lf)))  # noqa: E731
            f_scale = math.sqrt(self.lam.EI / (self.lam.rhoA * self.length**4)) / (2 * math.pi)
            grid = np.geomspace(0.01 * f_scale, f_scale * (6.0 * (n + 2)) ** 2, 1000)
            vals = np.array([g(f) for f in grid])
            roots = []
            for i in np.nonzero(np.sign(vals[:-1]) * np.sign(vals[1:]) < 0)[0]:
                roots.append(scipy.optimize.brentq(g, grid[i], grid[i + 1], xtol=1e-12, rtol=1e-14))
                if len(roots) == n:
                    break
        finally:
            self.c_kv = saved
        if len(roots) < n:
            raise ModelError(f"found only {len(roots)} of {n} natural frequencies")
        return np.array(roots)

    def loaded_frequencies(self, load, n=4):
        """Natural frequencies under a viscoelastic tip load, Hz: ``|s| / 2 pi`` of the complex
        roots of the damped characteristic equation (as ``rtctl.plant.facts`` reports them).

        Parameters
        ----------
        load : MaxwellLoad
        n : int
        """
        m, k0 = load.mass, load.k0
        br = list(load.branches)

        def lf(s):
            return m * s * s + k0 + sum(k * s * tau / (1.0 + s * tau) for k, tau in br)

        # Start from the undamped roots with every branch as a spring (w tau >> 1 at the modes).
        start = self.natural_frequencies(n, tip_mass=m, tip_k=k0 + sum(k for k, _ in br))
        out = []
        for f0 in start:
            w0 = 2.0 * math.pi * f0
            g = lambda p, w0=w0: self._char(p * w0, lf)  # noqa: E731
            z = min(0.9, self._c(w0) * w0 / 2.0)  # damping ratio of this mode
            p0 = complex(-z, math.sqrt(1.0 - z * z))
            try:
                p = scipy.optimize.newton(g, p0, x1=p0 * 1.001,
                                          tol=1e-13, maxiter=100)
            except RuntimeError as exc:
                raise ModelError(f"loaded mode near {f0:.4g} Hz did not converge: {exc}") from None
            out.append(abs(p) * f0)
        return np.array(out)


def _ri(z):
    return [z.real, z.imag]


def _load_stiffness(load, omega):
    if load is None:
        return 0.0
    if callable(load):
        return complex(load(omega))
    return complex(load.dynamic_stiffness(omega))
