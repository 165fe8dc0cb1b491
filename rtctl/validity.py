"""Where the physical models stop holding, checked on a scene before anything is built.

A scene may hold values every key's range allows but no model describes: a bimorph beam shorter
than it is thick runs and reports a tip amplitude that means nothing. :func:`check` estimates
each model's own error from its neglected terms and refuses a scene beyond ``REFUSE`` (one line
naming the key, its value and the range), warns beyond ``WARN``, and otherwise says nothing.

* **Bimorph beam (Euler-Bernoulli)** neglects shear deformation and rotary inertia. Timoshenko's
  correction to a bending mode of wave number ``k`` in a beam of thickness ``h`` lowers its
  frequency by about ``(k h)^2 (1 + E / (kappa G)) / 24`` (radius of gyration ``h / sqrt 12``;
  shear coefficient ``kappa = 5/6``, ``E / G = 2 (1 + nu)`` with ``nu = 0.3`` for the piezo
  ceramics and metal shims the layers are). For the first cantilever mode ``k = 1.875 / L``:
  1 % at ``L / h = 7.7``, 10 % at ``L / h = 2.4``. A beam wider than long bends as a plate
  (anticlastic curvature held: up to ``1 / (1 - nu^2)``, 10 %, stiffer): a warning.
* **PVDF plate (Kirchhoff)** neglects the same terms: the estimate at the highest kept mode
  (``plate.max_mode_hz``), ``k = (omega^2 rho h / D)^(1/4)``, ``nu`` the plate's own.
* **Pin actuators (em, solenoid, dot)** are linear lumped models (force constant, inductance
  and stroke independent of position); their limits (iron saturation, the magnetic gap) are
  not scene keys, so nothing here can check them. **SMA springs**: the model's transformation
  plateau has no end; NiTi transforms fully near 4 % tensile strain (seed 002, straight
  wire), shear ``sqrt(3) 4 % = 6.9 %`` (von Mises): a prestrain whose wire-surface shear strain
  at full travel (``2 prestrain``) exceeds it is refused.
"""

from __future__ import annotations

import math

from .errors import ModelError, SceneError

__all__ = ["check", "shear_error", "WARN", "REFUSE"]

#: Estimated relative error of a model's first mode beyond which a scene is warned about / refused.
WARN, REFUSE = 0.01, 0.10
#: Poisson ratio assumed for beam layers (PZT 0.31, steel and brass shims 0.3); materials have none.
BEAM_NU = 0.3
#: Shear coefficient of a rectangular section.
KAPPA = 5.0 / 6.0
#: First cantilever bending mode, beta_1 L.
BETA1_L = 1.875104
#: Largest wire-surface shear strain the SMA model describes (full transformation, see above).
SMA_SHEAR_MAX = math.sqrt(3.0) * 0.04


def shear_error(kh: float, nu: float) -> float:
    """Estimated relative frequency error of Euler-Bernoulli / Kirchhoff bending at wave number
    times thickness ``kh``: ``(kh)^2 (1 + 2 (1 + nu) / kappa) / 24``."""
    return kh * kh * (1.0 + 2.0 * (1.0 + nu) / KAPPA) / 24.0


def _ratio_at(err: float, nu: float) -> float:
    """``L / h`` at which the first cantilever mode's :func:`shear_error` is ``err``."""
    return BETA1_L * math.sqrt((1.0 + 2.0 * (1.0 + nu) / KAPPA) / (24.0 * err))


def _pct(err: float) -> str:
    """The estimate in words: a first-order estimate means nothing beyond 100 %."""
    return f"about {100 * err:.2g} %" if err <= 1.0 else "far more than 100 % (the model does not apply)"


def check(scene) -> list[str]:
    """Raise :class:`SceneError` where a model is far outside its validity range; return the
    warnings (one line each) where it is near its edge."""
    warnings: list[str] = []
    src = scene.source
    for g in scene.actuator:
        key = f"actuator.{g.name}"
        if g.type == "bimorph":
            _beam(src, key, g.beam, warnings)
            _sim_modes(scene, g, key, warnings)
        elif g.type == "pvdf":
            _plate(src, key, g.plate, warnings)
        elif g.type == "sma":
            _sma(src, key, g.sma)
    return warnings


def _beam(src, key, b, warnings) -> None:
    h = sum(layer.thickness for layer in b.layers)
    L = b.length
    err = shear_error(BETA1_L * h / L, BEAM_NU)
    what = (f"{key}.beam.length = {L:g} m is {L / h:.3g} times the beam's thickness {h * 1e3:.4g} mm (the sum of "
            f"{key}.beam.layers' thicknesses): the Euler-Bernoulli beam model neglects shear and rotary inertia, "
            f"which shifts the first mode by {_pct(err)}")
    ok = (f"it needs length / thickness >= {_ratio_at(REFUSE, BEAM_NU):.2g} to run and >= "
          f"{_ratio_at(WARN, BEAM_NU):.2g} for a {100 * WARN:g} % model")
    if err > REFUSE:
        raise SceneError(f"{src}: {what}; {ok}: lengthen the beam or thin its layers")
    if err > WARN:
        warnings.append(f"{what}; {ok}")
    if b.width > L:
        warnings.append(f"{key}.beam.width = {b.width:g} m exceeds its length {L:g} m: it bends as a plate, up to "
                        f"{100 * (1 / (1 - BEAM_NU ** 2) - 1):.0f} % stiffer than the beam model says "
                        "(the beam model wants width <= length)")


def _sim_modes(scene, g, key, warnings) -> None:
    """A simulated plant cut to ``beam.modes`` modes that the observer reads off by more than
    ``WARN`` (:mod:`rtctl.selfsense.truncation`): a warning, computed only where an observer
    reads the simulated device."""
    n = int(g.beam.modes)
    c = scene.control
    if n <= 0 or scene.io.backend != "sim" or not (c.observe or c.mode == "closed"):
        return
    from .models import Models

    models = Models(scene)
    full = models.auto_modes(g)
    if full <= n:
        return
    try:
        err, f = _observer_error(scene, models, g, n, _tone_freqs(scene, g))
    except ModelError:  # an observer refused at one of the check's frequencies: the run says so at its own
        return
    if err > WARN:
        kept = models.beam(g).modes()[0][n - 1]
        warnings.append(f"{key}.beam.modes = {n} keeps the simulated beam's modes up to {kept / 1e3:.3g} kHz: "
                        f"it leaves out modes near the drive's images at k fs +- f, which the observer's model "
                        f"has, so the observer reads this simulated device {_pct(err)} off at {f:g} Hz (more if that "
                        f"makes it misjudge the finger) and a closed loop holds its tips as far from their targets; "
                        f"{key}.beam.modes = 0 keeps the {full} modes it needs")


#: The last scene checked and its observer errors per (group, modes): a scene checked by the
#: command line and again by the run it starts computes them once, and nothing piles up
_ERRORS: list = [None, {}]


def _tone_freqs(scene, g) -> tuple:
    """The frequencies (Hz) an observer of bimorph group ``g`` reads: the skin's band of the
    check (``FREQS_HZ``) and every sine of the scene's tones on ``g``'s channels (a 1.2 kHz tone
    on a beam cut to 4 modes read 2 % off, outside that band)."""
    from .dsp.oscillator import beat_tones
    from .selfsense.truncation import FREQS_HZ

    mine = []
    if scene.stimulus.kind == "tones":
        for t in scene.stimulus.tones:
            if t.actuator == g.name:  # (a tone's channel counts within its actuator)
                mine += beat_tones(t.freq, t.beat, 1.0)[0].tolist()  # (no beat: the carrier twice)
    return tuple(sorted(set(FREQS_HZ) | {float(f) for f in mine if f > 0}))


def _observer_error(scene, models, g, n, freqs):
    from .selfsense.truncation import observer_error

    if _ERRORS[0] is not scene:
        _ERRORS[:] = [scene, {}]
    known = _ERRORS[1]
    if (g.name, n, freqs) not in known:
        known[(g.name, n, freqs)] = observer_error(models, g, n, freqs)
    return known[(g.name, n, freqs)]


def _plate(src, key, p, warnings) -> None:
    D = p.E * p.thickness ** 3 / (12.0 * (1.0 - p.nu ** 2))
    w = 2.0 * math.pi * p.max_mode_hz
    kh = (w * w * p.rho * p.thickness / D) ** 0.25 * p.thickness
    err = shear_error(kh, p.nu)
    what = (f"{key}.plate.thickness = {p.thickness:g} m is thick against the bending wavelength "
            f"{2 * math.pi * p.thickness / kh * 1e3:.3g} mm of its highest kept mode ({key}.plate.max_mode_hz = "
            f"{p.max_mode_hz:g} Hz): the Kirchhoff plate model neglects shear and rotary inertia, which shifts "
            f"that mode by {_pct(err)}")
    ok = f"it needs an error below {100 * REFUSE:g} % to run and below {100 * WARN:g} % for an accurate model"
    if err > REFUSE:
        raise SceneError(f"{src}: {what}; {ok}: lower max_mode_hz or thin the plate")
    if err > WARN:
        warnings.append(f"{what}; {ok}")


def _sma(src, key, s) -> None:
    from .plant.sma import SmaTaxel

    t = SmaTaxel(prestrain=s.prestrain)
    gamma = t.d * 2.0 * t.delta0 / (math.pi * t.D ** 2 * t.N)
    if gamma > SMA_SHEAR_MAX:
        limit = SMA_SHEAR_MAX * math.pi * t.D ** 2 * t.N / (2.0 * t.d)
        raise SceneError(f"{src}: {key}.sma.prestrain = {s.prestrain:g} m strains the spring wire to a shear strain "
                         f"of {100 * gamma:.3g} % at full travel, beyond the {100 * SMA_SHEAR_MAX:.2g} % at which "
                         f"NiTi has transformed fully (the model's plateau has no end); use a prestrain up to "
                         f"{limit:.3g} m")
