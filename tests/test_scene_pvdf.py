"""The bundled PVDF scene reproduces seed 004's superposition at the measurement point, end to
end through the loop and the trace: two neighbouring cells at 500 Vpp, 100 Hz and 110 Hz, beat
at 10 Hz on a ~105 Hz carrier, with peaks matching 1000 Vpp on one cell."""

import numpy as np
import pytest
from scipy.signal import hilbert

from rtctl import scene
from rtctl.engine.run import run
from rtctl.trace import TraceReader

FS = 48000.0


def probe(tmp_path, name, *sets):
    s = scene.load("pvdf-6x8", ["timing.duration=0.8", *sets])
    run(s, out_dir=tmp_path / name, plot=False, progress=False)
    x = TraceReader(tmp_path / name / "trace").signal("cells.probe_displacement")[0].astype(float)
    return x[int(0.3 * FS):int(0.8 * FS)]  # after the first plate transients


@pytest.mark.slow
def test_beat_at_the_probe_envelope_carrier_and_peak(tmp_path):
    pair = probe(tmp_path, "pair")
    one = probe(tmp_path, "one", "stimulus.tones.0.voltage=500.0", "stimulus.tones.1.voltage=0.0")
    a = hilbert(pair)
    env = np.abs(a)
    t = np.arange(env.size) / FS
    # envelope frequency: the dominant line of the envelope spectrum (0.5 s -> 2 Hz bins)
    spec = np.abs(np.fft.rfft(env - env.mean(), 8 * env.size))
    f_env = np.fft.rfftfreq(8 * env.size, 1 / FS)[np.argmax(spec)]
    assert f_env == pytest.approx(10.0, abs=0.3)
    # carrier: the instantaneous frequency weighted by the envelope power, which for two tones
    # is their power-weighted mean frequency (phase steps at the envelope nulls get no weight)
    m = (t > 0.05) & (t < 0.45)
    w = np.angle(a[1:] * np.conj(a[:-1])) * FS / (2 * np.pi)
    p = (env[1:] * env[:-1])[m[1:]]
    f_c = np.sum(w[m[1:]] * p) / np.sum(p)
    assert f_c == pytest.approx(105.0, abs=0.5)
    # the envelope peaks reach what 1000 Vpp on one cell gives (symmetric probe)
    assert env[m].max() == pytest.approx(np.abs(hilbert(one))[m].max(), rel=0.03)
