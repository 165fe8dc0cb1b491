"""``[io.faults]`` in the emulators: the audio emulator's plant injects the sensed, timing, amplifier
and device kinds around its kernels (the calls its C process callback runs), the serial emulator
the line kinds and the stop; each run against them has the outcome docs/faults.md gives."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from rtctl import scene
from rtctl.emulate import serial as es
from rtctl.errors import SceneError

# --- serial: the line faults ------------------------------------------------------------------

def test_scheduled_byte_faults_hit_their_fraction_only_within_their_window():
    frame = bytes(range(1, 201))
    f = es.Faults(scheduled=[("byte_flip", 1.0, 2.0, 1.0)])
    assert f.outgoing(frame) == frame            # before the first valid frame: nothing
    f.now = 0.5
    assert f.outgoing(frame) == frame
    f.now = 1.5
    out = f.outgoing(frame)
    diff = np.frombuffer(out, np.uint8) ^ np.frombuffer(frame, np.uint8)
    assert len(out) == len(frame) and np.all(np.unpackbits(diff).reshape(-1, 8).sum(axis=1) == 1)
    f = es.Faults(scheduled=[("byte_dup", 0.0, math.inf, 1.0)])
    f.now = 3.0
    assert f.outgoing(frame) == bytes(b for x in frame for b in (x, x)) and f.duplicated == 200
    f = es.Faults(scheduled=[("byte_drop", 0.0, 1.0, 1.0)])
    f.now = 0.1
    assert f.incoming(frame) == b"" and f.dropped == 200
    f.now = 1.0
    assert f.incoming(frame) == frame
    f = es.Faults(seed=3, scheduled=[("byte_drop", 0.0, 1.0, 0.1)])
    f.now = 0.0
    kept = sum(len(f.incoming(frame)) for _ in range(50))
    assert abs(kept / 10000 - 0.9) < 0.02    # 10000 bytes at 10 %: 3 sigma is 0.9 %


def test_the_scene_faults_map_to_the_serial_line():
    sc = scene.load("dot-4x4", ['io.faults.inject=[{kind="byte_flip", at=0.1, blocks=150, value=0.02}, '
                                '{kind="device_stopped", at=0.5}, {kind="byte_dup", at=0.2, blocks=0}]'])
    sched, stall = es.scene_faults(sc)
    p = 32 / 48000
    assert sched[0][0] == "byte_flip" and sched[0][1:] == pytest.approx((150 * p, 300 * p, 0.02))
    assert sched[1] == ("byte_dup", pytest.approx(300 * p), math.inf, 0.01)
    assert stall == pytest.approx(750 * p)
    with pytest.raises(SceneError, match="cannot be injected on emulate serial"):
        es.scene_faults(scene.load("dot-4x4", ['io.faults.inject=[{kind="amp_clipped", at=0.1}]']))


def _serial_run(tmp_path, emu_sets):
    from test_serial_emulator import Emulator

    emu = Emulator("dot-4x4", *[a for s in emu_sets for a in ("--set", s)])
    try:
        cmd = [sys.executable, "-m", "rtctl.cli", "run", "dot-4x4", "--set", "io.backend=serial",
               "--set", f"io.port={emu.port}", "--set", "timing.duration=1.5", "--out", str(tmp_path),
               "--no-plot", "--quiet"]
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    finally:
        code, err = emu.stop()
    return run, err


@pytest.mark.hil
def test_a_run_rides_through_a_noisy_serial_line(tmp_path):
    from rtctl.check import check_trace

    run, emu_err = _serial_run(tmp_path, ['io.faults.inject=[{kind="byte_flip", at=0.0, blocks=0, value=0.01}, '
                                          '{kind="byte_dup", at=0.0, blocks=0, value=0.005}]'])
    assert run.returncode == 0, run.stderr
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["faults"] == [] and s["io"]["resends"] > 0, s["io"]
    assert "answers corrupted" in emu_err
    assert check_trace(tmp_path)["ok"]


@pytest.mark.hil
def test_a_run_fades_when_the_serial_device_stops_answering(tmp_path):
    from rtctl.check import check_trace
    from rtctl.trace import TraceReader

    run, _ = _serial_run(tmp_path, ['io.faults.inject=[{kind="device_stopped", at=0.5}]'])
    assert run.returncode == 1, run.stderr
    lines = [x for x in run.stderr.splitlines() if x.startswith("rtctl: fault")]
    assert len(lines) == 1 and "I/O device lost" in lines[0]
    s = json.loads((tmp_path / "summary.json").read_text())
    assert 0.5 <= s["duration_s"] < 1.0
    assert np.all(TraceReader(tmp_path / "trace").signal("drive")[:, -1] == 0.0)
    assert check_trace(tmp_path)["ok"]


# --- audio: the emulator's plant ----------------------------------------------------------------

def _plant(faults):
    from rtctl.emulate.audio import Plant

    sc = scene.load("line-bimorph-5", [f"io.faults.inject={faults}"])
    return Plant(sc, 48000.0, 32)


def _periods(plant, n, volts=60.0):
    out = []
    for k in range(n):
        t = (k * 32 + np.arange(32)) / 48000.0
        plant.drive[:] = volts * np.sin(2 * np.pi * 100 * t)
        plant.step()
        out.append((plant.sensed.copy(), plant.truth[:, 3].copy()))
    return out


def test_the_audio_emulator_injects_sensed_and_amplifier_faults_at_their_period():
    clean = _periods(_plant("[]"), 40)
    p = _plant('[{kind="sensed_nan", at=0.0134, blocks=3, row=2}, '
               '{kind="amp_clipped", at=0.0134, blocks=10, value=0.2}]')
    got = _periods(p, 40)
    k0 = 20   # 0.0134 s at 48 kHz, block 32: block floor(20.1)
    for k in range(k0):
        np.testing.assert_array_equal(got[k][0], clean[k][0])
    assert np.all(np.isnan(got[k0][0][2])) and np.all(np.isnan(got[k0 + 2][0][2]))
    assert not np.any(np.isnan(got[k0 + 3][0][2]))
    assert not np.any(np.isnan(np.delete(got[k0][0], 2, axis=0)))
    # the amplifier's output within +-0.2 x 150 V one period after the clip began
    assert np.abs(np.array([g[1] for g in got[k0 + 1:k0 + 10]])).max() <= 30.0 * (1 + 1e-9)
    assert np.abs(np.array([g[1] for g in clean[k0 + 1:k0 + 10]])).max() > 50.0


def test_the_audio_emulator_goes_silent_when_the_device_stops_and_resets_per_run():
    p = _plant('[{kind="device_stopped", at=0.01}]')
    got = _periods(p, 30)
    k0 = 15
    assert np.any(got[k0 - 1][0] != 0.0)
    assert all(np.all(g[0] == 0.0) for g in got[k0:])   # digital silence: the audio run's guard
    p.reset()                                             # a new run connects: the plan starts over
    again = _periods(p, k0)
    np.testing.assert_array_equal(again[-1][0], got[k0 - 1][0])


def test_the_audio_emulator_refuses_a_kind_it_cannot_inject():
    with pytest.raises(SceneError, match="cannot be injected on emulate audio"):
        _plant('[{kind="xrun_burst", at=0.1}]')


@pytest.mark.hil
def test_an_audio_run_fades_when_the_emulated_device_stops(tmp_path):
    from hil_jack import JACKD

    if JACKD is None:
        pytest.skip("jackd not installed: audio HIL fault test skipped")
    from optional import require

    require("jack", "sounddevice")
    from hil_jack import CLI, EmulatorProcess, JackServer

    from rtctl.check import check_trace

    timing = ["timing.block=64", "timing.duration=3.0"]
    audio = ["io.backend=audio", "io.device=system", "io.host_api=JACK Audio Connection Kit", "io.xrun_limit=0"]
    with JackServer(period=64) as srv:
        emu = EmulatorProcess(srv, "line-bimorph-5", timing + ['io.faults.inject=[{kind="device_stopped", at=1.0}]'])
        try:
            assert emu.wait_for("waiting", 120), emu.out.seen
            cmd = CLI + ["run", "line-bimorph-5", "--json", "--no-plot", "--out", str(tmp_path),
                         *[a for o in timing + audio for a in ("--set", o)]]
            proc = subprocess.run(cmd, env=srv.env, capture_output=True, text=True, timeout=300)
        finally:
            emu.stop()
    assert proc.returncode == 1, proc.stderr
    assert "I/O device lost" in proc.stderr
    s = json.loads(proc.stdout)
    # the emulator counts periods from its connection to the run's ports, which precedes the
    # run's first block by the stream's start-up; the guard then waits io.silence_ms (50 ms)
    assert 0.5 <= s["duration_s"] < 2.0
    rep = check_trace(tmp_path)
    assert rep["ok"], rep["first"]

