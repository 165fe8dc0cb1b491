"""Signals under closed-loop amplitude control: tip targets in um, followed by the controller."""

import numpy as np
import pytest

from rtctl import scene
from rtctl.engine.rig import build
from rtctl.engine.run import run
from rtctl.errors import SceneError
from rtctl.trace import TraceReader

BASE = scene.resolve("line-bimorph-5-closed").read_text()
HEAD = BASE[: BASE.index("[[events]]")]
ACTUATOR = BASE[BASE.index("[[actuator]]"): BASE.index("[stimulus]")]
ASR = """
[stimulus]
kind = "tones"
signals = [
  {name = "c", type = "sine", freq = 120.0, amp = 12.0},
  {name = "env", type = "asr", attack = 0.1, sustain = 0.5, release = 0.1},
  {name = "b", type = "product", of = ["c", "env"]},
]
play = [{signal = "b", channel = 3, start = 0.1}]
[control]
mode = "closed"
"""


@pytest.fixture(scope="module")
def asr_run(tmp_path_factory):
    s = scene.loads(HEAD + ACTUATOR + ASR, ["timing.duration=1.0"])
    out = tmp_path_factory.mktemp("asr")
    run(s, out_dir=str(out), plot=False, progress=False)
    return TraceReader(out / "trace")


def test_a_sustained_target_is_held_and_silence_before_and_after(asr_run):
    tip, tgt = asr_run.signal("tip_um")[3], asr_run.signal("target_um")[3]
    fs, block = 48000, 32
    sustain = slice(int(0.45 * fs), int(0.7 * fs))  # the controller's first correction is done by then
    amp = np.ptp(tip[sustain]) / 2
    assert tgt[int(0.5 * fs) // block] == pytest.approx(12.0)
    assert amp == pytest.approx(12.0, rel=0.02)
    assert np.abs(tip[: int(0.09 * fs)]).max() < 1e-3  # before its start
    assert np.ptp(tip[int(0.95 * fs):]) / 2 < 0.05 * 12.0  # after its release


def test_a_closed_loop_target_needs_a_controlled_channel():
    pvdf = scene.resolve("pvdf-6x8").read_text()
    body = pvdf[: pvdf.index("[stimulus]")] + ASR.replace("channel = 3", "channel = 19")
    with pytest.raises(SceneError, match="not under amplitude control"):
        build(scene.loads(body))
