"""Plain numpy/scipy twins of the electromagnetic actuator and the Dot pin.

The equations are written here a second time, straight from the physics (not from the
``HybridBuilder`` forms the plants use), and stepped with ``scipy.linalg.expm`` per substep with
the contact/latch/stop state decided from the physical conditions at the start of each substep
(first-order switching, what ``HybridGroup(..., levels=0)`` does).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

__all__ = ["em_matrices", "em_simulate", "dot_simulate"]


def em_matrices(p, contact: bool):
    """``A, B, e`` of the EM plant, state ``(i, x, v, y, w, f_1..f_n)``, inputs ``(u, F_p)``.

    ``p``: an :class:`rtctl.plant.em.EMPlant` (only its plain parameters are read).
    """
    R, L, K = p.resistance, p.inductance, p.force_constant
    m, k, c = p.moving_mass, p.stiffness, p.damping
    f = p.finger
    nb = f.n_branches if f is not None else 0
    n = 3 + (2 + nb if f is not None else 0)
    A = np.zeros((n, n))
    B = np.zeros((n, 2))
    e = np.zeros(n)
    A[0, 0], A[0, 2], B[0, 0] = -R / L, -K / L, 1.0 / L
    A[1, 2] = 1.0
    A[2, 0], A[2, 1], A[2, 2] = K / m, -k / m, -c / m
    if f is not None:
        ms = f.mass
        A[3, 4] = 1.0
        A[4, 3] = -f.k0 / ms
        A[4, 5:] = -1.0 / ms
        B[4, 1] = -1.0 / ms
        e[4] = f.k0 * p.skin.surface / ms     # the tissue spring rests at the skin surface
        for j, (kj, tj) in enumerate(f.branches):
            A[5 + j, 4] = kj
            A[5 + j, 5 + j] = -1.0 / tj
        if contact:
            kc, cc = p.skin.k_contact, p.skin.c
            # F_c = kc (x - y) + cc (v - w): pushes the pin down and the skin up
            fc = np.zeros(n)
            fc[1], fc[3], fc[2], fc[4] = kc, -kc, cc, -cc
            A[2] -= fc / m
            A[4] += fc / ms
    return A, B, e


def _contact_force(p, z):
    if p.finger is None:
        return 0.0, False
    x, v, y, w = z[1], z[2], z[3], z[4]
    f = p.skin.k_contact * (x - y) + p.skin.c * (v - w)
    on = (x - y) > 0.0 and (f > 0.0 or p.skin.c == 0.0)
    return (f if on else 0.0), on


def _step_cache(p, fs, substeps, builder, keys):
    h = 1.0 / (fs * substeps)
    out = {}
    for key in keys:
        A, B, e = builder(p, key)
        n, m = B.shape
        M = np.zeros((n + m + 1, n + m + 1))
        M[:n, :n], M[:n, n:n + m], M[:n, -1] = A, B, e
        out[key] = expm(M * h)[:n]
    return out


def em_simulate(p, fs, drive, x0=None, substeps=2):
    """Run one EM channel over ``drive`` (V, shape (n_samples,)) at the plant's preload.

    Returns
    -------
    truth : ndarray, shape (4, n_samples)
        Height, velocity, contact force, voltage (outputs before each sample's update).
    current : ndarray, shape (n_samples,)
    """
    steps = _step_cache(p, fs, substeps, em_matrices, (False, True))
    n = 3 + (2 + p.finger.n_branches if p.finger is not None else 0)
    z = np.zeros(n) if x0 is None else np.array(x0, dtype=float)
    preload = p.preload
    truth = np.zeros((4, drive.size))
    cur = np.zeros(drive.size)
    for k, u in enumerate(drive):
        fc, _ = _contact_force(p, z)
        truth[:, k] = z[1], z[2], fc, u
        cur[k] = z[0]
        for _ in range(substeps):
            _, on = _contact_force(p, z)
            z = steps[on] @ np.concatenate([z, [u, preload, 1.0]])
    return truth, cur


def dot_simulate(plant, fs, drive, preload=0.0, x0=None, substeps=2):
    """Run one Dot pin over ``drive`` (V, shape (n_samples,)) with first-order switching.

    The coil voltage, latch side, end stops and contact are decided from the physics at the
    start of each substep; the per-mode matrices come from :func:`dot_matrices`.

    Returns
    -------
    truth : ndarray, shape (4, n_samples)
    """
    cache = {}
    h = 1.0 / (fs * substeps)
    n = plant.n_states
    z = plant.y0(preload=preload) if x0 is None else np.array(x0, dtype=float)
    truth = np.zeros((4, drive.size))
    for k, u in enumerate(drive):
        key = dot_mode(plant, z, u)
        truth[:, k] = z[1], z[2], dot_finger_force(plant, z, key), dot_coil_voltage(plant, u)
        for _ in range(substeps):
            key = dot_mode(plant, z, u)
            if key not in cache:
                A, b = dot_matrices(plant, key, preload)
                M = np.zeros((n + 1, n + 1))
                M[:n, :n], M[:n, n] = A, b
                cache[key] = expm(M * h)[:n]
            z = cache[key] @ np.concatenate([z, [1.0]])
    return truth


def dot_coil_voltage(plant, u):
    half = 0.5 * plant.supply
    return plant.supply if u > half else (-plant.supply if u < -half else 0.0)


def dot_mode(plant, z, u):
    """``(coil voltage, latch up?, bottom stop?, top stop?, contact?)`` at state ``z``."""
    x, v = z[1], z[2]
    h = plant.travel
    ks, cs = plant.stop_stiffness, plant.stop_damping
    bottom = (-x > 0.0) and (ks * (-x) + cs * (-v) > 0.0)
    top = (x - h > 0.0) and (ks * (x - h) + cs * v > 0.0)
    contact = False
    if plant.finger is not None:
        y, w = z[3], z[4]
        gap = x - y
        contact = gap > 0.0 and plant.skin.k_contact * gap + plant.skin.c * (v - w) > 0
    return (dot_coil_voltage(plant, u), x - 0.5 * h > 0.0, bottom, top, contact)


def dot_finger_force(plant, z, key):
    if not key[4]:
        return 0.0
    return plant.skin.k_contact * (z[1] - z[3]) + plant.skin.c * (z[2] - z[4])


def dot_matrices(plant, key, preload):
    """``A`` and the constant vector ``b`` of the Dot pin in mode ``key`` (``x' = A x + b``).

    State ``(i, x, v[, y, w, f_1..f_n])``; the coil voltage and the preload are constants of a
    mode here (the drive is held over a sample, the preload over a run).
    """
    vc, up, bottom, top, contact = key
    R, L, K = plant.resistance, plant.inductance, plant.force_constant
    m, c = plant.mass, plant.damping
    n = plant.n_states
    A = np.zeros((n, n))
    b = np.zeros(n)
    A[0, 0], A[0, 2], b[0] = -R / L, -K / L, vc / L
    A[1, 2] = 1.0
    A[2, 0], A[2, 2] = K / m, -c / m
    # the latch pulls towards the nearer end: a constant force, sign by the half of the travel
    b[2] = (plant.latch_force if up else -plant.latch_force) / m
    ks, cs, h = plant.stop_stiffness, plant.stop_damping, plant.travel
    if bottom:   # F = ks (-x) + cs (-v) upwards
        A[2, 1] -= ks / m
        A[2, 2] -= cs / m
    if top:      # F = ks (x - h) + cs v downwards
        A[2, 1] -= ks / m
        A[2, 2] -= cs / m
        b[2] += ks * h / m
    f = plant.finger
    if f is not None:
        ms = f.mass
        A[3, 4] = 1.0
        A[4, 3] = -f.k0 / ms
        A[4, 5:] = -1.0 / ms
        b[4] = (f.k0 * plant.skin.surface - preload) / ms
        for j, (kj, tj) in enumerate(f.branches):
            A[5 + j, 4] = kj
            A[5 + j, 5 + j] = -1.0 / tj
        if contact:
            kc, cc = plant.skin.k_contact, plant.skin.c
            fc = np.zeros(n)
            fc[1], fc[3], fc[2], fc[4] = kc, -kc, cc, -cc
            A[2] -= fc / m
            A[4] += fc / ms
    return A, b
