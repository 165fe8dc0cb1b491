"""Square and pulse tones (pulse trains in the block step), finger parameter sets by subject and
preload, and per-type scene keys."""

import numpy as np
import pytest
from test_rig import drive_of

from rtctl import scene
from rtctl.engine.rig import build
from rtctl.errors import SceneError
from rtctl.models import finger_load
from rtctl.needs import needs


def test_square_tone_is_plus_minus_voltage_at_half_duty_after_its_start():
    # 100 Hz at 48 kHz: 480 samples per period, 240 at +V then 240 at -V, starting at the
    # block holding the start time; the slew limit (5e6 V/s = 104 V/sample) passes the edges.
    s = scene.load("line-bimorph-5", ["stimulus.tones.1.shape=square", "stimulus.tones.1.freq=100.0",
                                      "stimulus.tones.1.voltage=20.0", "stimulus.tones.1.start=0.01"])
    n = needs(s)
    assert "dsp.pulse" in n.needed and "dsp.oscillator" in n.needed
    d = drive_of(build(s), 60)[1]
    k0 = int(0.01 * 48000 // 32) * 32
    assert np.all(d[:k0] == 0.0)
    period = d[k0:k0 + 480]
    assert np.all(period[:240] == 20.0) and np.all(period[240:] == -20.0)


def test_pulse_tone_duty_and_only_pulse_trains_when_no_sine():
    over = [f"stimulus.tones.{i}.shape=pulse" for i in range(5)] + [
        "stimulus.tones.0.duty=0.25", "stimulus.tones.0.freq=200.0", "stimulus.tones.0.voltage=10.0"]
    s = scene.load("line-bimorph-5", over)
    n = needs(s)
    assert "dsp.pulse" in n.needed and "dsp.oscillator" in n.left_out
    rig = build(s)
    assert rig.bank is None and [s.name for s in rig.stages if s.name in ("oscillators", "pulses")] == ["pulses"]
    d = drive_of(rig, 150)[0]
    # 200 Hz: 240 samples per period, high for 60; the DDS rounds the step to 2**-40 cycle, so an
    # edge may land one sample late, but the mean duty over 20 periods is exact to 1/4800.
    per = d[:240]
    assert np.all(per[:60] == 10.0) and np.all(per[61:] == 0.0)
    assert set(np.unique(d)) == {0.0, 10.0}
    assert np.count_nonzero(d[:4800]) / 4800 == pytest.approx(0.25, abs=1 / 4800)


def test_beat_pair_must_be_sine():
    with pytest.raises(SceneError, match="beat pair needs shape = 'sine'"):
        build(scene.load("line-bimorph-5", ["stimulus.tones.1.shape=square", "stimulus.tones.1.beat=2.0"]))


SUBJECTS = """
[scene]
name = "subjects"
[finger]
subject = "B"
preload = 0.4
subjects = [
  {name = "A", direction = "lateral", preload = 0.02, k0 = 111.0, branches = []},
  {name = "B", direction = "lateral", preload = 0.02, k0 = 222.0, branches = []},
  {name = "B", direction = "lateral", preload = 0.49, k0 = 333.0, branches = [{k = 10.0, tau = 0.01}]},
  {name = "B", direction = "normal", preload = 0.49, k0 = 444.0, branches = []},
]
[[actuator]]
name = "lat"
type = "bimorph"
max_voltage = 100.0
[actuator.beam]
length = 15.0e-3
width = 1.5e-3
layers = [{material = "PZT-5A", thickness = 0.3e-3}, {material = "PZT-5A", thickness = 0.3e-3}]
"""


def test_subject_set_nearest_in_preload_and_direction_is_used():
    s = scene.loads(SUBJECTS)
    f = finger_load(s, s.actuator[0])
    assert f.k0 == 333.0 and f.n_branches == 1   # B lateral at 0.49 N is nearest 0.4 N
    s2 = scene.loads(SUBJECTS, ["finger.preload=0.03"])
    assert finger_load(s2, s2.actuator[0]).k0 == 222.0
    s3 = scene.loads(SUBJECTS, ["finger.subject=C"])
    with pytest.raises(SceneError, match="finger.subject = 'C' has no lateral set"):
        finger_load(s3, s3.actuator[0])


def test_keys_of_another_actuator_type_are_refused():
    bad = SUBJECTS.replace('type = "bimorph"', 'type = "solenoid"')
    with pytest.raises(SceneError, match=r"actuator.lat.beam = .*applies to actuator type bimorph, not 'solenoid'"):
        scene.loads(bad)
