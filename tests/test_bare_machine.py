"""The I/O tests on a machine without PortAudio and JACK: they collect, the audio backend's logic
is still tested (stand-in callback types, fake stream), and what needs the real libraries skips
with one line naming what to install."""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
IO_MODULES = ["test_audio_backend.py", "test_audio_guard.py", "test_hil_audio.py", "test_io_daq_devices.py",
              "test_isolation.py"]


@pytest.mark.slow
def test_io_tests_pass_without_portaudio_and_jack(tmp_path):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(HERE / "bare_machine"), os.environ.get("PYTHONPATH", "")]))
    probe = subprocess.run([sys.executable, "-c", "import sounddevice"], env=env, capture_output=True, text=True)
    assert probe.returncode != 0 and "OSError" in probe.stderr  # the stand-in machine is what it claims
    xml = tmp_path / "io.xml"
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rs", f"--junitxml={xml}",
                        *[str(HERE / m) for m in IO_MODULES]],
                       env=env, cwd=HERE.parent, capture_output=True, text=True, timeout=900)
    tail = r.stdout[-3000:] + r.stderr[-2000:]
    assert r.returncode == 0, tail
    assert "error" not in r.stdout.splitlines()[-1], tail  # no collection error in the closing line
    cases = ET.parse(xml).getroot().iter("testcase")
    passed, skipped = set(), {}
    for c in cases:
        if c.find("skipped") is not None:
            skipped[f"{c.get('classname')}.{c.get('name')}"] = c.find("skipped").get("message", "")
        elif c.find("failure") is None and c.find("error") is None:
            passed.add(f"{c.get('classname')}.{c.get('name')}")
    backend = {p for p in passed if "test_audio_backend" in p}
    # the callback and engine thread driven by the fake stream, the C callback against the Python one
    for name in ("test_callback_maps_and_scales_both_ways", "test_device_loss_ends_the_run_quickly_with_zero_outputs",
                 "test_c_callback_gives_the_python_callbacks_blocks", "test_kernels_match_numpy"):
        assert any(name in p for p in backend), (name, sorted(backend))
    assert any("test_io_daq_devices" in p for p in passed) and any("test_audio_guard" in p for p in passed)
    # the HIL module skips, saying what to install; nothing else skips for want of the libraries
    hil = {k: v for k, v in skipped.items() if "test_hil_audio" in k}
    assert hil or "test_hil_audio.py" in r.stdout, tail
    reasons = " ".join(skipped.values()) + r.stdout
    assert "apt-get install" in reasons, tail
    assert not [k for k in skipped if "test_audio_backend" in k], skipped
