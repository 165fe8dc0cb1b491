"""The bundled SMA scene reproduces seed 002's bandwidth claim end to end (rtctl run --json)."""

import json

import pytest

from rtctl.cli import main


def run_json(capsys, tmp_path, *sets):
    args = ["run", "sma-8x8", "--json", "--no-plot", "--out", str(tmp_path)]
    for s in sets:
        args += ["--set", s]
    assert main(args) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.slow
def test_square_wave_at_1p5_hz_full_stroke_forced_much_smaller_still(capsys, tmp_path):
    # Seed 002 Fig. 11: with the mini-fan the taxel follows a 1.5 Hz square wave over its full
    # stroke (the raised/lowered positions are +-0.7 mm, so >= 1.4 mm peak-to-peak); in still
    # air the springs cannot cool within a half period and the stroke collapses.
    forced = run_json(capsys, tmp_path, "actuator.sma.cooling=forced", "timing.duration=6.0")
    still = run_json(capsys, tmp_path, "actuator.sma.cooling=still", "timing.duration=6.0")
    for summary in (forced, still):
        assert summary["faults"] == []     # the driver's cutoff keeps still air below t_max
    f = [c["true_um"] for c in forced["channels"] if c["freq_hz"]]
    s = [c["true_um"] for c in still["channels"] if c["freq_hz"]]
    assert len(f) == 8 and min(f) >= 700.0
    assert max(s) < 0.35 * min(f)
