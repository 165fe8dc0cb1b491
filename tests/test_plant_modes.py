"""How many modes the simulated bimorph keeps (``beam.modes = 0``: every mode up to 1.5 fs, at
least 4, and every mode near the images at 2, 3 and 4 fs +- f), and why: the drive's images
reach the segment currents through the modes near them, which the observer's model (the
continuum) has.
On a 30 mm beam the 4-mode plant is not the device the observer reads (13 % at 1 kHz); with its
modes it is (within 1 %). On an elastic root the finger's mass brings the 7th mode onto the
2 fs images, and a plant that stops at 1.5 fs is read up to 5 % off.
And on a calibrated beam whose observer magnifies the currents' misfit (above its first
resonance), the reported uncertainty says so and holds the true error.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from closed_forms import CANTILEVER_ROOTS

from rtctl import scene
from rtctl.engine.run import run
from rtctl.models import Models
from rtctl.selfsense.truncation import observer_errors

SCENE = "line-bimorph-5"
#: the bundled beam's section (two PZT-5A layers of 0.3 mm, 1.5 mm wide), 30 mm long
LONG = ["actuator.lateral.beam.length=0.03", "actuator.lateral.beam.modes=0"]
TONES = ('stimulus.tones=[{channel=0,freq=10.0,voltage=10.0},{channel=1,freq=80.0,voltage=10.0},'
         '{channel=2,freq=300.0,voltage=5.0},{channel=3,freq=700.0,voltage=5.0},{channel=4,freq=1000.0,voltage=5.0}]')
#: PZT-5A (docs/references.md): 1/s11E, density
E, RHO = 1.0 / 16.4e-12, 7750.0


def cantilever_frequencies(length, width=1.5e-3, h=0.6e-3, n=40):
    """Clamped-free Euler-Bernoulli frequencies of a homogeneous section, Hz: the tabulated roots
    of 1 + cos l cosh l = 0, then (2k - 1) pi / 2 (within 1e-7 from the 5th on)."""
    roots = np.r_[CANTILEVER_ROOTS, (2 * np.arange(CANTILEVER_ROOTS.size + 1, n + 1) - 1) * math.pi / 2]
    EI, rhoA = E * width * h**3 / 12.0, RHO * width * h
    return roots**2 / (2 * math.pi * length**2) * math.sqrt(EI / rhoA)


#: the beam's modal damping (the scene's ``beam.damping``)
ZETA = 0.01


@pytest.mark.parametrize("length,fs", [(0.008, 48000.0), (0.009, 48000.0), (0.011, 48000.0), (0.012, 48000.0),
                                       (0.0125, 48000.0), (0.024, 48000.0), (0.033, 48000.0),
                                       (0.011, 96000.0), (0.014, 96000.0), (0.0105, 96000.0)])
def test_the_plant_keeps_every_mode_up_to_one_and_a_half_fs_and_near_the_images(length, fs):
    """Finger lifted, so the closed-form cantilever is the beam: the count is its modes up to
    1.5 fs (at least 4), and up to the last mode within 3 half-widths (zeta f) of the images of
    tones up to fs / 16 around 2, 3 and 4 fs (at 48 kHz: the 4th of an 8 mm beam, at 146.1 kHz;
    the 5th of a 9 mm one and the 6th of an 11 mm one, at 190.8 kHz, where 1.5 fs keeps 3; the
    12.5 mm one's 5th and 6th at 98.9 and 147.7 kHz; none of the 12 mm one's; the 33 mm one's
    12th, 15th and 17th at 92.7, 147.3 and 190.8 kHz; at 96 kHz the 6th of an 11 mm beam, at
    190.8 kHz, and the 9th of a 14 mm one, at 281.3 kHz); a stated count is kept."""
    sc = scene.load(SCENE, [f"actuator.lateral.beam.length={length}", "actuator.lateral.beam.modes=0",
                            f"timing.fs={fs}", "actuator.lateral.sense.shunt=10", "finger.contact=false"])
    f = cantilever_frequencies(length)
    edges, last = [1.5 * fs], 0
    for k in (2, 3, 4):
        lo, hi = k * fs - fs / 16 - 3 * ZETA * f, k * fs + fs / 16 + 3 * ZETA * f
        near = np.flatnonzero((f >= lo) & (f <= hi))
        last = max(last, near[-1] + 1 if near.size else 0)
        edges += [lo, hi]
    want = max(4, int(np.count_nonzero(f <= 1.5 * fs)), last)
    # no mode within 2 % of a bound, where the FE's few 1e-3 could tip the count
    for edge in edges:
        assert np.min(np.abs(f / edge - 1)) > 0.02
    assert Models(sc).plant_modes(sc.actuator[0]) == want
    stated = scene.load(SCENE, [f"actuator.lateral.beam.length={length}", "actuator.lateral.beam.modes=6",
                                f"timing.fs={fs}", "actuator.lateral.sense.shunt=10"])
    assert Models(stated).plant_modes(stated.actuator[0]) == 6


#: a root on springs soft enough that the finger's skin mass moves the 7th mode onto 2 fs
ELASTIC = ["actuator.lateral.support.type=elastic", "actuator.lateral.support.k=2e4",
           "actuator.lateral.support.k_rot=0.5"]


def test_a_mode_the_finger_moves_onto_the_2fs_images_is_kept(tmp_path):
    """Unloaded, the elastic root's 7th mode is at 105 kHz, off the images; under the finger
    (0.1 g of skin) at 96.3 kHz, on them. The plant keeps it (and the 8th and 9th, unloaded at
    145.9 and 193.6 kHz, on the images at 3 and 4 fs), and the observer reads it within 0.5 %
    (measured 0.04 %); with the 6 modes up to 1.5 fs, up to 5 % off."""
    sc = scene.load(SCENE, ["actuator.lateral.beam.modes=0", *ELASTIC])
    m, g = Models(sc), sc.actuator[0]
    finger = m.finger(g)
    free = m.beam(g).modes()[0]
    loaded = m.beam(g).with_tip(finger.mass, finger.k0).modes()[0]
    assert np.count_nonzero(free <= 72e3) == 6 and free[6] > 104e3 and abs(loaded[6] - 96e3) < 1e3
    assert abs(free[7] - 146e3) < 1e3 and abs(free[8] - 193.6e3) < 1e3 and m.plant_modes(g) == 9
    auto = observe(tmp_path / "auto", ["actuator.lateral.beam.modes=0", *ELASTIC])
    six = observe(tmp_path / "six", ["actuator.lateral.beam.modes=6", *ELASTIC])
    print(f"\nobserver error %, elastic root: {np.round(auto, 2)} kept, {np.round(six, 2)} with 6 modes")
    assert np.all(np.abs(auto) < 0.5)
    assert np.max(np.abs(six)) > 2.0


def observe(out, extra, warnings=None):
    s = run(scene.load(SCENE, [TONES, "control.observe=true", "timing.duration=0.6", *extra]),
            out_dir=out, plot=False).summary
    if warnings is not None:
        warnings.extend(s["warnings"])
    return np.array([r["estimate_error_pct"] for r in s["channels"]])


def test_on_a_30mm_beam_the_observer_reads_the_plant_with_its_modes(tmp_path):
    """The observer's estimate against the plant's truth, 10 Hz ... 1 kHz: with the plant's
    modes (16: up to 1.5 fs, where its 8th, at 47.7 kHz, sits on the images of every tone, its
    11th near 2 fs, its 14th at 149.9 kHz under the finger near 3 fs, its 16th at 199.3 kHz near 4 fs) within
    1 %;
    with 4 (to 10 kHz), as the bundled scene keeps on its 15 mm beam, up to 13 % off.

    The scene check computes that misreading without a run (rtctl.selfsense.truncation: the
    plant's sampled response read by the observer's designs, in the frequency domain): it agrees
    with the runs' lock-in estimates (time domain, current noise and all) within 0.25 % at every
    tone, and its warning names the key, the misreading and the count that would do; the run
    with the plant's modes has no such warning."""
    warned, quiet = [], []
    auto = observe(tmp_path / "auto", LONG, quiet)
    four = observe(tmp_path / "four", LONG[:1] + ["actuator.lateral.beam.modes=4"], warned)
    print(f"\nobserver error %, 30 mm beam: its modes {np.round(auto, 2)}, 4 modes {np.round(four, 2)}")
    assert np.all(np.abs(auto) < 1.0)
    assert np.max(np.abs(four)) > 5.0
    sc = scene.load(SCENE, [TONES, "control.observe=true", LONG[0], "actuator.lateral.beam.modes=4"])
    computed = 100.0 * observer_errors(Models(sc), sc.actuator[0], 4, (10.0, 80.0, 300.0, 700.0, 1000.0))
    print(f"computed without a run: {np.round(computed, 2)}")
    assert np.all(np.abs(computed - four) < 0.25)
    mine = [w for w in warned if "beam.modes = 4" in w]
    assert len(mine) == 1 and "about 13 % off at 1000 Hz" in mine[0] and "beam.modes = 0 keeps the 16 modes" in mine[0]
    assert not any("beam.modes" in w for w in quiet)


@pytest.mark.slow
def test_a_calibration_whose_observer_magnifies_the_misfit_says_so(tmp_path):
    """A 30 mm beam, calibrated on the nominal device, closed loop: above its first loaded
    resonance (410 Hz) the observer turns a relative current error into 185-271 times the tip
    error, so the fit's 0.03 % misfit is worth several % there. Every tone's true error lies
    inside its reported uncertainty, which at 700 Hz and 1 kHz is mostly the observer's share
    (the scale's bound alone, 2.04 %, did not hold the 1 kHz error). The device keeps 9 modes
    (those up to 1.5 fs) where the model has them all: a misfit no fitted factor can remove
    (with its 11 modes the fit leaves a 1 kHz error of 0.8 % inside the scale's bound)."""
    tones = (TONES.replace("voltage=10.0}", "voltage=10.0,target_um=1.0}")
             .replace("voltage=5.0}", "voltage=5.0,target_um=0.2}"))
    s = run(scene.load("line-bimorph-5-closed", [LONG[0], "actuator.lateral.beam.modes=9", tones, "events=[]",
                                                 "timing.duration=1.0", "control.calibrate=auto"]),
            out_dir=tmp_path / "run", plot=False).summary
    scale = 100 * 0.02 / 0.98
    rows = s["channels"]
    print("\n" + "; ".join(f"{r['freqs_hz'][0]:g} Hz: error {r['error_pct']:+.2f} %, uncertainty "
                           f"{r['uncertainty_pct']:.2f} %, gain {r['observer_gain']:.0f}" for r in rows))
    for r in rows:
        assert r["controlled"] and not r["saturated"]
        assert abs(r["error_pct"]) < r["uncertainty_pct"], r["name"]
    high = [r for r in rows if r["freqs_hz"][0] >= 700.0]
    assert all(r["observer_gain"] > 100.0 and r["uncertainty_pct"] > 2 * scale for r in high)
    assert max(abs(r["error_pct"]) for r in high) > scale  # what the scale's bound alone missed


def test_the_scene_check_warns_only_where_an_observer_reads_a_plant_it_misreads():
    """The bundled closed-loop scene keeps 4 modes of its 15 mm beam: the observer reads that
    plant 0.56 % off (its 5th mode, at 69 kHz, is far from the images at fs +- f), under the 1 %
    the check warns from. The same 4 modes of a 30 mm beam, read by an observer, warn; unread
    (open loop, no observer), nothing is computed and nothing said."""
    from rtctl.selfsense.truncation import observer_error
    from rtctl.validity import check

    sc = scene.load("line-bimorph-5-closed")
    err, _ = observer_error(Models(sc), sc.actuator[0], 4)
    assert 0.003 < err < 0.01
    assert not any("beam.modes" in w for w in check(sc))
    long4 = [LONG[0], "actuator.lateral.beam.modes=4"]
    assert any("beam.modes = 4" in w for w in check(scene.load(SCENE, [*long4, "control.observe=true"])))
    assert not any("beam.modes" in w for w in check(scene.load(SCENE, long4)))


def test_the_scene_check_reads_the_scenes_own_tones_too():
    """A 1.2 kHz tone, beyond the check's band (10 Hz-1 kHz), on the closed-loop scene's beam cut
    to 4 modes: the observer reads that plant 1.1 % off there (a closed loop held the tip 2 % off,
    against 0.04 % with every mode), and the check names that tone's frequency; the scene's own
    tones (2-250 Hz, under 0.6 %) draw no warning."""
    from rtctl.validity import check

    quiet = scene.load("line-bimorph-5-closed")
    assert not [w for w in check(quiet) if "beam.modes" in w]
    sc = scene.load("line-bimorph-5-closed",
                    ["stimulus.tones=[{channel = 0, freq = 1200, voltage = 1, target_um = 2}]"])
    warned = [w for w in check(sc) if "beam.modes = 4" in w]
    err = observer_errors(Models(sc), sc.actuator[0], 4, (1200.0,))[0]
    assert 0.01 < abs(err) < 0.02
    assert len(warned) == 1 and f"about {100 * abs(err):.2g} % off at 1200 Hz" in warned[0], warned


def test_the_scene_check_reads_the_tones_of_its_own_group():
    """bimodal-4x4 observed, a lateral tone at 1.2 kHz (channel 5 of the lateral group, which
    follows the 16 EM pins): the check of the lateral beam cut to 4 modes names 1200 Hz, where
    the observer reads it most off; a 1.2 kHz tone on the EM group is not the beam's."""
    from rtctl.validity import check

    tone = "{actuator = \"%s\", channel = 5, freq = 1200.0, voltage = 1.0}"
    lateral = scene.load("bimodal-4x4", ["control.observe=true", f"stimulus.tones=[{tone % 'lateral'}]"])
    normal = scene.load("bimodal-4x4", ["control.observe=true", f"stimulus.tones=[{tone % 'normal'}]"])
    said = [w for w in check(lateral) if "beam.modes = 4" in w]
    assert len(said) == 1 and "off at 1200 Hz" in said[0], said
    assert not [w for w in check(normal) if "off at 1200 Hz" in w]
