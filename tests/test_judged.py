"""A played signal's channel is judged over the stretch where its signal plays (rtctl.engine.judged):
the stretches against the signal definitions worked by hand, and the summary of runs whose signal
ends before the run does against a tone held to the end."""

import pytest

from rtctl import scene
from rtctl.engine.judged import judged_span
from rtctl.engine.report import print_table
from rtctl.engine.run import run
from rtctl.stimulus import Stimulus

FS = 48000.0
OPEN = scene.resolve("line-bimorph-5").read_text().split("[stimulus]")[0] + '[stimulus]\nkind = "tones"\n'
CLOSED = scene.resolve("line-bimorph-5-closed").read_text()
CLOSED = CLOSED[: CLOSED.index("[[events]]")] + CLOSED[CLOSED.index("[[actuator]]"): CLOSED.index("[stimulus]")]


def span(stim, duration=1.0, channel=2):
    s = scene.loads(OPEN + stim, [f"timing.duration={duration}", "timing.block=32"])
    st = Stimulus(s, {"lateral": 0}, 5, FS, 32)
    return judged_span([v for v, _, _ in st.voices if v.channel == channel], int(round(duration * FS)))


def test_an_enveloped_burst_is_judged_over_its_sustain():
    sp = span('signals = [{name = "c", type = "sine", freq = 200.0, amp = 30.0},\n'
              '  {name = "e", type = "adsr", attack = 0.05, decay = 0.05, level = 0.5, sustain = 0.2, '
              'release = 0.05},\n'
              '  {name = "b", type = "product", of = ["c", "e"]}]\nplay = [{signal = "b", channel = 2, start = 0.1}]')
    assert sp["by"] == "steady"
    assert (sp["from"], sp["to"]) == (0.2 * FS, 0.4 * FS)  # start + attack + decay, + sustain
    assert sp["level"] == pytest.approx(15.0, abs=1e-12)  # amp x level
    assert (sp["on"], sp["off"]) == (0.1 * FS, 0.45 * FS)


def test_a_tone_for_the_whole_run_is_judged_from_its_fade_in_to_the_end():
    sp = span('signals = [{name = "c", type = "sine", freq = 200.0, amp = 30.0}]\n'
              'play = [{signal = "c", channel = 2, start = 0.1}]', duration=0.5)
    assert sp["by"] == "steady" and sp["level"] == 30.0
    assert (sp["from"], sp["to"]) == (0.1 * FS + 0.02 * FS, 0.5 * FS)  # after the 20 ms stimulus.ramp


def test_of_equal_sustains_the_last_and_of_unequal_the_longest_is_judged():
    note = ('{name = "c", type = "sine", freq = 200.0, amp = 30.0},\n'
            '  {name = "e", type = "asr", attack = 0.02, sustain = SUS, release = 0.02},\n'
            '  {name = "n", type = "product", of = ["c", "e"]}')
    sp = span(f'signals = [{note.replace("SUS", "0.1")},\n  {{name = "r", type = "repeat", of = ["n"], count = 3, '
              'gap = 0.05}]\nplay = [{signal = "r", channel = 2}]')
    # notes 0.14 s long, 0.05 s apart: the third sustains from 2 * 0.19 + 0.02 to + 0.1
    assert sp["by"] == "steady" and sp["from"] == pytest.approx(0.40 * FS) and sp["to"] == pytest.approx(0.50 * FS)
    long = note.replace("SUS", "0.2").replace('"c"', '"c2"').replace('"e"', '"e2"').replace('"n"', '"n2"')
    sp = span(f'signals = [{note.replace("SUS", "0.1")},\n  {long},\n  {{name = "s", type = "sequence", '
              'of = ["n2", "n"], gap = 0.0}]\nplay = [{signal = "s", channel = 2}]')
    assert sp["from"] == pytest.approx(0.02 * FS) and sp["to"] == pytest.approx(0.22 * FS)


def test_transients_are_judged_at_their_peak_and_a_chirp_by_its_stroke():
    sp = span('signals = [{name = "c", type = "sine", freq = 200.0, amp = 30.0},\n'
              '  {name = "e", type = "breakpoints", times = [0.0, 0.01, 0.04], levels = [0.0, 1.0, 0.0]},\n'
              '  {name = "b", type = "product", of = ["c", "e"]}]\nplay = [{signal = "b", channel = 2, start = 0.3}]')
    assert sp["by"] == "peak" and sp["level"] == pytest.approx(30.0)
    assert (sp["on"], sp["off"]) == (sp["from"], sp["to"]) == pytest.approx((0.3 * FS, 0.34 * FS))
    sp = span('signals = [{name = "c", type = "chirp", freq = 100.0, freq_end = 300.0, duration = 0.2, amp = 30.0},\n'
              '  {name = "e", type = "breakpoints", times = [0.0, 0.1, 0.2], levels = [0.0, 1.0, 0.0]},\n'
              '  {name = "b", type = "product", of = ["c", "e"]}]\nplay = [{signal = "b", channel = 2, start = 0.1}]')
    assert sp["by"] == "stroke" and (sp["on"], sp["off"]) == pytest.approx((0.1 * FS, 0.3 * FS))
    assert span('signals = [{name = "c", type = "sine", freq = 200.0, amp = 30.0}]\n'
                'play = [{signal = "c", channel = 2}]', channel=3) is None  # nothing there


def _summary(body, tmp_path, name, duration):
    s = scene.loads(body, [f"timing.duration={duration}"])
    return run(s, out_dir=str(tmp_path / name), plot=False, progress=False).summary


def test_an_open_loop_burst_that_ends_early_reads_as_the_same_tone_held_to_the_end(tmp_path, capsys):
    """line-bimorph-5, 30 V at 200 Hz on channel 2: a burst sustained 0.1 .. 0.6 s in a 1.2 s run is
    judged over its sustain's last 0.25 s; the amplitude is the one the tone held to the end of the
    same run reaches (the old end-of-run judgment read it as ~0 and not felt)."""
    burst = _summary(OPEN + 'signals = [{name = "c", type = "sine", freq = 200.0, amp = 30.0},\n'
                     '  {name = "e", type = "asr", attack = 0.05, sustain = 0.5, release = 0.05},\n'
                     '  {name = "b", type = "product", of = ["c", "e"]}]\n'
                     'play = [{signal = "b", channel = 2, start = 0.05}]', tmp_path, "burst", 1.2)
    tone = _summary(OPEN + 'tones = [{channel = 2, freq = 200.0, voltage = 30.0, receptor = "meissner"}]',
                    tmp_path, "tone", 1.2)
    b, t = burst["channels"][2], tone["channels"][2]
    assert b["judged"]["by"] == "steady"
    assert b["judged"]["from_s"] == pytest.approx(0.35) and b["judged"]["to_s"] == pytest.approx(0.6)
    assert b["judged"]["active_s"] == pytest.approx([0.05, 0.65])
    assert b["true_um"] == pytest.approx(t["true_um"], rel=1e-3)  # measured 4e-9
    assert b["felt"] == t["felt"] and b["threshold_um"] == pytest.approx(t["threshold_um"])
    assert b["settle_ms"] is not None and b["settle_ms"] < 600.0
    assert burst["channels"][0].get("judged") is None  # channels that play nothing: as before
    print_table(burst)
    print_table(tone)
    out = capsys.readouterr().out
    assert out.count("judged over") == 1 and ("lateral.2: judged over 0.350-0.600 s (the end of its longest steady "
                                              "stretch; the signal plays 0.050-0.650 s)") in out


def test_a_closed_loop_burst_is_judged_against_its_sustained_target(tmp_path):
    """line-bimorph-5-closed: a 12 um ASR sustain at 120 Hz (0.2 .. 0.7 s) in a 1.0 s run, released
    by 0.8 s: judged over 0.45 .. 0.7 s, within 2 % of its target and felt."""
    s = _summary(CLOSED + '[stimulus]\nkind = "tones"\nsignals = [\n'
                 '  {name = "c", type = "sine", freq = 120.0, amp = 12.0},\n'
                 '  {name = "env", type = "asr", attack = 0.1, sustain = 0.5, release = 0.1},\n'
                 '  {name = "b", type = "product", of = ["c", "env"]}]\n'
                 'play = [{signal = "b", channel = 3, start = 0.1}]\n[control]\nmode = "closed"\n',
                 tmp_path, "closed", 1.0)
    r = s["channels"][3]
    assert r["judged"]["by"] == "steady" and r["judged"]["from_s"] == pytest.approx(0.45)
    assert r["target_um"] == pytest.approx(12.0)
    assert abs(r["error_pct"]) < 2.0 and r["felt"] is True
    assert r["estimated_um"] == pytest.approx(r["true_um"], rel=0.05)



# a transient of 75 V at 146 Hz from 0.05 s, up in 7.5 ms and down by 0.08 s: its tip peaks near 15 um
TRANSIENT = OPEN + ('signals = [{name = "c", type = "sine", freq = 146.0, amp = 75.0},\n'
                    '  {name = "e", type = "breakpoints", times = [0.0, 0.0075, 0.03], levels = [0.0, 1.0, 0.0]},\n'
                    '  {name = "b", type = "product", of = ["c", "e"]}]\n'
                    'play = [{signal = "b", channel = 0, start = 0.05}]')


def test_a_run_cut_mid_transient_lasts_its_duration_and_is_judged_at_the_peak(tmp_path):
    # 0.07 s x 48 kHz / 32 is 105.00000000000001 blocks in floating point: a 106th block held the
    # transient's level at the cut for 32 samples, a "steady stretch" judged at 4 um, not felt
    summary = _summary(TRANSIENT, tmp_path, "cut", 0.07)
    assert summary["duration_s"] == pytest.approx(0.07, abs=1e-12)
    row = summary["channels"][0]
    assert row["judged"]["by"] == "peak"
    assert row["true_um"] > 10.0 and row["felt"] is True


def test_the_samples_past_a_duration_of_part_of_a_block_play_the_signal_on(tmp_path):
    # 0.0701 s is 105.15 blocks: the run plays 106, 27 samples past the duration; a signal that
    # stopped there held its level at the duration, judged as a steady stretch (4 um, not felt)
    summary = _summary(TRANSIENT, tmp_path, "part", 0.0701)
    assert summary["duration_s"] == pytest.approx(106 * 32 / FS, abs=1e-12)
    row = summary["channels"][0]
    assert row["judged"]["by"] == "peak" and row["judged"]["active_s"][1] == pytest.approx(106 * 32 / FS)
    assert row["true_um"] > 10.0 and row["felt"] is True


def test_a_saturated_transient_claims_no_amplitude_its_tip_never_reached(tmp_path):
    # heartbeat.ahap on the closed-loop scene, cut at 0.9 s: its swell saturates at its tone's
    # share of max_voltage. The row's estimate is the highest since the onset (16 um, a
    # transient's ring), which the table printed as "saturated at max_voltage: reaches 16.1 um"
    # where the tip never passed 9.5 um
    import numpy as np

    from rtctl.play import pattern_scene
    from rtctl.trace import TraceReader

    pattern = scene.resolve("line-bimorph-5").parent / "patterns" / "heartbeat.ahap"
    s, _ = pattern_scene(str(pattern), "line-bimorph-5-closed", (), 0.9)
    res = run(s, out_dir=str(tmp_path / "hb"), plot=False, progress=False)
    row = res.summary["channels"][0]
    assert row["judged"]["by"] == "peak" and row["saturated"]
    tip = np.abs(TraceReader(tmp_path / "hb" / "trace").signal("tip_um", 0)).max()
    reach = row.get("reachable_um")
    assert reach is None or reach <= 1.05 * tip, (reach, tip)
