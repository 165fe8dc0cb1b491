"""A run recorded on the audio backend against ``rtctl emulate audio`` (a private ``jackd -d
dummy``), replayed with ``rtctl replay --mode plant``: the recorded drive through the scene's
simulated plant must give back the recorded currents within 1 % rms over all rows (the emulator
is the same plant; what remains is its sensor noise, which the model's currents do not carry),
and with ``io.mismatch.eps33T = 1.1`` on the emulator alone (a device whose piezo permittivity
is 10 % above the model's) the replay must say the device's currents are about 1.1 times the
model's: the segment currents are dominated by the clamped capacitance's ``C dV/dt``, and C is
proportional to eps33T (docs/replay.md).

Skips cleanly without jackd or the JACK and PortAudio Python bindings (tests/optional.py)."""

from __future__ import annotations

import json
import re
import subprocess

import pytest
from hil_jack import CLI, JACKD
from optional import require

pytestmark = pytest.mark.hil

if JACKD is None:
    pytest.skip("jackd not installed (Debian: apt-get install jackd2): audio HIL tests skipped",
                allow_module_level=True)
require("jack", "sounddevice")

from test_hil_control import AUDIO, FS, emulator_alignment, on_audio, sets, timing, without_xruns  # noqa: E402

SCENE = "line-bimorph-5"


def audio_run(tmp_path, name, block, device):
    """An audio run against the emulator; a period the emulator did not hear as the run sent it
    (lost or repeated between them, seen in its record of the drive) counts as an xrun."""
    out = tmp_path / name
    r = on_audio(tmp_path, name, ["run", SCENE, "--json", "--no-plot", "--out", str(out),
                                  *sets(timing(block) + AUDIO)], block, device)
    xruns = json.loads(r["proc"].stdout)["io"]["xruns"]
    a = emulator_alignment(out, r["truth"] / "run-1", block)
    if not a["same"]:
        xruns = f"{xruns} in the run, and a period lost or repeated between it and the emulator"
    return dict(r, out=out, xruns=xruns, connected_s=a["k0"] * block / FS)


def audio_run_replayed(tmp_path, name, device=()):
    """An audio run without xruns (test_hil_control's tries; when every one has xruns the test
    skips: a glitch the plant never saw is not the model's fault), replayed on the plant."""
    r = without_xruns(lambda i, block: audio_run(tmp_path, f"{name}-{block}-{i}", block, device))
    # the emulator connects a few blocks into the run: its plant starts later than the model's,
    # and is compared from 0.1 s after it connected
    skip = f"{0.1 + r['connected_s']:.6f}"
    p = subprocess.run(CLI + ["replay", str(r["out"]), "--mode", "plant", "--skip", skip, "--json"],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    rep = json.loads(p.stdout)
    print(rep["line"])
    assert rep["latency_blocks"] == rep["recorded_latency_blocks"] == 2
    return rep


def test_an_audio_run_replayed_on_the_plant_it_ran_against_matches_within_1_percent(tmp_path):
    rep = audio_run_replayed(tmp_path, "same")
    assert rep["residual_pct"] < 1.0, rep["line"]
    # per row the floor is the device's sensor noise over its signal (about 1 % on the weakest rows)
    assert all(r["residual_pct"] < 2.0 for r in rep["rows"]), rep["rows"]
    assert "the model matches the device" in rep["line"]


def test_a_device_off_its_model_shows_the_size_of_the_mismatch(tmp_path):
    rep = audio_run_replayed(tmp_path, "mismatch", ["io.mismatch.eps33T=1.1"])
    assert rep["gain"] == pytest.approx(1.10, abs=0.01), rep["line"]
    assert 8.0 < rep["residual_pct"] < 11.0, rep["line"]
    m = re.search(r"its currents are ([0-9.]+) x the model's \(\+([0-9.]+) %\)", rep["line"])
    assert m and float(m.group(1)) == pytest.approx(1.10, abs=0.01) and 9.0 < float(m.group(2)) < 11.0, rep["line"]
