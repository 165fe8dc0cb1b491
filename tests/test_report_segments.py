"""The run report's segments (the start, then each event): the finger's contact in force, which
segments are long enough to judge, and observer estimates only from windows inside the last one."""

from __future__ import annotations

import pytest

from rtctl import scene
from rtctl.engine.run import run


def _rows(tmp_path, name, sets):
    return run(scene.load(name, sets), out_dir=tmp_path, plot=False).summary["channels"]


@pytest.mark.parametrize("first, then", [(True, False), (False, True)])
def test_felt_and_contact_are_the_run_ends_after_its_events(tmp_path, first, then):
    """A finger that lifts off at 0.3 s of a 0.6 s run feels nothing at the end, and one that
    lands then does (the report took the scene's starting contact for the whole run: every row
    said "yes" with the finger gone, and "NO (no contact)" with it on)."""
    ev = f'events=[{{at = 0.3, set = {{"finger.contact" = {str(then).lower()}}}}}]'
    rows = _rows(tmp_path, "line-bimorph-5", [f"finger.contact={str(first).lower()}", "timing.duration=0.6", ev])
    for r in rows:
        assert r["contact"] is then
        assert [r["start"]["contact"], r["events"][0]["contact"]] == [first, then]
        if then:  # judged by its amplitude against the threshold, after the landing
            assert r["felt"] is (r["true_um"] >= r["threshold_um"]), r
        else:
            assert r["felt"] is False, r
    if then:
        assert any(r["felt"] for r in rows)  # (the 40-250 Hz tips reach their thresholds)


def test_a_segment_too_short_to_judge_does_not_hide_the_others_settle_times(tmp_path):
    """Two events at one instant leave a segment of no length between them, and an event just
    before the end one shorter than a fit window: neither is judged, and each row's settle time is
    the worst of the segments that are (every row said "never settled" before)."""
    ev = ('events=[{at = 0.3, set = {"finger.preload" = 0.98}}, {at = 0.3, set = {"finger.preload" = 1.96}}, '
          '{at = 0.598, set = {"finger.preload" = 0.49}}]')
    rows = _rows(tmp_path, "line-bimorph-5", ["timing.duration=0.6", ev])
    for r in rows[2:]:  # 40, 120 and 250 Hz: fit windows of 25, 8.3 and 4 ms
        segs = [r["start"]] + r["events"]
        assert [s["judged"] for s in segs] == [True, False, True, False], segs
        times = [s["settle_ms"] for s in segs if s["judged"]]
        assert None not in times and r["settle_ms"] == max(times), r
    two = rows[0]  # 2 Hz: no segment holds its 0.5 s fit window, so nothing is judged
    assert not any(s["judged"] for s in [two["start"]] + two["events"]) and two["settle_ms"] is None


def test_the_estimate_is_read_only_from_windows_after_the_segment_starts(tmp_path):
    """The 2 Hz tone's window is 0.5 s: in a 0.6 s run only its last 0.1 s of estimates hold
    nothing before the tone started (the report took the median of the whole analysis window,
    57.3 um against a true 36.8, and called that what 150 V reaches). In 0.5 s no window fits,
    and the report says so instead of giving a figure."""
    rows = _rows(tmp_path / "a", "line-bimorph-5-closed", ["timing.duration=0.6", "events=[]"])
    r = rows[0]
    assert r["saturated"] and r["estimate_window"] is True
    assert r["estimated_um"] == pytest.approx(r["true_um"], rel=0.01), r
    assert r["reachable_um"] == r["estimated_um"]
    r = _rows(tmp_path / "b", "line-bimorph-5-closed", ["timing.duration=0.5", "events=[]"])[0]
    assert r["saturated"] and r["estimate_window"] is False and r["estimated_um"] is None
    assert r["reachable_um"] is None and r["true_um"] > 30.0
