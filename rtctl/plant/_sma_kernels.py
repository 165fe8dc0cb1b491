"""Numba kernels of the SMA antagonistic taxel group (see ``rtctl.plant.sma``).

Per taxel: two NiTi springs (index 0 = "raise" spring above the pin, 1 = "lower" spring below),
each with a lumped temperature and ``n_shells`` transformation shear strains (one per Gauss
radius of the wire cross-section). Per sample the temperatures advance exactly (exponential of
the linear thermal ODE for a DAC staircase input); every ``k_mech`` samples the pin force balance
is solved by implicit Euler on the transformation strains (safeguarded Newton on a continuous,
strictly decreasing, piecewise-linear residual), and the pin height is output linearly
interpolated between the last two solutions (one mechanical step of lag).

Kernels take only preallocated arrays, allocate nothing, raise nothing.

``fp`` (float parameters) layout, see ``SmaGroup``::

    0 kappa     surface shear strain per metre of deflection, d / (pi D^2 N)
    1 delta0    prestrain of both springs at x = 0, m
    2 g_m, 3 g_a             shear moduli, Pa
    4 ramp_lo, 5 ramp_hi     modulus ramp temperatures (A_s, A_f of the DSC), degC
    6 tau_cr    low-temperature (R/M reorientation) loading stress, Pa
    7 c_m, 8 m_s            loading line tau = c_m (T - m_s), Pa/K, degC
    9 c_a, 10 a_s           unloading line tau = c_a (T - a_s)
    11 alpha    per-sample thermal decay exp(-dt / tau_th)
    12 c_amb    (1 - alpha) T_amb
    13 c_heat   (1 - alpha) / (R h A)  (degC per V^2)
    14 inv_r    1 / R, 1/ohm (power V^2 / R)
    15 w        implicit-Euler weight h_mech / (h_mech + t_relax) (1 = rate independent)
    16 stop_down, 17 stop_up   pin travel to the end stops from x = 0, m
    18 t_max    over-temperature limit, degC
    19 vel_scale  fs / k_mech, 1/s
    20 t_cut    the driver's thermal cutoff: a spring at or above it gets no current, degC
"""

import math

from rtctl._numba import TINY, kernel

STATUS_NONFINITE = 2
STATUS_OVERTEMP = 4

N_FP = 21


@kernel
def shear_modulus(fp, t):
    """Shear modulus at temperature ``t`` (degC): G_M below the ramp, G_A above, linear between."""
    f = (t - fp[4]) / (fp[5] - fp[4])
    f = 0.0 if f < 0.0 else (1.0 if f > 1.0 else f)
    return fp[2] + (fp[3] - fp[2]) * f


@kernel
def tau_load(fp, t):
    """Loading (forward transformation / reorientation) shear stress at ``t``, Pa."""
    a = fp[7] * (t - fp[8])
    return a if a > fp[6] else fp[6]


@kernel
def tau_unload(fp, t):
    """Unloading (reverse transformation) shear stress at ``t``, Pa; never above the loading one."""
    u = fp[9] * (t - fp[10])
    tl = tau_load(fp, t)
    return u if u < tl else tl


@kernel
def spring_eval(gt, s, wq, kappa, delta, g, tl, tu, w, commit):
    """Force and stiffness of one spring after one implicit-Euler step of its shells.

    Shell ``i`` (normalized radius ``s[i]``) has shear strain ``gam = s[i] kappa delta`` and
    transformation strain ``gt[i]``; the admissible band is ``[lo, hi] = [max(0, gam - tl/g),
    max(0, gam - tu/g)]`` (stress between the unloading and loading lines, no negative
    transformation strain). Implicit Euler of ``gt' = (clip(gt, lo, hi) - gt) / t_relax``
    moves an outside ``gt`` the fraction ``w`` of the way to the violated bound.

    Parameters
    ----------
    gt : ndarray, shape (n_shells,)
        Transformation strains at the start of the step (overwritten if ``commit``).
    s, wq : ndarray, shape (n_shells,)
        Gauss radii on [0, 1] and force weights (N per Pa of shell stress).
    kappa, delta : float
        Surface strain per metre, deflection (m).
    g, tl, tu : float
        Shear modulus, loading and unloading stresses (Pa) at the end-of-step temperature.
    w : float
        Implicit-Euler weight in (0, 1].
    commit : bool

    Returns
    -------
    force : float
        Axial spring force, N (pulls the ends together when positive).
    stiffness : float
        d force / d delta, N/m (> 0).
    """
    p = 0.0
    dp = 0.0
    ga = kappa * delta
    for i in range(s.shape[0]):
        ds = s[i] * kappa
        gam = s[i] * ga
        lo = gam - tl / g
        lo = lo if lo > 0.0 else 0.0
        hi = gam - tu / g
        hi = hi if hi > 0.0 else 0.0
        g0 = gt[i]
        gn = g0
        dg = 0.0
        if g0 < lo:
            gn = g0 + w * (lo - g0)
            dg = w * ds
        elif g0 > hi:
            gn = g0 + w * (hi - g0)
            if hi > 0.0:
                dg = w * ds
        p += wq[i] * g * (gam - gn)
        dp += wq[i] * g * (ds - dg)
        if commit:
            # gt relaxes geometrically towards 0 on full recovery: flush before it is subnormal.
            gt[i] = gn if gn > TINY else 0.0
    return p, dp


@kernel
def pin_residual(gtu, gtl, s, wq, fp, x, gu, gl, tlu, tll, tuu, tul, fe, commit):
    """Net upward force on the pin at height ``x`` (N) and its derivative d/dx (N/m, < 0)."""
    kappa = fp[0]
    d0 = fp[1]
    w = fp[15]
    pu, ku = spring_eval(gtu, s, wq, kappa, d0 - x, gu, tlu, tuu, w, commit)
    pl, kl = spring_eval(gtl, s, wq, kappa, d0 + x, gl, tll, tul, w, commit)
    return pu - pl - fe, -ku - kl


@kernel
def solve_pin(gtu, gtl, s, wq, fp, x0, tu_c, tl_c, fe):
    """Implicit-Euler step of one taxel's springs and its pin force balance.

    Finds ``x`` in ``[-stop_down, stop_up]`` with ``P_up(d0 - x) - P_low(d0 + x) = fe`` (else
    the end stop that holds the pin), commits the shells' new transformation strains and
    returns ``(x, net)`` where ``net = P_up - P_low`` at ``x`` (N, the pin's push on whatever
    holds it down). Safeguarded Newton: the residual is continuous, piecewise linear and
    strictly decreasing in ``x``, so a bracket update per evaluation plus bisection when Newton
    leaves the bracket converges in a few steps; NaN inputs end after ``60`` iterations.
    """
    gu = shear_modulus(fp, tu_c)
    gl = shear_modulus(fp, tl_c)
    tlu = tau_load(fp, tu_c)
    tll = tau_load(fp, tl_c)
    tuu = tau_unload(fp, tu_c)
    tul = tau_unload(fp, tl_c)
    a = -fp[16]
    b = fp[17]
    a_known = False
    b_known = False
    x = x0
    if not (x > a):
        x = a
    if not (x < b):
        x = b
    for it in range(60):
        r, dr = pin_residual(gtu, gtl, s, wq, fp, x, gu, gl, tlu, tll, tuu, tul, fe, False)
        if r == 0.0:
            break
        if r > 0.0:
            a = x
            a_known = True
        else:
            b = x
            b_known = True
        if abs(r) < 1e-12 or b - a < 1e-15:
            break
        xn = x - r / dr
        if it >= 30:
            xn = 0.5 * (a + b)   # Newton cycling between linear pieces: plain bisection
        elif xn >= b:
            if not b_known:
                xn = b      # probe the upper stop once: if the residual is still > 0 there, stop
            else:
                xn = 0.5 * (a + b)
        elif xn <= a:
            if not a_known:
                xn = a
            else:
                xn = 0.5 * (a + b)
        if xn == x:
            break
        x = xn
    if not (x > -fp[16]):
        x = -fp[16]
    if not (x < fp[17]):
        x = fp[17]
    r, dr = pin_residual(gtu, gtl, s, wq, fp, x, gu, gl, tlu, tll, tuu, tul, fe, True)
    return x, r + fe


@kernel
def sma_group_process(ip, fp, s, wq, temp, gt, xs, clock, f_ext, probe, drive, sensed, truth):
    """Advance a group of SMA taxels by one block (see ``rtctl.plant.SmaGroup``).

    Parameters
    ----------
    ip : ndarray of int64, shape (6,)
        ``(k_mech, crossbar, slot_samples, n_rows, n_cols, n_shells)``.
    fp : ndarray, shape (N_FP,)
        Float parameters (module docstring).
    s, wq : ndarray, shape (n_shells,)
        Gauss radii and force weights.
    temp : ndarray, shape (n_channels, 2)
        Spring temperatures, degC (raise, lower); updated.
    gt : ndarray, shape (n_channels, 2, n_shells)
        Transformation shear strains; updated.
    xs : ndarray, shape (n_channels, 3)
        Previous and current mechanical solutions of the pin height (m) and the net spring
        force at the current one (N); updated.
    clock : ndarray of int64, shape (2,)
        Samples since the last mechanical solve; samples into the crossbar scan; updated.
    f_ext : ndarray, shape (n_channels,)
        Finger force pressing each pin down, N (negative reads as 0).
    probe : ndarray, shape (2, >= n)
        Written: hottest spring temperature (degC) and total electrical power (W) per sample
        (the first ``probe.shape[1]`` samples of a longer call).
    drive : ndarray, shape (n_channels, n)
        Signed spring voltage request, V: > 0 heats the raise spring, < 0 the lower one.
    sensed : ndarray, shape (0, n)
    truth : ndarray, shape (n_channels, 4, n)
        Written: pin height (m), velocity (m/s), force on the finger (N), applied voltage (V).

    Returns
    -------
    int
        Bit value 2: a state is NaN/Inf; bit value 4: a spring exceeded ``t_max`` in this block.
    """
    k = ip[0]
    xbar = ip[1]
    slot = ip[2]
    n_rows = ip[3]
    n_cols = ip[4]
    nc, n = drive.shape
    alpha = fp[11]
    c_amb = fp[12]
    c_heat = fp[13]
    inv_r = fp[14]
    stop_lo = -fp[16]
    vscale = fp[19]
    n_probe = probe.shape[1] if probe.shape[1] < n else n
    for t in range(n_probe):
        probe[0, t] = -1e300
        probe[1, t] = 0.0
    hot = -1e300
    cm = clock[0]
    cs = clock[1]
    # Channel-outer loops: every row of drive and truth is read and written contiguously; the
    # two clocks are the same for all channels, so each channel replays them from the start.
    for ch in range(nc):
        cm = clock[0]
        cs = clock[1]
        row = ch // n_cols
        tu = temp[ch, 0]
        tl = temp[ch, 1]
        x0 = xs[ch, 0]
        x1 = xs[ch, 1]
        net = xs[ch, 2]
        fe = f_ext[ch]
        fe = fe if fe > 0.0 else 0.0
        for t in range(n):
            v = drive[ch, t]
            if xbar != 0 and row != (cs // slot) % n_rows:
                v = 0.0
            # The driver cuts a spring's current while it is at or above t_cut (decided on
            # the temperature before this sample, as firmware sensing the wire would).
            if (v > 0.0 and tu >= fp[20]) or (v < 0.0 and tl >= fp[20]):
                v = 0.0
            v2 = v * v
            # "not (v <= 0)": a NaN drive heats the raise spring with NaN, so it shows up as
            # a non-finite state instead of vanishing.
            tu = alpha * tu + c_amb + (c_heat * v2 if not (v <= 0.0) else 0.0)
            tl = alpha * tl + c_amb + (c_heat * v2 if v < 0.0 else 0.0)
            cm += 1
            if cm >= k:
                cm = 0
                x, net = solve_pin(gt[ch, 0], gt[ch, 1], s, wq, fp, x1, tu, tl, fe)
                x0 = x1
                x1 = x
            frac = cm / k
            truth[ch, 0, t] = x0 + frac * (x1 - x0)
            truth[ch, 1, t] = (x1 - x0) * vscale
            # At the lower stop the finger also rests on the stop: the pin carries only the
            # springs' net push.
            ff = fe
            if x1 <= stop_lo:
                ff = net if net < fe else fe
                ff = ff if ff > 0.0 else 0.0
            truth[ch, 2, t] = ff
            truth[ch, 3, t] = v
            cs += 1
            if cs >= slot * n_rows:
                cs = 0
            th = tu if tu > tl else tl
            if th > hot:
                hot = th
            if t < n_probe:
                if th > probe[0, t]:
                    probe[0, t] = th
                probe[1, t] += v2 * inv_r
        temp[ch, 0] = tu
        temp[ch, 1] = tl
        xs[ch, 0] = x0
        xs[ch, 1] = x1
        xs[ch, 2] = net
    clock[0] = cm
    clock[1] = cs
    status = 0
    if hot > fp[18]:
        status |= STATUS_OVERTEMP
    for ch in range(nc):
        ok = math.isfinite(temp[ch, 0]) and math.isfinite(temp[ch, 1]) and math.isfinite(xs[ch, 1])
        for j in range(gt.shape[2]):
            ok = ok and math.isfinite(gt[ch, 0, j]) and math.isfinite(gt[ch, 1, j])
        if not ok:
            status |= STATUS_NONFINITE
    return status
