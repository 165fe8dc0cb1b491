"""Stability on stiff and extreme cases: bounded, finite, physically sane -- or refused.

Each case builds the model the rig would build, runs the rig's kernel and checks it against
something we did not discretize: the exact continuous step response ``y(t) = C A^-1 (e^{A t}
- I) B u + D u`` from one matrix exponential per checkpoint (no recursion), conserved energy,
or a ``ModelError`` raised up front. Cases return :class:`Case`; :func:`run_cases` runs them
all. Plants with contact or end stops add their cases through :func:`register_case` (see
:func:`contact_case` and :func:`group_step_case`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.integrate
import scipy.linalg as sla

from rtctl.errors import ModelError
from rtctl.numerics.base import default_bimorph_plant, default_finger, skin_contact_model

__all__ = ["Case", "run_cases", "register_case", "CASES", "exact_step", "contact_case",
           "group_step_case", "FULL_SCALE_V"]

#: Full-scale drive of the bundled bimorph scenes (``actuator.max_voltage``), V.
FULL_SCALE_V = 150.0
FS = 48000.0


@dataclass(frozen=True)
class Case:
    """Outcome of one stability case.

    Attributes
    ----------
    case : str
    passed : bool or None
        None: the case could not run (a model it needs is not there); ``detail`` says why.
    detail : str
        The measured numbers behind the verdict.
    """

    case: str
    passed: bool | None
    detail: str

    def as_json(self) -> dict:
        return {"case": self.case, "passed": self.passed, "detail": self.detail}


CASES: dict = {}


def register_case(name: str):
    """Decorator: register ``fn(quick: bool) -> Case or list of Case`` under ``name``."""
    def deco(fn):
        CASES[name] = fn
        return fn
    return deco


def run_cases(quick: bool = False, names=None, progress=None) -> list:
    """Run the registered cases (all, or ``names``) and return a flat list of :class:`Case`.

    A case that raises is reported as failed with the exception, never swallowed silently.
    """
    out = []
    for name in (names or list(CASES)):
        t0 = time.perf_counter()
        try:
            got = CASES[name](quick)
        except Exception as exc:  # noqa: BLE001 - a crash is a failed case, with its reason
            got = Case(name, False, f"raised {type(exc).__name__}: {exc}")
        got = got if isinstance(got, list) else [got]
        out += got
        if progress:
            for c in got:
                verdict = {True: "pass", False: "FAIL", None: "n/a"}[c.passed]
                progress(f"  {verdict:4s} {c.case:28s} {c.detail}  "
                         f"[{time.perf_counter() - t0:.1f} s]")
    return out


# --------------------------------------------------------------------------------------------
# References


def exact_step(A, B, C, D, u: float, times) -> np.ndarray:
    """Exact response to a step ``u`` at t = 0 from rest, at ``times``.

    ``x(t) = int_0^t e^{A s} ds B u`` from the Van Loan exponential of ``[[A, B], [0, 0]] t``,
    one exponential per time (no recursion, so no accumulated error to share with a kernel).
    Not for strongly non-normal ``A``: on a near-Jordan block the exponential at long times
    was 5e-8 off (against Radau at rtol 1e-13), so :func:`near_defective` uses Radau.

    Returns
    -------
    ndarray, shape (n_outputs, len(times))
    """
    A, B, C, D = (np.atleast_2d(np.asarray(m, dtype=np.float64)) for m in (A, B, C, D))
    n = A.shape[0]
    M = np.zeros((n + 1, n + 1))
    M[:n, :n] = A
    M[:n, n] = B[:, 0]
    out = np.empty((C.shape[0], len(times)))
    for i, t in enumerate(times):
        x = sla.expm(M * t)[:n, n] * u
        out[:, i] = C @ x + D[:, 0] * u
    return out


def _checkpoints(n: int, count: int = 24) -> np.ndarray:
    return np.unique(np.geomspace(1, n - 1, count).astype(np.int64))


def _row_rel_error(y, ref) -> float:
    scale = np.max(np.abs(ref), axis=1)
    scale[scale == 0.0] = 1.0
    return float(np.max(np.max(np.abs(y - ref), axis=1) / scale))


def _run_group(group, drive):
    """Run a one-channel group over ``drive`` (n,), in pieces; truth (4, n), sticky status."""
    n = drive.size
    truth = np.empty((1, 4, n))
    sensed = np.empty((group.n_channels * group.n_sensed, n))
    status = group.process(np.ascontiguousarray(drive[None]), sensed, truth)
    return truth[0], status


def _bimorph_step_case(name, plant, n, tol=1e-6, u=FULL_SCALE_V, extra=""):
    """Full-scale step through ``SimGroup`` against :func:`exact_step`, plus finiteness."""
    from rtctl.plant import SimGroup
    g = SimGroup(plant, FS, 1)
    truth, status = _run_group(g, np.full(n, u))
    s = plant.sys
    k = _checkpoints(n)
    ref = exact_step(s.A, s.B, s.C[:4], s.D[:4], u, k / FS)
    err = _row_rel_error(truth[:, k], ref)
    finite = bool(np.all(np.isfinite(truth))) and not (status & 2)
    ok = finite and err <= tol
    return Case(name, ok, f"{g.modal.form} (cond {g.modal.cond:.3g}), {n} samples, "
                          f"max rel. error vs exact step {err:.2e} (<= {tol:g}), "
                          f"finite {finite}{extra}"), g, truth


# --------------------------------------------------------------------------------------------
# Cases


@register_case("maxwell_tau")
def maxwell_tau(quick: bool = False) -> list:
    """Finger branch relaxation times 1e-8 s ... 1e3 s, one at a time and all together."""
    n = 4800 if quick else 24000
    taus = (1e-8, 1e-5, 1e-2, 1.0, 1e3)
    out = []
    for tau in taus:
        plant = default_bimorph_plant(finger_branches=((300.0, tau),))
        out.append(_bimorph_step_case(f"maxwell_tau_{tau:.0e}_s", plant, n)[0])
    plant = default_bimorph_plant(finger_branches=tuple((300.0, t) for t in taus))
    out.append(_bimorph_step_case("maxwell_tau_all", plant, n)[0])
    return out


@register_case("zero_damping")
def zero_damping(quick: bool = False) -> Case:
    """Undamped beam (zeta = 0, no finger): discrete modes stay on the unit circle."""
    plant = default_bimorph_plant(finger_branches=None, damping=0.0)
    case, g, _ = _bimorph_step_case("zero_damping", plant, 4800 if quick else 48000)
    pairs, _ = g.modal.blocks()
    radius = np.hypot(pairs[:, 0], pairs[:, 1])
    worst = float(np.max(radius - 1.0))
    ok = case.passed and worst <= 1e-12
    return Case(case.case, ok, case.detail + f", largest |z| - 1 = {worst:.1e} (<= 1e-12)")


@register_case("modes_above_nyquist")
def modes_above_nyquist(quick: bool = False) -> Case:
    """Twelve beam modes (up to ~450 kHz) at 48 kHz: exact discretization stays stable."""
    plant = default_bimorph_plant(n_modes=12)
    lam = np.linalg.eigvals(plant.sys.A)
    z = lam / FS
    rk4 = float(np.max(np.abs(1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24)))
    case, g, _ = _bimorph_step_case(
        "modes_above_nyquist", plant, 4800 if quick else 24000,
        extra=(f"; top mode {plant.modes_hz[-1] / 1e3:.0f} kHz vs Nyquist {FS / 2e3:.0f} kHz "
               f"(explicit RK4 would amplify by {rk4:.3g} per sample)"))
    return case


@register_case("stiffness_1e12")
def stiffness_1e12(quick: bool = False) -> Case:
    """Eigenvalues spanning 12 decades: a 1e3 s finger branch and a 160 MHz amplifier."""
    plant = default_bimorph_plant(finger_branches=((300.0, 0.004), (80.0, 1e3)),
                                  amp_bandwidth_hz=1e9 / (2 * math.pi))
    mag = np.abs(np.linalg.eigvals(plant.sys.A))
    ratio = float(mag.max() / mag.min())
    case, _, _ = _bimorph_step_case("stiffness_1e12", plant, 4800 if quick else 24000,
                                    extra=f"; stiffness ratio {ratio:.2g}")
    return Case(case.case, case.passed and ratio >= 1e12, case.detail)


@register_case("full_scale_step")
def full_scale_step(quick: bool = False) -> Case:
    """150 V step on the default channel: exact, no voltage overshoot, bounded tip."""
    plant = default_bimorph_plant()
    n = 4800 if quick else 48000
    case, g, truth = _bimorph_step_case("full_scale_step", plant, n)
    s = plant.sys
    dc = float((s.D[0, 0] - s.C[0] @ np.linalg.solve(s.A, s.B[:, 0])) * FULL_SCALE_V)
    tip_peak = float(np.max(np.abs(truth[0])))
    v_peak = float(np.max(truth[3]))
    ok = case.passed and v_peak <= FULL_SCALE_V * (1 + 1e-12) and tip_peak <= 2.0 * abs(dc)
    return Case(case.case, ok, case.detail + f"; peak V {v_peak:.6g} (<= {FULL_SCALE_V:g}), "
                                             f"peak tip {tip_peak * 1e6:.3g} um <= 2 x DC "
                                             f"{abs(dc) * 1e6:.3g} um")


@register_case("near_defective")
def near_defective(quick: bool = False) -> list:
    """A Jordan chain and a near-defective one: modal form refused, dense runs exactly."""
    from rtctl.numerics.runner import LtiRunner
    from rtctl.plant.lti import StateSpace, c2d, to_modal
    out = []
    for label, eps in (("jordan", 0.0), ("eps_1e-10", 1e-10)):
        a = -2e3
        A = np.array([[a, 1e3, 0.0], [0.0, a * (1 + eps), 1e3], [0.0, 0.0, a * (1 - eps)]])
        B, C, D = np.array([[0.0], [0.0], [1.0]]), np.eye(3), np.zeros((3, 1))
        sysd = c2d(StateSpace(A, B, C, D), 1 / FS)
        try:
            to_modal(sysd, form="modal")
            refused = "modal form accepted (expected a refusal)"
        except ModelError as exc:
            refused = ""
            msg = str(exc).split(";")[0]
        run = LtiRunner(sysd)
        n = 4800
        y = np.empty((1, 3, n))
        status = run.process(np.ones((1, n)), y)
        k = _checkpoints(n)
        ref = scipy.integrate.solve_ivp(lambda t, x, A=A, B=B: A @ x + B[:, 0], (0.0, k[-1] / FS),
                                        np.zeros(3), method="Radau", t_eval=k / FS,
                                        rtol=1e-13, atol=1e-22, jac=lambda t, x, A=A: A).y
        err = _row_rel_error(y[0][:, k], C @ ref)
        ok = not refused and run.modal.form == "dense" and err <= 1e-9 and status == 0
        out.append(Case(f"near_defective_{label}", ok,
                        refused or f"modal refused ({msg}); ran {run.modal.form}, max rel. "
                                   f"error vs Radau (rtol 1e-13) {err:.1e} (<= 1e-9)"))
    return out


@register_case("subnormal_decay")
def subnormal_decay(quick: bool = False) -> list:
    """Free decay to zero after a pulse: no subnormal state, no slowdown (modal and dense)."""
    from rtctl.plant import SimGroup
    # No finger: its 1.4 s branch would take ~1000 s to reach 1e-308; beam modes at 1 %
    # damping reach it in ~20 s.
    plant = default_bimorph_plant(finger_branches=None, damping=0.05 if quick else 0.01)
    piece = 48000
    n_pieces = 12 if quick else 40
    out = []
    for form in ("auto", "dense"):
        g = SimGroup(plant, FS, 1, form=form)
        tiny = np.finfo(np.float64).tiny
        truth = np.empty((1, 4, piece))
        sensed = np.empty((g.n_sensed, piece))
        drive = np.zeros((1, piece))
        drive[0, :48] = FULL_SCALE_V
        times, subnormal, status = [], 0, 0
        for _ in range(n_pieces):
            t0 = time.perf_counter()
            status |= g.process(drive, sensed, truth)
            times.append(time.perf_counter() - t0)
            drive[0, :48] = 0.0
            x = g.state
            subnormal += int(np.count_nonzero((x != 0.0) & (np.abs(x) < tiny)))
        zero = bool(np.all(g.state == 0.0))
        slow = min(times[-3:]) / min(times[1:4])
        ok = subnormal == 0 and slow <= 3.0 and not (status & 2) and zero
        out.append(Case(f"subnormal_decay_{g.modal.form}", ok,
                        f"{n_pieces * piece} samples after a {FULL_SCALE_V:g} V pulse: "
                        f"{subnormal} subnormal states, all states zero at the end {zero}, "
                        f"time per sample decayed/active {slow:.2f} (<= 3)"))
    return out


@register_case("energy_drift")
def energy_drift(quick: bool = False) -> Case:
    """1e8 samples (quick: 1e6) of the undamped beam: mechanical energy constant."""
    from rtctl.plant import SimGroup
    plant = default_bimorph_plant(finger_branches=None, damping=0.0)
    g = SimGroup(plant, FS, 1)
    names = plant.sys.state_names
    nr = sum(1 for s in names if s.startswith("eta") and not s.endswith("_dot"))
    om2 = (2 * math.pi * plant.modes_hz) ** 2

    def energy():
        x = g.physical_state()[:, 0]
        return 0.5 * float(x[nr:2 * nr] @ x[nr:2 * nr] + om2 @ x[:nr] ** 2), float(x[2 * nr])

    total = 10**6 if quick else 10**8
    piece = 2**18
    truth = np.empty((1, 4, piece))
    sensed = np.empty((g.n_sensed, piece))
    drive = np.zeros((1, piece))
    drive[0, :24] = FULL_SCALE_V        # a 0.5 ms pulse, then free vibration
    status = g.process(drive, sensed, truth)
    drive[0, :24] = 0.0
    e0, v_left = energy()
    done, worst, t0 = piece, 0.0, time.perf_counter()
    while done < total:
        if total - done < piece:
            piece = total - done
            truth, sensed = np.empty((1, 4, piece)), np.empty((g.n_sensed, piece))
            drive = np.zeros((1, piece))
        status |= g.process(drive, sensed, truth)
        done += piece
        worst = max(worst, abs(energy()[0] / e0 - 1.0))
    wall = time.perf_counter() - t0
    ok = worst <= 1e-6 and not (status & 2) and v_left == 0.0
    return Case("energy_drift", ok, f"{done:.0e} samples ({done / FS / 3600:.2f} h at 48 kHz) "
                                    f"in {wall:.1f} s: largest relative energy drift "
                                    f"{worst:.1e} (<= 1e-6), amplifier voltage at start of "
                                    f"free vibration {v_left:g} V")


@register_case("refusals")
def refusals(quick: bool = False) -> Case:
    """Models that cannot run safely are refused up front with a ModelError naming why."""
    from rtctl.plant import MaxwellLoad, SimGroup
    from rtctl.plant.lti import StateSpace, c2d, to_modal
    jordan = c2d(StateSpace([[-1.0, 1.0], [0.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]], [[0.0]]),
                 1 / FS)
    tries = {
        "branch tau = 0": lambda: MaxwellLoad(1e-4, 300.0, ((300.0, 0.0),)),
        "branch tau = inf": lambda: MaxwellLoad(1e-4, 300.0, ((300.0, math.inf),)),
        "negative skin mass": lambda: MaxwellLoad(-1e-4, 300.0),
        "NaN in A": lambda: StateSpace([[math.nan]], [[1.0]], [[1.0]], [[0.0]]),
        "dt = 0": lambda: c2d(StateSpace([[-1.0]], [[1.0]], [[1.0]], [[0.0]]), 0.0),
        "modal form of a Jordan block": lambda: to_modal(jordan, form="modal"),
        "shunt pole below fs": lambda: SimGroup(default_bimorph_plant(shunt_ohm=1e5), FS, 1),
    }
    missed, said = [], []
    for label, fn in tries.items():
        try:
            fn()
            missed.append(label)
        except ModelError as exc:
            said.append(f"{label}: {str(exc)[:60]}")
    return Case("refusals", not missed,
                f"{len(said)}/{len(tries)} refused with ModelError"
                + (f"; NOT refused: {', '.join(missed)}" if missed else ""))


# --------------------------------------------------------------------------------------------
# Hooks for plants with contact and end stops (registered by the plants' problems)


def contact_case(name: str, make_group: Callable, drive, force_bound: float,
                 disp_bound: float) -> Case:
    """Contact made and lost under ``drive`` (V, shape (n,)) by a one-channel group.

    Passes when every truth sample is finite, the contact force (row 2) is never negative,
    is exactly zero somewhere (contact lost) and positive somewhere (contact made), stays
    below ``force_bound`` (N), the displacement below ``disp_bound`` (m), and no status
    reports NaN/Inf.
    """
    g = make_group()
    g.reset()
    truth, status = _run_group(g, np.asarray(drive, dtype=np.float64))
    f, x = truth[2], truth[0]
    finite = bool(np.all(np.isfinite(truth)))
    lost, made = int(np.count_nonzero(f == 0.0)), int(np.count_nonzero(f > 0.0))
    ok = (finite and not (status & 2) and float(np.min(f)) >= 0.0 and lost > 0 and made > 0
          and float(np.max(f)) <= force_bound and float(np.max(np.abs(x))) <= disp_bound)
    return Case(name, ok, f"finite {finite}, force {np.min(f):.3g} .. {np.max(f):.3g} N "
                          f"(<= {force_bound:g}), |x| <= {np.max(np.abs(x)):.3g} m "
                          f"(<= {disp_bound:g}), {lost} samples out of contact, {made} in")


def group_step_case(name: str, make_group: Callable, full_scale_v: float, n: int,
                    disp_bound: float, unit: str = "V") -> Case:
    """Full-scale up and down drive steps (``unit`` of the drive, V for actuators) through a
    one-channel group: finite, bounded."""
    g = make_group()
    g.reset()
    drive = np.zeros(n)
    drive[n // 4:n // 2] = full_scale_v
    drive[n // 2:3 * n // 4] = -full_scale_v
    truth, status = _run_group(g, drive)
    finite = bool(np.all(np.isfinite(truth)))
    peak = float(np.max(np.abs(truth[0]))) if finite else math.inf
    ok = finite and not (status & 2) and peak <= disp_bound
    return Case(name, ok, f"+-{full_scale_v:g} {unit} steps, {n} samples: finite {finite}, "
                          f"peak |x| {peak:.3g} m (<= {disp_bound:g})")


@register_case("contact")
def contact(quick: bool = False) -> list:
    """Zero preload: a 250 Hz, 100 um pin vibration loses and regains contact; a 10 mm/s
    full-scale pin velocity step up and down (kinematic pin, rtctl.plant.contact)."""
    try:
        from rtctl.plant.hybrid import HybridGroup
        model, x0, params = skin_contact_model(0.0)
    except ImportError as exc:
        return Case("contact", None, f"not run: rtctl.plant.contact / hybrid do not import "
                                     f"({exc}); register contact_case for the contact model")
    n = 4800 if quick else 48000
    h = 100e-6 * np.sin(2 * math.pi * 250.0 * np.arange(n + 1) / FS)

    def make():
        return HybridGroup(model, FS, 1, x0, params=params)
    # Sane force: an impact at up to twice the pin's peak speed on the penalty spring-damper
    # (v (sqrt(k_c m) + c_c)), plus the tissue's instantaneous stiffness over the stroke.
    from rtctl.plant.contact import SkinContact
    skin = SkinContact(default_finger())
    v = 2 * math.pi * 250.0 * 100e-6
    bound = 2 * v * (math.sqrt(skin.k_contact * skin.finger.mass) + skin.c) + \
        skin.finger.relaxation(0.0) * 2 * 100e-6
    return [contact_case("zero_preload_contact_loss", make, np.diff(h) * FS, force_bound=bound,
                         disp_bound=2e-4),
            # The pin is kinematic: it moves 0.01 m/s x n/4 samples, and must not go further.
            group_step_case("contact_full_scale_step", make, 0.01, n,
                            disp_bound=1.001 * 0.01 * (n // 4) / FS, unit="m/s pin velocity")]
