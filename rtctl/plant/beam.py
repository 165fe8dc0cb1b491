"""Euler-Bernoulli finite elements of a layered piezoelectric beam with segmented electrodes.

This is the physics "truth" for the bimorph actuators: a clamped (or elastically supported),
free-tipped cantilever made of bonded layers, some piezoelectric, whose electrodes are split
along the length into independent segments (seed 000, Eq. 2: two segments for self-sensing,
four to identify the support).

Model
-----
Hermite cubic elements, nodal DOFs ``[w, psi]`` (transverse displacement in m, slope
``psi = dw/dx`` in rad), consistent mass, no shear deformation or rotary inertia (Euler-Bernoulli:
valid for slender beams, length >> total thickness). With ``q`` the free DOFs::

    M q'' + C q' + K q = Theta V + F_ext          (V: segment voltages, shape (n_seg,))
    Q = Theta^T q + diag(Cp) V                     (Q: charge into each segment's + terminal)

**Section.** The neutral axis is the E-weighted centroid of the stack; ``EI = sum E_i I_i`` about
it; ``rhoA = sum rho_i w t_i``.

**Electromechanics.** A piezo layer ``i`` with voltage ``V_i`` across it feels the field
``V_i / t_i`` and, about the neutral axis, the moment per volt ``mu_i = s_i e31_i w z_i`` and the
axial force per volt ``n_i = s_i e31_i w`` (``z_i``: its centroid above the neutral axis). The
poling sign ``s_i = -sign(z_i) sign(d31_i)`` is chosen so that every layer bends the beam the same
way (layers above the neutral axis are poled opposite to those below, for either sign of
``d31``); hence ``mu_i = -|e31_i| w |z_i| <= 0``.

* ``parallel``: every piezo layer sees the full port voltage, ``V_i = V`` (``f_i = 1``).
* ``series``: the piezo layers are stacked in series between the two port electrodes, with
  floating equipotential electrodes (a conductive shim, or bonded electrodes) between them that
  carry no net charge. For two identical layers this is ``V_i = V / 2``; in general (unequal
  layers, or three or more: their moments per volt differ with the distance from the neutral
  axis, e.g. 0.324/0.324/0.351 for three identical layers) the division follows from charge
  balance: ``f = C_l^-1 1 / (1^T C_l^-1 1)`` (the capacitive divider), and keeping the floating
  electrodes' charge balanced costs an extra rotational stiffness between the segment's end
  slopes (``Section.electrical_stiffness``, zero only when every layer's moment per volt is the
  same, e.g. two identical layers). This is the exact static condensation of the floating
  electrodes.

Here ``C_l = diag(c_i) + n n^T / EA`` is the per-length capacitance of the layers with the beam
held in bending but free to stretch, ``c_i = eps33S_i w / t_i``. The axial stretch is condensed
statically: its first resonance (``sqrt(E/rho) / (4 L)``, tens of kHz for millimetre beams) lies
far above the band, and it vanishes for a symmetric stack (a bimorph) where ``sum n_i V_i = 0``.
So ``Cp = cp_per_length * segment length`` is the capacitance of a segment with the bending DOFs
blocked (``eps33S`` per layer, layers combined as the connection says).

With ``m_p = sum_i f_i mu_i`` (N m/V, ``<= 0``), the electrode of segment ``j`` between ``x_a`` and
``x_b`` loads the beam with the moment pair ``+m_p`` at ``psi(x_a)`` and ``-m_p`` at ``psi(x_b)``:
``Theta[:, j] = m_p (e_psi(x_a) - e_psi(x_b))``, i.e. the difference of the end slopes.

Sign conventions
----------------
* ``w`` and the tip force ``F`` point the same way ("up"); ``psi`` and a tip moment are positive
  counter-clockwise (they raise the tip).
* **A positive voltage moves the tip up** (``deflection_per_volt() > 0``) for every stack and
  either sign of ``d31``: a homogeneous bimorph gives Smits & Choi's ``3 |d31| L^2 / (2 h^2)``.
* ``Theta``: at the distal end of each segment its rotation entry is ``-m_p > 0``, at the proximal
  end ``+m_p < 0`` (dropped at a clamped root, where the clamp takes it).
* Charge: ``Q = Theta^T q + Cp V``. Pushing the tip up (positive ``F``) with the electrodes
  shorted puts a positive charge on them (reciprocity: charge per force = deflection per volt).
* ``blocked_force_per_volt()`` is the force the tip exerts on a rigid stop holding it at
  ``w = 0`` (slope free); it has the sign of the free motion, as Smits & Choi's ``F_b``. The stop
  (or an external force) must apply minus this value.

Numerics
--------
The stiffness matrix of a cantilever mixes N/m with N m/rad entries (ratio ``1/le^2``) and has a
condition number growing like ``n_elements^4``. Every solve and the eigenproblem therefore use the
symmetric Jacobi scaling ``D = diag(K)^-1/2`` (it removes the units and the ``EI`` scale, so thin
or long beams cost no accuracy: the scaled condition number depends only on the mesh), a Cholesky
factorization, and LAPACK's condition estimate, which must stay below ``COND_MAX = 1e12``. It is
3e6 at the default 24 elements, 8e10 at 300 and passes 1e12 near 550, so ``elements`` is capped
at 500; static round-off is about 1e-16 times it (3e-12 relative at 24 elements). A segment far
shorter than its neighbours, or a support or tip spring many orders stiffer than the beam, also
raises :class:`~rtctl.errors.ModelError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import scipy.linalg
import scipy.linalg.lapack

from rtctl.errors import ModelError
from rtctl.plant.materials import Material

__all__ = [
    "Layer",
    "BeamSpec",
    "SupportSpec",
    "Section",
    "BeamFE",
    "build_beam",
    "section_of",
    "COND_MAX",
    "MAX_ELEMENTS",
]

#: Most elements accepted: beyond this the condition number check would fail anyway.
MAX_ELEMENTS = 500

#: Largest condition number of the Jacobi-scaled stiffness or mass matrix accepted.
COND_MAX = 1e12

_CONNECTIONS = ("series", "parallel")
_SUPPORTS = ("clamped", "elastic")


def _positive(owner: str, name: str, value, unit: str) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ModelError(f"{owner}.{name} must be a number ({unit}), got {value!r}") from None
    if not (math.isfinite(value) and value > 0.0):
        raise ModelError(f"{owner}.{name} must be a positive finite number ({unit}), got {value!r}")
    return value


@dataclass(frozen=True)
class Layer:
    """One bonded layer of the beam, listed from the bottom face up.

    Parameters
    ----------
    material : Material
        Its material; ``d31 == 0`` makes it passive.
    thickness : float
        Thickness, m.
    """

    material: Material
    thickness: float

    def __post_init__(self):
        if not isinstance(self.material, Material):
            raise ModelError(f"Layer.material must be a Material, got {type(self.material).__name__}")
        object.__setattr__(self, "thickness", _positive("Layer", "thickness", self.thickness, "m"))


@dataclass(frozen=True)
class BeamSpec:
    """Geometry, stack and electrodes of a layered piezoelectric cantilever.

    Parameters
    ----------
    length : float
        Free length from the support to the tip, m.
    width : float
        Width, m.
    layers : tuple of Layer
        The stack from the bottom face up; at least one piezoelectric layer.
    connection : {"series", "parallel"}
        How the piezo layers are wired to each segment's port (see the module docstring).
    segments : tuple of float
        Electrode split as fractions of the length from the support outward; each > 0, summing
        to 1. ``(1.0,)`` is a single electrode.
    damping : float
        Modal damping ratio of every mode, in [0, 1).
    elements : int
        Total number of finite elements, distributed over the segments in proportion to their
        length (at least one each) so that every segment boundary is a node. Default 24.

    Raises
    ------
    ModelError
        Naming the invalid quantity.
    """

    length: float
    width: float
    layers: tuple[Layer, ...]
    connection: str
    segments: tuple[float, ...]
    damping: float
    elements: int = 24

    def __post_init__(self):
        set_ = object.__setattr__
        set_(self, "length", _positive("BeamSpec", "length", self.length, "m"))
        set_(self, "width", _positive("BeamSpec", "width", self.width, "m"))
        layers = tuple(self.layers)
        if not layers or not all(isinstance(layer, Layer) for layer in layers):
            raise ModelError("BeamSpec.layers must be a non-empty sequence of Layer")
        if not any(layer.material.is_piezo for layer in layers):
            raise ModelError("BeamSpec.layers has no piezoelectric layer (every d31 is 0)")
        set_(self, "layers", layers)
        if self.connection not in _CONNECTIONS:
            raise ModelError(
                f"BeamSpec.connection must be one of {_CONNECTIONS}, got {self.connection!r}"
            )
        try:
            segments = tuple(float(s) for s in self.segments)
        except (TypeError, ValueError):
            raise ModelError(f"BeamSpec.segments must be numbers, got {self.segments!r}") from None
        if not segments or not all(math.isfinite(s) and s > 0.0 for s in segments):
            raise ModelError(
                f"BeamSpec.segments must be positive fractions of the length, got {segments!r}"
            )
        if abs(math.fsum(segments) - 1.0) > 1e-9:
            raise ModelError(
                f"BeamSpec.segments must sum to 1, got {segments!r} (sum {math.fsum(segments)!r})"
            )
        set_(self, "segments", segments)
        try:
            damping = float(self.damping)
        except (TypeError, ValueError):
            damping = math.nan
        if not (0.0 <= damping < 1.0):
            raise ModelError(f"BeamSpec.damping must be a ratio in [0, 1), got {self.damping!r}")
        set_(self, "damping", damping)
        try:
            integral = not isinstance(self.elements, bool) and int(self.elements) == self.elements
        except (TypeError, ValueError, OverflowError):
            integral = False
        if not integral:
            raise ModelError(f"BeamSpec.elements must be an integer, got {self.elements!r}")
        elements = int(self.elements)
        if elements > MAX_ELEMENTS:
            raise ModelError(
                f"BeamSpec.elements = {elements} exceeds {MAX_ELEMENTS}: the scaled stiffness "
                "condition number grows like elements^4 (about 1e12 at 550) and the dense "
                "solves like elements^3; 24 elements already give 1e-5 relative frequency error"
            )
        if elements < len(segments):
            raise ModelError(
                f"BeamSpec.elements = {elements} must be at least the number of segments "
                f"({len(segments)})"
            )
        set_(self, "elements", elements)

    @property
    def thickness(self) -> float:
        """Total thickness of the stack, m."""
        return math.fsum(layer.thickness for layer in self.layers)


@dataclass(frozen=True)
class SupportSpec:
    """Support at the root of the cantilever (the tip is free).

    Parameters
    ----------
    kind : {"clamped", "elastic"}
        ``clamped`` fixes ``w`` and ``psi`` at the root. ``elastic`` ties them to ground with a
        translational spring ``k`` and a rotational spring ``k_rot``; an infinite value fixes that
        DOF. Both must be > 0: a cantilever with a zero root spring is a mechanism.
    k : float
        Translational stiffness, N/m (``inf`` = rigid).
    k_rot : float
        Rotational stiffness, N m/rad (``inf`` = rigid).
    mass : float
        Mass moving with the root's translation, kg (``elastic`` only): a support that is
        itself the moving part of another actuator (the bimodal display's perpendicular
        actuator carries the bimorph; seed 000 section 3.3, R_m).
    inertia : float
        Rotary inertia on the root's rotation, kg m^2 (``elastic`` only).
    """

    kind: str = "clamped"
    k: float = math.inf
    k_rot: float = math.inf
    mass: float = 0.0
    inertia: float = 0.0

    def __post_init__(self):
        if self.kind not in _SUPPORTS:
            raise ModelError(f"SupportSpec.kind must be one of {_SUPPORTS}, got {self.kind!r}")
        for name, unit in (("k", "N/m"), ("k_rot", "N m/rad")):
            try:
                value = float(getattr(self, name))
            except (TypeError, ValueError):
                raise ModelError(
                    f"SupportSpec.{name} must be a number ({unit}), got {getattr(self, name)!r}"
                ) from None
            if math.isnan(value) or value < 0.0:
                raise ModelError(f"SupportSpec.{name} must be >= 0 ({unit}) or inf, got {value!r}")
            if self.kind == "clamped" and value != math.inf:
                raise ModelError(
                    f"SupportSpec.{name} = {value!r} is given for a clamped support; "
                    "use kind='elastic' for a compliant root"
                )
            object.__setattr__(self, name, value)
        for name, dof in (("mass", "k"), ("inertia", "k_rot")):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value >= 0.0):
                raise ModelError(f"SupportSpec.{name} must be finite and >= 0, got {value!r}")
            if value and getattr(self, dof) == math.inf:
                raise ModelError(f"SupportSpec.{name} = {value!r} sits on a rigid DOF ({dof} = inf): "
                                 f"give a finite {dof} for a moving support")
            object.__setattr__(self, name, value)


@dataclass(frozen=True)
class Section:
    """Per-length properties of the layered section (uniform along the beam).

    Attributes
    ----------
    neutral_axis : float
        Height of the E-weighted neutral axis above the bottom face, m.
    EI : float
        Bending stiffness about the neutral axis, N m^2.
    EA : float
        Axial stiffness, N.
    rhoA : float
        Mass per length, kg/m.
    moment_per_volt : float
        ``m_p``, bending moment per port volt about the neutral axis, N m/V (<= 0, see the module
        docstring for the sign).
    cp_per_length : float
        Port capacitance per length with bending blocked, F/m.
    electrical_stiffness : float
        Stiffening from the floating inter-layer electrodes of a series stack, N m^2; a segment of
        length ``l`` gets a rotational spring ``electrical_stiffness / l`` between its end slopes.
        Zero for ``parallel``, and for series stacks whose layers all have the same moment per
        volt (two identical layers); e.g. 3.9 % of EI for three identical layers.
    fractions : tuple of float
        Share ``f_i`` of the port voltage across each layer (0 for passive layers).
    """

    neutral_axis: float
    EI: float
    EA: float
    rhoA: float
    moment_per_volt: float
    cp_per_length: float
    electrical_stiffness: float
    fractions: tuple


def section_of(spec: BeamSpec) -> Section:
    """Section properties of ``spec`` (see the module docstring for the equations).

    Parameters
    ----------
    spec : BeamSpec

    Returns
    -------
    Section
    """
    w = spec.width
    t = np.array([layer.thickness for layer in spec.layers])
    E = np.array([layer.material.E for layer in spec.layers])
    rho = np.array([layer.material.rho for layer in spec.layers])
    z_bot = np.concatenate(([0.0], np.cumsum(t)[:-1]))
    z_top = z_bot + t
    EA = float(np.sum(E * w * t))
    z_na = float(np.sum(E * t * (z_bot + z_top) / 2.0) / np.sum(E * t))
    # Layer-wise I about the neutral axis from (z_top^3 - z_bot^3)/3: no cancellation between
    # parallel-axis terms, so thin layers far from the axis keep full precision.
    zb, zt = z_bot - z_na, z_top - z_na
    EI = float(np.sum(E * w * (zt**3 - zb**3) / 3.0))
    rhoA = float(np.sum(rho * w * t))

    piezo = [i for i, layer in enumerate(spec.layers) if layer.material.is_piezo]
    e31 = np.array([spec.layers[i].material.e31 for i in piezo])
    eps_s = np.array([spec.layers[i].material.eps33S for i in piezo])
    zc = (zb[piezo] + zt[piezo]) / 2.0
    # Poling chosen so every layer helps: s_i e31_i z_i = -|e31_i| |z_i|.
    mu = -np.abs(e31) * w * np.abs(zc)  # N m per volt across the layer
    sign_n = -np.sign(zc) * np.sign(e31)
    sign_n[sign_n == 0.0] = 1.0  # a layer centred on the axis: moment 0, poling arbitrary
    n_ax = sign_n * e31 * w  # N per volt across the layer
    c = eps_s * w / t[piezo]  # F/m
    C_l = np.diag(c) + np.outer(n_ax, n_ax) / EA  # bending blocked, axially free

    fractions = np.zeros(len(spec.layers))
    if spec.connection == "parallel":
        f = np.ones(len(piezo))
        cp = float(np.sum(C_l))
        k_el = 0.0
    else:
        ones = np.ones(len(piezo))
        C_inv = np.linalg.inv(C_l)  # tiny, well-conditioned (diagonal + rank one, c_i > 0)
        S = float(ones @ C_inv @ ones)
        f = (C_inv @ ones) / S
        cp = 1.0 / S
        k_el = float(mu @ C_inv @ mu - (ones @ C_inv @ mu) ** 2 / S)
        # Cauchy-Schwarz makes k_el >= 0; round-off can leave -eps * scale.
        k_el = max(k_el, 0.0)
        if k_el <= 1e-12 * float(mu @ C_inv @ mu):
            k_el = 0.0
    fractions[piezo] = f
    m_p = float(np.sum(f * mu))
    return Section(
        neutral_axis=z_na,
        EI=EI,
        EA=EA,
        rhoA=rhoA,
        moment_per_volt=m_p,
        cp_per_length=cp,
        electrical_stiffness=k_el,
        fractions=tuple(float(x) for x in fractions),
    )


def _element_counts(segments: tuple, elements: int) -> list[int]:
    """Elements per segment: proportional to length, at least one each, summing to ``elements``."""
    raw = np.asarray(segments) * elements
    counts = np.maximum(1, np.floor(raw).astype(int))
    while counts.sum() < elements:
        counts[np.argmax(raw - counts)] += 1
    while counts.sum() > elements:
        spare = np.where(counts > 1, counts - raw, -np.inf)
        counts[np.argmax(spare)] -= 1
    return [int(c) for c in counts]


def _hermite(le: float, EI: float, rhoA: float) -> tuple[np.ndarray, np.ndarray]:
    """Stiffness and consistent mass of one Hermite cubic beam element, DOFs [w1, psi1, w2, psi2]."""
    L2 = le * le
    k = EI / le**3 * np.array(
        [
            [12.0, 6.0 * le, -12.0, 6.0 * le],
            [6.0 * le, 4.0 * L2, -6.0 * le, 2.0 * L2],
            [-12.0, -6.0 * le, 12.0, -6.0 * le],
            [6.0 * le, 2.0 * L2, -6.0 * le, 4.0 * L2],
        ]
    )
    m = rhoA * le / 420.0 * np.array(
        [
            [156.0, 22.0 * le, 54.0, -13.0 * le],
            [22.0 * le, 4.0 * L2, 13.0 * le, -3.0 * L2],
            [54.0, 13.0 * le, 156.0, -22.0 * le],
            [-13.0 * le, -3.0 * L2, -22.0 * le, 4.0 * L2],
        ]
    )
    return k, m


def build_beam(spec: BeamSpec, support: SupportSpec | None = None) -> BeamFE:
    """Assemble the finite-element model of ``spec`` on ``support``.

    Parameters
    ----------
    spec : BeamSpec
    support : SupportSpec, optional
        Default: clamped.

    Returns
    -------
    BeamFE

    Raises
    ------
    ModelError
        A mechanism (an elastic support with ``k = 0`` or ``k_rot = 0``) or a numerically unsafe
        model (scaled condition number above :data:`COND_MAX`).

    Examples
    --------
    >>> from rtctl.plant.materials import material
    >>> pzt = material("PZT-5A")
    >>> spec = BeamSpec(15e-3, 1.5e-3, (Layer(pzt, 0.3e-3), Layer(pzt, 0.3e-3)),
    ...                 "parallel", (0.5, 0.5), 0.01)
    >>> fe = build_beam(spec)
    >>> f, _ = fe.modes(1)
    >>> round(float(f[0]))
    1208
    """
    support = SupportSpec() if support is None else support
    if not isinstance(spec, BeamSpec) or not isinstance(support, SupportSpec):
        raise ModelError("build_beam needs a BeamSpec and a SupportSpec")
    if support.kind == "elastic":
        for name in ("k", "k_rot"):
            if getattr(support, name) == 0.0:
                raise ModelError(
                    f"SupportSpec.{name} = 0 leaves the cantilever a mechanism (a rigid-body "
                    "motion with no stiffness); give it a positive value or inf"
                )
    sec = section_of(spec)

    counts = _element_counts(spec.segments, spec.elements)
    bounds = np.concatenate(([0.0], np.cumsum(spec.segments)))
    bounds[-1] = 1.0
    bounds *= spec.length
    xs = [np.array([0.0])]
    seg_nodes = [0]
    for j, nj in enumerate(counts):
        xs.append(np.linspace(bounds[j], bounds[j + 1], nj + 1)[1:])
        seg_nodes.append(seg_nodes[-1] + nj)
    nodes = np.concatenate(xs)
    n_nodes = nodes.size
    n_full = 2 * n_nodes

    K = np.zeros((n_full, n_full))
    M = np.zeros((n_full, n_full))
    for e in range(n_nodes - 1):
        ke, me = _hermite(nodes[e + 1] - nodes[e], sec.EI, sec.rhoA)
        sl = slice(2 * e, 2 * e + 4)
        K[sl, sl] += ke
        M[sl, sl] += me

    n_seg = len(spec.segments)
    Theta = np.zeros((n_full, n_seg))
    Cp = np.empty(n_seg)
    for j in range(n_seg):
        a, b = 2 * seg_nodes[j] + 1, 2 * seg_nodes[j + 1] + 1  # slope DOFs at the segment ends
        Theta[a, j] += sec.moment_per_volt
        Theta[b, j] -= sec.moment_per_volt
        length_j = nodes[seg_nodes[j + 1]] - nodes[seg_nodes[j]]
        Cp[j] = sec.cp_per_length * length_j
        if sec.electrical_stiffness > 0.0:
            kr = sec.electrical_stiffness / length_j
            K[np.ix_([a, b], [a, b])] += kr * np.array([[1.0, -1.0], [-1.0, 1.0]])

    # Root: springs on the kept DOFs, infinite ones removed.
    keep = np.ones(n_full, dtype=bool)
    for dof, kk, mm in ((0, support.k, support.mass), (1, support.k_rot, support.inertia)):
        if kk == math.inf:
            keep[dof] = False
        else:
            K[dof, dof] += kk
            M[dof, dof] += mm
    table = np.full(n_full, -1, dtype=np.intp)
    table[keep] = np.arange(int(keep.sum()))
    return BeamFE(
        spec=spec,
        support=support,
        section=sec,
        nodes=nodes,
        dof_table=table.reshape(n_nodes, 2),
        segment_nodes=np.array(seg_nodes, dtype=np.intp),
        M=M[np.ix_(keep, keep)],
        K=K[np.ix_(keep, keep)],
        Theta=Theta[keep],
        Cp=Cp,
    )


def _readonly(a, dtype=float) -> np.ndarray:
    a = np.array(a, dtype=dtype, order="C")
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class BeamFE:
    """Assembled finite-element model of a layered piezoelectric cantilever.

    Build it with :func:`build_beam`. Arrays are read-only; :meth:`with_tip` returns a new model.

    Attributes
    ----------
    spec : BeamSpec
    support : SupportSpec
    section : Section
        Per-length section properties.
    nodes : ndarray, shape (n_nodes,)
        Node positions from the root, m.
    dof_table : ndarray of int, shape (n_nodes, 2)
        Index of the free DOF ``[w, psi]`` of each node, -1 where the support fixes it.
    segment_nodes : ndarray of int, shape (n_seg + 1,)
        Node index of each electrode boundary (first 0, last ``n_nodes - 1``).
    M, K : ndarray, shape (n_dof, n_dof)
        Mass (kg, kg m, kg m^2) and stiffness (N/m, N, N m/rad) over the free DOFs, support
        springs and tip load included.
    Theta : ndarray, shape (n_dof, n_seg)
        Electromechanical coupling, N/V on ``w`` rows, N m/V on ``psi`` rows.
    Cp : ndarray, shape (n_seg,)
        Blocked capacitance of each segment, F.
    tip_mass : float
        Point mass added at the tip by :meth:`with_tip`, kg.
    tip_k : float
        Translational spring to ground added at the tip by :meth:`with_tip`, N/m.
    """

    spec: BeamSpec
    support: SupportSpec
    section: Section
    nodes: np.ndarray
    dof_table: np.ndarray
    segment_nodes: np.ndarray
    M: np.ndarray
    K: np.ndarray
    Theta: np.ndarray
    Cp: np.ndarray
    tip_mass: float = 0.0
    tip_k: float = 0.0

    def __post_init__(self):
        set_ = object.__setattr__
        for name in ("nodes", "M", "K", "Theta", "Cp"):
            set_(self, name, _readonly(getattr(self, name)))
        for name in ("dof_table", "segment_nodes"):
            set_(self, name, _readonly(getattr(self, name), np.intp))
        n = self.K.shape[0]
        if self.M.shape != (n, n) or self.Theta.shape != (n, self.Cp.size):
            raise ModelError(f"BeamFE shapes disagree: M {self.M.shape}, K {self.K.shape}, "
                             f"Theta {self.Theta.shape}, Cp {self.Cp.shape}")
        if not (np.all(np.isfinite(self.K)) and np.all(np.isfinite(self.M))):
            raise ModelError("BeamFE matrices contain non-finite values")
        d = np.diag(self.K)
        if np.any(d <= 0.0) or np.any(np.diag(self.M) <= 0.0):
            raise ModelError("BeamFE has a DOF without stiffness or mass: a mechanism")
        D = 1.0 / np.sqrt(d)
        Ks = D[:, None] * self.K * D[None, :]
        Ms = D[:, None] * self.M * D[None, :]
        factors = []
        for label, A in (("stiffness", Ks), ("mass", Ms)):
            try:
                c = scipy.linalg.cho_factor(A, lower=True, check_finite=False)
            except np.linalg.LinAlgError:
                raise ModelError(
                    f"BeamFE {label} matrix is not positive definite (a mechanism, or a "
                    "negative spring or mass)"
                ) from None
            # LAPACK's 1-norm estimate from the factor: O(n^2), unlike a full SVD.
            rcond, info = scipy.linalg.lapack.dpocon(c[0], np.linalg.norm(A, 1), uplo="L")
            if info != 0 or not rcond * COND_MAX >= 1.0:
                raise ModelError(
                    f"BeamFE {label} matrix is numerically unsafe: scaled condition number "
                    f"~{1.0 / rcond if rcond > 0 else math.inf:.3g} > {COND_MAX:.0e}. Causes: "
                    f"too many elements ({self.spec.elements}), a segment far shorter than the "
                    "others, or a support/tip spring or tip mass many orders beyond the beam's "
                    "own (use k = inf for a rigid support)"
                )
            factors.append(c)
        set_(self, "_scale", D)
        set_(self, "_chol", factors[0])
        set_(self, "_Ks", Ks)
        set_(self, "_Ms", Ms)

    # ------------------------------------------------------------------ indexing
    @classmethod
    def from_spec(cls, spec: BeamSpec, support: SupportSpec | None = None) -> BeamFE:
        """Same as :func:`build_beam`."""
        return build_beam(spec, support)

    @property
    def n_dof(self) -> int:
        """Number of free DOFs."""
        return self.K.shape[0]

    @property
    def n_seg(self) -> int:
        """Number of electrode segments (ports)."""
        return self.Cp.size

    def dof_of(self, node: int, which: str) -> int:
        """Index of a node's DOF in ``q``.

        Parameters
        ----------
        node : int
            Node number, ``0`` at the root; negative values count from the tip (``-1``).
        which : {"w", "psi"}
            Transverse displacement or slope.

        Raises
        ------
        ModelError
            Unknown node or name, or a DOF the support fixes.
        """
        if which not in ("w", "psi"):
            raise ModelError(f"dof_of: which must be 'w' or 'psi', got {which!r}")
        n_nodes = self.nodes.size
        if not (-n_nodes <= int(node) < n_nodes):
            raise ModelError(f"dof_of: node {node} outside 0..{n_nodes - 1}")
        idx = int(self.dof_table[int(node), 0 if which == "w" else 1])
        if idx < 0:
            raise ModelError(f"dof_of: {which} of node {node} is fixed by the {self.support.kind} support")
        return idx

    @property
    def tip(self) -> int:
        """Index of the tip transverse displacement DOF."""
        return self.dof_of(-1, "w")

    @property
    def tip_rot(self) -> int:
        """Index of the tip slope DOF."""
        return self.dof_of(-1, "psi")

    # ------------------------------------------------------------------ dynamics
    def _eig(self) -> tuple[np.ndarray, np.ndarray]:
        cache = self.__dict__.get("_eig_cache")
        if cache is None:
            lam, y = scipy.linalg.eigh(self._Ks, self._Ms)
            if lam[0] <= 0.0:
                raise ModelError(f"BeamFE eigenvalue {lam[0]:.3g} <= 0: not positive definite")
            phi = self._scale[:, None] * y
            # Deterministic signs: the tip moves up in every mode (or the largest entry is > 0).
            ref = phi[self.tip]
            big = phi[np.argmax(np.abs(phi), axis=0), np.arange(phi.shape[1])]
            flip = np.where(np.abs(ref) > 1e-9 * np.abs(big), np.sign(ref), np.sign(big))
            phi = phi * flip[None, :]
            cache = (_readonly(np.sqrt(lam)), _readonly(phi))
            object.__setattr__(self, "_eig_cache", cache)
        return cache

    def modes(self, n: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Undamped natural frequencies and mass-normalized mode shapes, ascending.

        Parameters
        ----------
        n : int, optional
            How many modes (default: all ``n_dof``).

        Returns
        -------
        freqs_hz : ndarray, shape (n,)
            Natural frequencies, Hz.
        shapes : ndarray, shape (n_dof, n)
            Mode shapes with ``shapes.T @ M @ shapes = I``; each with a positive tip displacement.
        """
        omega, phi = self._eig()
        n = self.n_dof if n is None else int(n)
        if not (1 <= n <= self.n_dof):
            raise ModelError(f"modes: n must be in 1..{self.n_dof}, got {n}")
        return omega[:n] / (2.0 * math.pi), phi[:, :n].copy()

    def damping_matrix(self, zeta=None) -> np.ndarray:
        """Modal damping matrix ``C = M Phi diag(2 zeta omega) Phi^T M`` over all modes.

        Parameters
        ----------
        zeta : float or array_like of shape (n_dof,), optional
            Damping ratio per mode; default ``spec.damping``.

        Returns
        -------
        C : ndarray, shape (n_dof, n_dof)
            Damping, N s/m (N m s/rad on slope rows), symmetric positive semidefinite.
        """
        omega, phi = self._eig()
        zeta = self.spec.damping if zeta is None else zeta
        z = np.broadcast_to(np.asarray(zeta, dtype=float), omega.shape)
        if np.any(~np.isfinite(z)) or np.any(z < 0.0):
            raise ModelError(f"damping_matrix: zeta must be finite and >= 0, got {zeta!r}")
        mp = self.M @ phi
        C = (mp * (2.0 * z * omega)[None, :]) @ mp.T
        return (C + C.T) / 2.0

    def with_tip(self, mass: float = 0.0, k: float = 0.0) -> BeamFE:
        """A new model with a point mass and/or a spring to ground at the tip.

        Parameters
        ----------
        mass : float
            Point mass on the tip displacement, kg (>= 0).
        k : float
            Translational spring from the tip to ground, N/m (>= 0).

        Returns
        -------
        BeamFE
            Loads accumulate: ``tip_mass`` and ``tip_k`` hold the totals.
        """
        for name, value in (("mass", mass), ("k", k)):
            if not (math.isfinite(value) and value >= 0.0):
                raise ModelError(f"with_tip: {name} must be finite and >= 0, got {value!r}")
        M = np.array(self.M)
        K = np.array(self.K)
        M[self.tip, self.tip] += mass
        K[self.tip, self.tip] += k
        return replace(self, M=M, K=K, tip_mass=self.tip_mass + mass, tip_k=self.tip_k + k)

    # ------------------------------------------------------------------ statics
    def static_solve(self, B: np.ndarray) -> np.ndarray:
        """Static displacements ``K^-1 B``.

        Parameters
        ----------
        B : ndarray, shape (n_dof,) or (n_dof, m)
            Loads (N on ``w`` rows, N m on ``psi`` rows).

        Returns
        -------
        ndarray, same shape as ``B``
            Displacements (m) and slopes (rad).
        """
        B = np.asarray(B, dtype=float)
        D = self._scale if B.ndim == 1 else self._scale[:, None]
        return D * scipy.linalg.cho_solve(self._chol, D * B)

    def static_tip_matrix(self) -> np.ndarray:
        """Static tip responses in Smits & Choi's layout, all segments driven together.

        Returns
        -------
        G : ndarray, shape (3, 3)
            Rows: tip slope (rad), tip deflection (m), total charge (C); columns: per tip moment
            (N m), per tip force (N), per volt (V). Symmetric (reciprocity); ``G[2, 2]`` is the
            free capacitance.
        """
        theta = self.Theta.sum(axis=1)
        B = np.zeros((self.n_dof, 3))
        B[self.tip_rot, 0] = 1.0
        B[self.tip, 1] = 1.0
        B[:, 2] = theta
        X = self.static_solve(B)
        G = np.empty((3, 3))
        G[0] = X[self.tip_rot]
        G[1] = X[self.tip]
        G[2] = theta @ X
        G[2, 2] += self.Cp.sum()
        return G

    def static_compliance(self) -> float:
        """Tip deflection per tip force, m/N."""
        e = np.zeros(self.n_dof)
        e[self.tip] = 1.0
        return float(self.static_solve(e)[self.tip])

    def deflection_per_volt(self) -> float:
        """Free tip deflection per volt on all segments, m/V (> 0, see the sign conventions)."""
        return float(self.static_solve(self.Theta.sum(axis=1))[self.tip])

    def blocked_force_per_volt(self) -> float:
        """Force on a rigid stop holding the tip at ``w = 0`` (slope free), per volt, N/V.

        Equals ``deflection_per_volt() / static_compliance()``; it has the sign of the free
        motion (Smits & Choi's ``F_b``); the stop applies minus this value to the beam.
        """
        return self.deflection_per_volt() / self.static_compliance()

    def free_capacitance_matrix(self) -> np.ndarray:
        """Stress-free static capacitance between the segment ports, F.

        Returns
        -------
        C : ndarray, shape (n_seg, n_seg)
            ``diag(Cp) + Theta^T K^-1 Theta``: charge on each segment per volt on each segment.
        """
        C = self.Theta.T @ self.static_solve(self.Theta)
        C = (C + C.T) / 2.0
        C[np.diag_indices_from(C)] += self.Cp
        return C

    def capacitance(self) -> float:
        """Stress-free static capacitance of all segments in parallel, F."""
        return float(self.free_capacitance_matrix().sum())
