"""Plain numpy / Python-loop twins of the SMA taxel kernels (``rtctl.plant._sma_kernels``).

Written from the equations in ``rtctl/plant/sma.py`` and ``docs/plants/sma.md``, not from the
kernels: the shell update is vectorized numpy, the pin balance is solved with scipy's
``brentq``, and the group is a per-sample loop in sample-outer order.
"""

import math

import numpy as np
from scipy.optimize import brentq


def modulus(plant, t):
    return float(plant.shear_modulus(t))


def shells_step(gt, s, wq, kappa, delta, g, tl, tu, w):
    """Implicit-Euler shell step: returns (force N, new strains)."""
    gam = s * kappa * delta
    lo = np.maximum(0.0, gam - tl / g)
    hi = np.maximum(0.0, gam - tu / g)
    target = np.clip(gt, lo, hi)
    gn = gt + w * (target - gt)
    return float(np.sum(wq * g * (gam - gn))), gn


def pin_step(plant, gtu, gtl, t_up, t_low, fe, w):
    """Pin height, net spring force and new strains after one implicit-Euler step (brentq)."""
    gu, gl = modulus(plant, t_up), modulus(plant, t_low)
    tlu, tll = float(plant.tau_load(t_up)), float(plant.tau_load(t_low))
    tuu, tul = float(plant.tau_unload(t_up)), float(plant.tau_unload(t_low))
    d0, kap = plant.delta0, plant.kappa

    def net(x):
        pu, _ = shells_step(gtu, plant.s, plant.wq, kap, d0 - x, gu, tlu, tuu, w)
        pl, _ = shells_step(gtl, plant.s, plant.wq, kap, d0 + x, gl, tll, tul, w)
        return pu - pl

    a, b = -plant.stop_down, plant.stop_up
    if net(a) - fe <= 0.0:
        x = a
    elif net(b) - fe >= 0.0:
        x = b
    else:
        x = brentq(lambda z: net(z) - fe, a, b, xtol=1e-16, rtol=1e-15, maxiter=500)
    _, gu_new = shells_step(gtu, plant.s, plant.wq, kap, d0 - x, gu, tlu, tuu, w)
    _, gl_new = shells_step(gtl, plant.s, plant.wq, kap, d0 + x, gl, tll, tul, w)
    return x, net(x), gu_new, gl_new


def group_run(plant, fs, k, drive, f_ext, crossbar=False, rows=1, slot=1):
    """Sample-by-sample group simulation from the installed state.

    Returns truth ``(nc, 4, n)``, final temperatures ``(nc, 2)``, hottest temperature and
    total power per sample ``(2, n)``.
    """
    nc, n = drive.shape
    cols = nc // rows
    h_mech = k / fs
    w = 1.0 if plant.relax_time == 0 else h_mech / (h_mech + plant.relax_time)
    tau_th = plant.heat_capacity / (plant.h * plant.area)
    a = math.exp(-1.0 / (fs * tau_th))
    gain = 1.0 / (plant.resistance * plant.h * plant.area)   # degC per V^2 at steady state
    temp = np.full((nc, 2), plant.t_ambient)
    gi = plant.installed_strains()
    gts = [[gi.copy(), gi.copy()] for _ in range(nc)]
    xp = np.zeros(nc)
    xc = np.zeros(nc)
    netc = np.zeros(nc)
    truth = np.zeros((nc, 4, n))
    probe = np.zeros((2, n))
    cm = 0
    for t in range(n):
        active = (t // slot) % rows
        v_applied = drive[:, t].copy()
        if crossbar:
            v_applied[np.arange(nc) // cols != active] = 0.0
        v_applied[((v_applied > 0) & (temp[:, 0] >= plant.t_cut))
                  | ((v_applied < 0) & (temp[:, 1] >= plant.t_cut))] = 0.0
        p_up = np.where(v_applied > 0, v_applied**2, 0.0)
        p_low = np.where(v_applied < 0, v_applied**2, 0.0)
        temp[:, 0] = plant.t_ambient + gain * p_up + (temp[:, 0] - plant.t_ambient - gain * p_up) * a
        temp[:, 1] = plant.t_ambient + gain * p_low + (temp[:, 1] - plant.t_ambient - gain * p_low) * a
        cm += 1
        if cm == k:
            cm = 0
            for ch in range(nc):
                fe = max(f_ext[ch], 0.0)
                x, net, g0, g1 = pin_step(plant, gts[ch][0], gts[ch][1], temp[ch, 0], temp[ch, 1],
                                          fe, w)
                gts[ch] = [g0, g1]
                xp[ch], xc[ch], netc[ch] = xc[ch], x, net
        for ch in range(nc):
            truth[ch, 0, t] = xp[ch] + cm / k * (xc[ch] - xp[ch])
            truth[ch, 1, t] = (xc[ch] - xp[ch]) * fs / k
            fe = max(f_ext[ch], 0.0)
            truth[ch, 2, t] = min(fe, max(netc[ch], 0.0)) if xc[ch] <= -plant.stop_down else fe
            truth[ch, 3, t] = v_applied[ch]
        probe[0, t] = temp.max()
        probe[1, t] = np.sum(v_applied**2) / plant.resistance
    return truth, temp, probe
