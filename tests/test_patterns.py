"""Haptic pattern files (.ahap, .haptic): what is read, what is warned, clamped and refused, and
`rtctl play` on a closed-loop (targets in um) and an open-loop (volts) scene."""

import json

import numpy as np
import pytest
from test_cli import run_cli

from rtctl import patterns
from rtctl.errors import PatternError, SceneError
from rtctl.play import pattern_scene
from rtctl.stimulus import Stimulus


def test_heartbeat_ahap_reads_as_two_transients_and_a_curved_continuous_event():
    p = patterns.load("heartbeat.ahap")
    assert p.warnings == []
    assert p.transients == [(0.05, 1.0, 0.3), (0.30, 0.7, 0.3)]
    (t0, times, levels, _, sharps), = p.continuous
    assert t0 == 0.6
    np.testing.assert_allclose(times, [0.0, 0.2, 0.6], atol=1e-12)
    np.testing.assert_allclose(levels, [0.8 * 0.3, 0.8 * 1.0, 0.8 * 0.2])  # intensity x its control curve
    np.testing.assert_allclose(sharps, 0.6)


def test_swell_haptic_reads_its_envelopes_and_an_emphasis_transient():
    p = patterns.load("swell.haptic")
    assert p.warnings == []
    assert p.transients == [(0.25, 1.0, 0.8)]
    (t0, times, levels, ftimes, fv), = p.continuous
    np.testing.assert_allclose(times, [0.0, 0.25, 0.6, 0.8])
    np.testing.assert_allclose(levels, [0.0, 0.9, 0.4, 0.0])
    np.testing.assert_allclose(np.interp([0.0, 0.4, 0.8], ftimes, fv), [0.2, 0.45, 0.7])


def _amp_at(st, channel, t):
    return sum(float(np.interp(t * 48000, v.x, v.amp)) for v, _, _ in st.voices if v.channel == channel)


def test_open_loop_plays_intensity_times_half_max_voltage_at_the_sharpness_frequency():
    """pvdf-6x8 (max_voltage 500 V): full = 250 V; sharpness 0.6 -> 80 + 0.6 (300 - 80) = 212 Hz."""
    s, warnings = pattern_scene("heartbeat.ahap", "pvdf-6x8", ["stimulus.pattern.channel=19"])
    assert warnings == [] and s.timing.duration == 1.3  # the pattern's end + a transient, a ramp, 50 ms
    st = Stimulus(s, {"cells": 0}, 48, 48000.0, 32)
    assert _amp_at(st, 19, 0.8) == pytest.approx(0.8 * 1.0 * 250.0, abs=1e-9)
    assert _amp_at(st, 19, 0.7) == pytest.approx(0.8 * (0.3 + 0.7 * 0.5) * 250.0, abs=1e-9)
    assert _amp_at(st, 19, 0.05 + 0.03 / 4) == pytest.approx(1.0 * 250.0, abs=1e-9)  # the first beat's peak
    assert {round(v.freq[0], 9) for v, _, _ in st.voices} == {80 + 0.3 * 220, 80 + 0.6 * 220}


def test_closed_loop_plays_tip_targets_at_fixed_frequencies():
    """line-bimorph-5-closed: full = 0 -> the receptor threshold + margin_db (6 dB) per tone; the
    .haptic frequency envelope is held at its first value, and a warning says so."""
    s, warnings = pattern_scene("swell.haptic", "line-bimorph-5-closed", ["stimulus.pattern.full=10"])
    assert len(warnings) == 1 and "closed loop holds it at 124 Hz" in warnings[0]
    st = Stimulus(s, {"lateral": 0}, 5, 48000.0, 32)
    assert all(closed for _, closed, _ in st.voices)
    assert all(np.ptp(v.freq) == 0.0 for v, _, _ in st.voices)
    # targets in m: amplitude 0.9 of full = 10 um at 0.25 s, plus the emphasis bump's peak there
    cont = [v for v, _, _ in st.voices if v.freq[0] == pytest.approx(124.0)]
    assert float(np.interp(0.25 * 48000, cont[0].x, cont[0].amp)) == pytest.approx(9e-6, rel=1e-12)


def _write(tmp_path, name, obj):
    p = tmp_path / name
    p.write_text(obj if isinstance(obj, str) else json.dumps(obj))
    return str(p)


def test_unknown_keys_are_warned_and_out_of_range_values_clamped_and_reported(tmp_path):
    f = _write(tmp_path, "odd.ahap", {"Version": 1, "Colour": "red", "Pattern": [
        {"Event": {"Time": 0.1, "EventType": "HapticTransient", "Wobble": 3,
                   "EventParameters": [{"ParameterID": "HapticIntensity", "ParameterValue": 1.5},
                                       {"ParameterID": "AttackTime", "ParameterValue": 0.1}]}},
        {"Event": {"Time": 0.2, "EventType": "AudioCustom"}}]})
    p = patterns.load(f)
    assert p.transients == [(0.1, 1.0, 0.5)]  # clamped to 1; Core Haptics' default sharpness 0.5
    text = "\n".join(p.warnings)
    for words in (".Colour: not used", "Pattern[0].Event.Wobble: not used",
                  "EventParameters[0].ParameterValue (HapticIntensity) = 1.5 is outside [0, 1]: clamped to 1",
                  "'AttackTime': not used",
                  "'AudioCustom': not a haptic event"):
        assert words in text


@pytest.mark.parametrize("name, content, words", [
    ("a.ahap", "{not json", "not valid JSON"),
    ("a.ahap", {"Version": 1}, "missing 'Pattern'"),
    ("a.ahap", {"Pattern": [{"Event": {"Time": "soon", "EventType": "HapticTransient"}}]}, "must be a finite number"),
    ("a.ahap", {"Pattern": []}, "no haptic events"),
    ("a.haptic", {"version": {"major": 2}, "signals": {}}, "only version 1"),
    ("a.haptic", {"version": {"major": 1}, "signals": {"continuous": {"envelopes": {"amplitude": [
        {"time": 0.5, "amplitude": 1}, {"time": 0.1, "amplitude": 0}]}}}}, "in time order"),
    ("a.wav", "RIFF", "not a pattern file"),
])
def test_malformed_patterns_are_refused_in_one_line_exit_2(capsys, tmp_path, name, content, words):
    f = _write(tmp_path, name, content)
    with pytest.raises(PatternError):
        patterns.load(f)
    code, out, err = run_cli(capsys, "play", f, "--scene", "pvdf-6x8")
    assert code == 2 and words in err and err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.parametrize("pattern, scene_name, more", [
    ("heartbeat.ahap", "line-bimorph-5-closed", ()), ("swell.haptic", "line-bimorph-5-closed", ()),
    ("heartbeat.ahap", "pvdf-6x8", ()), ("swell.haptic", "pvdf-6x8", ("--duration", "1.0"))])
def test_play_runs_with_the_usual_summary_and_trace(capsys, tmp_path, pattern, scene_name, more):
    code, out, err = run_cli(capsys, "play", pattern, "--scene", scene_name, "--out", str(tmp_path), "--json",
                             "--no-plot", *more)
    assert code == 0, err
    summary = json.loads(out)
    assert summary["scene"] == scene_name and (tmp_path / "trace").is_dir()


def test_a_pattern_plays_through_a_virtual_source():
    """stimulus.pattern.spatial: the heartbeat on array-bimorph-5x5's sweep reaches only the middle
    row, and at 0.6 s (source between columns 2 and 3) channels 12 and 13 share its level."""
    s, _ = pattern_scene("heartbeat.ahap", "array-bimorph-5x5", ["stimulus.pattern.spatial=sweep",
                                                                  "stimulus.pattern.full=100"])
    st = Stimulus(s, {"array": 0}, 25, 48000.0, 32)
    assert {v.channel for v, _, _ in st.voices} == {10, 11, 12, 13, 14}
    # at 0.625 s (a gain update, past the 20 ms fade-in) the source is at column 2.625 and the
    # intensity curve at 0.3 + 0.7 * 0.025 / 0.2 of the event's 0.8
    t = 0.625
    level = 0.8 * (0.3 + 0.7 * 0.025 / 0.2) * 100.0
    assert _amp_at(st, 12, t) == pytest.approx(level * 0.375, abs=1e-9)
    assert _amp_at(st, 13, t) == pytest.approx(level * 0.625, abs=1e-9)


def test_play_drops_scene_events_after_a_shorter_run_with_one_warning(capsys, tmp_path):
    """line-bimorph-5-closed has events at 0.8, 1.4 and 1.8 s: `play --duration 1.3` keeps the
    first and drops the other two in one line; `run --duration 1.3` still refuses them."""
    s, warnings = pattern_scene("heartbeat.ahap", "line-bimorph-5-closed", duration=1.3)
    assert s.timing.duration == 1.3 and [ev["at"] for ev in s.get("events")] == [0.8]
    assert len(warnings) == 1 and "events.1..2 (at 1.4, 1.8 s)" in warnings[0] and "dropped" in warnings[0]
    s, warnings = pattern_scene("heartbeat.ahap", "line-bimorph-5-closed", duration=1.5)
    assert [ev["at"] for ev in s.get("events")] == [0.8, 1.4] and "events.2 (at 1.8 s)" in warnings[0]
    s, warnings = pattern_scene("heartbeat.ahap", "line-bimorph-5-closed")  # the scene's 2.4 s: all kept
    assert warnings == [] and len(s.get("events")) == 3
    code, out, err = run_cli(capsys, "play", "heartbeat.ahap", "--scene", "line-bimorph-5-closed", "--duration",
                             "1.3", "--out", str(tmp_path), "--json", "--no-plot")
    assert code == 0, err
    assert err.count("\n") == 1 and "events.1..2" in err and json.loads(out)["duration_s"] == pytest.approx(1.3)
    code, _, err = run_cli(capsys, "run", "line-bimorph-5-closed", "--duration", "1.3", "--out", str(tmp_path / "r"))
    assert code == 2 and "events.1.at = 1.4: after the end of the run (1.3 s)" in err


def _ahap_continuous(*curves, dur=2.0, intensity=1.0):
    return {"Pattern": [
        {"Event": {"Time": 0.0, "EventType": "HapticContinuous", "EventDuration": dur,
                   "EventParameters": [{"ParameterID": "HapticIntensity", "ParameterValue": intensity}]}},
        *[{"ParameterCurve": {"ParameterID": "HapticIntensityControl", "Time": t,
                              "ParameterCurveControlPoints": [{"Time": a, "ParameterValue": v} for a, v in pts]}}
          for t, pts in curves]]}


def test_a_later_curve_takes_over_from_its_start(tmp_path):
    """Curve A (1 from 0 to 1 s) and B at 0.5 s (0 to 0.7 s): from 0.5 s on B rules, held at its
    last value; a step at 0.5 s as two points at one time, every time in order."""
    f = _write(tmp_path, "over.ahap", _ahap_continuous((0.0, [(0.0, 1.0), (1.0, 1.0)]),
                                                       (0.5, [(0.0, 0.0), (0.2, 0.0)])))
    p = patterns.load(f)
    (t0, times, levels, _, _), = p.continuous
    np.testing.assert_allclose(times, [0.0, 0.5, 0.5, 0.7, 2.0])
    np.testing.assert_allclose(levels, [1.0, 1.0, 0.0, 0.0, 0.0])
    # cut mid-ramp: A (0 -> 1 over 1 s) gives way at 0.4 s to B at 0.5, which ramps 0.5 -> 0.9
    f = _write(tmp_path, "cut.ahap", _ahap_continuous((0.0, [(0.0, 0.0), (1.0, 1.0)]),
                                                      (0.4, [(0.0, 0.5), (0.5, 0.9)]), dur=1.0))
    (t0, times, levels, _, _), = patterns.load(f).continuous
    np.testing.assert_allclose(times, [0.0, 0.4, 0.4, 0.9, 1.0])
    np.testing.assert_allclose(levels, [0.0, 0.4, 0.5, 0.9, 0.9])
    # a transient reads the curve that rules at its time
    f = _write(tmp_path, "tr.ahap", {"Pattern": [
        *_ahap_continuous((0.0, [(0.0, 1.0), (1.0, 1.0)]), (0.5, [(0.0, 0.25), (0.2, 0.25)]))["Pattern"][1:],
        {"Event": {"Time": 0.6, "EventType": "HapticTransient"}}]})
    assert patterns.load(f).transients == [(0.6, 0.25, 0.5)]


def test_events_that_play_nothing_are_warned_and_a_pattern_of_only_them_refused(tmp_path):
    f = _write(tmp_path, "zero.ahap", {"Pattern": [
        {"Event": {"Time": 0.1, "EventType": "HapticTransient",
                   "EventParameters": [{"ParameterID": "HapticIntensity", "ParameterValue": 0}]}},
        {"Event": {"Time": 0.2, "EventType": "HapticTransient"}}]})
    p = patterns.load(f)
    assert p.transients == [(0.2, 1.0, 0.5)]
    assert p.warnings == [f"{f}: Pattern[0].Event: intensity 0 at 0.1 s (HapticIntensity 0 x "
                          "HapticIntensityControl 1): plays nothing (ignored)"]
    f = _write(tmp_path, "zero.ahap", _ahap_continuous((0.0, [(0.0, 0.0)])))
    with pytest.raises(PatternError, match=r"nothing to play: Pattern\[0\].Event: intensity 0 throughout"):
        patterns.load(f)
    f = _write(tmp_path, "same.haptic", {"version": {"major": 1}, "signals": {"continuous": {"envelopes": {
        "amplitude": [{"time": 0.5, "amplitude": 1}, {"time": 0.5, "amplitude": 1}]}}}})
    with pytest.raises(PatternError, match="nothing to play: .*every breakpoint at 0.5 s: the envelope lasts no time"):
        patterns.load(f)
    f = _write(tmp_path, "silent.haptic", {"version": {"major": 1}, "signals": {"continuous": {"envelopes": {
        "amplitude": [{"time": 0, "amplitude": 0}, {"time": 1, "amplitude": 0}]}}}})
    with pytest.raises(PatternError, match="nothing to play: .*every amplitude is 0"):
        patterns.load(f)


def test_pattern_events_after_a_shorter_run_are_dropped_with_a_warning(capsys, tmp_path):
    """heartbeat.ahap's continuous event starts at 0.6 s: `--duration 0.4` leaves it out and says
    so; `--duration 0.9` plays it cut off and says that."""
    s, warnings = pattern_scene("heartbeat.ahap", "line-bimorph-5", duration=0.4)
    assert warnings == ["heartbeat.ahap: Pattern[2].Event (at 0.6 s) comes at or after the end of the run "
                        "(0.4 s): dropped"]
    assert sorted(p["start"] for p in s.to_dict()["stimulus"]["play"]) == [0.05, 0.30]
    s, warnings = pattern_scene("heartbeat.ahap", "line-bimorph-5", duration=0.9)
    assert warnings == ["heartbeat.ahap: Pattern[2].Event (to 1.2 s) goes on after the end of the run (0.9 s): "
                        "cut off"]
    f = _write(tmp_path, "late.ahap", {"Pattern": [{"Event": {"Time": 0.5, "EventType": "HapticTransient"}}]})
    code, _, err = run_cli(capsys, "play", f, "--scene", "line-bimorph-5", "--duration", "0.4")
    assert code == 2 and "every event starts at or after the end of the run (0.4 s)" in err and err.count("\n") == 1


def test_a_pattern_too_long_to_play_names_the_pattern_not_the_scene(capsys, tmp_path):
    f = _write(tmp_path, "long.ahap", {"Pattern": [{"Event": {"Time": 0.1, "EventType": "HapticTransient"}},
                                                   {"Event": {"Time": 1e6, "EventType": "HapticTransient"}}]})
    with pytest.raises(PatternError, match=r"long.ahap: Pattern\[1\].Event ends at 1e\+06 s: .* longer than the "
                                           "86400 s a run may"):
        pattern_scene(f, "line-bimorph-5")
    code, _, err = run_cli(capsys, "play", f, "--scene", "line-bimorph-5")
    assert code == 2 and "long.ahap: Pattern[1].Event" in err and ".toml" not in err


@pytest.mark.parametrize("band", ["[0, 0]", "[80, 24000]"])
def test_a_band_outside_the_playable_frequencies_names_stimulus_pattern_band(capsys, band):
    with pytest.raises(SceneError, match=r"stimulus\.pattern\.band = .*: both ends must be in \(0, fs / 2 = 24000\)"):
        pattern_scene("heartbeat.ahap", "line-bimorph-5", [f"stimulus.pattern.band={band}"])
    code, _, err = run_cli(capsys, "play", "heartbeat.ahap", "--scene", "line-bimorph-5",
                           f"--set=stimulus.pattern.band={band}")
    assert code == 2 and ("stimulus.pattern.band" in err) and "signals" not in err, err


def test_an_event_with_more_breakpoints_than_a_signal_holds_is_refused_naming_it(tmp_path):
    pts = [(i * 1e-4, float(i % 2)) for i in range(12000)]
    f = _write(tmp_path, "many.ahap", _ahap_continuous((0.0, pts)))
    with pytest.raises(PatternError, match=r"many.ahap: Pattern\[0\].Event \(at 0 s\) has 12001 breakpoints"):
        pattern_scene(f, "line-bimorph-5")
