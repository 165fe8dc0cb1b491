"""Plain numpy/loop twins and references for ``rtctl.plant.hybrid`` (as stumpy's tests/naive.py).

* :func:`process` is the loop twin of ``hybrid_process``: the same algorithm written the obvious
  way (modes from ``model.mode``, steps from ``PG``), one channel at a time.
* :func:`reference` integrates the *continuous* model with ``scipy.integrate.solve_ivp`` and
  terminal events on every switch function, restarting in the new mode at each crossing; it
  shares nothing with the kernels but the model's mode tables.
"""

import numpy as np
from scipy.integrate import solve_ivp

from rtctl._numba import TINY


def excursion(model, mode, c, x, xt, u, frac_h):
    """Twin of ``_excursion``: may a relevant switch have crossed and come back in the piece?"""
    n = model.n_states
    cls = model.mode_class
    z0 = np.concatenate([x, u, [1.0]])
    z1 = np.concatenate([xt, u, [1.0]])
    for i in range(model.n_switches):
        if cls[mode ^ (1 << i)] == cls[mode]:
            continue
        sd = model.S[i, :n] @ model.M[model.class_rep[c]]     # slope of switch i in class c
        s0, s1 = model.S[i] @ z0, model.S[i] @ z1
        d0, d1 = sd @ z0 * frac_h, sd @ z1 * frac_h
        on = s0 > 0.0
        if (on and d0 >= 0.0) or (not on and d0 <= 0.0) or (s1 > 0.0) != on:
            continue
        for t in (0.25, 0.5, 0.75):
            h00, h10 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t
            h01, h11 = 3 * t**2 - 2 * t**3, t**3 - t**2
            if (h00 * s0 + h10 * d0 + h01 * s1 + h11 * d1 > 0.0) != on:
                return True
    return False


def substep(model, PG, x, u, levels, max_events, kmin, h, stats=None):
    """One substep with bisection localization; returns the new state."""
    cls = model.mode_class
    full = 1 << levels
    remaining, events = full, 0
    z_u = np.concatenate([u, [1.0]])

    def go(c, k, x):
        y = PG[c, k] @ np.concatenate([x, z_u])
        y[np.abs(y) < TINY] = 0.0
        return y

    while remaining > 0:
        mode = model.mode(x, u)
        c0 = cls[mode]
        k = kmin[c0]
        while (full >> k) > remaining:
            k += 1
        while True:
            xt = go(c0, k, x)
            if events >= max_events:
                break
            c1 = cls[model.mode(xt, u)]
            if c1 == c0:
                if k == levels or not excursion(model, mode, c0, x, xt, u, h / (1 << k)):
                    break
            elif k == levels:
                events += 1
                break
            k += 1
        x = xt
        remaining -= full >> k
    if stats is not None:
        stats["events"] = stats.get("events", 0) + events
    return x


def process(model, PG, x0, params, drive, substeps, levels, max_events, out_rows, h,
            stats=None):
    """Twin of ``hybrid_process`` for one channel (no ADC): outputs before each update.

    ``h`` is the substep (s). Returns ``(y, x)``: outputs ``(len(out_rows), n_samples)`` and
    the final state.
    """
    x = np.array(x0, dtype=np.float64)
    kmin = model.piece_levels(h, levels)
    y = np.empty((len(out_rows), drive.size))
    for k, v in enumerate(drive):
        u = np.concatenate([[v], params])
        y[:, k] = model.outputs(x, u)[out_rows]
        for _ in range(substeps):
            x = substep(model, PG, x, u, levels, max_events, kmin, h, stats)
    return y, x


def reference(model, x0, params, drive, fs, rtol=1e-10, atol=None, method="Radau"):
    """Continuous-time reference: the DAC staircase ``drive`` (held per sample) through the
    switched model, integrated by ``solve_ivp`` with terminal events on the switch functions.

    Returns the states at every sample instant, shape ``(n_samples + 1, n)``.
    """
    n = model.n_states
    x = np.array(x0, dtype=np.float64)
    xs = [x.copy()]
    dt = 1.0 / fs
    atol = 1e-14 if atol is None else atol
    # Group equal consecutive inputs: integrate each constant stretch in one go.
    edges = np.flatnonzero(np.diff(drive)) + 1
    starts = np.concatenate([[0], edges])
    stops = np.concatenate([edges, [drive.size]])
    for a, b in zip(starts, stops):
        u = np.concatenate([[drive[a]], params])
        z_u = np.concatenate([u, [1.0]])
        t_eval = (np.arange(a + 1, b + 1)) * dt
        t0, t1 = a * dt, b * dt
        mode = model.mode(x, u)
        out = []
        while True:
            A = model.M[mode]

            def f(t, y, A=A, z_u=z_u):
                return A[:, :n] @ y + A[:, n:] @ z_u

            evs = []
            for i in range(model.n_switches):
                def ev(t, y, i=i, z_u=z_u):
                    return model.S[i, :n] @ y + model.S[i, n:] @ z_u
                ev.terminal = True
                # Only a crossing *out of* the current side of switch i ends the stretch.
                ev.direction = -1.0 if mode >> i & 1 else 1.0
                evs.append(ev)
            te = t_eval[t_eval > t0]
            sol = solve_ivp(f, (t0, t1), x, method=method, rtol=rtol, atol=atol, t_eval=te,
                            events=evs, jac=A[:, :n], first_step=min(1e-9, t1 - t0))
            out.append(np.asarray(sol.y, dtype=np.float64).reshape(n, -1).T)
            if sol.status == 1:
                hit = [i for i, e in enumerate(sol.t_events) if len(e)][0]
                t0 = float(sol.t_events[hit][0])
                x = np.array(sol.y_events[hit][0])
                mode ^= 1 << hit
                if t1 - t0 <= 0.0:
                    break
                continue
            x = sol.y[:, -1].copy()
            break
        got = np.vstack(out) if out else np.zeros((0, n))
        xs.extend(got)
    return np.array(xs)


def count_events(model, PG, x0, params, drive, substeps, levels, max_events, h):
    stats = {}
    process(model, PG, x0, params, drive, substeps, levels, max_events, [0], h, stats)
    return stats["events"]
