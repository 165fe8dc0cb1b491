"""Closed-loop amplitude control in whole runs on the simulated rig: targets reached, the honest
saturation of an unreachable one, settle times, and nothing compiled for open-loop scenes."""

from __future__ import annotations

import numpy as np
import pytest

from rtctl import scene
from rtctl.control._kernels import DEADBAND
from rtctl.engine.rig import build
from rtctl.engine.run import run


@pytest.fixture(scope="module")
def closed(tmp_path_factory):
    out = tmp_path_factory.mktemp("closed")
    return run(scene.load("line-bimorph-5", ["control.mode=closed", "timing.duration=1.5"]), out_dir=out,
               plot=False).summary


def test_reachable_targets_are_met_and_the_rest_saturate_honestly(closed):
    rows = {r["name"]: r for r in closed["channels"]}
    for name in ("lateral.2", "lateral.3", "lateral.4"):  # 40, 120, 250 Hz: reachable
        r = rows[name]
        assert r["controlled"] and not r["saturated"]
        assert abs(r["error_pct"]) < 1.0, r  # true amplitude against the target
        # the loop holds the estimate within its deadband of the target; the row's estimate is a
        # median over the run's second half (0.75 s) of estimates whose noise the row states, each
        # window one independent draw: at 250 Hz (0.16 um, 0.0025 um of noise, 4 ms windows) that
        # median alone scatters by about 0.15 %, at 40 and 120 Hz by under 0.01 %
        draws = 0.75 / r["observer_window_s"]
        scatter = 1.25 * r["noise_um"] / r["target_um"] / np.sqrt(draws)
        assert abs(r["estimated_um"] / r["target_um"] - 1) < DEADBAND + 3 * scatter, r
        assert r["felt"] is True
    for name in ("lateral.0", "lateral.1"):  # 2 and 10 Hz need more than 150 V under this finger
        r = rows[name]
        assert r["saturated"] and r["v_peak"] <= 150.0
        assert r["reachable_um"] == pytest.approx(r["true_um"], rel=0.02)
        assert r["error_pct"] < -30
    assert "amplitude control saturated" in " ".join(closed["warnings"])
    assert not any(r.get("at_floor") for r in closed["channels"])  # (no estimate left the tip)
    assert "at its floor" not in " ".join(closed["warnings"])


def test_closed_loop_settles_within_five_periods_or_50_ms(closed):
    rows = {r["name"]: r for r in closed["channels"]}
    for name, f in (("lateral.2", 40.0), ("lateral.3", 120.0), ("lateral.4", 250.0)):
        assert rows[name]["settle_ms"] <= 1e3 * max(5 / f, 0.05), rows[name]


def test_open_loop_compiles_no_controller_closed_loop_one_per_group():
    ol = [s.name for s in build(scene.load("line-bimorph-5", ["timing.duration=0.01"])).stages]
    assert not any(n.startswith(("control", "observer")) for n in ol)
    rig = build(scene.load("line-bimorph-5", ["control.mode=closed"]))
    cl = [s.name for s in rig.stages]
    # one observer for the group (each channel's window its own: tests/test_rig_observer.py), one
    # controller right after it, both after the limiter
    assert [n for n in cl if n.startswith("control")] == ["control lateral"]
    assert [n for n in cl if n.startswith("observer")] == ["observer lateral"]
    assert cl.index("limiter") < cl.index("observer lateral") == cl.index("control lateral") - 1
    # its columns: every tone of every channel, each reading its own channel's row of the group
    (_, st, ctl), = rig.controllers
    from rtctl.control._kernels import CHANNEL, OBS_CH

    assert st is rig.observer_stages[0][1] and ctl.n == 5
    assert ctl.index[OBS_CH].tolist() == ctl.index[CHANNEL].tolist() == list(range(5))


#: Four channels whose tones have four windows (80 Hz: 600 samples, 19 blocks; 235 + 265 Hz by
#: least squares: 1600, 50 blocks, two columns of one channel; 120 Hz: 800, 25; 40 Hz: 2400, 75),
#: the finger pressing, lifting and returning, and a target stepped by an event
TWIN = ("line-bimorph-5-closed", [
    "actuator.lateral.grid=[1, 4]", "timing.duration=0.9",
    "stimulus.tones=[{channel = 0, freq = 80, voltage = 1.0, target_um = 6.0}, "
    "{channel = 1, freq = 250, beat = 30, voltage = 1.0, target_um = 6.6}, "
    "{channel = 2, freq = 120, voltage = 1.0, target_um = 3.0}, "
    "{channel = 3, freq = 40, voltage = 1.0, target_um = 4.0}]",
    'events=[{at = 0.3, set = {"finger.preload" = 1.96}}, {at = 0.45, set = {"stimulus.tones.2.target_um" = 5.0}}, '
    '{at = 0.6, set = {"finger.contact" = false}}, {at = 0.75, set = {"finger.contact" = true}}]'])


def test_one_controller_per_group_runs_as_a_controller_per_channel_bitwise(tmp_path):
    """The group's one controller against the reference twin (tests/per_channel_rig.py: a
    controller stage per channel on views of the group's observer, as the rig once was): the
    same trace bitwise, the same summary, channels with different windows and a beat pair."""
    import json

    from per_channel_rig import PerChannelRig

    from rtctl.control._kernels import BANK
    from rtctl.trace import TraceReader

    sc = scene.load(*TWIN)
    group, twin = build(sc), PerChannelRig(sc)
    assert [s.name for s in twin.stages if s.name.startswith("control")] == [
        f"control lateral.{i}" for i in range(4)]
    assert [s.name for s in group.stages if s.name.startswith("control")] == ["control lateral"]
    (_, _, ctl), = group.controllers
    # each column waits and watches as its channel's own controller did
    for _, _, one in twin.controllers:
        cols = [int(np.nonzero(ctl.index[BANK] == b)[0][0]) for b in one.index[BANK]]
        assert np.array_equal(ctl.state[:, cols], one.state) and np.array_equal(ctl.target[:, cols], one.target)
    # 80 and 40 Hz wait for their low-pass's memory too; 120 Hz and up are not low-passed
    obs = group.observer_stages[0][1].observer
    assert np.flatnonzero(obs.prefilter).tolist() == [0, 3]
    w80, w40 = (-(-(w + int(obs.prefilter_memory[c])) // group.block) for c, w in ((0, 600), (3, 2400)))
    assert sorted(set(ctl.warm.tolist())) == [group.latency + w + 1 for w in (w80, 25, 50, w40)]
    runs = {}
    for name, rig in (("group", group), ("twin", twin)):
        run(sc, tmp_path / name, plot=False, rig=rig)
        runs[name] = (TraceReader(tmp_path / name / "trace").records,
                      json.loads((tmp_path / name / "summary.json").read_text()))
    (ra, sa), (rb, sb) = runs["group"], runs["twin"]
    assert len(ra) == len(rb) > 0
    for f in ra.dtype.names:
        if f not in ("compute_us", "wake_late_us"):
            assert ra[f].tobytes() == rb[f].tobytes(), f"trace field {f} differs"
    varying = {"realtime_factor", "cpu_realtime_factor", "build_s", "block_time_us", "wake_late_us", "realtime"}
    assert sa.keys() == sb.keys()
    for k in sa:
        if k not in varying:
            assert sa[k] == sb[k], f"summary {k}: {sa[k]!r} != {sb[k]!r}"
    rows = {r["name"]: r for r in sa["channels"]}
    assert all(rows[f"lateral.{i}"]["controlled"] for i in range(4))
    assert [rows[f"lateral.{i}"]["observer_window_s"] for i in range(4)] == [600 / 48e3, 1600 / 48e3,
                                                                             800 / 48e3, 2400 / 48e3]


def test_closed_loop_needs_tones():
    from rtctl.errors import SceneError

    with pytest.raises(SceneError, match="control.mode = closed needs stimulus.kind = 'tones'"):
        build(scene.load("line-bimorph-5", ["control.mode=closed", "stimulus.kind=shape"]))


@pytest.mark.parametrize("second", ["{channel = 0, freq = 250, voltage = 1, target_um = 2}",
                                    "{channel = 0, freq = 265, voltage = 1, target_um = 2}"])
def test_two_tones_at_one_frequency_of_a_channel_are_refused_under_control(second):
    """Two tones of one channel at 250 Hz, or a 250 / 30 Hz beat pair (235 + 265 Hz) and a 265 Hz
    tone: the observer reads one amplitude per frequency, so their two controllers would each read
    the sum of both (the first held its drive at the floor, 34 % low): a clear error naming the
    channel and the frequency. Open loop plays them as the sum they are."""
    from rtctl.errors import SceneError

    first = ("{channel = 0, freq = 250, voltage = 1, target_um = 1}" if "250" in second
             else "{channel = 0, freq = 250, beat = 30, voltage = 1, target_um = 1}")
    tones = f"stimulus.tones=[{first}, {second}]"
    f = "250" if "250" in second else "265"
    with pytest.raises(SceneError, match=f"channel lateral.0 plays {f} Hz in more than one tone"):
        build(scene.load("line-bimorph-5-closed", [tones, "events=[]"]))
    build(scene.load("line-bimorph-5", [tones]))


def test_two_tones_at_one_frequency_are_observed_as_their_sum(tmp_path):
    """Observe-only, two 1 V tones of lateral.0 at 250 Hz are one 2 V sine there: the observer
    reads it once (it had read the sum once per tone, +100 %) and its estimate agrees with the
    simulated tip, and with lateral.1 playing one 2 V tone."""
    tones = ("stimulus.tones=[{channel = 0, freq = 250, voltage = 1}, {channel = 0, freq = 250, voltage = 1}, "
             "{channel = 1, freq = 250, voltage = 2}]")
    s = scene.load("line-bimorph-5", [tones, "timing.duration=0.3", "control.observe=true"])
    two, one = run(s, out_dir=tmp_path, plot=False).summary["channels"][:2]
    assert two["true_um"] == pytest.approx(one["true_um"], rel=1e-9)
    assert two["estimated_um"] == pytest.approx(two["true_um"], rel=0.01)  # the scene's 4 modes: 0.4-0.6 %
    assert two["estimated_um"] == pytest.approx(one["estimated_um"], rel=1e-3)  # (each channel its own noise)


def test_a_played_voice_at_a_held_tone_frequency_is_refused():
    """A closed scene's 120 Hz tone on lateral.3 and a played 120 Hz sine on the same channel:
    the voice's controller and the tone's would each read their sum. Refused, naming both; the
    same voice on another channel is not."""
    from rtctl.errors import SceneError

    play = ['stimulus.signals=[{name = "c", type = "sine", freq = 120.0, amp = 12.0}]',
            "stimulus.play=[{signal = 'c', channel = 3, start = 0.1}]", "events=[]"]
    with pytest.raises(SceneError, match="channel lateral.3 plays 120 Hz in a tone and in a played voice"):
        build(scene.load("line-bimorph-5-closed", play))
    build(scene.load("line-bimorph-5-closed", [*play[:1], "stimulus.play=[{signal = 'c', channel = 2, start = 0.1}]",
                                               "events=[]"]))


def test_closed_loop_refuses_a_scene_with_nothing_to_hold_and_names_what_plays_open_loop():
    """Solenoid pins (pulse tones) and SMA taxels: nothing self-sensing reads, so a closed loop
    would have run open loop and said nothing; refused, naming the pins and their actuator.
    bimodal-4x4: its lateral bimorphs are held, its EM pin's 10 Hz tone plays open loop, and a
    warning says so. The bundled closed scene holds every tone: no such warning."""
    from rtctl.errors import SceneError

    with pytest.raises(SceneError, match=r"no tone to hold at a target: .* pins\.0, pins\.4, pins\.8 on "
                                         r"actuator 'pins' \(solenoid, which self-sensing does not read\)"):
        build(scene.load("solenoid-3x3", ["control.mode=closed"]))
    with pytest.raises(SceneError, match="no tone to hold at a target"):
        build(scene.load("sma-8x8", ["control.mode=closed"]))
    rig = build(scene.load("bimodal-4x4", ["control.mode=closed"]))
    assert sorted(ctl.n for _, _, ctl in rig.controllers) == [2]
    assert rig.warnings == ["control.mode = closed: these tones play open loop: normal.5 on actuator 'normal' "
                            "(em, which self-sensing does not read)"]
    assert not [w for w in build(scene.load("line-bimorph-5-closed")).warnings if "open loop" in w]


def test_a_tone_target_in_um_overrides_the_receptor_margin():
    rig = build(scene.load("line-bimorph-5", ["control.mode=closed", "stimulus.tones.4.target_um=0.3"]))
    assert rig.targets_um[4] == pytest.approx(0.3)
    assert np.isfinite(rig.targets_um).all()


def test_the_report_judges_against_the_target_in_force(tmp_path):
    """A target stepped by an event: the row, and the event's segment, are judged against the new
    target, the start's segment against the old one; a channel of two tones against the sum of
    their targets (its amplitude is the sum of theirs, as a beat pair's is its two sines'), and
    the trace's target line says the same. (The report judged the 5 um step against the scene's
    12 um, -58 %; the two tones' 6 um sum against the first tone's 5 um, +19 %.)"""
    from rtctl.trace import TraceReader

    tones = ("[{channel = 0, freq = 100, voltage = 1.0, target_um = 5.0}, "
             "{channel = 0, freq = 300, voltage = 1.0, target_um = 1.0}, "
             "{channel = 1, freq = 120, voltage = 1.0, target_um = 6.0}]")
    s = scene.load("line-bimorph-5-closed", ["actuator.lateral.grid=[1, 2]", f"stimulus.tones={tones}",
                                             'events=[{at = 0.3, set = {"stimulus.tones.2.target_um" = 3.0}}]',
                                             "timing.duration=0.6"])
    res = run(s, out_dir=tmp_path, plot=False)
    two, stepped = res.summary["channels"]
    assert two["target_um"] == pytest.approx(6.0, rel=1e-12) and abs(two["error_pct"]) < 2.0, two
    assert two["error_pct"] == pytest.approx(100 * (two["true_um"] / 6.0 - 1), rel=1e-9)
    assert stepped["target_um"] == pytest.approx(3.0, rel=1e-12) and abs(stepped["error_pct"]) < 2.0, stepped
    (ev,) = stepped["events"]
    assert ev["target_um"] == pytest.approx(3.0, rel=1e-12)
    assert ev["error_pct"] == pytest.approx(stepped["error_pct"], rel=1e-12)
    st = stepped["start"]
    assert st["target_um"] == pytest.approx(6.0, rel=1e-12) and abs(st["error_pct"]) < 2.0
    assert st["error_pct"] == pytest.approx(100 * (st["true_um"] / 6.0 - 1), rel=1e-9)
    line = TraceReader(tmp_path / "trace").signal("target_um")
    k = int(round(0.3 * s.timing.fs)) // s.timing.block
    assert np.all(line[0] == 6.0)
    assert np.all(line[1, :k] == 6.0) and np.all(line[1, k:] == 3.0)


def test_an_events_target_of_0_is_the_receptors_threshold_as_in_the_scene(tmp_path):
    """``target_um = 0`` means the receptor's threshold raised by ``control.margin_db`` in the scene,
    and so in an event: the 40 Hz tone steps from 5 um to the Meissner target (it went silent
    instead), and the report judges it there. A tone without a threshold is refused in one line."""
    from rtctl import perception
    from rtctl.errors import SceneError

    ev = 'events=[{at = 0.4, set = {"stimulus.tones.2.target_um" = 0}}]'
    s = scene.load("line-bimorph-5-closed", [ev, "stimulus.tones.2.target_um=5", "timing.duration=0.8"])
    row = run(s, out_dir=tmp_path, plot=False).summary["channels"][2]
    want = 1e6 * perception.target_m(40.0, "meissner", s.control.margin_db)
    assert row["start"]["target_um"] == pytest.approx(5.0, rel=1e-12) and abs(row["start"]["error_pct"]) < 2.0
    assert row["target_um"] == pytest.approx(want, rel=1e-12) and row["events"][0]["target_um"] == row["target_um"]
    assert abs(row["error_pct"]) < 2.0 and row["true_um"] > 2 * 5.0, row
    with pytest.raises(SceneError, match=r"events.0.set: stimulus.tones.2.target_um = 0 asks for the receptor's "
                                         r"threshold, and receptor 'meissner' has none at 3000 Hz"):
        build(scene.load("line-bimorph-5-closed", [ev, "stimulus.tones.2.target_um=5", "stimulus.tones.2.freq=3000"]))


def test_an_estimate_that_does_not_follow_the_tip_holds_the_drive_at_its_floor(tmp_path):
    """Current noise 100 times the scene's (1e-4 V at the ADC): the 250 Hz tone's 0.16 um target
    is read through noise of its own size, which no drop of drive moves, and every correction
    down divided the drive again (down to 1e-16 V, the channel silent and its row showing only
    an error). The drive holds at its floor instead: the target over 4 times the most tip per volt
    any load allows (the finger lifted, its two sets, each 3x softer and stiffer), here from the
    simulated plant (the finite-element beam, not the observer's transfer-matrix twin) within 2 %;
    the row and the warnings say so. The other channels are unaffected."""
    from rtctl.models import Models
    from rtctl.plant.bimorph import BimorphPlant
    from rtctl.plant.finger import MaxwellLoad
    from rtctl.plant.frontend import Amplifier, CurrentSense
    from rtctl.safety import CONTROL_FLOOR, STATUS_NAMES
    from rtctl.trace import TraceReader

    s = scene.load("line-bimorph-5-closed", ["actuator.lateral.sense.noise=1e-4", "timing.duration=1.2", "events=[]"])
    summary = run(s, out_dir=tmp_path, plot=False).summary
    rows = {r["name"]: r for r in summary["channels"]}
    r = rows["lateral.4"]
    assert r["at_floor"] and r["floor_s"] > 0.5 and not r["saturated"] and r["felt"] is False, r
    assert STATUS_NAMES[CONTROL_FLOOR] in summary["warnings"]
    assert not any(rows[n]["at_floor"] for n in ("lateral.0", "lateral.1", "lateral.2", "lateral.3"))
    g = s.actuator[0]
    beam = Models(s).beam(g)
    loads = [None] + [MaxwellLoad(sub.mass, sub.k0 * x, tuple((b.k, b.tau) for b in sub.branches))
                      for sub in s.finger.subjects for x in (1 / 3, 1.0, 3.0)]
    top = max(abs(BimorphPlant(beam, Amplifier(g.amplifier.bandwidth), CurrentSense(g.sense.shunt, g.sense.aa_cutoff),
                               load).frequency_response([250.0])[0, 0]) for load in loads)
    floor = r["target_um"] * 1e-6 / (4.0 * top)
    drive = TraceReader(tmp_path / "trace").signal("drive", 4)
    fs = summary["fs"]
    peaks = np.abs(drive[int(0.1 * fs):int(1.1 * fs)]).reshape(-1, int(0.05 * fs)).max(axis=1)  # 50 ms windows
    assert peaks.min() == pytest.approx(floor, rel=0.02)  # held there, never below


def test_a_target_near_the_noise_floor_is_warned_of_before_the_run(tmp_path):
    """20 times the scene's current noise (2e-5 V at the ADC over its 100 ohm shunt): the 250 Hz
    tone's 0.16 um target is 3.2 times its estimate's noise floor (0.05 um rms over the 4 ms
    window), under the 50 that hold it within 1 % (docs/control.md); the build says so in the
    run's warnings, for that channel alone, with the bias it expects (a Rician mean, (floor / y)^2
    / 4). The summary gives every controlled channel's floor, 20 times the scene's own."""
    plain = build(scene.load("line-bimorph-5-closed"))
    assert plain.warnings == []
    s = scene.load("line-bimorph-5-closed", ["actuator.lateral.sense.noise=2e-5", "timing.duration=0.3", "events=[]"])
    summary = run(s, out_dir=tmp_path, plot=False).summary
    warned = [w for w in summary["warnings"] if "noise floor" in w]
    assert len(warned) == 1, warned
    assert warned[0].startswith("channel lateral.4: the 250 Hz target 0.16 um is 3.2 times"), warned
    assert "reads high by about 2.4 %" in warned[0]
    rows = {r["name"]: r for r in summary["channels"]}
    assert rows["lateral.4"]["noise_um"] == pytest.approx(0.16 / 3.2, rel=0.02)
    # the ADC's step (24 bits over +-1 V: 3.4 nV rms) is under 1 % of the scene's 1 uV noise
    for name in ("lateral.0", "lateral.1", "lateral.2", "lateral.3", "lateral.4"):
        base = 1e6 * plain.control_noise[int(np.flatnonzero(plain.bank.chan == int(name[-1]))[0])]
        assert rows[name]["noise_um"] == pytest.approx(20.0 * base, rel=0.01)


@pytest.mark.parametrize("times, warned", [(45.0, True), (55.0, False)])
def test_the_noise_margin_is_50_floors_and_covers_the_targets_events_set(times, warned):
    """The 250 Hz tone's floor is 0.0025 um: a target 45 times it is warned of, 55 times not
    (measured: 40 times held within 0.78 % but one noise seed took 702 ms to settle, 50 times
    within 0.72 % and 40 ms, 5 times up to 4.4 % off). An event's target is judged as the
    scene's: the 40 Hz tone stepped to 0.001 um at 0.3 s is named with its event (it was not)."""
    floor = build(scene.load("line-bimorph-5-closed")).control_noise
    rig = build(scene.load("line-bimorph-5-closed", [f"stimulus.tones.4.target_um={times * 0.0025}"]))
    noise = [w for w in rig.warnings if "noise floor" in w]
    assert [w.startswith("channel lateral.4: the 250 Hz target 0.11") and f" um is {times:g} times" in w
            for w in noise] == ([True] if warned else []), noise
    assert floor == pytest.approx(rig.control_noise, rel=1e-12) and 1e6 * max(floor.values()) < 0.03
    ev = 'events=[{at = 0.3, set = {"stimulus.tones.2.target_um" = 0.001}}]'
    noise = [w for w in build(scene.load("line-bimorph-5-closed", [ev])).warnings if "noise floor" in w]
    assert len(noise) == 1 and noise[0].startswith("channel lateral.2: the 40 Hz target 0.001 um (events.0, at "
                                                   "0.3 s) is 0.23 times the self-sensing noise floor"), noise


def test_the_release_rule_is_on_where_the_window_is_long_with_three_noise_floors():
    """The bundled closed scene: the 2, 10, 40 and 120 Hz tones (windows of 500-16.7 ms, at least
    8 ms; the lifted beam the most responsive load there) watch for a finger that lets go, with 3
    times their estimate's noise floor as allowance; 250 Hz (a 4 ms window) does not. The drop it
    makes is the target over the lifted beam's tip per volt, which the model's beam gives here
    directly."""
    from rtctl.control._kernels import GMAX, JNOISE

    s = scene.load("line-bimorph-5-closed")
    rig = build(s)
    (_, st, ctl), = rig.controllers
    noise = np.array([rig.control_noise[int(b)] for bank in rig.stimulus.bank_index for b in bank])
    on = ctl.state[JNOISE] >= 0
    assert on.tolist() == [True, True, True, True, False]
    np.testing.assert_allclose(ctl.state[JNOISE, on], 3.0 * noise[on], rtol=1e-12)
    f = np.array([2.0, 10.0, 40.0, 120.0])
    lifted = (np.abs(st.observer.beam.response(f, None)["tip"])
              / np.abs(1.0 + 1j * f / s.group("lateral").amplifier.bandwidth))
    np.testing.assert_allclose(ctl.state[GMAX, on], lifted, rtol=1e-9)
    # 500 Hz, beside a loaded mode that a finger makes more responsive than the lifted beam, and
    # with a long window on a two-tone channel (500 Hz with 35 Hz): no release rule for it
    rig = build(scene.load("line-bimorph-5-closed", [
        "stimulus.tones=[{channel = 0, freq = 500, voltage = 1, target_um = 5}, "
        "{channel = 0, freq = 35, voltage = 1, target_um = 5}]", "events=[]"]))
    (_, st, ctl), = rig.controllers
    assert (ctl.state[JNOISE] >= 0).tolist() == [False, True]


def test_a_lift_off_drops_the_drive_within_blocks(tmp_path):
    """The finger pressing with 200 g lifts off a 40 Hz tone held at 6.3 um (and a 250 Hz one,
    whose 4 ms window has no release rule): the 40 Hz drive drops once, and its tip overshoots
    the target by under half of what the event alone does at the held drive (the simulated
    device's own tip per volt lifted over that under the finger, over +100 % here); the summary
    counts the release."""
    from rtctl.engine.report import against_target
    from rtctl.io.sim import build_group, device_models
    from rtctl.trace import TraceReader

    tones = ("stimulus.tones=[{channel = 0, freq = 40, voltage = 1, target_um = 6.3}, "
             "{channel = 1, freq = 250, voltage = 1, target_um = 0.5}]")
    common = ["actuator.lateral.grid=[1, 2]", tones, "finger.preload=1.96"]
    s = scene.load("line-bimorph-5-closed", [*common, 'events=[{at = 0.6, set = {"finger.contact" = false}}]',
                                             "timing.duration=0.9"])
    rows = run(s, out_dir=tmp_path, plot=False).summary["channels"]
    assert [r["releases"] for r in rows] == [1, 0]
    gains = []
    for contact in ("true", "false"):
        d = scene.load("line-bimorph-5-closed", [*common, "events=[]", f"finger.contact={contact}"])
        plant = build_group(device_models(d), d.actuator[0], 0, d.timing.fs, d.timing.block).plant
        gains.append(abs(plant.frequency_response(np.array([40.0]))[0, 0]))
    alone = 100.0 * (gains[1] / gains[0] - 1.0)
    r = TraceReader(tmp_path / "trace")
    got = against_target(r.signal("tip_um", 0), r.time(), [40.0], 0.6, 0.9, 6.3)
    assert alone > 100.0 and got["overshoot_pct"] < 0.5 * alone, (alone, got)


def test_a_ring_after_a_press_is_cancelled_and_counted(tmp_path):
    """A device off its model (d31, E, eps33T x0.9, half the damping, a soft finger), calibrated:
    the 200 g press puts a loaded mode near the 500 Hz tone, and after the loop's correction the
    tip still swings by about a quarter of the target, decaying over some 27 ms; with the drive
    held it leaves the 5 % band 56 ms after the press (docs/control.md, "A ring cancelled"). A
    pulse of drive cancels the ring: within 5 % by 50 ms, and the summary counts the pulse."""
    from bench_module import load

    from rtctl.engine.report import against_target
    from rtctl.trace import TraceReader

    sweep = load("control_sweep")
    press, end = 0.6, 0.8
    pressing = ((press, {"finger.preload": 1.96}),)  # 50 g to 200 g
    s = scene.load(sweep.SCENE, sweep.overrides(sweep.LOW, ((500, 0, 10.5),), True, pressing, end))
    summary = run(s, out_dir=tmp_path, plot=False).summary
    r = summary["channels"][0]
    assert r["pulses"] >= 1 and r["releases"] == 0
    n = int(round(summary["duration_s"] * summary["fs"]))
    t = np.arange(n) / summary["fs"]
    tip = TraceReader(tmp_path / "trace").signal("tip_um", 0)[:n]
    fig = against_target(tip, t, [500.0], press, end, 10.5)
    assert fig["settle_ms"] <= 50.0, fig
