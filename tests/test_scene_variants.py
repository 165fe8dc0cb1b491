"""Every bundled display scene has a rendered variant (image, Braille or shape) that runs end to
end: the renderer feeds the loop and the simulated plant moves. The image is a real photograph
shipped with matplotlib (not drawn by us)."""

import json

import pytest
from matplotlib import cbook

from rtctl.cli import main

PHOTO = cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)

VARIANTS = {
    "line-bimorph-5": ["stimulus.kind=image", "stimulus.method=beat", f"stimulus.image={PHOTO}",
                       "stimulus.voltage=100.0"],
    # the image open loop while the finger presses, lifts and returns within the half second
    "line-bimorph-5-closed": ["control.mode=open", "stimulus.kind=image", "stimulus.method=beat",
                              f"stimulus.image={PHOTO}", "stimulus.voltage=100.0", "events.0.at=0.1",
                              "events.1.at=0.2", "events.2.at=0.3"],
    "pvdf-6x8": ["stimulus.kind=image", "stimulus.method=beat", f"stimulus.image={PHOTO}"],
    "solenoid-3x3": ["stimulus.kind=image", "stimulus.method=frequency", f"stimulus.image={PHOTO}"],
    "dot-4x4": ["stimulus.kind=image", "stimulus.method=canny", f"stimulus.image={PHOTO}", "stimulus.speed=2000.0"],
    "sma-8x8": ["stimulus.kind=braille", "stimulus.text=hi", "stimulus.frame_s=0.5"],
    "array-bimorph-5x5": ["stimulus.kind=shape", "stimulus.shape=ring", "stimulus.play=[]", "stimulus.voltage=100.0"],
    "bimodal-4x4": ["stimulus.kind=shape", "stimulus.shape=cross", "stimulus.actuator=normal", "stimulus.voltage=3.0"],
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(VARIANTS))
def test_rendered_variant_runs_and_moves_the_display(name, capsys, tmp_path):
    args = ["run", name, "--json", "--no-plot", "--out", str(tmp_path), "--duration", "0.5"]
    for s in VARIANTS[name]:
        args += ["--set", s]
    assert main(args) == 0, capsys.readouterr().err
    summary = json.loads(capsys.readouterr().out)
    assert summary["faults"] == []
    moved = [c["true_um"] for c in summary["channels"] if c["true_um"]]
    assert moved and max(moved) > 0.01, summary["channels"][:3]
    assert any(c["v_peak"] > 0 for c in summary["channels"])


def test_every_bundled_scene_has_a_variant():
    from rtctl import scene

    assert set(scene.bundled()) == set(VARIANTS)


def test_stimulus_normalize_reaches_the_beat_renderer():
    """`stimulus.normalize` picks the beat renderer's normalising count (seed 004's physiological
    maximum by default, the image's densest place on request): the scene key is not ignored."""
    from rtctl import scene
    from rtctl.engine.rig import build

    base = ["stimulus.kind=image", "stimulus.method=beat", f"stimulus.image={PHOTO}"]
    field = build(scene.load("line-bimorph-5", base)).stimulus.render.renderer
    image = build(scene.load("line-bimorph-5", base + ["stimulus.normalize=image"])).stimulus.render.renderer
    assert (field.normalize, image.normalize) == ("field", "image")
