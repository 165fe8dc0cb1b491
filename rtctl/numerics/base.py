"""What the work-precision problems and the stability cases share: the :class:`Problem`
contract and its registry, the ``solve_ivp`` driver, :func:`group_problem`, and the default
models of the bundled scenes (bimorph channel, finger, kinematic pin on the skin).

It imports nothing else from :mod:`rtctl.numerics`, so that :mod:`.problems`, :mod:`.plants`
and :mod:`.stability` can all import it and none of them another: a plant module registering
its problem imports this module, never :mod:`.problems` (which imports the plant modules to
register them). :mod:`.problems` re-exports every name here.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.integrate

from rtctl.errors import ModelError

__all__ = ["Problem", "Setting", "PROBLEMS", "register", "group_problem", "integrate",
           "relative_error", "TRUTH_ROWS", "default_bimorph_plant", "default_finger",
           "skin_contact_model"]


#: Rows compared by every problem: the group contract's truth rows.
TRUTH_ROWS = ("tip_m", "tip_velocity_m_s", "tip_force_n", "voltage_v")


@dataclass(frozen=True)
class Setting:
    """One way of producing the outputs on the sample grid.

    Attributes
    ----------
    method : str
        Family shown as one line in the diagram, e.g. ``"rtctl foh"``, ``"dlsim zoh"``.
    setting : str
        The knob within the family, e.g. ``"fs x4"``.
    prepare : callable
        ``prepare() -> run``; ``run() -> ndarray, shape (n_outputs, n_samples)``. ``prepare``
        builds, discretizes and compiles (not timed); ``run`` is timed and must be repeatable.
    ours : bool
        True for rtctl kernels, False for baselines.
    """

    method: str
    setting: str
    prepare: Callable
    ours: bool = True


@dataclass(frozen=True)
class Problem:
    """A plant, an input and a reference, for the work-precision report.

    Attributes
    ----------
    name : str
    description : str
        The plant and the input, one line.
    reference_doc : str
        What the reference is, one line (printed with the report).
    fs : float
        Output grid rate, Hz; outputs are compared at ``t_k = k / fs``.
    n_samples : int
    output_names : tuple of str
    reference : callable
        ``() -> ndarray, shape (n_outputs, n_samples)`` (may be expensive; called once).
    settings : tuple of Setting
    rhs : callable
        ``rhs(t, y, u) -> dy/dt`` of one channel.
    y0 : ndarray, shape (n_states,)
    input : callable
        ``input(t, seg) -> u`` inside segment ``seg`` (the drive voltage, V).
    outputs : callable
        ``outputs(Y, t, seg) -> ndarray, shape (n_outputs, len(t))`` from states
        ``Y, shape (n_states, len(t))`` inside segment ``seg``.
    breaks : ndarray
        Segment start times, s, starting with 0 (the input may jump only there).
    y_scale : ndarray, shape (n_states,)
        Typical magnitude of each state; ``atol = rtol * y_scale``.
    jac : callable, optional
        ``jac(t, y, u) -> (n_states, n_states)``.
    linear : bool
    """

    name: str
    description: str
    reference_doc: str
    fs: float
    n_samples: int
    output_names: tuple
    reference: Callable
    settings: tuple
    rhs: Callable
    y0: np.ndarray
    input: Callable
    outputs: Callable
    breaks: np.ndarray
    y_scale: np.ndarray
    jac: Callable | None = None
    linear: bool = False
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def t(self) -> np.ndarray:
        """Sample times, s, shape (n_samples,)."""
        return np.arange(self.n_samples) / self.fs

    @property
    def t_end(self) -> float:
        return self.n_samples / self.fs

    def reference_outputs(self) -> np.ndarray:
        """The reference, computed once, shape (n_outputs, n_samples)."""
        if "ref" not in self._cache:
            self._cache["ref"] = np.asarray(self.reference(), dtype=np.float64)
        return self._cache["ref"]


PROBLEMS: dict = {}


def register(name: str):
    """Decorator: register ``builder(quick=False) -> Problem`` under ``name``."""
    def deco(builder):
        PROBLEMS[name] = builder
        return builder
    return deco



def relative_error(y, ref) -> float:
    """Largest error on the grid relative to each row's peak, worst row.

    ``max_rows max_k |y - ref| / max_k |ref|``; rows whose reference is identically zero are
    compared absolutely. NaN or Inf anywhere gives ``inf``.

    Parameters
    ----------
    y, ref : ndarray, shape (n_outputs, n_samples)
    """
    y, ref = np.asarray(y, dtype=np.float64), np.asarray(ref, dtype=np.float64)
    if y.shape != ref.shape or not np.all(np.isfinite(y)):
        return math.inf
    scale = np.max(np.abs(ref), axis=1)
    scale[scale == 0.0] = 1.0
    return float(np.max(np.max(np.abs(y - ref), axis=1) / scale))


def integrate(problem: Problem, method: str, rtol: float, atol_scale: float | None = None,
              max_step: float = np.inf):
    """Run ``solve_ivp`` over every input segment and return the outputs on the grid.

    Parameters
    ----------
    problem : Problem
    method : {"Radau", "BDF", "LSODA", "RK45", ...}
    rtol : float
    atol_scale : float, optional
        ``atol = atol_scale * problem.y_scale`` (default ``rtol``).
    max_step : float

    Returns
    -------
    y : ndarray, shape (n_outputs, n_samples)
        NaN where the integrator failed.
    wall_s : float
        Time spent inside ``solve_ivp`` (output evaluation excluded).
    """
    import time

    atol = (rtol if atol_scale is None else atol_scale) * problem.y_scale
    t = problem.t
    breaks = np.append(np.asarray(problem.breaks, dtype=np.float64), problem.t_end)
    y = np.full((len(problem.output_names), t.size), np.nan)
    state = np.asarray(problem.y0, dtype=np.float64).copy()
    wall = 0.0
    # LSODA may abort at t = 0 on loose tolerances unless it is given a first step; it also
    # rejects a constant-array jac (scipy/scipy#10864; docs/references.md, Numerics).
    extra = {"first_step": 0.1 / problem.fs} if method == "LSODA" else {}
    for seg in range(breaks.size - 1):
        ta, tb = breaks[seg], breaks[seg + 1]
        idx = np.flatnonzero((t >= ta) & (t < tb))
        t_eval = np.append(t[idx], tb)

        def fun(tt, yy, seg=seg):
            return problem.rhs(tt, yy, problem.input(tt, seg))
        if problem.jac is not None and method in ("Radau", "BDF", "LSODA"):
            extra["jac"] = (lambda tt, yy, seg=seg: problem.jac(tt, yy, problem.input(tt, seg)))
        t0 = time.perf_counter()
        sol = scipy.integrate.solve_ivp(fun, (ta, tb), state, method=method, t_eval=t_eval,
                                        rtol=rtol, atol=atol, max_step=max_step, **extra)
        wall += time.perf_counter() - t0
        if sol.status != 0 or sol.y.shape[1] != t_eval.size:
            break
        if idx.size:
            y[:, idx] = problem.outputs(sol.y[:, :-1], t[idx], seg)
        state = sol.y[:, -1]
    return y, wall



# --------------------------------------------------------------------------------------------
# Any plant offering the simulated-group contract plus rhs / y0 / outputs.


def group_problem(name: str, make_group: Callable, rhs: Callable, y0, outputs: Callable, *,
                  fs: float, levels, hold_s: float, substeps=(1, 2, 4, 8, 16),
                  description: str = "", jac: Callable | None = None, truth_lag: int = 0,
                  ref_method: str = "Radau", ref_rtol: float = 1e-12,
                  y_scale=None, rows=(0, 1, 2, 3)) -> Problem:
    """A work-precision problem for a plant behind the simulated-group contract.

    **Input model.** The drive is a staircase: ``levels[i]`` (V) held for ``hold_s`` each, the
    same samples the group kernel receives (a DAC holds them), so the reference sees exactly
    the kernel's input: a ``ref_method`` run at ``ref_rtol``, restarted at each level change.
    Output sample ``k`` is compared at ``t_k = k / fs`` with the state at ``t_k`` and drive
    ``u_k`` (a group reporting the state after its sample sets ``truth_lag=1``).

    Parameters
    ----------
    name : str
    make_group : callable
        ``make_group(fs, substeps) -> group`` with one channel (``process``, ``reset``,
        ``n_sensed``); ``reset()`` must put it in the state ``y0``.
    rhs : callable
        ``rhs(t, y, u) -> dy/dt`` of one channel.
    y0 : array_like, shape (n_states,)
    outputs : callable
        ``outputs(y, u) -> (4,)``, the truth rows.
    fs : float
        Sample rate, Hz.
    levels : array_like
        Drive levels, V.
    hold_s : float
        Time each level is held, s (rounded to whole samples).
    substeps : sequence of int
        Settings of the kernel in the diagram.
    jac : callable, optional
        ``jac(t, y, u)`` for the implicit integrators.
    truth_lag : int or "group"
        Samples by which the group's truth lags its state (``"group"``: ``group.lag_samples``,
        e.g. the SMA taxel interpolating between mechanical solves).
    ref_method, ref_rtol : str, float
        Reference integrator and tolerance.
    y_scale : array_like, optional
        Typical state magnitudes for ``atol``; default from a ``rtol = 1e-6`` pilot run.
    rows : sequence of int
        Truth rows compared (default all four). A quasi-static plant (the SMA pin has no mass)
        has no meaningful instantaneous velocity to compare, only its position.

    Returns
    -------
    Problem
    """
    levels = np.asarray(levels, dtype=np.float64)
    hold = max(1, int(round(hold_s * fs)))
    n = hold * levels.size
    drive = np.ascontiguousarray(np.repeat(levels, hold))[None]
    y0 = np.asarray(y0, dtype=np.float64)
    if truth_lag != "group" and not (isinstance(truth_lag, int) and truth_lag >= 0):
        raise ModelError(f"truth_lag must be an int >= 0 or 'group' (the group's lag_samples), "
                         f"got {truth_lag!r}")

    rows = list(rows)

    def out_fn(Y, t, seg):
        u = levels[seg]
        return np.stack([np.asarray(outputs(Y[:, i], u), dtype=np.float64)[rows]
                         for i in range(Y.shape[1])], axis=1)

    base = dict(name=name, description=description or f"{name}: {levels.size} drive levels",
                fs=float(fs), n_samples=n, output_names=tuple(TRUTH_ROWS[r] for r in rows), rhs=rhs, y0=y0,
                input=lambda t, seg: levels[seg], outputs=out_fn,
                breaks=np.arange(levels.size) * hold / fs, jac=jac, linear=False)
    if y_scale is None:
        pilot = Problem(reference_doc="", reference=None, settings=(),
                        y_scale=np.maximum(np.abs(y0), 1e-300), **base)
        y_scale = _state_scale(pilot)

    def make_setting(k):
        def prepare():
            g = make_group(float(fs), int(k))
            sensed = np.empty((g.n_sensed, n))
            truth = np.empty((1, 4, n))
            g.reset()
            g.process(drive[:, :8].copy(), sensed[:, :8].copy(), truth[:, :, :8].copy())

            def go():
                g.reset()
                g.process(drive, sensed, truth)
                lag = int(g.lag_samples) if truth_lag == "group" else truth_lag
                if lag:
                    first = out_fn(y0[:, None], np.zeros(1), 0)
                    return np.concatenate([np.repeat(first, lag, axis=1), truth[0, rows, :-lag]], axis=1)
                return truth[0, rows]
            go.form = "group"
            return go
        return Setting("rtctl group", f"substeps {k}", prepare)

    prob = Problem(reference_doc=(f"{ref_method} at rtol {ref_rtol:g} of the same drive "
                                  "staircase, restarted at each level change"),
                   reference=None, settings=tuple(make_setting(k) for k in substeps),
                   y_scale=np.asarray(y_scale, dtype=np.float64), **base)

    def reference():
        y = integrate(prob, ref_method, ref_rtol)[0]
        if not np.all(np.isfinite(y)):
            raise ModelError(f"{name}: the {ref_method} reference failed at rtol {ref_rtol:g} "
                             "(step size too small at a switch?); loosen ref_rtol")
        return y
    object.__setattr__(prob, "reference", reference)
    return prob


def _state_scale(pilot: Problem) -> np.ndarray:
    """Peak magnitude of each state over a loose Radau run (floor: 1e-9 of the largest)."""
    breaks = np.append(pilot.breaks, pilot.t_end)
    y, peak = pilot.y0.copy(), np.abs(pilot.y0)
    for seg in range(breaks.size - 1):
        sol = scipy.integrate.solve_ivp(lambda t, yy, seg=seg: pilot.rhs(t, yy, pilot.input(t, seg)),
                                        (breaks[seg], breaks[seg + 1]), y, method="Radau",
                                        rtol=1e-6, atol=1e-12 * max(1.0, float(np.max(peak))))
        peak = np.maximum(peak, np.max(np.abs(sol.y), axis=1))
        y = sol.y[:, -1]
    top = float(np.max(peak)) if peak.size else 1.0
    return np.maximum(peak, 1e-9 * top if top > 0 else 1e-300)



# --------------------------------------------------------------------------------------------
# Default models of the bundled scenes.


def default_bimorph_plant(finger_branches=((300.0, 0.004), (150.0, 0.07), (80.0, 1.4)),
                          finger_mass=1e-4, finger_k0=300.0, damping=0.01, n_modes=4,
                          amp_bandwidth_hz=20e3, shunt_ohm=100.0, aa_cutoff_hz=15e3):
    """The bimorph channel of the bundled scenes: 15 x 1.5 mm PZT-5A parallel bimorph, two
    equal electrode segments, three-branch Maxwell finger, 20 kHz amplifier, 15 kHz AA filter.

    Parameters are SI (N/m, s, kg, Hz, ohm); ``finger_branches=None`` leaves the finger off.

    Returns
    -------
    BimorphPlant
    """
    from rtctl.plant import BUILTIN, Amplifier, BeamSpec, BimorphPlant, CurrentSense, Layer, MaxwellLoad, build_fe
    pzt = BUILTIN["PZT-5A"]
    fe = build_fe(BeamSpec(15e-3, 1.5e-3, (Layer(pzt, 0.3e-3), Layer(pzt, 0.3e-3)),
                           "parallel", (0.5, 0.5), damping))
    finger = None if finger_branches is None else \
        MaxwellLoad(finger_mass, finger_k0, tuple(finger_branches))
    return BimorphPlant(fe, Amplifier(amp_bandwidth_hz), CurrentSense(shunt_ohm, aa_cutoff_hz),
                        finger, n_modes=n_modes)


def default_finger():
    """The three-branch finger of the bundled scenes (4 ms, 70 ms, 1.4 s: Pawluk & Howe 1999,
    docs/references.md)."""
    from rtctl.plant.finger import MaxwellLoad
    return MaxwellLoad(1e-4, 300.0, ((300.0, 0.004), (150.0, 0.07), (80.0, 1.4)))


def skin_contact_model(preload_n: float = 0.0, finger=None):
    """Kinematic pin on the skin (:func:`rtctl.plant.contact.kinematic_pin_model`).

    Returns ``(model, x0, params)``: the pin rests at height 0, the skin at rest on it.
    """
    from rtctl.plant.contact import SkinContact, kinematic_pin_model
    finger = finger or default_finger()
    model = kinematic_pin_model(SkinContact(finger))
    x0, _ = model.equilibrium([0.0, preload_n], fixed={0: 0.0})
    return model, x0, [preload_n]
