"""Hardware in the loop through a real audio server: a private ``jackd -d dummy`` (48 kHz, period
64), the scene's plant as a JACK client (``rtctl emulate audio``), and ``rtctl run`` with
``io.backend = "audio"`` on PortAudio's JACK device ``system``.

Ordering: the emulator starts first and prints ``waiting`` once its ports exist; the run's stream
registers its ports (``rtctl:out_N``/``rtctl:in_N``) when it starts, the emulator connects to them
at once (a JACK port-registration callback wakes it) and prints ``ready``. The first blocks of a
run may go out before that connection: the comparison with the ``sim`` backend uses the last
second of a two-second run.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time

import numpy as np
import pytest
from hil_jack import CLI, JACKD, EmulatorProcess, FakeRun, JackServer, emulator_errors, xrun_causes
from optional import require

pytestmark = pytest.mark.hil

if JACKD is None:
    pytest.skip("jackd not installed (Debian: apt-get install jackd2): audio HIL tests skipped",
                allow_module_level=True)
require("jack", "sounddevice")  # the emulator's JACK client, the run's PortAudio stream

SCENE = "line-bimorph-5"
TIMING = ["timing.block=64", "timing.duration=2.0"]  # the emulator and the runs of the tests below the fixture
# The xrun-burst guard off: these runs judge rtctl's share of the xruns (and the 60 s bench found
# up to 9 flagged blocks in 0.5 s at block 64 on this VM, 135 at block 32 when it was busy);
# the guard itself is tested in test_audio_guard.py.
AUDIO = ["io.backend=audio", "io.device=system", "io.host_api=JACK Audio Connection Kit", "io.xrun_limit=0"]
FREQS = (2.0, 10.0, 40.0, 120.0, 250.0)  # the scene's tone per channel


def sets(items):
    return [a for o in items for a in ("--set", o)]


def rtctl_run(srv, out, extra=(), **kw):
    """``rtctl run SCENE --json`` on the audio backend against ``srv``; the CompletedProcess."""
    cmd = CLI + ["run", SCENE, "--json", "--no-plot", "--out", str(out), *sets(AUDIO), *extra]
    return subprocess.run(cmd, env=srv.env, capture_output=True, text=True, timeout=300, **kw)


def clean(r) -> bool:
    """A run with no xrun flag, no late block and nothing jackd logged as an xrun."""
    io = r["audio"]["io"]
    return not (io["xruns"] or io["late_blocks"] or r["causes"])


def attempt(tmp, i, block):
    """One audio run at ``block`` (JACK's period too) against the emulator, what jackd logged
    meanwhile, and the same scene on the sim backend."""
    from rtctl import scene
    from rtctl.engine.run import run

    timing = [f"timing.block={block}", "timing.duration=2.0"]
    sim = run(scene.load(SCENE, timing), out_dir=tmp / f"sim-{block}", plot=False)
    with JackServer(period=block) as srv:
        emu = EmulatorProcess(srv, SCENE, timing)
        try:
            assert emu.wait_for("waiting", 120), emu.out.seen
            mark = len(srv.log_text())
            # the observer on: its drive/current pairing must match the audio round trip
            proc = rtctl_run(srv, tmp / f"audio-{block}-{i}", extra=sets(timing + ["control.observe=true"]))
            log = srv.log_text()[mark:]
            ready = emu.wait_for("ready", 2.0)
        finally:
            code, emu_err = emu.stop()
    assert proc.returncode == 0, proc.stderr
    return dict(block=block, sim=sim.summary, audio=json.loads(proc.stdout), sim_dir=tmp / f"sim-{block}",
                audio_dir=tmp / f"audio-{block}-{i}", ready=ready, causes=xrun_causes(log), emu_code=code,
                emu_err=emu_err)


@pytest.fixture(scope="module")
def audio_run(tmp_path_factory):
    """Up to two runs at block 64, then two at 256 (a 5.3 ms period), until one is clean; else the
    last, with ``tries`` saying what each had. On this 2-vCPU VM jackd's dummy driver and its
    clients miss deadlines for the machine's reasons at block 64 in most runs (figures:
    docs/backends/audio.md); the checks that do not need a clean run are judged on any."""
    tmp = tmp_path_factory.mktemp("hil-audio")
    tries = []
    for block in (64, 256):
        for i in (1, 2):
            r = attempt(tmp, i, block)
            io = r["audio"]["io"]
            tries.append(f"block {block}: {io['xruns']} xrun flags, {io['late_blocks']} late blocks, "
                         f"jackd {r['causes'] or 'none'}")
            if clean(r):
                return dict(r, tries=tries)
    return dict(r, tries=tries)


def lockin(x, f, fs):
    t = np.arange(x.size) / fs
    return 2 * np.mean(x * np.exp(-2j * np.pi * f * t))


def test_audio_run_reaches_the_sim_amplitudes(audio_run):
    from rtctl.trace import TraceReader

    r = audio_run
    assert r["ready"], "the emulator never connected to the run's ports"
    # the run's end (its ports going) and SIGTERM are the emulator's normal end
    assert r["emu_code"] == 0 and not emulator_errors(r["emu_err"]), r["emu_err"]
    io = r["audio"]["io"]
    block = r["block"]
    print(f"judged at block {block}; tries: {r['tries']}")
    assert io["device"] == "system (JACK Audio Connection Kit)" and io["blocks"] >= 1500 * 64 // block, io
    assert io["error"] is None and not r["audio"]["faults"] and io["inputs_live"] is True
    sim, aud = TraceReader(r["sim_dir"] / "trace"), TraceReader(r["audio_dir"] / "trace")
    fs, n = 48000.0, 96000
    # the drive is the rig's own: identical sample for sample (schedules land at block 0 in both)
    np.testing.assert_array_equal(aud.signal("drive")[:, :n], sim.signal("drive")[:, :n])
    for a, s in zip(r["audio"]["channels"], r["sim"]["channels"]):
        assert a["v_peak"] == s["v_peak"] and a["name"] == s["name"]
    # What came back needs a clean run: a lost or doubled JACK period inside the lock-in window
    # moves every row's amplitude and phase (-1.2 ... -5.8 % seen in a run with hundreds of
    # xruns), and the observer magnifies it
    if not clean(r):
        pytest.skip(f"xruns in every try ({'; '.join(r['tries'])}): the sensed rows and the observer are "
                    "not judged on a run that lost periods")
    # sensed currents: the last second (integer periods of every tone), per row at its tone
    S_a, S_s = aud.signal("sensed")[:, n // 2:n], sim.signal("sensed")[:, n // 2:n]
    assert S_a.shape == S_s.shape == (10, n // 2)
    turns, devs = [], []
    for row in range(10):
        f = FREQS[row // 2]
        za, zs = lockin(S_a[row], f, fs), lockin(S_s[row], f, fs)
        devs.append(abs(za) / abs(zs) - 1)
        if f >= 40:  # the phase lag is well defined above the noise
            turns.append((f, np.angle(za / zs)))
    print(f"sensed amplitude audio/sim - 1 per row: {np.round(np.array(devs) * 100, 3)} %")
    assert max(abs(d) for d in devs) < 0.01, devs
    # sim reads each block's currents one block late; JACK's cycle adds one more block. One tone's
    # phase gives the lag only modulo its period (250 Hz: 192 samples, under a block of 256): the
    # lag is the one delay, in samples, that every tone's phase agrees with (40, 120 and 250 Hz
    # together repeat every 4800 samples)
    worst = [max(abs(np.angle(np.exp(1j * (ph + 2 * np.pi * f * lag / fs)))) for f, ph in turns)
             for lag in range(4 * block)]
    lag = int(np.argmin(worst))
    print(f"extra lag {lag} samples ({lag / block:g} blocks), phase residual {worst[lag]:.2e} rad")
    assert worst[lag] < 0.01 and 0.5 < lag / block < 2.5, (lag, worst[lag])
    # the observer, pairing each current block with the drive two blocks before it, estimates
    # the tip from the audio round trip as the simulation's truth says (within 1 %).
    # An xrun puts a glitch into the lock-in window (0.5 s here) that the observer, working on a
    # ~7 % motional share of the current, magnifies (4.7 % at 250 Hz / 1 V seen once): the
    # comparison needs a clean run, and says so when it did not get one.
    errs = [a["estimated_um"] / s["true_um"] - 1 for a, s in zip(r["audio"]["channels"], r["sim"]["channels"])]
    print(f"observer through the audio round trip vs sim truth: {np.round(np.array(errs) * 100, 3)} %")
    assert max(abs(e) for e in errs) < 0.01, errs


def test_no_xruns(audio_run):
    """Zero xruns at block 64 (else at 256), or else none of rtctl's making.

    rtctl's own share is its callback's work, which must never take longer than a block. When
    the server reports xruns anyway, jackd's log says why: on a virtual machine the dummy driver's
    timer fires late, or a client's real-time thread is not running yet at the deadline (the
    vCPU was idle and woke late). Those are the machine's, and the test skips, saying so.
    """
    r = audio_run
    io = r["audio"]["io"]
    causes = r["causes"]
    print(f"xruns: PortAudio flags {io['xruns']} (first at block {io['first_xrun_block']}); jackd: {causes or 'none'}; "
          f"late blocks {io['late_blocks']}; longest pause {io['max_callback_gap_us']:.0f} us; cfunc {io['cfunc']} "
          f"({io['cfunc_note']})")
    assert io["cfunc"], io["cfunc_note"]
    # rtctl's share: the callback's work (median wall time per block) is a small part of a block.
    # A "late" block is one whose callback took more than a block of wall time: on a loaded 2-vCPU
    # machine that is the thread being preempted mid-callback (seen once in CI), not its work.
    bt, period_us = r["audio"]["block_time_us"], r["block"] / 48000 * 1e6
    assert bt["p50"] < 0.1 * period_us, bt
    if not clean(r):
        pytest.skip(f"xruns in every try ({'; '.join(r['tries'])}), the callback's median at {bt['p50']:.1f} us "
                    f"of {period_us:.0f} us: this machine's scheduling")


def run_and_kill(tmp_path, kill):
    """A 20 s audio run against the emulator; ``kill(srv, emu)`` 1 s after the emulator
    connected. Returns ``(returncode, stdout, stderr, seconds from the kill to the exit)``."""
    with JackServer(period=64) as srv:
        emu = EmulatorProcess(srv, SCENE, TIMING)
        try:
            assert emu.wait_for("waiting", 120), emu.out.seen
            cmd = CLI + ["run", SCENE, "--json", "--no-plot", "--out", str(tmp_path / "run"),
                         *sets(TIMING + AUDIO + ["timing.duration=20"])]
            proc = subprocess.Popen(cmd, env=srv.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                    start_new_session=True)
            try:
                assert emu.wait_for("ready", 120), emu.out.seen
                time.sleep(1.0)  # >= 750 live blocks, the tests below need 300
                kill(srv, emu)
                t_kill = time.perf_counter()
                out, err = proc.communicate(timeout=60)
                t_exit = time.perf_counter()
            finally:
                if proc.poll() is None:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()
        finally:
            emu.stop()
    assert proc.returncode == 1, (proc.returncode, err)
    assert "Traceback" not in err and "Assertion" not in err
    return out, err, t_exit - t_kill


def test_killing_the_audio_server_ends_the_run(tmp_path):
    """The audio server is the device: SIGKILL it mid-run, as if the interface were unplugged."""
    from rtctl.safety import DEVICE_LOST
    from rtctl.trace import TraceReader

    out, err, exit_s = run_and_kill(tmp_path, lambda srv, emu: srv.kill())
    lines = [x for x in err.splitlines() if x.startswith("rtctl:")]
    assert lines and "I/O device lost" in lines[0] and "system (JACK Audio Connection Kit) lost" in lines[0], err
    summary = json.loads(out)
    io = summary["io"]
    print(f"loss noticed {io['loss_detected_after_ms']:.1f} ms after the last callback; process exit "
          f"{exit_s:.2f} s after the kill")
    assert io["loss_detected_after_ms"] < 100
    assert summary["duration_s"] < 10
    tr = TraceReader(tmp_path / "run" / "trace")
    drive, status = tr.signal("drive"), tr.status
    assert tr.n_blocks > 300 and np.any(status & DEVICE_LOST)
    assert np.max(np.abs(drive[:, : 300 * 64])) > 10  # it was playing
    assert np.all(drive[:, -1] == 0.0)  # and the trace ends at 0 V


def test_killing_the_emulator_ends_the_run(tmp_path):
    """The emulator is the plant and its sense chain: SIGKILL it mid-run. JACK disconnects its
    ports, the run's inputs go digitally silent, and the device thread's guard ends the run
    (io.silence_ms, 50 ms) and fades the outputs, all within 100 ms of the last live block."""
    from rtctl.safety import DEVICE_LOST
    from rtctl.trace import TraceReader

    out, err, exit_s = run_and_kill(tmp_path, lambda srv, emu: os.killpg(emu.proc.pid, signal.SIGKILL))
    lines = [x for x in err.splitlines() if x.startswith("rtctl:")]
    assert lines and "I/O device lost: every input sample exactly 0" in lines[0], err
    summary = json.loads(out)
    assert summary["duration_s"] < 10
    tr = TraceReader(tmp_path / "run" / "trace")
    drive, sensed, status = tr.signal("drive"), tr.signal("sensed"), tr.status
    live = np.flatnonzero(np.any(sensed.reshape(sensed.shape[0], -1, 64) != 0, axis=(0, 2)))
    lost = np.flatnonzero(status & DEVICE_LOST)
    zero = np.flatnonzero(np.all(drive[:, 63::64] == 0, axis=0))  # blocks ending at 0 V on every channel
    assert live.size > 300 and lost.size and zero.size
    end = zero[zero >= lost[0]][0]  # the fade's last block
    ms = (end - live[-1]) * 64 / 48.0
    print(f"last live block {live[-1]}, fault at {lost[0]}, outputs at 0 V from block {end}: "
          f"{ms:.1f} ms after the last live block; process exit {exit_s:.2f} s after the kill")
    assert ms <= 100
    assert np.max(np.abs(drive[:, : 300 * 64])) > 10 and np.all(drive[:, -1] == 0.0)


def test_emulator_refuses_a_rate_mismatch_and_a_missing_server():
    with JackServer(period=64) as srv:
        emu = EmulatorProcess(srv, SCENE, ["timing.fs=44100"])
        emu.proc.wait(120)
        code, err = emu.stop()
    assert code == 2 and "the JACK server runs at 48000 Hz, the scene at 44100 Hz" in err, err
    assert len([x for x in err.splitlines() if x.strip()]) == 1
    gone = subprocess.run([*CLI, "emulate", "audio", SCENE, "--server", "rtctl-no-such-server"],
                          capture_output=True, text=True, timeout=60, env=dict(os.environ, JACK_NO_START_SERVER="1"))
    assert gone.returncode == 2 and "no JACK server to join" in gone.stderr, gone.stderr
    assert len(gone.stderr.splitlines()) == 1, gone.stderr


def test_runs_ending_while_the_emulator_connects_are_its_normal_end():
    """A run's ports go one by one when its stream closes (PortAudio unregisters them, then the
    client closes), at any point of the emulator's discovery, wiring and watch. Twelve runs
    end so - at the emulator's first connection to them, and right after it wired them, ports
    going in either order - and the emulator serves each and ends on SIGTERM with status 0 and
    no error (the old emulator died in 3 of 14 module runs: "internal error: JackError: Port
    'rtctl:out_4' not available", exit 3)."""
    cycles = 12
    with JackServer(period=64) as srv:
        emu = EmulatorProcess(srv, SCENE, TIMING)
        try:
            assert emu.wait_for("waiting", 120), emu.out.seen
            run = FakeRun(srv, cycles, n_out=16, n_in=16, wired=5 + 10)  # PortAudio's ports on 16 channels
            try:
                done = run.wait_done(300)
            finally:
                _, run_err = run.stop()
            alive = emu.proc.poll() is None
        finally:
            code, err = emu.stop()
            jackd = [x for x in srv.log_text().splitlines() if "XRun" not in x and "Process error" not in x
                     and "not finished" not in x and "finished after" not in x]  # its other complaints
    out = emu.out.rest()
    print(f"fake runs: {run.out.seen}; emulator: {out.count('ready')} x ready; stderr {err!r}")
    assert alive and code == 0 and not emulator_errors(err), (code, err)
    assert done, (run.out.seen, run_err, jackd[-20:])
    # the 8 runs that waited for their wiring got it; the 4 ending at the first connection may not
    assert 8 <= out.count("ready") <= cycles, out
