"""The observer across a drive step (``Observer(steps=True)``, the default): a window whose drive
changed reads the tip as the lock-in of the true tip over the same window does, where the bare
observer read it at up to several times its amplitude (the currents' capacitive share has a
boundary term the drive's phasor has not); a steady tone reads the same either way."""

import numpy as np
import pytest

from rtctl.dsp.lockin import LockIn
from rtctl.plant import TRUTH_NAMES, Amplifier, BimorphPlant, CurrentSense, SimGroup
from rtctl.plant.beam import BeamSpec, Layer, build_beam
from rtctl.plant.materials import BUILTIN
from rtctl.selfsense.frontend import FrontEnd
from rtctl.selfsense.rt import Observer, short_windows
from rtctl.selfsense.sweep import finger_loads, truth_modes
from rtctl.selfsense.tmm import TMMBeam

PZT = BUILTIN["PZT-5A"]
FS, BLOCK = 48000.0, 32


def fe_model(thickness=0.3e-3):
    spec = BeamSpec(15e-3, 1.5e-3, (Layer(PZT, thickness), Layer(PZT, thickness)), "parallel", (0.5, 0.5), 0.01)
    return build_beam(spec)


def step_run(freqs, v0, v1, load="50g", lstsq=False, thickness=0.3e-3, rise_blocks=8, prefilter=None):
    """A plant in steady state at ``v0`` volts per tone, the drive stepped to ``v1`` after two
    windows (a raised cosine over ``rise_blocks``: a faster one rings the loaded first mode, at
    600 Hz, which both readings and the truth's lock-in pass differently); per block from the
    step on, for two windows, the estimates' tip amplitude with and without the correction and
    the lock-in of the true tip over the same window."""
    fe = fe_model(thickness)
    freqs = np.asarray(freqs, dtype=float)
    finger = finger_loads()[load]
    sense = CurrentSense(100.0, 20e3, 2, noise_rms_v=0.0)
    plant = BimorphPlant(fe, Amplifier(20e3), sense, finger, n_modes=truth_modes(fe, FS))
    group = SimGroup(plant, FS, 1, max_block=BLOCK)
    w = 2 * np.pi * freqs
    ms = group.modal.sys
    z = np.exp(1j * w / FS)
    group.state[:, 0] = sum(np.linalg.solve(zk * np.eye(ms.n_states) - ms.A, ms.B[:, 0]) * v0 for zk in z).real
    kw = {}
    if lstsq:
        win, lsq, hop = short_windows(freqs[None, :], FS, BLOCK)
        kw = dict(window=win, lstsq=lsq, hop=hop)
    front = FrontEnd(FS, 20e3, 20e3, 2)
    model = TMMBeam.from_fe(fe_model())          # the model the observer was designed on
    with_, without = (Observer(model, freqs[None, :], FS, BLOCK, front, image_load=finger, steps=s,
                               prefilter=prefilter, **kw) for s in (True, False))
    W = with_.window
    truth = LockIn(1, freqs[None, :], FS, W, hop=with_.hop, lstsq=with_.lstsq)
    drive, sensed = np.zeros((1, BLOCK)), np.zeros((plant.n_seg, BLOCK))
    tr = np.zeros((1, len(TRUTH_NAMES), BLOCK))
    n_pre = 2 * W // BLOCK                       # the start (the filter's, at 0 V before it) long gone
    n_post = 2 * W // BLOCK + rise_blocks
    rows = []
    for b in range(n_pre + n_post):
        n = b * BLOCK + np.arange(BLOCK)
        x = np.clip((n - n_pre * BLOCK + 1) / (rise_blocks * BLOCK), 0.0, 1.0)
        a = v0 + (v1 - v0) * 0.5 * (1.0 - np.cos(np.pi * x))
        drive[0] = np.sum(a * np.cos(w[:, None] * n[None, :] / FS), axis=0)
        assert group.process(drive, sensed, tr) == 0
        for obs in (with_, without):
            assert obs.process(drive, sensed) == 0
        truth.process(np.ascontiguousarray(tr[0, :1]))
        if b >= n_pre:
            rows.append((np.abs(with_.phasors()[0]), np.abs(without.phasors()[0]), np.abs(truth.phasor[0])))
    return np.array(rows)                         # (blocks, 3, n_tones)


def worst(rows):
    """Worst relative error of the estimates with and without the correction, over the blocks."""
    e = np.abs(rows[:, :2] / rows[:, 2:3] - 1.0)
    return e[:, 0].max(), e[:, 1].max()


# Measured (no current noise, the model exact, a 50 g finger): worst over the two windows after
# the step, with / without the correction: 10 Hz 1.6 / 188 % (low-passed at 263 Hz, as the closed
# loop does: 1.4 / 186 %), 40 Hz 2.2 / 138 %, 250 Hz 7.7 / 147 %, 1 kHz 13 / 65 %. What is left
# grows with the tone: the tip's own transient (the beam's ring), which the truth's lock-in reads
# otherwise than the currents'. A steady tone reads its truth to 1e-4 either way.
@pytest.mark.parametrize("freqs,v0,v1,prefilter,bound", [([10.0], 40.0, 70.0, None, 0.03),
                                                         ([10.0], 40.0, 70.0, 263.0, 0.03),
                                                         ([40.0], 40.0, 80.0, 263.0, 0.04),
                                                         ([250.0], 10.0, 5.0, None, 0.12),
                                                         ([1000.0], 2.0, 4.0, None, 0.2)])
def test_a_window_over_a_drive_step_reads_the_tip_as_its_own_lock_in(freqs, v0, v1, prefilter, bound):
    with_, without = worst(step_run(freqs, v0, v1, prefilter=prefilter))
    assert with_ < bound
    assert without > 0.6                          # what it read before


def test_a_beat_pair_read_by_least_squares_across_a_step():
    with_, without = worst(step_run([235.0, 265.0], 10.0, 20.0, lstsq=True))   # 2.3 / 44 %
    assert with_ < 0.05
    assert without > 0.4


def test_a_free_tip_across_a_step():
    with_, without = worst(step_run([10.0], 40.0, 70.0, load="none", prefilter=263.0))  # 1.1 / 130 %
    assert with_ < 0.03
    assert without > 1.0


def test_a_device_off_its_model_keeps_most_of_the_gain():
    """The correction is the model's (its currents per drive volt): on a device 5 % thicker than
    its model the steady reading is 55 % off (uncalibrated), and the step adds 7 % to that, where
    it added 121 % without the correction."""
    rows = step_run([10.0], 40.0, 70.0, thickness=0.315e-3, prefilter=263.0)
    steady = abs(rows[-1, 0, 0] / rows[-1, 2, 0] - 1.0)
    with_, without = worst(rows)
    assert with_ < steady + 0.15
    assert without > steady + 1.0


@pytest.mark.parametrize("freqs,lstsq,prefilter", [([80.0], False, None), ([10.0], False, 263.0),
                                                   ([235.0, 265.0], True, None)])
def test_a_steady_tone_reads_the_same_with_and_without(freqs, lstsq, prefilter):
    """The boundary term of a steady tone is 0 over any window (whole periods or least squares,
    low-passed or not): the correction changes nothing but rounding."""
    rows = step_run(freqs, 10.0, 10.0, lstsq=lstsq, prefilter=prefilter)
    np.testing.assert_allclose(rows[:, 0], rows[:, 1], rtol=1e-9)
    assert np.all(np.abs(rows[:, 0] / rows[:, 2] - 1.0) < 1e-3)
