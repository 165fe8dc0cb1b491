"""What one sweep point computes (``--what``), from the package's own models, as flat columns.

* ``model``: per bimorph group ``G``, :func:`rtctl.model_report.model_facts` (what ``rtctl
  model`` prints, without its transfer-matrix cross-check): ``G.f1_hz`` ... ``G.f4_hz`` free,
  ``G.f1_loaded_hz`` ... under the scene's finger, ``G.static_compliance_m_per_n``,
  ``G.deflection_per_volt_m``, ``G.blocked_force_per_volt_n``, ``G.capacitance_f``.
* ``reach``: per receptor ``R`` that a sine tone on a bimorph group addresses, the largest tip
  amplitude at ``max_voltage`` under the finger over that receptor's tones: each tone alone on
  its channel at the group's ``max_voltage`` (a beat pair: half of it on each of its two tones,
  the envelope peak), through the simulated plant's frequency response (the finite-element beam
  with the modes ``beam.modes`` keeps, finger and amplifier: what a ``sim`` run's tip does in steady state).
  Columns ``R.reach_um``, ``R.freq_hz`` and ``R.channel`` (the tone that reaches furthest),
  ``R.threshold_um`` (:mod:`rtctl.perception`), ``R.margin_db`` (``20 log10(reach /
  threshold)``), ``R.needed_v`` (the drive that would just reach the threshold) and ``R.felt``
  (reach >= threshold with a finger on the display, as ``rtctl run`` judges it).
* ``selfsense``: per bimorph group, the self-sensing observer's errors on the simulated plant
  (:func:`rtctl.selfsense.sweep.run_case`, as ``rtctl selfsense``), worst over the group's tone
  frequencies (default 10, 250, 1000 Hz): ``G.amp_err_pct``, ``G.phase_err_deg``,
  ``G.force_err_pct``, ``G.wave_err_pct``, ``G.cond``.
* ``run``: a whole run on the simulated rig, per channel with a tone ``C``: ``C.true_um``,
  ``C.error_pct``, ``C.settle_ms``, ``C.felt``, ``C.saturated``, ``C.reachable_um``,
  ``C.estimated_um``, and ``faults`` (how many) with the first one in ``fault``. The run itself
  comes from the caller (``runner``, the engine's ``run``): this package does not import the
  engine, the command line hands it over.

A task is plain data (the scene's TOML text, its ``--set`` strings, point indices), so that
workers anywhere rebuild the scene and compile from their own numba cache; nothing built is sent.
"""

from __future__ import annotations

import math
import time

from ..errors import RtctlError

WHATS = ("model", "reach", "selfsense", "run")

#: Frequencies of the observer accuracy for a bimorph group without a tone (``rtctl selfsense``'s).
SELFSENSE_FREQS = (10.0, 250.0, 1000.0)
#: Drive of each observer case, V (``rtctl selfsense``'s; the current noise is set as an SNR).
SELFSENSE_VOLTS = 10.0


def parse_whats(text: str) -> tuple[str, ...]:
    """``--what``: one of :data:`WHATS` or several, comma-separated."""
    whats = tuple(w.strip() for w in text.split(",") if w.strip())
    bad = [w for w in whats if w not in WHATS]
    if bad or not whats:
        raise RtctlError(f"--what {text!r}: must be one or more of {', '.join(WHATS)} (comma-separated)")
    return tuple(dict.fromkeys(whats))


#: Modules each ``--what`` imports on its first point (scipy and the models: ~1 s a process).
MODULES = {
    "model": ("rtctl.scene", "rtctl.model_report", "rtctl.models", "rtctl.plant.facts"),
    "reach": ("rtctl.scene", "rtctl.models", "rtctl.plant.bimorph", "rtctl.plant.frontend", "rtctl.perception"),
    "selfsense": ("rtctl.scene", "rtctl.models", "rtctl.selfsense.sweep"),
    "run": ("rtctl.scene", "rtctl.models"),
}


def warm(whats) -> str:
    """Import what the points of ``whats`` need, so that a worker's first point costs what the
    others do (the sweep's start-up pays the imports, its rate is the points'). Returns the
    rtctl version, which a sweep's workers report before the first task."""
    import importlib

    import rtctl

    for w in whats:
        for m in MODULES[w]:
            importlib.import_module(m)
    return rtctl.__version__


def check(scene, whats) -> None:
    """Refuse (RtctlError, one line) a scene that a ``--what`` has nothing to compute on."""
    bimorphs = [g.name for g in scene.actuator if g.type == "bimorph"]
    for w in whats:
        if w in ("model", "selfsense") and not bimorphs:
            raise RtctlError(f"{scene.source}: --what {w} needs a bimorph actuator group (have "
                             f"{', '.join(f'{g.name} ({g.type})' for g in scene.actuator)})")
        if w == "reach" and not _reach_tones(scene):
            raise RtctlError(f"{scene.source}: --what reach needs a sine tone on a bimorph group with a receptor "
                             "(stimulus.kind = 'tones', a tone whose receptor answers at its frequency)")
        if w == "run":
            from ..needs import needs, unavailable_message

            if scene.io.backend != "sim":
                raise RtctlError(f"{scene.source}: --what run sweeps the simulated rig; io.backend = "
                                 f"{scene.io.backend!r} (set io.backend=sim)")
            n = needs(scene)
            if n.unavailable:
                raise RtctlError(unavailable_message(n.unavailable[0], n.needed[n.unavailable[0]]))


def metrics(scene, whats, runner=None) -> dict:
    """The columns of one point: every ``--what`` in ``whats`` on ``scene`` (see the module
    docstring). ``runner``: the engine's ``run(scene, out_dir=..., plot=...)``, for ``run``."""
    out: dict = {}
    for w in whats:
        if w == "model":
            out.update(model_metrics(scene))
        elif w == "reach":
            out.update(reach_metrics(scene))
        elif w == "selfsense":
            out.update(selfsense_metrics(scene))
        elif w == "run":
            if runner is None:
                raise RtctlError("--what run needs the engine's run function (runner)")
            out.update(run_metrics(scene, runner))
        else:
            raise RtctlError(f"unknown --what {w!r}")
    return out


def model_metrics(scene) -> dict:
    from ..model_report import model_facts

    out = {}
    for name, f in model_facts(scene, tmm=False).items():
        if "note" in f:  # not a bimorph: no model facts
            continue
        for i, x in enumerate(f["natural_frequencies_hz"], 1):
            out[f"{name}.f{i}_hz"] = float(x)
        for i, x in enumerate(f["loaded_natural_frequencies_hz"], 1):
            out[f"{name}.f{i}_loaded_hz"] = float(x)
        for k in ("static_compliance_m_per_n", "deflection_per_volt_m", "blocked_force_per_volt_n", "capacitance_f"):
            out[f"{name}.{k}"] = float(f[k])
    return out


def _reach_tones(scene) -> list:
    """``(tone index, tone, receptor)`` of every sine tone on a bimorph group with a receptor."""
    from ..perception import auto_receptor

    if scene.stimulus.kind != "tones":
        return []
    out = []
    for i, t in enumerate(scene.stimulus.tones):
        if t.shape != "sine" or scene.group(t.actuator).type != "bimorph":
            continue
        receptor = auto_receptor(t.freq) if t.receptor == "auto" else t.receptor
        if receptor:
            out.append((i, t, receptor))
    return out


def reach_metrics(scene) -> dict:
    import numpy as np

    from ..models import Models
    from ..perception import threshold_m
    from ..plant.bimorph import BimorphPlant
    from ..plant.frontend import Amplifier, CurrentSense

    models, plants, best = Models(scene), {}, {}
    for _, t, receptor in _reach_tones(scene):
        g = scene.group(t.actuator)
        if g.name not in plants:  # the simulated plant's own build (rtctl.io.sim), noise aside
            plants[g.name] = BimorphPlant(models.beam(g), Amplifier(g.amplifier.bandwidth),
                                          CurrentSense(g.sense.shunt, g.sense.aa_cutoff, g.sense.aa_order),
                                          models.finger(g), n_modes=models.plant_modes(g))
        if t.beat > 0:
            from ..dsp import beat_tones

            freqs, volts = beat_tones(t.freq, t.beat, g.max_voltage)
        else:
            freqs, volts = np.array([t.freq]), np.array([g.max_voltage])
        tip = np.abs(plants[g.name].frequency_response(freqs)[:, 0])  # m per commanded volt
        amp = float(np.sum(tip * volts))  # a pair's envelope peak: its two tones in phase
        if receptor not in best or amp > best[receptor][0]:
            best[receptor] = (amp, t, g, threshold_m(t.freq, receptor))
    out = {}
    for receptor, (amp, t, g, thr) in best.items():
        margin = 20.0 * math.log10(amp / thr) if amp > 0 and math.isfinite(thr) else math.nan
        out[f"{receptor}.reach_um"] = amp * 1e6
        out[f"{receptor}.freq_hz"] = float(t.freq)
        out[f"{receptor}.channel"] = f"{g.name}.{t.channel}"
        out[f"{receptor}.threshold_um"] = thr * 1e6
        out[f"{receptor}.margin_db"] = margin
        out[f"{receptor}.needed_v"] = g.max_voltage * thr / amp if amp > 0 else math.inf
        # a tip moving in air is felt by no one, however far it moves (rtctl run's rule)
        out[f"{receptor}.felt"] = bool(scene.finger.contact and amp >= thr)
    return out


def selfsense_metrics(scene) -> dict:
    from ..dsp.oscillator import beat_tones
    from ..models import Models
    from ..selfsense.sweep import run_case, truth_modes

    models, out = Models(scene), {}
    fs = float(scene.timing.fs)
    for g in scene.actuator:
        if g.type != "bimorph":
            continue
        fe, finger = models.beam(g), models.finger(g)
        tones = scene.stimulus.tones if scene.stimulus.kind == "tones" else ()
        freqs = sorted({float(f) for t in tones if t.actuator == g.name and t.shape == "sine"
                        for f in ((t.freq,) if t.beat == 0 else beat_tones(t.freq, t.beat, 1.0)[0])})
        kw = dict(fs=fs, block=int(scene.timing.block), amplifier_hz=g.amplifier.bandwidth,
                  aa_cutoff_hz=g.sense.aa_cutoff, aa_order=g.sense.aa_order, shunt=g.sense.shunt,
                  n_modes=truth_modes(fe, fs, models.plant_modes(g)))
        cases = [run_case(fe, finger, [f], [SELFSENSE_VOLTS], **kw) for f in (freqs or SELFSENSE_FREQS)]
        out[f"{g.name}.amp_err_pct"] = max(c["amp_err_pct"] for c in cases)
        out[f"{g.name}.phase_err_deg"] = max(c["phase_err_deg"] for c in cases)
        out[f"{g.name}.force_err_pct"] = max(c["force_err_pct"] for c in cases)
        out[f"{g.name}.wave_err_pct"] = max(100.0 * c["wave_err"] for c in cases)
        out[f"{g.name}.cond"] = max(c["cond"] for c in cases)
    return out


#: Per-channel values of a run's summary that a sweep keeps (none depends on the wall clock).
RUN_KEYS = ("true_um", "error_pct", "settle_ms", "felt", "saturated", "reachable_um", "estimated_um", "floor_s",
            "releases", "pulses")


def run_metrics(scene, runner) -> dict:
    import tempfile

    with tempfile.TemporaryDirectory(prefix="rtctl-sweep-") as tmp:
        summary = runner(scene, out_dir=tmp, plot=False).summary
    out: dict = {}
    for row in summary["channels"]:
        if row.get("freq_hz") is None:  # an idle channel
            continue
        for k in RUN_KEYS:
            v = row.get(k)
            out[f"{row['name']}.{k}"] = bool(v) if k == "saturated" else v
    out["faults"] = len(summary["faults"])
    out["fault"] = summary["faults"][0] if summary["faults"] else None
    return out


def compute(task: dict) -> list[dict]:
    """Run one task: its points, one after another, each in its own ``try``: a failed point is
    a result with its error message, never a failed task.

    Parameters
    ----------
    task : dict
        ``text`` (scene TOML), ``origin`` (where it came from, for messages and relative
        paths), ``set`` (the sweep's ``--set`` strings), ``points`` (``[index, [--set strings
        of the point]]`` pairs), ``what`` (tuple of :data:`WHATS`), ``runner`` (or None).

    Returns
    -------
    list of dict
        Per point: ``index``, ``metrics`` (dict), ``error`` (None or one line), ``seconds``.
    """
    from .. import scene as scene_mod

    out = []
    for index, sets in task["points"]:
        t0 = time.perf_counter()
        try:
            sc = scene_mod.loads(task["text"], [*task["set"], *sets], task["origin"])
            m, err = metrics(sc, task["what"], task.get("runner")), None
        except RtctlError as e:
            m, err = {}, str(e)
        except Exception as e:  # a model's numerical failure, a bug: the point's row says which
            m, err = {}, f"{type(e).__name__}: {e}"
        if err is not None:
            err = " ".join(err.split())  # one line in the table
        out.append({"index": int(index), "metrics": m, "error": err, "seconds": time.perf_counter() - t0})
    return out
