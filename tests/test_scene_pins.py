"""The bundled Dot and bimodal scenes run end to end and show their seed behaviour."""

import json

import numpy as np
import pytest

from rtctl import scene
from rtctl.cli import main
from rtctl.engine.run import run
from rtctl.model_report import model_facts
from rtctl.render.braille import braille_frames
from rtctl.trace import TraceReader


@pytest.mark.slow
def test_dot_shows_each_braille_page_with_latched_pins(tmp_path):
    # 8-dot "rtctl", two cells per 4x4 page, 0.25 s a page: at the end of each page every pin
    # stands where the page says (up = the 0.5 mm dot height, down = 0) under the finger.
    s = scene.load("dot-4x4", ["timing.duration=0.75"])
    run(s, out_dir=tmp_path, plot=False, progress=False)
    tip = TraceReader(tmp_path / "trace").signal("tip_um")
    frames = braille_frames("rtctl", (4, 4), 8).reshape(-1, 16)
    for page in range(3):
        k = int((page + 1) * 0.25 * 48000) - 64
        up = tip[:, k] > 250.0
        np.testing.assert_array_equal(up, frames[page % len(frames)].astype(bool))
        assert np.all(tip[up, k] > 400.0) and np.all(np.abs(tip[~up, k]) < 50.0)


def test_bimodal_bimorph_rides_on_the_em_armature():
    # support.type = "actuator": the armature's mass and suspension form the bimorph's root,
    # so its first loaded mode lies below the clamped one; a wrong carrier is refused.
    s = scene.load("bimodal-4x4")
    moving = model_facts(s)["lateral"]["natural_frequencies_hz"][0]
    clamped = model_facts(scene.load("bimodal-4x4", ["actuator.lateral.support.type=clamped"]))
    assert moving < 0.99 * clamped["lateral"]["natural_frequencies_hz"][0]
    from rtctl.errors import SceneError

    with pytest.raises(SceneError, match="no actuator named .nope."):
        model_facts(scene.load("bimodal-4x4", ["actuator.lateral.support.actuator=nope"]))


@pytest.mark.slow
def test_bimodal_run_reaches_merkel_normally_and_pacinian_laterally(capsys, tmp_path):
    assert main(["run", "bimodal-4x4", "--json", "--no-plot", "--out", str(tmp_path)]) == 0
    rows = {c["name"]: c for c in json.loads(capsys.readouterr().out)["channels"]}
    assert rows["normal.5"]["true_um"] >= 30.0       # Merkel threshold, seed 000
    assert rows["lateral.5"]["true_um"] >= 0.08      # Pacinian threshold
    assert rows["normal.0"]["v_peak"] == 0.0


@pytest.mark.slow
def test_solenoid_full_stroke_between_stiff_stops_and_rolloff_at_340_hz(capsys, tmp_path):
    assert main(["run", "solenoid-3x3", "--json", "--no-plot", "--out", str(tmp_path)]) == 0
    rows = {c["name"]: c for c in json.loads(capsys.readouterr().out)["channels"]}
    assert rows["pins.0"]["true_um"] == pytest.approx(100.0, abs=1.0)   # 200 um peak-to-peak
    assert rows["pins.4"]["true_um"] == pytest.approx(100.0, abs=1.0)
    assert rows["pins.8"]["true_um"] < 0.8 * rows["pins.0"]["true_um"]  # the coil's L/R at 340 Hz
    r = TraceReader(tmp_path / "trace")
    tip, force = r.signal("tip_um"), r.signal("tip_force")
    assert tip.max() < 200.0 + 1.0 and tip.min() > -1.0                # the stiff stops hold
    assert force.min() >= 0.0                                           # the skin never pulls
