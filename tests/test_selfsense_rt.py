"""Real-time observer: kernel vs naive twin, and the issue's accuracy targets on the FE plant."""

import math

import numpy as np
import pytest

from naive_selfsense import observer_block, rebuild
from rtctl.plant.beam import BeamSpec, Layer, build_beam
from rtctl.plant.materials import BUILTIN
from rtctl.selfsense.rt import Observer, tone_window
from rtctl.selfsense.sweep import finger_loads, run_case
from rtctl.selfsense.tmm import TMMBeam

PZT = BUILTIN["PZT-5A"]
FS, BLOCK = 48000.0, 32


def fe_model():
    spec = BeamSpec(15e-3, 1.5e-3, (Layer(PZT, 0.3e-3), Layer(PZT, 0.3e-3)), "parallel",
                    (0.5, 0.5), 0.01)
    return build_beam(spec)


def test_kernel_matches_naive_twin():
    rng = np.random.default_rng(5)
    freqs = np.array([[245.0, 255.0], [1000.0, 0.0], [120.0, 40.0]])
    obs = Observer(TMMBeam.from_fe(fe_model()), freqs, FS, BLOCK)
    H = rng.standard_normal(obs.H.shape)
    H[1, 1] = 0.0                                  # the unused slot
    obs.H[:] = H
    W = obs.window
    assert W == tone_window(freqs, FS, BLOCK) and W % BLOCK == 0
    n = np.arange(W)
    drive = np.stack([np.cos(2 * np.pi * f[0] * n / FS + 0.3) + rng.standard_normal(W) for f in freqs])
    sensed = rng.standard_normal((3 * obs.n_seg, W)) * 1e-6
    for b in range(W // BLOCK):
        sl = slice(b * BLOCK, (b + 1) * BLOCK)
        assert obs.process(np.ascontiguousarray(drive[:, sl]), np.ascontiguousarray(sensed[:, sl])) == 0
    Hc = H[..., 0] + 1j * H[..., 1]
    want = observer_block(Hc, drive, sensed, freqs, FS, obs.n_seg)
    got = obs.est[..., 0] + 1j * obs.est[..., 1]
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12 * np.abs(want).max())
    wave = rebuild(want[:, :, 0], freqs, FS, W - BLOCK, BLOCK)
    np.testing.assert_allclose(obs.wave, wave, rtol=1e-9, atol=1e-9 * np.abs(wave).max())


def test_nonfinite_reading_is_flagged():
    obs = Observer(TMMBeam.from_fe(fe_model()), [[250.0]], FS, BLOCK)
    drive = np.zeros((1, BLOCK))
    sensed = np.full((2, BLOCK), np.nan)
    assert obs.process(drive, sensed) != 0


CASES = [([10.0], 20.0), ([250.0], 20.0), ([1000.0], 20.0), ([245.0, 255.0], 10.0),
         ([995.0, 1005.0], 10.0)]


@pytest.mark.slow
@pytest.mark.parametrize("load", ["50g", "2g", "none"])
@pytest.mark.parametrize("freqs,volts", CASES, ids=["10Hz", "250Hz", "1kHz", "beat250", "beat1k"])
def test_observer_on_fe_plant_60db(freqs, volts, load):
    """Issue target: amplitude within 1 %, phase within 1 degree at 60 dB SNR (measured worst
    0.43 % and 0.32 deg). Force: measured 0.7-1.1 % without contact, 1.3-6.1 % at 50 g and
    1.3-19 % at 2 g (see docs/selfsense.md: aliased-image model vs the 4-mode plant)."""
    r = run_case(fe_model(), finger_loads()[load], freqs, [volts] * len(freqs), snr_db=60.0)
    assert r["amp_err_pct"] < 1.0
    assert r["phase_err_deg"] < 1.0
    assert r["cond"] < 10
    limit = {"none": 5.0, "50g": 8.0, "2g": 25.0}[load]
    assert r["force_err_pct"] < limit
