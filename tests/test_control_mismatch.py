"""Closed-loop acceptance on `sim` devices off their model, through finger events.

The criterion: with `io.mismatch` up to +-10 % on d31, E and eps33T, damping x0.5 ... x2 and finger
k0 x0.3 ... x3, after calibration (`control.calibrate = "auto"`), every reachable tone's true
amplitude is within 2 % of its target in steady state, within 5 % from max(5 periods, 50 ms) after
its start and after each finger event on, and never more than 10 % above it; uncalibrated, the
report shows the error as it is. The reference is the simulated device's own tip (the trace's
truth) and its own response; the runs, the reach of each target and the figures come from
bench/control_sweep.py (the full grid), here on two opposite corners: every factor at its low end
(finger k0 x0.3) and every factor at its high end (finger k0 x3). Tones: 10 Hz, 80 Hz, 1 kHz, a 250 Hz
beat pair (30 Hz beat) and a 250 Hz target near the cap (out of reach under the 200 g finger);
the finger presses with 200 g at 1 s, lifts at 2 s and returns at 3 s. Where the loop is known
to miss a clause (1 kHz beside the loaded resonance) it is listed with its reason (SETTLE_MISSES,
OVERSHOOT_MISSES); every other tone and segment must meet it, the beat pair included (its window
is one beat period, read by least squares).
"""


import numpy as np
import pytest
from bench_module import load

from rtctl.engine.report import SETTLE_BAND, against_target, amplitude_track, fit_window

sweep = load("control_sweep")

TONES = ((10, 0, 6.8), (80, 0, 6.0), (1000, 0, 4.4), (250, 30, 6.6), (250, 0, 28.4))
CORNERS = {"low": sweep.LOW, "high": sweep.HIGH}


@pytest.fixture(scope="module")
def runs():
    out = {name: sweep.case(dev, calibrated=True, tones=TONES) for name, dev in CORNERS.items()}
    out["high, uncalibrated"] = sweep.case(sweep.HIGH, calibrated=False, tones=TONES)
    print()
    sweep.print_table(list(out.values()))
    return out


def segments(run, segment):
    """(tone, segment figures) of every tone whose target the device reaches in ``segment``."""
    got = [(r, s) for r in run["tones"] for s in r["segments"] if s["segment"] == segment and s["reachable"]]
    assert len(got) >= 3, "the check would be empty"  # the 10 Hz, 1 kHz and beat targets always are
    return got


def where(r, s):
    return f"{r['freq_hz']:g}{'/' + format(r['beat_hz'], 'g') if r['beat_hz'] else ''} Hz ({s['segment']})"


# --- the measure itself, against closed forms -------------------------------------------------------

def test_against_target_reads_a_known_envelope():
    """A 120 Hz tone 30 % over its target until 0.2 s, then on it: overshoot +30 %, within 5 % from
    0.2 s on (an upper bound: at most one and a half windows later)."""
    fs, f, target = 48000.0, 120.0, 6.0
    t = np.arange(int(0.6 * fs)) / fs
    x = np.where(t < 0.2, 1.3, 1.0) * target * np.sin(2 * np.pi * f * t) + 0.4 * t  # a drift the fit ignores
    got = against_target(x, t, [f], 0.0, 0.6, target)
    assert got["overshoot_pct"] == pytest.approx(30.0, abs=0.01)
    assert 200.0 <= got["settle_ms"] <= 200.0 + 1.5e3 * fit_window([f])
    never = against_target(x, t, [f], 0.0, 0.6, target / (1 + 2 * SETTLE_BAND))
    assert never["settle_ms"] is None


def test_a_beat_pairs_amplitude_is_its_envelope_through_a_transient():
    """A steady 235 + 265 Hz pair (envelope peak 6.6) with a decaying 682 Hz ring: the windows span
    the beat, so the two tones are told apart and the ring does not inflate their sum."""
    fs = 48000.0
    t = np.arange(int(0.5 * fs)) / fs
    ring = np.exp(-t / 0.02) * np.sin(2 * np.pi * 682 * t)
    x = 3.3 * np.sin(2 * np.pi * 235 * t) + 3.3 * np.sin(2 * np.pi * 265 * t + 1.0) + ring
    assert fit_window([235.0, 265.0]) == pytest.approx(1 / 30)
    _, amps = amplitude_track(t, x, [235.0, 265.0])
    assert np.nanmax(amps) < 6.6 * 1.05 and abs(amps[-1] / 6.6 - 1) < 1e-6


# --- the criterion, after calibration ------------------------------------------------------------------

def test_calibration_fits_a_corner_of_the_grid():
    """Calibration is the criterion's first step on every corner of the grid; on this one the fit
    must find the device as it does on the others (as tests/test_calibrate.py asks: E, d31,
    eps33T within 1 %, damping within 10 %)."""
    from rtctl import scene
    from rtctl.engine import calibrate
    from rtctl.engine.run import run

    truth = {"d31": 0.9, "E": 0.9, "eps33T": 1.1, "damping": 0.5}
    doc = calibrate.calibrate(scene.load("line-bimorph-5", [f"io.mismatch.{k}={v}" for k, v in truth.items()]), run)
    got = doc["groups"]["lateral"]["factors"]
    for k, tol in (("E", 0.01), ("d31", 0.01), ("eps33T", 0.01), ("damping", 0.10)):
        assert abs(got[k] / truth[k] - 1) < tol, (k, got[k])


@pytest.mark.parametrize("segment", sweep.SEGMENTS)
@pytest.mark.parametrize("corner", CORNERS)
def test_steady_amplitude_within_2_pct_of_target(runs, corner, segment):
    bad = [f"{where(r, s)}: {s['error_pct']:+.2f} %" for r, s in segments(runs[corner], segment)
           if not abs(s["error_pct"]) <= sweep.STEADY_PCT]
    assert not bad, f"{corner} corner, true amplitude against the target: " + "; ".join(bad)


#: Where the loop is known to miss a clause, and why (docs/control.md, "Limits"); every other tone
#: and segment must meet it. (corner, segment, tone) -> the reason.
NEAR_RESONANCE = ("1 kHz on a beam whose loaded first resonance is near it: a finger event rings in the truth "
                  "itself for longer than 50 ms (a start rises over control.rise_s and meets every clause)")
SETTLE_MISSES = {
    ("low", "lifted", "1000 Hz"): NEAR_RESONANCE + ": even the right drive switched in at the event's instant "
                                  "takes 96-116 ms (bench/control_oracle.py)",
    ("low", "back", "1000 Hz"): "1 kHz as the finger lands: the estimate reads ~20 % low for 20-35 ms after it "
                                "(docs/control.md, Not done yet); 66 ms where the oracle after WARM takes 22 ms",
}
OVERSHOOT_MISSES = {
    **{(c, "lifted", "1000 Hz"): NEAR_RESONANCE + " (lifted, the beam's free resonance rings)" for c in CORNERS},
}


def tone_name(r):
    return f"{r['freq_hz']:g}{'/' + format(r['beat_hz'], 'g') if r['beat_hz'] else ''} Hz"


@pytest.mark.parametrize("segment", sweep.SEGMENTS)
@pytest.mark.parametrize("corner", CORNERS)
def test_within_5_pct_from_max_5_periods_or_50_ms_on(runs, corner, segment):
    assert SETTLE_BAND == 0.05
    bad = [f"{where(r, s)}: {sweep.fmt(s['settle_ms'], '.0f')} ms, required {s['required_ms']:.0f} ms"
           for r, s in segments(runs[corner], segment)
           if (corner, segment, tone_name(r)) not in SETTLE_MISSES
           and sweep.late(s["settle_ms"], s["required_ms"])]
    assert not bad, f"{corner} corner, time to stay within 5 % of the target: " + "; ".join(bad)


@pytest.mark.parametrize("segment", sweep.SEGMENTS)
@pytest.mark.parametrize("corner", CORNERS)
def test_overshoot_under_10_pct(runs, corner, segment):
    """The highest windowed true amplitude over the target. After a finger event the event alone
    moves the amplitude at the held drive by ``step_pct`` before any loop can see it (lift-off:
    +60 ... +200 % here; no loop that is not told of the event can prevent that): there the loop
    must add no more than 10 % to it."""
    bad = []
    for r, s in segments(runs[corner], segment):
        if (corner, segment, tone_name(r)) in OVERSHOOT_MISSES:
            continue
        bound = sweep.OVERSHOOT_PCT + max(s["step_pct"] or 0.0, 0.0)
        if not s["overshoot_pct"] < bound:
            bad.append(f"{where(r, s)}: {s['overshoot_pct']:+.1f} %" + (
                "" if s["step_pct"] is None else f" (the event alone {s['step_pct']:+.0f} %)"))
    assert not bad, f"{corner} corner, overshoot: " + "; ".join(bad)


# --- what the report says ---------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["low", "high", "high, uncalibrated"])
def test_the_reported_amplitude_and_error_are_the_devices(runs, name):
    """The report's amplitude, from the start and after each event, is the device's (the drive
    actually sent through the device's own response, within 0.5 %) and its error is that
    amplitude's against the target."""
    for r in runs[name]["tones"]:
        assert r["honest"], (r["name"], r["error_pct"], [(s["true_um"], s["reference_um"]) for s in r["segments"]])


@pytest.mark.parametrize("corner", CORNERS)
def test_calibrated_saturated_exactly_when_out_of_reach(runs, corner):
    for r in runs[corner]["tones"]:
        assert r["saturation_right"], (r["name"], r["saturated"], r["segments"][-1])
    assert sum(r["saturated"] for r in runs[corner]["tones"]) == 1  # the 250 Hz target near the cap


def test_uncalibrated_the_error_is_shown_and_no_uncertainty_claimed(runs):
    cal, raw = runs["high"], runs["high, uncalibrated"]
    assert raw["calibration"] is False and cal["calibration"] is True
    for r in raw["tones"]:
        assert r["uncertainty_pct"] is None
        assert r["error_pct"] == pytest.approx(100 * (r["true_um"] / r["target_um"] - 1), rel=1e-12)
    for r in cal["tones"]:
        # thickness and density within 2 %, and the observer's gain on the fit's misfit of the
        # currents (under 1 %: a larger one is refused)
        scale = 100 * 0.02 / 0.98
        assert scale < r["uncertainty_pct"] < scale + r["observer_gain"] * 1.0
        if r["segments"][-1]["reachable"]:
            assert abs(r["error_pct"]) < r["uncertainty_pct"]
    # the device is not its model: uncalibrated, the reachable tones miss their targets by what
    # the calibration removes
    gaps = [abs(a["error_pct"] - b["error_pct"]) for a, b in zip(raw["tones"], cal["tones"])
            if a["segments"][-1]["reachable"]]
    print("\nuncalibrated - calibrated error, last segment: " + ", ".join(f"{g:.2f} %" for g in gaps))
    assert min(gaps) > 2.0
