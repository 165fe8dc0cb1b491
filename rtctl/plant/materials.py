"""Piezoelectric and passive layer materials for the bimorph model.

A material is the four numbers a thin, uniaxially stressed beam layer needs: the short-circuit
Young's modulus ``E = 1/s11^E``, the transverse charge constant ``d31``, the relative permittivity
at constant stress ``eps33T`` and the density. A passive layer (shim, electrode, glue) is a
material with ``d31 = 0``.

Built-in values
---------------
``PZT-5A`` and ``PZT-5H``: Erturk & Inman, *Piezoelectric Energy Harvesting* (2011), Table E.1
(``s11^E``, ``d31``, ``eps33T/eps0``, ``rho``), as copied in ``docs/references.md``.

``PVDF``: Measurement Specialties (MEAS) *Piezo Film Sensors Technical Manual*, table of typical
properties of uniaxially stretched film: ``d31 = 23 pC/N``, ``eps33T/eps0 = 12`` (12-13),
``rho = 1780 kg/m^3``, Young's modulus 2-4 GPa, of which we take ``E = 2.5 GPa``. Tzou's PVDF
bimorph benchmark uses ``E = 2 GPa`` (``e31 = 0.046 C/m^2``); pass ``{"E": 2e9}`` as an override
to reproduce it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from scipy.constants import epsilon_0

from rtctl.errors import ModelError

__all__ = ["EPS0", "Material", "BUILTIN", "material"]

#: Vacuum permittivity, F/m (CODATA, from scipy.constants).
EPS0 = float(epsilon_0)


@dataclass(frozen=True)
class Material:
    """Linear properties of one beam layer.

    Parameters
    ----------
    E : float
        Young's modulus at constant electric field, ``1/s11^E``, Pa.
    d31 : float
        Transverse piezoelectric charge constant, m/V (= C/N). Zero for a passive layer.
        Its sign does not change the bending direction: the model chooses each layer's poling
        so that every layer helps (see :mod:`rtctl.plant.beam`).
    eps33T : float
        Relative permittivity at constant stress (dimensionless, > 0).
    rho : float
        Density, kg/m^3.

    Raises
    ------
    ModelError
        If a value is not finite, ``E``, ``eps33T`` or ``rho`` is not positive, or the coupling
        ``k31^2`` is not below 1 (the clamped permittivity would not be positive).

    Examples
    --------
    >>> m = Material(E=1 / 16.4e-12, d31=-171e-12, eps33T=1700, rho=7750)
    >>> round(m.k31_sq, 3)
    0.118
    """

    E: float
    d31: float
    eps33T: float
    rho: float

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise ModelError(f"Material.{f.name} must be a number, got {value!r}") from None
            if not math.isfinite(value):
                raise ModelError(f"Material.{f.name} must be finite, got {value!r}")
            object.__setattr__(self, f.name, value)
        for name, unit in (("E", "Pa"), ("eps33T", "(relative)"), ("rho", "kg/m^3")):
            if getattr(self, name) <= 0.0:
                raise ModelError(
                    f"Material.{name} must be > 0 {unit}, got {getattr(self, name)!r}"
                )
        if self.k31_sq >= 1.0:
            raise ModelError(
                f"Material coupling k31^2 = d31^2 E / (eps0 eps33T) = {self.k31_sq:.3g} must be "
                f"below 1 (d31={self.d31!r}, E={self.E!r}, eps33T={self.eps33T!r}); check units "
                "(d31 in m/V, E in Pa, eps33T relative)"
            )

    @property
    def is_piezo(self) -> bool:
        """True if the layer is piezoelectric (``d31 != 0``)."""
        return self.d31 != 0.0

    @property
    def e31(self) -> float:
        """Piezoelectric stress constant ``e31 = d31 E`` of a uniaxially stressed layer, C/m^2."""
        return self.d31 * self.E

    @property
    def k31_sq(self) -> float:
        """Squared transverse coupling factor ``k31^2 = d31^2 E / (eps0 eps33T)`` (dimensionless)."""
        return self.d31**2 * self.E / (EPS0 * self.eps33T)

    @property
    def eps33S(self) -> float:
        """Absolute permittivity of a beam layer at constant strain, F/m.

        ``eps0 eps33T (1 - k31^2)``: clamped along the beam axis, stress-free across it, which is
        the permittivity a thin uniaxially stressed layer has (not the bulk ``eps33^S``).
        """
        return EPS0 * self.eps33T * (1.0 - self.k31_sq)


BUILTIN: dict[str, Material] = {
    "PZT-5A": Material(E=1.0 / 16.4e-12, d31=-171e-12, eps33T=1700.0, rho=7750.0),
    "PZT-5H": Material(E=1.0 / 16.5e-12, d31=-274e-12, eps33T=3400.0, rho=7500.0),
    "PVDF": Material(E=2.5e9, d31=23e-12, eps33T=12.0, rho=1780.0),
}

_KEYS = tuple(f.name for f in fields(Material))


def material(name: str, overrides: dict | None = None) -> Material:
    """Resolve a material by name, with optional partial or full overrides.

    Parameters
    ----------
    name : str
        A key of :data:`BUILTIN` (``"PZT-5A"``, ``"PZT-5H"``, ``"PVDF"``) or any other name for a
        custom material, which then needs a full table in ``overrides``.
    overrides : dict or None
        Values for some of ``E`` (Pa), ``d31`` (m/V), ``eps33T`` (relative), ``rho`` (kg/m^3).
        For a built-in they replace the built-in values; for a custom name all four are needed.

    Returns
    -------
    Material

    Raises
    ------
    ModelError
        Unknown keys in ``overrides``; a custom name whose table misses keys (the message lists
        them); or a value the :class:`Material` checks reject.

    Examples
    --------
    >>> material("PZT-5A").rho
    7750.0
    >>> round(material("PVDF", {"E": 2e9}).e31, 6)
    0.046
    >>> material("brass", {"E": 100e9, "d31": 0.0, "eps33T": 1.0, "rho": 8500.0}).is_piezo
    False
    """
    table = dict(overrides or {})
    unknown = sorted(set(table) - set(_KEYS))
    if unknown:
        raise ModelError(
            f"material {name!r}: unknown keys {unknown}; allowed are {list(_KEYS)}"
        )
    if name in BUILTIN:
        base = BUILTIN[name]
        values = {k: table.get(k, getattr(base, k)) for k in _KEYS}
    else:
        missing = [k for k in _KEYS if k not in table]
        if missing:
            raise ModelError(
                f"material {name!r} is not built in ({', '.join(BUILTIN)}); a custom material "
                f"needs a full table, missing keys: {missing}"
            )
        values = table
    try:
        return Material(**values)
    except ModelError as exc:
        raise ModelError(f"material {name!r}: {exc}") from None
