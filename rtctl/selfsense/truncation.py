"""What the observer reads of a simulated bimorph cut to fewer modes than its drive's images reach.

The observer's model is the continuum: every mode, and with them the answer of the modes near
the drive's images. The DAC's staircase puts an image of each tone at ``k fs +- f``; a mode near
one answers with a current that the ADC folds back onto ``f`` itself, and the observer predicts
that share from the drive. A simulated plant cut to ``beam.modes`` modes has no such answer where
it left those modes out: the simulated device is then not the device the observer is built for,
and a closed loop holds its tips off target by what the observer misreads.

:func:`observer_error` computes that misreading in the frequency domain, without a run: the
plant's exact sampled response to the staircase (``c2d``, zero-order hold) at the skin band's
frequencies, read by the observer's designs (:func:`~rtctl.selfsense.observer.design_many`), its
tip estimate against the plant's own tip, under the scene's finger and with the finger lifted.
"""

from __future__ import annotations

import numpy as np

#: Frequencies the misreading is computed at, Hz (the skin's band, as the accuracy sweep's).
FREQS_HZ = (10.0, 25.0, 63.0, 160.0, 400.0, 1000.0)


def observer_errors(models, group, n_modes: int, freqs_hz=FREQS_HZ, lifted: bool = False) -> np.ndarray:
    """The observer's relative tip-amplitude error (estimate over truth, minus 1) at each of
    ``freqs_hz`` (Hz, below ``fs / 2``), reading the simulated plant of bimorph ``group`` cut to
    ``n_modes`` modes, under the scene's finger (``lifted``: without it). Nothing random: the
    plant's sampled response and the observer's design for the same load.

    Parameters
    ----------
    models : rtctl.models.Models
    group : the scene's actuator group (``type = "bimorph"``)
    n_modes : int
        Modes the simulated plant keeps.
    """
    from ..models import OBSERVER_MAX_COND
    from ..plant.bimorph import BimorphPlant
    from ..plant.frontend import Amplifier, CurrentSense
    from ..plant.lti import c2d
    from .observer import design_many

    fs = float(models.scene.timing.fs)
    freqs = [float(f) for f in freqs_hz]
    if not all(0.0 < f < fs / 2 for f in freqs):
        raise ValueError(f"frequencies must lie in 0 < f < fs / 2 = {fs / 2:g} Hz, got {freqs}")
    beam = models.beam(group)
    s = group.sense
    sense = CurrentSense(s.shunt, s.aa_cutoff, s.aa_order, s.bits, s.full_scale, s.noise)
    load = None if lifted else models.finger(group)
    plant = BimorphPlant(beam, Amplifier(group.amplifier.bandwidth), sense, load, n_modes=n_modes)
    d = c2d(plant.sys, 1.0 / fs, "zoh")
    sensed = [i for i, name in enumerate(plant.OUTPUT_NAMES) if name.startswith("sensed")]
    designs = design_many(models.observer_beam(group), freqs, models.frontend(group, fs), image_load=load,
                          max_cond=OBSERVER_MAX_COND)
    eye = np.eye(d.A.shape[0])
    out = np.empty(len(freqs))
    for k, f in enumerate(freqs):
        x = np.linalg.solve(np.exp(2j * np.pi * f / fs) * eye - d.A, d.B[:, 0])
        tip = d.C[0] @ x + d.D[0, 0]
        est = designs[f].H[0] @ np.concatenate(([1.0], d.C[sensed] @ x + d.D[sensed, 0]))
        out[k] = abs(est) / abs(tip) - 1.0
    return out


def observer_error(models, group, n_modes: int, freqs_hz=FREQS_HZ) -> tuple[float, float]:
    """The largest of :func:`observer_errors`' magnitudes, under the scene's finger and lifted,
    and the frequency it is at (Hz)."""
    freqs = [float(f) for f in freqs_hz if 0.0 < f < models.scene.timing.fs / 2]
    if not freqs:
        return 0.0, 0.0
    lifts = (False, True) if models.finger(group) is not None else (True,)
    err = np.abs([observer_errors(models, group, n_modes, freqs, lifted) for lifted in lifts]).max(axis=0)
    k = int(np.argmax(err))
    return float(err[k]), freqs[k]
