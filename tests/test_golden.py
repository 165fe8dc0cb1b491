"""Golden traces: every bundled scene still does what its golden in tests/golden/ recorded, within
the tolerances docs/golden.md derives; a 1 % change of a physical constant or a mutated kernel
makes the comparison fail (the goldens can catch what they are for)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from numba import njit

from rtctl import scene
from rtctl.dsp import pulse_process
from rtctl.engine import golden


def test_every_bundled_scene_has_a_golden():
    assert sorted(p.stem for p in golden.DEFAULT_DIR.glob("*.json")) == sorted(scene.bundled())


@pytest.mark.parametrize("name", scene.bundled())
def test_every_golden_run_kept_the_limiters_promises(name):
    """The stored golden itself was checked sample by sample (rtctl check-trace) and passed."""
    inv = golden.load(name)["invariants"]
    assert inv["ok"] is True and not any(inv["violations"].values()), inv


@pytest.mark.parametrize("name", scene.bundled())
def test_the_scene_matches_its_golden(name):
    """A difference names the quantity, row and frame; `python -m rtctl.engine.golden` shows all
    of them and rewrites the goldens when the change is meant."""
    diff = golden.compare(golden.load(name), golden.fingerprint(name))
    assert not diff, f"{name} differs from tests/golden/{name}.json:\n" + "\n".join(diff[:15])


@pytest.mark.parametrize("name", ["line-bimorph-5", "line-bimorph-5-closed"])
def test_a_material_constant_one_percent_off_fails_the_golden(name, monkeypatch):
    """PZT-5A's d31 (the built-in table every model and the simulated device read) 1 % larger;
    under closed-loop control too, whose controllers make up for it (the drive and the currents
    show it, and the golden's wider tolerance there still sees it)."""
    from rtctl.plant import materials

    m = materials.BUILTIN["PZT-5A"]
    monkeypatch.setitem(materials.BUILTIN, "PZT-5A", dataclasses.replace(m, d31=m.d31 * 1.01))
    diff = golden.compare(golden.load(name), golden.fingerprint(name))
    assert any(line.startswith("envelopes.sensed") for line in diff), diff[:5]
    assert any(line.startswith(("lockin.tip_um", "lockin.drive")) for line in diff), diff[:5]


@pytest.mark.parametrize("name", ["line-bimorph-5", "solenoid-3x3", "line-bimorph-5-closed"])
def test_the_tolerance_absorbs_a_perturbation_far_beyond_the_last_bit(name):
    """The simulated finger 1e-9 stiffer (about 10^7 ulp; platform libm and LAPACK differences
    are a few ulp per operation): within each scene's tolerance, the smooth scene's default and
    the two wider ones alike."""
    diff = golden.compare(golden.load(name), golden.fingerprint(name, ["io.mismatch.finger_k0=1.000000001"]))
    assert not diff, diff[:5]


def test_a_plate_modulus_one_percent_off_fails_the_golden():
    """The PVDF display's plate Young's modulus 1 % larger (its cells' stiffness and resonances)."""
    e = scene.load("pvdf-6x8").group("cells").plate.E
    mutated = golden.fingerprint("pvdf-6x8", [f"actuator.cells.plate.E={e * 1.01!r}"])
    diff = golden.compare(golden.load("pvdf-6x8"), mutated)
    assert any(line.startswith("envelopes.tip_um") for line in diff), diff[:5]


@njit(nogil=True)
def pulse_process_low(state, pending, out):
    """The pulse kernel with its levels 0.1 % low: a mutated kernel (high ones the limiter would clamp
    at max_voltage: the golden names that too, as a channel limited)."""
    pulse_process(state, pending, out)
    for c in range(out.shape[0]):
        for i in range(out.shape[1]):
            out[c, i] *= 0.999


def test_a_mutated_kernel_fails_the_golden(monkeypatch):
    import rtctl.dsp
    import rtctl.engine.compose

    def uncomposed(stages):  # the rig then calls its stages from Python (no generated module cached)
        raise TypeError("the stages run from Python in this test")

    monkeypatch.setattr(rtctl.dsp, "pulse_process", pulse_process_low)
    monkeypatch.setattr(rtctl.engine.compose, "compose", uncomposed)
    diff = golden.compare(golden.load("solenoid-3x3"), golden.fingerprint("solenoid-3x3"))
    assert any(line.startswith("envelopes.drive.rms") for line in diff), diff[:5]
    assert any(line.startswith("envelopes.tip_force") for line in diff), diff[:5]


def test_within_tolerance_passes_and_beyond_fails():
    """The comparison itself: a change of a tenth of the tolerance passes, ten tolerances fail,
    a phase is compared on the circle, and a changed flag or a vanished quantity is named."""
    g = {"scene": "s", "fs": 1.0, "block": 1, "frame_blocks": 1, "frames": 3, "blocks": 3, "channels": ["a"],
         "envelopes": {"drive": {"rms": [[1.0, 2.0, 4.0]]}},
         "lockin": {"tip a 1 Hz": {"amp": [1.0, 1.0, 0.0], "phase": [np.pi - 1e-6, 0.0, 3.0]}},
         "summary": {"faults": [], "channels": [{"felt": True, "true_um": 10.0}]}}

    def moved(rms=0.0, phase=0.0, felt=True, um=10.0):
        h = dict(g, envelopes={"drive": {"rms": [[1.0, 2.0, 4.0 * (1 + rms)]]}},
                 lockin={"tip a 1 Hz": {"amp": [1.0, 1.0, 0.0], "phase": [-np.pi + phase, 0.0, 0.0]}},
                 summary={"faults": [], "channels": [{"felt": felt, "true_um": um}]})
        return golden.compare(g, h)

    assert moved(rms=0.1 * golden.RTOL, phase=1e-6) == []  # -pi + 1e-6 is pi - 1e-6 less 2e-6 rad round
    assert moved(rms=10 * golden.RTOL)[0].startswith("envelopes.drive.rms[0][2]")
    assert moved(phase=100 * golden.RTOL)[0].startswith("lockin.tip a 1 Hz.phase[0]")
    assert moved(felt=False) == ["summary.channels[0].felt: True -> False"]
    assert moved(um=10.0 * (1 + 10 * golden.RTOL))[0].startswith("summary.channels[0].true_um")
    assert golden.compare(g, dict(g, channels=["b"])) == ["channels: ['a'] -> ['b']"]


@pytest.mark.parametrize("f, frame", [(250.0, 960), (100.0, 960), (2.0, 960), (333.3, 480)])
def test_the_lockin_gives_a_sines_amplitude_and_phase(f, frame):
    """Against the closed form: ``A cos(2 pi f t + phi)`` over whole periods gives ``A`` and
    ``phi`` (to the leakage of a period rounded to whole samples); shorter than a period (2 Hz in
    20 ms), it is the frame's own projection, still the same for the same samples."""
    fs, n_frames, amp, phi = 48000.0, 3, 2.5, 0.7
    t = np.arange(frame * n_frames) / fs
    a, p = golden._lockin(amp * np.cos(2 * np.pi * f * t + phi), t, f, frame, n_frames, fs)
    if frame * f / fs >= 1:
        np.testing.assert_allclose(a, amp, rtol=2e-3)
        np.testing.assert_allclose(p, phi, atol=2e-3)
    else:
        assert np.all(a > 0) and np.all(np.isfinite(p))
