"""The per-channel table ``rtctl run`` prints: a channel of several tones lists every tone's
frequency (a beat pair is one tone, at its carrier), as the plot's panel titles do, and a
saturated tone that has only a share of its channel's max_voltage says so, with the share in
volts."""

from __future__ import annotations

import contextlib
import io

import pytest

from rtctl import scene
from rtctl.engine.report import print_table
from rtctl.engine.run import run

# line-bimorph-5-closed (max_voltage 150 V): channel 0 a 40 Hz tone whose 60 um is out of reach
# beside a 250 Hz one (two sines: each tone's cap is 75 V); channel 1 three tones; channel 2 a
# beat pair alone (250 Hz carrier, 240 and 260 Hz sines: the whole 150 V) out of reach at 200 um
TONES = ('stimulus.tones=['
         '{channel = 0, freq = 40.0, voltage = 40.0, receptor = "meissner", target_um = 60.0}, '
         '{channel = 0, freq = 250.0, voltage = 1.0, receptor = "pacinian"}, '
         '{channel = 1, freq = 120.0, voltage = 30.0, receptor = "meissner"}, '
         '{channel = 1, freq = 180.5, voltage = 1.0, receptor = "pacinian"}, '
         '{channel = 1, freq = 250.25, voltage = 1.0, receptor = "pacinian"}, '
         '{channel = 2, freq = 250.0, beat = 20.0, voltage = 30.0, receptor = "pacinian", target_um = 200.0}]')


@pytest.fixture(scope="module")
def summary(tmp_path_factory):
    sets = ["timing.duration=0.3", "events=[]", TONES]
    return run(scene.load("line-bimorph-5-closed", sets), out_dir=tmp_path_factory.mktemp("t"), plot=False).summary


def _table(summary) -> list[str]:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        print_table(summary)
    return buf.getvalue().splitlines()


@pytest.fixture(scope="module")
def lines(summary):
    return _table(summary)


def _line(lines, name):
    return next(x for x in lines if x.startswith(name + " "))


def test_every_tone_of_a_channel_is_in_the_frequency_column(summary, lines):
    """The column printed only the first tone's frequency (40.0 for the 40 + 250 Hz channel)."""
    rows = summary["channels"]
    assert rows[0]["tones_hz"] == [40.0, 250.0] and rows[1]["tones_hz"] == [120.0, 180.5, 250.25]
    assert "tones_hz" not in rows[2]  # a beat pair is one tone, though its freqs_hz has two sines
    assert rows[2]["freqs_hz"] == [240.0, 260.0]
    head = lines[1]
    end = head.index("freq Hz") + len("freq Hz")  # the column's right edge
    want = {"lateral.0": "40+250", "lateral.1": "120+180.5+250.25", "lateral.2": "250.0", "lateral.3": "-"}
    for name, text in want.items():
        line = _line(lines, name)
        assert line[:end].endswith(" " + text), (line, head)
        assert line[end:].split()[0] == f"{summary['channels'][int(name[-1])]['v_peak']:.1f}", line
    assert len(lines[2]) == len(head) and set(lines[2]) == {"-"}


def test_a_saturated_tone_with_a_share_of_max_voltage_says_so(summary, lines):
    """Channel 0's 40 Hz tone is capped at 75 V (150 V over the channel's two sines) and channel
    1's tones at 50 V (three), which the table called "saturated at max_voltage"; the beat pair
    alone on channel 2 has all 150 V."""
    rows = summary["channels"]
    assert rows[0]["saturated"] and rows[0]["share_v"] == [75.0]
    assert rows[0]["v_peak"] < 150.0
    reach = f"{rows[0]['reachable_um']:.3g}"
    assert _line(lines, "lateral.0").endswith(f"(saturated at its share of max_voltage, 75 V: reaches {reach} um)")
    assert rows[2]["saturated"] and "share_v" not in rows[2]
    assert rows[2]["v_peak"] == pytest.approx(150.0, rel=1e-3)
    reach = f"{rows[2]['reachable_um']:.3g}"
    assert _line(lines, "lateral.2").endswith(f"(saturated at max_voltage: reaches {reach} um)")
    # the 120 Hz tone needs about 56 V (alone on its channel above), its share beside two more is 50
    assert rows[1]["saturated"] and rows[1]["share_v"] == [50.0]
    assert "(saturated at its share of max_voltage, 50 V: reaches" in _line(lines, "lateral.1")


def test_a_played_signals_voices_are_listed_once_per_frequency(tmp_path):
    """heartbeat.ahap on the closed-loop scene plays three voices on channel 0 (212, 146 and 146
    Hz): the column said 212.0, and its saturated voice is capped at 50 V, a third of 150 V."""
    from rtctl.play import pattern_scene

    pattern = scene.resolve("line-bimorph-5").parent / "patterns" / "heartbeat.ahap"
    s, _ = pattern_scene(str(pattern), "line-bimorph-5-closed", (), 0.9)
    summary = run(s, out_dir=str(tmp_path / "hb"), plot=False, progress=False).summary
    row = summary["channels"][0]
    assert row["tones_hz"] == [212.0, 146.0, 146.0] and row["saturated"] and row["share_v"] == [50.0]
    lines = _table(summary)
    head = lines[1]
    end = head.index("freq Hz") + len("freq Hz")
    line = _line(lines, "lateral.0")
    assert line[:end].endswith(" 212+146") and "(saturated at its share of max_voltage, 50 V" in line


def test_every_tone_of_a_channel_is_in_its_plot_panels_title(tmp_path, monkeypatch):
    """The plot's panel titles, like the table, showed only a channel's first tone."""
    import matplotlib.figure

    titles = []

    def keep(fig, *a, **k):
        titles.extend(ax.get_title(loc="left") for ax in fig.axes)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)
    run(scene.load("line-bimorph-5-closed", ["timing.duration=0.1", "events=[]", TONES]), out_dir=tmp_path)
    want = {"lateral.0": "40+250 Hz", "lateral.1": "120+180.5+250.25 Hz", "lateral.2": "250 Hz"}
    for name, text in want.items():
        got = [x for x in titles if x.startswith(name + " ")]
        assert len(got) == 1 and f" {text} " in got[0], (name, titles)
