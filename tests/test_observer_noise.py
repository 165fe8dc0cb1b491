"""The self-sensing estimate's noise floor (``Observer.noise_floor``) against the observer itself
run on white current noise: plain lock-in windows, a least-squares window, a low-passed channel."""

from __future__ import annotations

import numpy as np
import pytest

from rtctl import scene
from rtctl.models import Models
from rtctl.selfsense.rt import prefilter_cutoffs, short_windows


def _observer(freqs):
    s = scene.load("line-bimorph-5-closed")
    m, g = Models(s), s.actuator[0]
    fs, block = s.timing.fs, s.timing.block
    window, lstsq, hop = short_windows(freqs, fs, block)
    return m.observer(g, freqs, fs, block, window=window, hop=hop, lstsq=lstsq,
                      prefilter=prefilter_cutoffs(freqs, fs, m.lowest_mode(g)))


def test_the_noise_floor_is_the_rms_the_observer_reads_from_white_current_noise():
    """Four channels (250 Hz and 1 kHz over whole periods, 235 + 265 Hz by least squares over one
    beat period, 80 Hz low-passed), no drive, each segment's current white noise of 1 uA rms:
    over 8 s the rms of each tone's tip estimate (every block, from the first full window on) is
    the floor within 10 % (the estimate of an rms from 60-2000 independent windows)."""
    freqs = np.array([[250.0, 0.0], [1000.0, 0.0], [235.0, 265.0], [80.0, 0.0]])
    obs = _observer(freqs)
    assert obs.lstsq.tolist() == [False, False, True, False] and obs.prefilter[3] > 0 and obs.prefilter[0] == 0
    sigma = 1e-6
    floor = obs.noise_floor(sigma)
    rng = np.random.default_rng(7)
    drive = np.zeros((4, obs.block))
    blocks = int(8.0 * obs.fs / obs.block)
    first = int(np.ceil((obs.window + obs.prefilter_memory.max()) / obs.block)) + 1
    est = np.zeros((blocks - first, 4, 2), dtype=complex)
    for k in range(blocks):
        obs.process(drive, rng.normal(0.0, sigma, (4 * obs.n_seg, obs.block)))
        if k >= first:
            est[k - first] = obs.est[:, :, 0, 0] + 1j * obs.est[:, :, 0, 1]
    rms = np.sqrt(np.mean(np.abs(est) ** 2, axis=0))
    used = freqs > 0
    np.testing.assert_allclose(rms[used], floor[used], rtol=0.10)
    assert np.all(floor[~used] == 0.0)
    # least squares over one beat period pays for its short window: more noise per tone than a
    # plain window of the same length would leave
    n = obs.windows[2]
    assert np.all(floor[2] > np.sqrt(4.0 / n * np.max(np.sum(obs.Hc[2, :, :, 0, 1:, :] ** 2, axis=(2, 3)), axis=1))
                  * sigma * 0.999)


def test_the_noise_floor_scales_with_the_noise_and_falls_with_the_window():
    """Linear in the current noise; over a window four times longer (250 Hz, 4 ms against 16 ms,
    the same design) half of it."""
    obs = _observer(np.array([[250.0, 0.0]]))
    f1 = obs.noise_floor(1e-6)[0, 0]
    assert obs.noise_floor(3e-6)[0, 0] == pytest.approx(3.0 * f1, rel=1e-12)
    s = scene.load("line-bimorph-5-closed")
    m, g = Models(s), s.actuator[0]
    long = m.observer(g, np.array([[250.0, 0.0]]), s.timing.fs, s.timing.block, window=4 * int(obs.windows[0]),
                      hop=obs.hop)
    assert long.noise_floor(1e-6)[0, 0] == pytest.approx(0.5 * f1, rel=1e-9)
