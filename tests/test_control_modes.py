"""Which loaded mode rings beside a tone: the simulated plant's poles against the continuum
transfer-matrix beam's resonances, under the scene's finger sets and fingers three times softer
and stiffer."""

from __future__ import annotations

import numpy as np
import pytest

from rtctl import scene
from rtctl.models import FINGER_SPREAD, Models
from rtctl.plant.finger import MaxwellLoad


def _peak(beam, load, lo, hi):
    """The frequency (Hz) of the tip response's largest magnitude between lo and hi, to 0.1 Hz
    (on a 4 Hz grid, then within 4 Hz of its best)."""
    f = np.arange(lo, hi, 4.0)
    best = f[np.argmax(np.abs(beam.response(f, load)["tip"]))]
    f = np.arange(best - 4.0, best + 4.0, 0.1)
    return f[np.argmax(np.abs(beam.response(f, load)["tip"]))]


@pytest.mark.parametrize("tone", [500.0, 1000.0])
def test_the_nearest_loaded_mode_is_the_continuum_beams_resonance(tone):
    """line-bimorph-5-closed: the loaded mode nearest to the tone over the finger's two sets,
    each as set and at k0 / 3 and x 3, and the finger lifted, from the plant's poles, within 1 %
    of the transfer-matrix beam's resonance under the same load (another model of the same
    beam). At 500 Hz that is the 200 g set at k0 / 3 (585 Hz); the sets as given put it 130 Hz
    away."""
    s = scene.load("line-bimorph-5-closed")
    m = Models(s)
    g = s.actuator[0]
    df, tau = m.nearest_modes(g, np.array([tone]))
    beam = m.observer_beam(g)
    peaks = []
    for load in [m.finger(g), *m.other_fingers(g)]:
        for x in ((1.0,) if load is None else (1.0, 1.0 / FINGER_SPREAD, FINGER_SPREAD)):
            the = None if load is None else MaxwellLoad(load.mass, load.k0 * x, load.branches)
            peaks.append(_peak(beam, the, 300.0, 1600.0))
    nearest = min(peaks, key=lambda p: abs(p - tone))
    assert df[0] == pytest.approx(abs(nearest - tone), abs=0.01 * nearest)
    assert 1e-3 < tau[0] < 0.1  # a loaded mode's ring: milliseconds to tens of them
    if tone == 500.0:
        assert nearest == pytest.approx(585.0, abs=6.0)
        as_set = [_peak(beam, load, 300.0, 1600.0) for load in [m.finger(g), *m.other_fingers(g)]]
        assert min(abs(p - tone) for p in as_set) > 120.0


@pytest.mark.parametrize("order", [2, 4, 5])
def test_the_loaded_modes_hold_the_sense_chains_filter_of_the_scenes_order(order):
    """The plant the loaded modes come from has the scene's anti-alias filter: its oscillating
    poles are the analog Butterworth's of ``sense.aa_order`` at ``sense.aa_cutoff``
    (scipy.signal.butter), each pair once per sensed segment (each has its filter)."""
    import scipy.signal

    fc = 9e3
    s = scene.load("line-bimorph-5-closed", [f"actuator.lateral.sense.aa_order={order}",
                                             f"actuator.lateral.sense.aa_cutoff={fc:g}"])
    m = Models(s)
    g = s.actuator[0]
    f, tau = m.loaded_modes(g, m.finger(g))
    z, p, k = scipy.signal.butter(order, 2.0 * np.pi * fc, analog=True, output="zpk")
    pairs = p[p.imag > 1e-6 * np.abs(p)]
    assert pairs.size == order // 2
    for q in pairs:
        hit = np.abs(f - q.imag / (2.0 * np.pi)) < 1e-6 * fc
        assert hit.sum() == len(g.beam.segments)
        assert tau[hit] == pytest.approx(np.full(hit.sum(), -1.0 / q.real), rel=1e-6)
