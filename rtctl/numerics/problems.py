"""Work-precision problems: one plant, one input, one stated reference, several ways to run it.

A :class:`Problem` holds everything the report needs for one plant:

* the **reference** output on the sample grid ``t_k = k / fs`` and a sentence saying what it is;
* **settings** of our kernels (and of baselines that reuse our discrete matrices, such as
  ``scipy.signal.dlsim``), each a ``prepare() -> run`` pair so that building and compiling stay
  out of the timing;
* a continuous model ``rhs(t, y, u)`` with the input ``u(t)`` for ``scipy.integrate.solve_ivp``,
  restarted at every discontinuity of the input (``breaks``) so that adaptive methods are not
  charged for stepping over jumps.

Builders are registered by name (:func:`register`, :data:`PROBLEMS`); each takes ``quick`` and
returns a :class:`Problem`. Linear plants use :func:`bimorph_problem`'s pattern (an analytic
steady-state reference); any plant offering the simulated-group contract plus ``rhs``/``y0``/
``outputs`` gets one through :func:`group_problem` in a few lines, e.g.::

    from rtctl.numerics.base import group_problem, register

    @register("solenoid")
    def _solenoid(quick=False):
        plant = SolenoidPlant()
        return group_problem("solenoid", lambda fs, k: SolenoidGroup(plant, fs, 1, substeps=k),
                             plant.rhs, plant.y0, plant.outputs, fs=48000.0,
                             levels=[0.0, 12.0, 0.0, -12.0], hold_s=0.01 if quick else 0.05)

The contract, the registry and :func:`group_problem` live in :mod:`rtctl.numerics.base`
(re-exported here): a plant module imports them from there, since this module imports the plant
modules (:mod:`.plants`) to register their problems.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.signal

from rtctl.errors import ModelError
from rtctl.numerics.base import (
    PROBLEMS,
    TRUTH_ROWS,
    Problem,
    Setting,
    default_bimorph_plant,
    group_problem,
    integrate,
    register,
    relative_error,
    skin_contact_model,
)
from rtctl.plant.lti import StateSpace, augment_tones, c2d, tone_state

__all__ = ["Problem", "Setting", "PROBLEMS", "register", "build", "bimorph_problem",
           "default_bimorph_plant", "group_problem", "integrate", "relative_error",
           "TRUTH_ROWS"]


def build(name: str, quick: bool = False) -> Problem:
    """Build the registered problem ``name``."""
    if name not in PROBLEMS:
        raise ModelError(f"no work-precision problem {name!r}; registered: "
                         f"{', '.join(sorted(PROBLEMS)) or 'none'}")
    return PROBLEMS[name](quick=quick)


# --------------------------------------------------------------------------------------------
# The bimorph channel (with finger): a linear plant, analytic reference.


def sine_steady_state(sys: StateSpace, freq_hz: float, amplitude: float):
    """Initial state and output phasor of the periodic response to ``amplitude sin(w t)``.

    With ``X = (j w I - A)^-1 B amplitude`` the state ``x(t) = Im(X e^{j w t})`` solves
    ``x' = A x + B u`` exactly for ``u = amplitude sin(w t)`` (no transient), so starting from
    ``x0 = Im X`` the analytic output is ``y(t) = Im(Y e^{j w t})``, ``Y = C X + D amplitude``.

    Returns
    -------
    x0 : ndarray, shape (n_states,)
    X : ndarray, shape (n_states,), complex
    Y : ndarray, shape (n_outputs,), complex
    """
    w = 2.0 * math.pi * freq_hz
    X = np.linalg.solve(1j * w * np.eye(sys.n_states) - sys.A, sys.B[:, 0] * amplitude)
    Y = sys.C @ X + sys.D[:, 0] * amplitude
    return X.imag.copy(), X, Y


def _lti_settings(sel, cascade, x0, freq_hz, amplitude, fs, n, zoh_rates, foh_rates,
                  dlsim_rates, plant=None):
    """Settings of the linear problem: our kernel (SimGroup, LtiRunner) and dlsim."""
    from rtctl.numerics.runner import LtiRunner

    w = 2.0 * math.pi * freq_hz
    aug = augment_tones(sel, [freq_hz])
    x0_aug = np.concatenate([x0, tone_state([amplitude])])

    def discrete(kind, k):
        dt = 1.0 / (fs * k)
        if kind == "tones":
            return c2d(aug, dt, "zoh")
        return c2d(sel, dt, kind)

    def fine_input(kind, k):
        if kind == "tones":
            return np.zeros((1, n * k))
        # u[0] = 0: with foh the discrete state x[k] - Gamma2 u[k] then starts at x0 exactly.
        return np.ascontiguousarray(amplitude * np.sin(w * np.arange(n * k) / (fs * k)))[None]

    def runner_setting(kind, k):
        def prepare():
            sysd = discrete(kind, k)
            tones = kind == "tones"
            run = LtiRunner(sysd, blocks=None if tones else cascade, input_free=tones)
            run.set_state(x0_aug if tones else x0)
            u = fine_input(kind, k)
            y = np.empty((1, sysd.n_outputs, u.shape[1]))
            run.process(u[:, :8].copy(), y[:, :, :8].copy())   # compile outside the timing

            def go():
                run.reset()
                run.process(u, y)
                return y[0, :, ::k]
            go.form = run.modal.form
            return go
        return Setting(f"rtctl {kind}", f"fs x{k}", prepare)

    def dlsim_setting(kind, k):
        def prepare():
            sysd = discrete(kind, k)
            u = fine_input(kind, k)[0]
            xi = x0_aug if kind == "tones" else x0
            system = (sysd.A, sysd.B, sysd.C, sysd.D, sysd.dt)

            def go():
                _, yout, _ = scipy.signal.dlsim(system, u, x0=xi)
                return yout.T[:, ::k]
            go.form = "dense"
            return go
        return Setting(f"dlsim {kind}", f"fs x{k}", prepare, ours=False)

    out = []
    if plant is not None:
        def prepare_group():
            from rtctl.plant import SimGroup
            g = SimGroup(plant, fs, 1)
            z0 = np.linalg.solve(g.modal.T, x0)
            u = fine_input("zoh", 1)
            sensed = np.empty((g.n_seg, n))
            truth = np.empty((1, 4, n))
            g.process(u[:, :8].copy(), sensed[:, :8].copy(), truth[:, :, :8].copy())

            def go():
                g.reset()
                g.state[:, 0] = z0
                g.process(u, sensed, truth)
                return truth[0]
            go.form = g.modal.form
            return go
        out.append(Setting("rtctl SimGroup zoh", "fs x1", prepare_group))
    out += [runner_setting("zoh", k) for k in zoh_rates]
    out += [runner_setting("foh", k) for k in foh_rates]
    out.append(runner_setting("tones", 1))
    for kind, rates in (("zoh", dlsim_rates[:1]), ("foh", dlsim_rates), ("tones", (1,))):
        out += [dlsim_setting(kind, k) for k in rates]
    return tuple(out)


@register("bimorph")
def bimorph_problem(quick: bool = False, fs: float = 48000.0, freq_hz: float = 250.0,
                    amplitude_v: float = 100.0, duration_s: float | None = None,
                    plant=None) -> Problem:
    """The bimorph channel with finger under a continuous sine, against its analytic response.

    **Input model.** The reference sees the continuous sine ``u(t) = amplitude_v sin(2 pi
    freq_hz t)`` and starts on its periodic orbit (:func:`sine_steady_state`), so the
    reference output is exactly ``Im(H(j w) amplitude e^{j w t})`` from the frequency response,
    with no transient and no integrator. Our kernels see that sine sampled at ``fs x k``:

    * ``zoh`` (``SimGroup``, the rig's kernel, and :class:`~rtctl.numerics.runner.LtiRunner`):
      exact for the DAC staircase, so against a continuous sine its error is the half-sample
      hold delay, O(1/(fs k)) -- the input model, not the integrator;
    * ``foh``: exact for the straight lines through the samples, O(1/(fs k)^2);
    * ``tones``: the sine generated by oscillator states inside the plant
      (:func:`~rtctl.plant.lti.augment_tones`), exact to round-off at any rate.

    ``dlsim`` runs the very same discrete matrices (so it has the same error; only its time
    differs); ``solve_ivp`` integrates ``x' = A x + B u(t)`` with the continuous sine.

    Parameters
    ----------
    quick : bool
        Shorter run and fewer settings (for tests).
    fs : float
        Output rate, Hz.
    freq_hz, amplitude_v : float
        The drive sine (default 250 Hz, 100 V peak).
    duration_s : float, optional
        Default 0.05 s (quick: 0.01 s).
    plant : BimorphPlant, optional
        Default :func:`default_bimorph_plant`.

    Returns
    -------
    Problem
    """
    plant = default_bimorph_plant() if plant is None else plant
    n = int(round((duration_s or (0.01 if quick else 0.05)) * fs))
    s = plant.sys
    sel = StateSpace(s.A, s.B, s.C[:4], s.D[:4])
    x0, X, Y = sine_steady_state(sel, freq_hz, amplitude_v)
    w = 2.0 * math.pi * freq_hz
    A, b, C, D = sel.A, sel.B[:, 0], sel.C, sel.D[:, 0]

    def reference():
        return (Y[:, None] * np.exp(1j * w * np.arange(n) / fs)[None]).imag

    def u_of(t, seg=0):
        return amplitude_v * np.sin(w * t)

    if quick:
        rates = dict(zoh_rates=(1, 4), foh_rates=(1, 4, 16), dlsim_rates=(1, 4))
    else:
        rates = dict(zoh_rates=(1, 4, 16, 64), foh_rates=(1, 2, 4, 8, 16, 32),
                     dlsim_rates=(1, 4, 16))
    settings = _lti_settings(sel, plant.cascade, x0, freq_hz, amplitude_v, fs, n,
                             plant=plant, **rates)
    return Problem(
        name="bimorph",
        description=(f"bimorph + 3-branch finger ({s.n_states} states, modes "
                     f"{', '.join(f'{f:.0f}' for f in plant.modes_hz)} Hz), "
                     f"{amplitude_v:g} V sine at {freq_hz:g} Hz, {n} samples at {fs:g} Hz"),
        reference_doc=("analytic periodic response Im(H(jw) A e^{jwt}) to a continuous sine, "
                       "started on its orbit"),
        fs=fs, n_samples=n, output_names=TRUTH_ROWS, reference=reference, settings=settings,
        rhs=lambda t, y, u: A @ y + b * u, y0=x0, input=u_of,
        outputs=lambda Y, t, seg: C @ Y + D[:, None] * u_of(t)[None],
        breaks=np.zeros(1), y_scale=np.abs(X), jac=lambda t, y, u: A, linear=True)


@register("skin_contact")
def skin_contact_problem(quick: bool = False, fs: float = 48000.0, preload_n: float = 0.0):
    """Kinematic pin on the skin with zero preload (``rtctl.plant.contact``): contact is lost
    and regained as the pin velocity staircase moves it up and down (a hybrid, switched-linear
    plant; ``HybridGroup`` at 1-16 substeps against a Radau run at rtol 1e-11: at 1e-12
    Radau fails at the contact switches)."""
    from rtctl.plant.hybrid import HybridGroup
    model, x0, params = skin_contact_model(preload_n)
    # Pin velocity, m/s, 2 ms each: up 40 um, down past the skin (contact lost), back up.
    levels = [0.02, -0.04, 0.03] if quick else \
        [0.02, -0.04, 0.0, 0.03, -0.01, 0.0, 0.05, -0.05, 0.02, -0.02]
    p = float(preload_n)
    return group_problem(
        "skin_contact",
        lambda f, k: HybridGroup(model, f, 1, x0, params=params, substeps=k),
        lambda t, y, u: model.rhs(t, y, [u, p]), x0,
        lambda y, u: model.outputs(y, [u, p])[:4], fs=fs, levels=levels, hold_s=2e-3,
        substeps=(1, 4, 16) if quick else (1, 2, 4, 8, 16), ref_rtol=1e-11,
        description=f"kinematic pin on the skin, preload {p:g} N, pin velocity staircase "
                    f"{len(levels)} x 2 ms at {fs:g} Hz")


# Plants registered from their own modules, imported last so that the report lists the bimorph
# and the skin contact first (PROBLEMS keeps registration order).
from rtctl.numerics import plants as _plants  # noqa: E402,F401
