"""Closed forms for the bimorph finite-element tests (plain numpy/scipy, no rtctl model code).

Sources (see docs/references.md):

* Euler-Bernoulli cantilever roots of ``1 + cos l cosh l = 0`` and ``f_n = l_n^2/(2 pi L^2)
  sqrt(EI/(rho A))``; tip force/moment deflections; tip spring and tip mass characteristic
  equations.
* Smits & Choi (1991) table for a homogeneous two-layer bimorph, series as printed, parallel with
  the V column and the charge row doubled and the capacitance x4; blocked force.
* :func:`laminate`: a continuum derivation written here, independent of the model's neutral-axis
  formulation: classical laminate theory about the *bottom face* (axial strain and curvature as
  unknowns, zero axial force), layer free strains ``d31 V_i / t_i``, layer charges from
  ``D3 = e31 S1 + eps33S E3``, and for ``series`` floating inter-layer electrodes whose charge
  balances (all layers carry the same charge, voltages add up to the port voltage).

Only *readings* of a spec's data are used (dimensions, layer materials); nothing is imported from
``rtctl.plant.beam`` beyond the spec classes the caller passes in.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq

EPS0 = 8.8541878128e-12  # F/m, CODATA 2018

#: Roots of 1 + cos(l) cosh(l) = 0 (docs/references.md).
CANTILEVER_ROOTS = np.array([1.8751040687, 4.6940911330, 7.8547574382, 10.995540735])

#: Tip-spring limit K -> inf (clamped-pinned, docs/references.md) and tip-mass root at mu = 1.
CLAMPED_PINNED_ROOT = 3.926602
TIP_MASS_MU1_ROOT = 1.247917


def cantilever_frequencies(EI: float, rhoA: float, length: float, n: int = 4) -> np.ndarray:
    """Clamped-free natural frequencies ``l_n^2 / (2 pi L^2) sqrt(EI / rhoA)``, Hz, shape (n,)."""
    return CANTILEVER_ROOTS[:n] ** 2 / (2.0 * math.pi * length**2) * math.sqrt(EI / rhoA)


def loaded_char(l: float, K: float = 0.0, mu: float = 0.0) -> float:
    """Cantilever with a tip spring ``K = k L^3/EI`` and tip mass ``mu = m/(rho A L)``.

    ``l^3 (1 + cos l cosh l) + (K - mu l^4) (sin l cosh l - cos l sinh l)``: the REFERENCES
    tip-spring equation with the spring replaced by its dynamic stiffness ``k - m omega^2``
    (``omega^2 = l^4 EI / (rho A L^4)``); at ``K = 0`` dividing by ``l^3`` gives the REFERENCES
    tip-mass equation. Scaled by ``cosh l`` to stay O(1).
    """
    c, s, ch, sh = math.cos(l), math.sin(l), math.cosh(l), math.sinh(l)
    return (l**3 * (1.0 + c * ch) + (K - mu * l**4) * (s * ch - c * sh)) / ch


def loaded_root(K: float = 0.0, mu: float = 0.0, which: int = 0, l_max: float = 20.0) -> float:
    """The ``which``-th positive root of :func:`loaded_char` (0: first), found by brentq."""
    grid = np.linspace(1e-3, l_max, 20001)
    vals = np.array([loaded_char(x, K, mu) for x in grid])
    idx = np.nonzero(np.sign(vals[:-1]) * np.sign(vals[1:]) < 0)[0]
    a = grid[idx[which]]
    b = grid[idx[which] + 1]
    return brentq(loaded_char, a, b, args=(K, mu), xtol=1e-15, rtol=1e-14)


def _homogeneous(spec):
    layers = spec.layers
    if len(layers) != 2 or layers[0] != layers[1]:
        raise ValueError("Smits & Choi's table needs two identical layers")
    return layers[0].material, 2.0 * layers[0].thickness


def closed_forms(spec) -> dict:
    """Smits & Choi (1991) table for a homogeneous two-layer bimorph, signed as printed.

    Parameters
    ----------
    spec : BeamSpec
        Two identical piezo layers; ``length``, ``width``, ``connection`` are read.

    Returns
    -------
    dict
        ``table``: ndarray (3, 3), rows tip rotation (rad), tip deflection (m), charge (C);
        columns per tip moment (N m), tip force (N), volt (V), with ``d31`` signed as printed.
        ``blocked_force`` (N/V), ``capacitance`` (free, F, = table[2, 2]), ``EI`` (N m^2),
        ``rhoA`` (kg/m), ``frequencies_hz`` (first four, Hz).
    """
    mat, h = _homogeneous(spec)
    L, w = spec.length, spec.width
    s11, d31 = 1.0 / mat.E, mat.d31
    k31_sq = d31**2 * mat.E / (EPS0 * mat.eps33T)
    par = spec.connection == "parallel"
    gv = 2.0 if par else 1.0  # V column and charge row
    gc = 4.0 if par else 1.0  # capacitance
    table = np.array(
        [
            [12 * s11 * L / (w * h**3), 6 * s11 * L**2 / (w * h**3), gv * 3 * d31 * L / h**2],
            [6 * s11 * L**2 / (w * h**3), 4 * s11 * L**3 / (w * h**3), gv * 3 * d31 * L**2 / (2 * h**2)],
            [gv * 3 * d31 * L / h**2, gv * 3 * d31 * L**2 / (2 * h**2),
             gc * EPS0 * mat.eps33T * w * L * (1 - k31_sq / 4) / h],
        ]
    )
    EI = mat.E * w * h**3 / 12.0
    rhoA = mat.rho * w * h
    return {
        "table": table,
        "blocked_force": gv * 3 * d31 * w * h / (8 * s11 * L),
        "capacitance": table[2, 2],
        "EI": EI,
        "rhoA": rhoA,
        "frequencies_hz": cantilever_frequencies(EI, rhoA, L),
    }


def laminate(spec, length: float | None = None) -> dict:
    """Static tip responses of a general layered cantilever with one electrode, from continuum theory.

    Poling follows rtctl's documented convention: a layer whose centroid lies above the neutral
    axis has free strain ``-|d31| V_i / t_i`` for a positive port voltage (it contracts), one
    below has ``+|d31| V_i / t_i``, so a positive voltage raises the tip.

    Parameters
    ----------
    spec : BeamSpec
    length : float, optional
        Cantilever length, m (default ``spec.length``).

    Returns
    -------
    dict
        ``table`` (3, 3) in :func:`closed_forms` layout, ``EI`` (about the neutral axis from
        ``D - B^2/A``, N m^2), ``rhoA`` (kg/m), ``neutral_axis`` (m above the bottom face).
    """
    L = spec.length if length is None else length
    w = spec.width
    t = np.array([ly.thickness for ly in spec.layers])
    E = np.array([ly.material.E for ly in spec.layers])
    rho = np.array([ly.material.rho for ly in spec.layers])
    d31 = np.array([ly.material.d31 for ly in spec.layers])
    eps_t = np.array([ly.material.eps33T for ly in spec.layers])
    zt = np.cumsum(t)
    zb = zt - t
    zbar = (zt + zb) / 2.0
    A = np.sum(E * w * t)
    B = np.sum(E * w * t * zbar)
    D = np.sum(E * w * (zt**3 - zb**3) / 3.0)
    z_na = B / A
    p = np.nonzero(d31 != 0.0)[0]
    sigma = -np.sign(zbar[p] - z_na) * np.sign(d31[p])  # poling sign per piezo layer
    e31 = sigma * d31[p] * E[p]  # signed e31 in the port-voltage frame
    eps_s = EPS0 * eps_t[p] - d31[p] ** 2 * E[p]
    c = eps_s * w / t[p]  # F/m per layer
    P = e31 * w  # axial force of free strain per volt across the layer: E w t (d V / t)
    R = e31 * w * zbar[p]  # its moment about the bottom face
    Gi = np.linalg.inv(np.array([[A, B], [B, D]]))
    # integral over x of [eps0, kappa'] = Gi @ [P.V L, R.V L - IM]; IM = int M_b dx.
    row_e = (Gi[0, 0] * P + Gi[0, 1] * R) * L
    row_k = (Gi[1, 0] * P + Gi[1, 1] * R) * L
    # charge of layer i: e31_i w (int eps0 + zbar_i int kappa') + c_i L V_i
    Hq = np.outer(e31 * w, row_e) + np.outer(e31 * w * zbar[p], row_k) + np.diag(c * L)
    hm = -(e31 * w) * (Gi[0, 1] + zbar[p] * Gi[1, 1])  # per unit IM
    n_p = p.size

    table = np.empty((3, 3))
    for col, (M0, F, V) in enumerate(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))):
        IM = M0 * L + F * L**2 / 2.0  # int_0^L M_b dx, M_b(x) = M0 + F (L - x)
        IW = M0 * L**2 / 2.0 + F * L**3 / 3.0  # int_0^L (L - x) M_b dx
        if spec.connection == "parallel":
            Vv = np.full(n_p, V)
            Q = float(np.sum(Hq @ Vv + hm * IM))
        else:
            # unknowns [V_1..V_n, Q]: Q_i(V) = Q for all i, sum V_i = V
            S = np.zeros((n_p + 1, n_p + 1))
            S[:n_p, :n_p] = Hq
            S[:n_p, n_p] = -1.0
            S[n_p, :n_p] = 1.0
            rhs = np.concatenate((-hm * IM, [V]))
            sol = np.linalg.solve(S, rhs)
            Vv, Q = sol[:n_p], float(sol[n_p])
        int_k = row_k @ Vv - Gi[1, 1] * IM  # int kappa' dx, w'' = -kappa'
        int_lk = row_k @ Vv * L / 2.0 - Gi[1, 1] * IW  # int (L - x) kappa' dx
        table[:, col] = (-int_k, -int_lk, Q)
    return {
        "table": table,
        "EI": D - B * B / A,
        "rhoA": float(np.sum(rho * w * t)),
        "neutral_axis": z_na,
    }
