"""Closed-loop amplitude control through a real audio server: the scene ``line-bimorph-5`` under
``control.mode = "closed"`` runs with ``io.backend = "audio"`` against ``rtctl emulate audio`` on a
private ``jackd -d dummy`` (48 kHz, period = block: 64, or 256 when 64 had xruns), and must
reach the tip amplitudes the ``sim`` backend's run of the same scene at the same block reaches.

The audio run knows its tips only from the observer, like a run on hardware. The true tip is the
simulated device's: the emulator writes it (``--truth DIR``) beside the drive it received. The
run's trace and the emulator's are put side by side by their drive, which must be the same
sample for sample (a JACK cycle lost or doubled anywhere in the run would break that), and the
true amplitude is fitted as the run report fits the ``sim`` truth (rtctl.engine.report).

The round trip is two blocks here, one on ``sim``: the observer must pair each current block
with the drive two blocks before it, and the controller must wait for it. A wrong latency does
not show in the run's own figures (with ``io.latency_blocks = 1`` the estimate sits on the target
while the true 40, 120 and 250 Hz tips are 78 to 95 % short): only the device's truth tells.

Xruns: a run with any (PortAudio's flags, which include every server xrun while the stream runs)
is not judged; it is run once more, and when that one has xruns too, twice more at block 256 (a
5.3 ms period instead of 1.3 ms: a VM whose vCPUs wake a few ms late now and then loses far fewer
periods; figures in docs/backends/audio.md). When those have xruns
too the test skips, naming them and what jackd said caused them (docs/backends/audio.md).

The same with the finger events of ``line-bimorph-5-closed`` (the finger presses from 50 to 200 g,
lifts off, comes back): the emulator plays them on its own clock (``rtctl emulate audio``), and
every segment between them must settle where the ``sim`` run's does, at the drive it needs there.
"""

from __future__ import annotations

import json
import math
import subprocess
import time

import numpy as np
import pytest
from hil_jack import CLI, JACKD, EmulatorProcess, JackServer, emulator_errors, xrun_causes
from optional import require

pytestmark = pytest.mark.hil

if JACKD is None:
    pytest.skip("jackd not installed (Debian: apt-get install jackd2): audio HIL tests skipped",
                allow_module_level=True)
require("jack", "sounddevice")  # the emulator's JACK client, the run's PortAudio stream

SCENE = "line-bimorph-5"
FS = 48000.0
#: The blocks (= JACK periods) tried in turn, two runs each, until one run has no xrun.
BLOCKS = (64, 256)


def duration(block) -> float:
    """2 s in whole blocks: every reachable tone settles within 0.2 s of its start (checked below
    on the device's truth), and the report's window for the 2 Hz channel, two periods capped at
    half the run, fits."""
    return math.ceil(2.0 * FS / block) * block / FS


def timing(block):
    return [f"timing.block={block}", f"timing.duration={duration(block)!r}"]


CLOSED = ["control.mode=closed"]
AUDIO = ["io.backend=audio", "io.device=system", "io.host_api=JACK Audio Connection Kit",
         "io.xrun_limit=0"]  # the burst guard off: a run with xruns is retried or skipped, never judged
# A device off its model, known only to the simulated hardware (sim, the emulator): never the run's.
MISMATCH = ["io.mismatch.d31=0.9", "io.mismatch.E=1.08"]
TOLERANCE = 0.02  # audio against sim, true amplitude, per channel


def sets(items):
    return [a for o in items for a in ("--set", o)]


def on_audio(tmp, name, command, block, device=(), ok_if=lambda proc: proc.returncode == 0, scene=SCENE,
             times=timing):
    """``rtctl COMMAND`` against the emulator of ``scene`` (started with ``times(block)`` and
    ``device`` overrides and ``--truth``) on a private server of period ``block``. Returns a
    dict: the process, its wall time, the emulator's exit status, stderr and ``ready`` count, the
    truth directory, jackd's xrun causes meanwhile and the block."""
    truth = tmp / f"{name}-truth"
    with JackServer(period=block) as srv:
        emu = EmulatorProcess(srv, scene, times(block) + list(device), extra=["--truth", str(truth)])
        try:
            assert emu.wait_for("waiting", 120), emu.out.seen
            mark = len(srv.log_text())
            t0 = time.monotonic()
            proc = subprocess.run(CLI + command, env=srv.env, capture_output=True, text=True, timeout=600)
            wall = time.monotonic() - t0
            log = srv.log_text()[mark:]
        finally:
            code, err = emu.stop()
    ready = emu.out.rest().count("ready")
    assert ok_if(proc), proc.stderr
    assert code == 0 and not emulator_errors(err), err
    return dict(proc=proc, wall=wall, emu_err=err, ready=ready, truth=truth, causes=xrun_causes(log), block=block)


def closed_loop_on_audio(tmp, name, block, run=(), device=(), scene=SCENE, times=timing):
    """A closed-loop ``rtctl run`` on the audio backend; its summary added as ``summary``."""
    out = tmp / name
    r = on_audio(tmp, name, ["run", scene, "--json", "--no-plot", "--out", str(out),
                             *sets(times(block) + CLOSED + AUDIO + list(run))], block, device, scene=scene,
                 times=times)
    r.update(summary=json.loads(r["proc"].stdout), out=out)
    r["xruns"] = r["summary"]["io"]["xruns"]
    return r


def without_xruns(attempt, blocks=BLOCKS):
    """``attempt(i, block)`` (a dict with ``xruns`` and ``causes``) at each of ``blocks`` in turn,
    twice each, until a try has no xruns: that try, with ``tries``. Skips when every try had xruns."""
    seen = []
    for block in blocks:
        for i in (1, 2):
            r = attempt(i, block)
            if not r["xruns"]:
                return dict(r, tries=len(seen) + 1)
            seen.append(f"block {block}: {r['xruns']} (jackd: {r['causes']})")
    pytest.skip(f"xruns in every try ({'; '.join(seen)}): this machine's scheduling, the run is not judged")


def emulator_alignment(run_dir, truth_dir, block: int) -> dict:
    """Where the emulator's record of the drive sits against the run's trace, and whether it heard
    every block: ``k0`` the run's blocks that went out before the emulator connected, ``off`` the
    emulator's period that received the run's block 0 (negative: connected after it), ``last``
    the run's last driven block, and ``same``: the drive agrees sample for sample over everything
    both hold (False: a period lost or repeated between them, a glitch neither xrun count saw).

    The emulator's record and the run's trace are aligned on their last driven block (the run's
    final fade)."""
    from rtctl.trace import TraceReader

    run, dev = TraceReader(run_dir / "trace"), TraceReader(truth_dir)
    assert dev.block == run.block == block and dev.fs == run.fs == FS
    assert dev.channels == run.channels, (dev.channels, run.channels)
    # every JACK period since the plant's reset is there, in order (the ring never lapped)
    np.testing.assert_array_equal(dev.records["block"], np.arange(dev.n_blocks))
    rd, dd = run.signal("drive"), dev.signal("drive")

    def driven(d):
        return np.flatnonzero(np.any(d.reshape(d.shape[0], -1, block) != 0, axis=(0, 2)))

    last = driven(rd)[-1]
    off = driven(dd)[-1] - last
    k0 = max(0, -off)
    # float32 through JACK and the traces: a few ulp, far below any glitch of a lost period
    same = bool(np.allclose(dd[:, (k0 + off) * block:(last + 1 + off) * block],
                            rd[:, k0 * block:(last + 1) * block], rtol=1e-6, atol=1e-6))
    return dict(k0=k0, off=off, last=last, same=same, run=run, dev=dev)


def device_tip(run_dir, truth_dir, n: int, block: int, offset=False) -> np.ndarray:
    """The emulator's true tip (um) at each of the run's first ``n`` samples, ``(channels, n)``;
    NaN for samples that went out before the emulator connected. With ``offset``, also the
    emulator's period that received the run's block 0 (negative: connected after it).
    The drive must agree sample for sample over everything both hold (:func:`emulator_alignment`)."""
    a = emulator_alignment(run_dir, truth_dir, block)
    k0, off, last = a["k0"], a["off"], a["last"]
    assert last * block >= n - block, (last, n)  # the run drove to its end (its fade follows)
    assert k0 < 50, f"the emulator connected {k0} blocks into the run"
    assert a["same"], "the emulator's drive differs from the run's: a period lost or repeated between them"
    rd = a["run"].signal("drive")
    tip = np.full((rd.shape[0], n), np.nan)
    tip[:, k0 * block:] = a["dev"].signal("tip_um")[:, (k0 + off) * block:off * block + n]
    return (tip, off) if offset else tip


def amplitudes(tip, rows) -> list[float]:
    """Per channel, the true amplitude as the run report fits it (rtctl.engine.report): over
    its analysis window at the run's end, at the channel's tone frequencies."""
    from rtctl.engine.report import analysis_window, fit_amplitudes

    n = tip.shape[1]
    t = np.arange(n) / FS
    out = []
    for ch, row in enumerate(rows):
        m = t >= t[-1] - analysis_window(n / FS, row["freqs_hz"])
        assert np.all(np.isfinite(tip[ch][m]))
        out.append(float(fit_amplitudes(tip[ch][m], t[m], row["freqs_hz"]).sum()))
    return out


def settle_s(tip, rows, final) -> list[float | None]:
    """Per channel, seconds from the tone's start until its true amplitude stays within the
    report's 5 % band of ``final`` (rtctl.engine.report.settle_time)."""
    from rtctl.engine.report import settle_time

    t = np.arange(tip.shape[1]) / FS
    ok = np.all(np.isfinite(tip), axis=0)  # from the emulator's connection on
    return [settle_time(tip[ch][ok], t[ok], row["freqs_hz"], t[ok][0], f) for ch, (row, f)
            in enumerate(zip(rows, final))]


def run_sim(tmp, name, block, extra=()):
    from rtctl import scene
    from rtctl.engine.run import run

    return run(scene.load(SCENE, timing(block) + CLOSED + list(extra)), out_dir=tmp / f"{name}-{block}", plot=False)


def compare(sim, aud) -> dict:
    """The audio run against the sim run: its health, the device's truth against the sim
    truth per channel, the observer against the device's truth. Returns the figures."""
    from rtctl.trace import TraceReader

    s, a = sim.summary, aud["summary"]
    io = a["io"]
    assert aud["ready"] == 1, aud["emu_err"]
    assert io["device"] == "system (JACK Audio Connection Kit)" and io["error"] is None and io["inputs_live"] is True
    assert io["cfunc"], io["cfunc_note"]
    assert not a["faults"] and not s["faults"] and io["xruns"] == 0
    # the observer and the controller take the audio round trip, not sim's one block; the audio
    # backend's figure is a constant, so it is checked against what the stream reports here
    assert TraceReader(aud["out"] / "trace").layout["meta"]["latency_blocks"] == 2
    block = aud["block"]
    assert round((io["latency_in_s"] + io["latency_out_s"]) * FS / block, 6) == 2, io
    assert s["block"] == a["block"] == block
    sim_trace = TraceReader(sim.out_dir / "trace")
    assert sim_trace.layout["meta"]["latency_blocks"] == 1
    n = round(a["duration_s"] * FS)
    assert n == round(s["duration_s"] * FS) == round(duration(block) * FS)
    # the fit used here is the report's: it gives the sim run's own true_um from its trace
    sim_tip = sim_trace.signal("tip_um")[:, :n]
    np.testing.assert_allclose(amplitudes(sim_tip, s["channels"]), [r["true_um"] for r in s["channels"]], rtol=1e-9)
    tip = device_tip(aud["out"], aud["truth"] / "run-1", n, block)
    true = amplitudes(tip, a["channels"])
    settle = settle_s(tip, a["channels"], true)
    fig = {"sim_um": [r["true_um"] for r in s["channels"]], "audio_um": true, "settle_s": settle,
           "estimated_um": [r["estimated_um"] for r in a["channels"]], "wall_s": aud["wall"],
           "xruns": io["xruns"], "tries": aud["tries"], "block": block, "jackd": aud["causes"]}
    fig["diff_pct"] = [100 * (x / y - 1) for x, y in zip(true, fig["sim_um"])]
    fig["estimate_pct"] = [100 * (e / x - 1) for e, x in zip(fig["estimated_um"], true)]
    print(json.dumps(fig, indent=None, default=lambda v: round(v, 4)))
    for r_s, r_a, x, e, st in zip(s["channels"], a["channels"], true, fig["estimated_um"], settle):
        assert r_a["controlled"] and r_s["controlled"] and r_a["name"] == r_s["name"]
        # 2 and 10 Hz are out of reach at 150 V under the finger on both backends; at the cap
        # the tip is the plant's answer to max_voltage, which must agree as well
        assert r_a["saturated"] == r_s["saturated"], (r_a, r_s)
        assert abs(x / r_s["true_um"] - 1) < TOLERANCE, (r_a["name"], x, r_s["true_um"])
        # the observer's estimate through the round trip against the device's truth (on sim it
        # is within 0.5 %): a current paired with the wrong drive block would be far off
        assert abs(e / x - 1) < 0.01, (r_a["name"], e, x)
        if not r_s["saturated"]:  # settled before the window the amplitude is fitted over
            assert st is not None and st < a["duration_s"] / 2, (r_a["name"], st)
    return fig


@pytest.fixture(scope="module")
def tmp(tmp_path_factory):
    return tmp_path_factory.mktemp("hil-control")


def test_closed_loop_on_audio_reaches_the_sim_amplitudes(tmp):
    """Each channel's true tip amplitude over audio within 2 % of the sim run's, the observer
    within 1 % of the device's truth, in a run without xruns."""
    aud = without_xruns(lambda i, block: closed_loop_on_audio(tmp, f"audio-{block}-{i}", block))
    compare(run_sim(tmp, "sim", aud["block"]), aud)


def test_calibrated_closed_loop_on_audio_reaches_the_sim_amplitudes(tmp):
    """A device off its model (d31 x0.9, E x1.08; the emulator's and sim's secret), calibrated
    over audio and then held closed loop: the true amplitudes within 2 % of the sim run that
    calibrates itself (``control.calibrate = "auto"``) on the same device.

    Calibration wants the finger lifted; the emulator's finger cannot be lifted during a run, so
    the calibration runs against an emulator started without finger contact (the user lifting
    the finger when ``rtctl calibrate`` asks), the closed loop against one with the finger, as
    ``rtctl calibrate`` then ``control.calibration = FILE`` do on hardware."""
    from rtctl.trace import TraceReader

    cal = tmp / "calibration.json"

    def calibrate(i, block):
        r = on_audio(tmp, f"calibrate-{block}-{i}", ["calibrate", SCENE, "--json", "--out", str(cal),
                                                      *sets(timing(block) + AUDIO)], block,
                     device=MISMATCH + ["finger.contact=false"],
                     ok_if=lambda p: p.returncode == 0 or "(xrun)" in p.stderr)
        # the excitation refuses xruns in its window itself (the measurement is void): a run refused
        # for that counts as one with xruns
        r["xruns"] = "the excitation refused" if r["proc"].returncode != 0 else 0
        return r

    def closed(i, block):
        return closed_loop_on_audio(tmp, f"audio-calibrated-{block}-{i}", block,
                                    run=[f"control.calibration={cal}"], device=MISMATCH)

    # calibration and the closed loop at one block: the first block at which both get a run
    # without xruns (each skips the test only at the last block)
    for n, block in enumerate(BLOCKS):
        last = n == len(BLOCKS) - 1
        try:
            without_xruns(calibrate, (block,))
            aud = without_xruns(closed, (block,))
            break
        except pytest.skip.Exception:
            if last:
                raise
    doc = json.loads(cal.read_text())
    assert doc["backend"] == "audio" and doc["excitation"]["latency_blocks"] == 2
    sim = run_sim(tmp, "sim-calibrated", block, MISMATCH + ["control.calibrate=auto"])
    ref = json.loads((sim.out_dir / "calibration.json").read_text())
    got, want = doc["groups"]["lateral"], ref["groups"]["lateral"]
    print(f"block {block}: calibration over audio: {got['factors']}, residual {got['residual_pct']:.3f} %, cond "
          f"{got['cond']:.0f}; on sim: {want['factors']}, residual {want['residual_pct']:.3f} %")
    for k, v in want["factors"].items():  # the same device seen through either backend
        assert abs(got["factors"][k] / v - 1) < 0.005, (k, got["factors"][k], v)
    assert aud["summary"]["calibration"]["file"] == str(cal)
    # the device the loop held was the mismatched one (the run itself never learns it)
    assert TraceReader(aud["truth"] / "run-1").layout["meta"]["mismatch"] == {"d31": 0.9, "E": 1.08}
    compare(sim, aud)


EVENTS_SCENE = "line-bimorph-5-closed"


def test_finger_events_on_audio_settle_where_sim_does(tmp):
    """``line-bimorph-5-closed``: the finger presses from 50 to 200 g, lifts off, comes back. The
    emulator plays those events on its clock (from the first period the run drives; the run's
    block count is not on the wire), the closed loop through audio answers them, and in every
    segment between them each channel's true amplitude and the drive holding it are within 2 % of
    the ``sim`` run's (the drive a 200 g finger or a lifted one needs is not the 50 g finger's: a
    finger that kept its first load would fail here), and settles where the sim run's does."""
    from rtctl import scene
    from rtctl.engine.report import analysis_window, fit_amplitudes, settle_time
    from rtctl.engine.run import run
    from rtctl.events import block_of
    from rtctl.trace import TraceReader

    def times(block):
        return [f"timing.block={block}"]  # the scene's 2.4 s: whole blocks at 64 and 256

    aud = without_xruns(lambda i, block: closed_loop_on_audio(tmp, f"events-{block}-{i}", block, scene=EVENTS_SCENE,
                                                              times=times))
    block = aud["block"]
    sc = scene.load(EVENTS_SCENE, times(block))
    sim = run(sc, out_dir=tmp / f"events-sim-{block}", plot=False)
    s, a = sim.summary, aud["summary"]
    assert aud["ready"] == 1 and a["io"]["error"] is None and not a["faults"] and not s["faults"]
    assert "C process callback" in aud["emu_err"], aud["emu_err"]  # the events' generated code ran
    n = round(a["duration_s"] * FS)
    tip, off = device_tip(aud["out"], aud["truth"] / "run-1", n, block, offset=True)
    sim_tip = TraceReader(sim.out_dir / "trace").signal("tip_um")[:, :n]
    drives = {"sim": TraceReader(sim.out_dir / "trace").signal("drive")[:, :n],
              "audio": TraceReader(aud["out"] / "trace").signal("drive")[:, :n]}
    # the emulator's clock: its period 0 is the first it heard driven; the run drives from its
    # block 1 (a closed loop's first command), or from the block it connected at
    dd = TraceReader(aud["truth"] / "run-1").signal("drive")
    heard = int(np.flatnonzero(np.any(dd.reshape(dd.shape[0], -1, block) != 0, axis=(0, 2)))[0])
    lag = int(heard - off)  # the run's block the emulator's clock starts at
    assert lag == max(1, -off), (heard, off)
    t = np.arange(n) / FS
    starts = [0.0] + [block_of(e.at, FS, block) * block / FS for e in sc.events]
    fig = {"block": block, "tries": aud["tries"], "emulator_lag_blocks": lag, "segments": []}
    for ch, (rs, ra) in enumerate(zip(s["channels"], a["channels"])):
        assert rs["controlled"] and ra["controlled"] and ra["name"] == rs["name"]
        freqs = rs["freqs_hz"]
        for i, seg in enumerate([rs["start"], *rs["events"]]):
            t0, t1 = starts[i], starts[i + 1] if i + 1 < len(starts) else n / FS
            assert seg["t_s"] == pytest.approx(t0)
            win = min(analysis_window(t1 - t0, freqs), (t1 - t0) / 2)
            m = (t >= t1 - win) & (t < t1)
            got = float(fit_amplitudes(tip[ch][m], t[m], freqs).sum())
            want = float(fit_amplitudes(sim_tip[ch][m], t[m], freqs).sum())
            assert want == pytest.approx(seg["true_um"], rel=1e-6)  # the report's own figure
            volts = {k: float(fit_amplitudes(d[ch][m], t[m], freqs).sum()) for k, d in drives.items()}
            # on audio, from where the emulated finger moved (the lag after the run's event block)
            t_ev = t0 + (lag if i else 0) * block / FS
            inside = (t >= t_ev) & (t < t1) & np.isfinite(tip[ch])
            st = settle_time(tip[ch][inside], t[inside], freqs, t_ev, got)
            row = {"ch": rs["name"], "seg": i, "sim_um": want, "audio_um": got, "sim_v": volts["sim"],
                   "audio_v": volts["audio"], "sim_settle_ms": seg["settle_ms"],
                   "audio_settle_ms": None if st is None else 1e3 * st}
            fig["segments"].append(row)
            assert abs(got / want - 1) < TOLERANCE, row
            assert abs(volts["audio"] / volts["sim"] - 1) < TOLERANCE, row
            # settled inside every segment the sim run settles in (how fast is the round trip's
            # business: at block 256 audio's extra 5.3 ms per correction shows; docs/control.md)
            assert (st is None) == (seg["settle_ms"] is None), row
    print(json.dumps(fig, default=lambda v: round(v, 4)))
