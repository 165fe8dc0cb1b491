"""Actuator model facts for ``rtctl model``: natural frequencies and static tip values."""

from __future__ import annotations

from rtctl.plant.beam import BeamFE

__all__ = ["model_facts"]


def model_facts(fe: BeamFE, tip_mass: float = 0.0, tip_k: float = 0.0, n: int = 4) -> dict:
    """Natural frequencies (free and tip-loaded) and static tip facts of a beam model.

    Parameters
    ----------
    fe : BeamFE
        The beam on its support, without the finger load.
    tip_mass : float
        Point mass at the tip for the loaded frequencies, kg.
    tip_k : float
        Spring from the tip to ground for the loaded frequencies, N/m.
    n : int
        Number of natural frequencies to report.

    Returns
    -------
    dict
        ``natural_frequencies_hz`` (list of n floats, unloaded), ``loaded_natural_frequencies_hz``
        (list of n floats, with ``tip_mass`` and ``tip_k``), and, at the tip of the unloaded beam
        with all segments driven together: ``static_compliance_m_per_n`` (m/N),
        ``deflection_per_volt_m`` (m/V), ``blocked_force_per_volt_n`` (N/V, force on a rigid
        stop at the tip) and ``capacitance_f`` (stress-free, F).

    Examples
    --------
    >>> from rtctl.plant.beam import BeamSpec, Layer, build_beam
    >>> from rtctl.plant.materials import material
    >>> pzt = material("PZT-5A")
    >>> spec = BeamSpec(15e-3, 1.5e-3, (Layer(pzt, 0.3e-3), Layer(pzt, 0.3e-3)),
    ...                 "parallel", (0.5, 0.5), 0.01)
    >>> facts = model_facts(build_beam(spec), tip_k=300.0)
    >>> sorted(facts)[:2]
    ['blocked_force_per_volt_n', 'capacitance_f']
    """
    free, _ = fe.modes(n)
    loaded, _ = fe.with_tip(mass=tip_mass, k=tip_k).modes(n)
    return {
        "natural_frequencies_hz": [float(f) for f in free],
        "loaded_natural_frequencies_hz": [float(f) for f in loaded],
        "static_compliance_m_per_n": fe.static_compliance(),
        "deflection_per_volt_m": fe.deflection_per_volt(),
        "blocked_force_per_volt_n": fe.blocked_force_per_volt(),
        "capacitance_f": fe.capacitance(),
    }


def loaded_natural_frequencies(fe: BeamFE, finger, n: int = 4) -> list[float]:
    """Natural frequencies of the beam under a generalized Maxwell finger, Hz.

    The full finite-element model (every DOF, modal damping) with the skin mass at the tip and
    the finger's branches as extra first-order states; electrodes voltage-driven (short-circuit
    for the dynamics). Each oscillatory eigenvalue pair gives ``|lambda| / 2 pi``, the undamped
    natural frequency of a damped mode (exact for modal damping; the Maxwell branches make the
    load frequency dependent, so this is the frequency at which that mode rings under the finger).
    The real eigenvalues are the finger's relaxation and are left out.

    Parameters
    ----------
    fe : BeamFE
        The beam without finger.
    finger : MaxwellLoad
        ``mass``, ``k0`` and ``branches`` ((k, tau) pairs).
    n : int
        How many frequencies.
    """
    import numpy as np
    import scipy.linalg as sla

    loaded = fe.with_tip(mass=finger.mass, k=finger.k0)
    M, K = np.asarray(loaded.M), np.asarray(loaded.K)
    C = np.asarray(fe.damping_matrix())
    nd = M.shape[0]
    k = np.array([b[0] for b in finger.branches], dtype=float)
    tau = np.array([b[1] for b in finger.branches], dtype=float)
    nb = k.size
    e = np.zeros(nd)
    e[fe.tip] = 1.0
    # Scale each DOF by its static flexibility so translations (m) and rotations (rad) weigh alike.
    s = 1.0 / np.sqrt(np.diag(K))
    Ms, Ks, Cs, es = (s[:, None] * M * s), (s[:, None] * K * s), (s[:, None] * C * s), s * e
    Minv_K = sla.solve(Ms, Ks, assume_a="pos")
    Minv_C = sla.solve(Ms, Cs, assume_a="pos")
    Minv_e = sla.solve(Ms, es, assume_a="pos")
    A = np.zeros((2 * nd + nb, 2 * nd + nb))
    A[:nd, nd:2 * nd] = np.eye(nd)
    A[nd:2 * nd, :nd] = -Minv_K
    A[nd:2 * nd, nd:2 * nd] = -Minv_C
    A[nd:2 * nd, 2 * nd:] = -np.outer(Minv_e, np.ones(nb))
    A[2 * nd:, nd:2 * nd] = np.outer(k, es)
    A[2 * nd:, 2 * nd:] = -np.diag(1.0 / tau) if nb else np.zeros((0, 0))
    lam = np.linalg.eigvals(A)
    osc = lam[lam.imag > 1e-9 * np.abs(lam)]
    return [float(f) for f in np.sort(np.abs(osc))[:n] / (2 * np.pi)]
