"""The rig: tones switch on when the scene says, beat pairs, channel layout, buffers."""

import numpy as np
import pytest

from rtctl import scene
from rtctl.engine.rig import build


def drive_of(rig, n_blocks):
    out = []
    for k in range(n_blocks):
        rig.apply_schedule(k)
        rig.advance()
        out.append(rig.out.copy())
    return np.concatenate(out, axis=1)


def test_tone_starts_ramped_at_its_start_time():
    s = scene.load("line-bimorph-5", ["stimulus.tones.2.start=0.01"])
    rig = build(s)
    d = drive_of(rig, 40)
    k0 = int(0.01 * 48000 // 32) * 32
    assert np.all(d[2, :k0] == 0.0)
    # the amplitude ramps linearly from 0 to 40 V across the block: |v| <= 40 (i + 1) / 32
    assert np.all(np.abs(d[2, k0:k0 + 32]) <= 40.0 * np.arange(1, 33) / 32 + 1e-9)
    assert np.max(np.abs(d[2, k0 + 32:])) == pytest.approx(40.0, rel=1e-3)


def test_beat_pair_envelope_and_carrier():
    s = scene.load("line-bimorph-5", ["stimulus.tones.4.beat=10.0", "stimulus.tones.4.voltage=2.0"])
    rig = build(s)
    d = drive_of(rig, int(0.3 * 48000 / 32))[4, 32:]
    assert np.max(np.abs(d)) == pytest.approx(2.0, rel=1e-3)  # envelope peak = pair voltage
    t = (32 + np.arange(d.size)) / 48000
    ref = np.cos(2 * np.pi * 245 * t) + np.cos(2 * np.pi * 255 * t)
    np.testing.assert_allclose(d, ref, atol=1e-9)


def test_channel_layout_and_buffers():
    rig = build(scene.load("line-bimorph-5", ["actuator.lateral.grid=[2, 3]"]))
    assert rig.n_channels == 6 and rig.channel_names[4] == "lateral.4"
    assert rig.out.shape == (6, 32) and rig.sensed.shape == (12, 32)
    assert rig.out.flags.c_contiguous and rig.out.dtype == np.float64
    assert rig.truth.shape == (6, 4, 32)


def test_sensed_currents_lag_the_drive_by_one_block():
    rig = build(scene.load("line-bimorph-5", ["io.seed=3", "actuator.lateral.sense.noise=0.0"]))
    rig.apply_schedule(0)
    rig.advance()
    assert np.all(rig.sensed == 0.0)  # the first read comes before any write
    rig.advance()
    assert np.any(rig.sensed != 0.0)
