"""`rtctl check` compiles the stimulus as `rtctl run` does: every bad signal definition is refused by
both in the same one line, exit 2 (check builds no plant and compiles no kernel)."""

import pytest
from test_cli import run_cli

from rtctl import scene

OPEN = scene.resolve("line-bimorph-5").read_text().split("[stimulus]")[0]
CLOSED = scene.resolve("line-bimorph-5-closed").read_text()
CLOSED = CLOSED[: CLOSED.index("[[events]]")] + CLOSED[CLOSED.index("[[actuator]]"): CLOSED.index("[stimulus]")]
PVDF = scene.resolve("pvdf-6x8").read_text()
PVDF = PVDF[: PVDF.index("[stimulus]")]
SINE = '{name = "a", type = "sine", freq = 100.0, amp = 10.0}'

BAD = [  # (base, [stimulus] body, words the one line holds)
    (OPEN, f'signals = [{SINE}]\nplay = [{{signal = "b"}}]', "no such stimulus.signals item"),
    (OPEN, 'signals = [{name = "a", type = "sum", of = ["b"]}, {name = "b", type = "sum", of = ["a"]}]\n'
           'play = [{signal = "a"}]', "refers back to itself"),
    (OPEN, 'signals = [{name = "a", type = "chirp", freq = 100.0, freq_end = 200.0}]\nplay = [{signal = "a"}]',
     "needs a duration"),
    (OPEN, 'signals = [{name = "a", type = "chirp", freq = 100.0, freq_end = 30000.0, duration = 0.1}]\n'
           'play = [{signal = "a"}]', "freq_end = 30000"),
    (OPEN, 'signals = [{name = "a", type = "chirp", freq = 100.0, freq_end = 300.0, duration = 0.05}, '
           '{name = "b", type = "sine", freq = 200.0}, {name = "p", type = "product", of = ["a", "b"]}]\n'
           'play = [{signal = "p"}]', "crosses 0 Hz"),
    (OPEN, 'signals = [{name = "a", type = "sine", freq = 30000.0}]\nplay = [{signal = "a"}]', "fs / 2"),
    (OPEN, 'signals = [{name = "a", type = "sine", freq = 15000.0}, {name = "b", type = "sine", freq = 10000.0}, '
           '{name = "p", type = "product", of = ["a", "b"]}]\nplay = [{signal = "p"}]', "a tone reaches 25000 Hz"),
    (OPEN, f'signals = [{SINE}, {{name = "s", type = "sequence", of = ["a", "a"]}}]\nplay = [{{signal = "s"}}]',
     "lasts the whole run"),
    (OPEN, f'signals = [{SINE}, {{name = "r", type = "repeat", of = ["a", "a"], count = 2}}]\n'
           'play = [{signal = "r"}]', "a repeat names one signal"),
    (OPEN, 'signals = [{name = "e", type = "breakpoints", times = [0.0, 0.1], levels = [0.0, 1.0, 0.0]}]\n'
           'play = [{signal = "e"}]', "as many levels as times"),
    (OPEN, 'signals = [{name = "n", type = "noise", band = [300.0, 100.0], amp = 1.0}]\nplay = [{signal = "n"}]',
     "0 < low < high"),
    (OPEN, f'signals = [{SINE}, {{name = "a", type = "dc"}}]\nplay = [{{signal = "a"}}]', "unique"),
    (OPEN, f'signals = [{SINE}]\nplay = [{{signal = "a", channel = 5}}]', "channels 0..4"),
    (OPEN, f'signals = [{SINE}]\nplay = [{{signal = "a", unit = "um"}}]', "open loop plays volts"),
    (OPEN, 'tones = [{channel = 0, freq = 50.0, voltage = 10.0, shape = "square", beat = 2.0}]',
     "a beat pair needs shape = 'sine'"),
    (OPEN, 'tones = [{channel = 0, freq = 50.0, voltage = 10.0, shape = "square"}, '
           '{channel = 0, freq = 60.0, voltage = 10.0, shape = "pulse"}]', "already plays a square/pulse tone"),
    (CLOSED, 'signals = [{name = "a", type = "chirp", freq = 100.0, freq_end = 200.0, duration = 0.1, amp = 5.0}]'
             '\nplay = [{signal = "a"}]\n[control]\nmode = "closed"', "closed loop needs tones of fixed frequency"),
    (CLOSED, 'signals = [{name = "d", type = "dc", amp = 5.0}]\nplay = [{signal = "d"}]\n[control]\nmode = "closed"',
     "closed loop holds tones, not levels"),
    (CLOSED, f'signals = [{SINE}]\nplay = [{{signal = "a", unit = "V"}}]\n[control]\nmode = "closed"',
     "closed loop plays tip targets"),
    (CLOSED, f'signals = [{SINE}]\nplay = [{{signal = "a", unit = "threshold", receptor = "ruffini"}}]\n'
             '[control]\nmode = "closed"', "no receptor threshold at 100 Hz"),
    (PVDF, f'signals = [{SINE}]\nplay = [{{signal = "a", channel = 19}}]\n[control]\nmode = "closed"',
     "channel cells.19 plays a tip target but is not under amplitude control"),
]


def _scene_file(tmp_path, base, body):
    p = tmp_path / "bad.toml"
    p.write_text(base + '\n[stimulus]\nkind = "tones"\n' + body + "\n")
    return str(p)


@pytest.mark.parametrize("base, body, words", BAD, ids=[w for *_, w in BAD])
def test_check_refuses_a_bad_stimulus_in_the_line_run_gives(capsys, tmp_path, base, body, words):
    path = _scene_file(tmp_path, base, body)
    code_c, out_c, err_c = run_cli(capsys, "check", path)
    code_r, _, err_r = run_cli(capsys, "run", path, "--duration", "0.2", "--out", str(tmp_path / "run"), "--no-plot",
                               "--quiet")
    assert (code_c, code_r) == (2, 2), (err_c, err_r)
    assert words in err_c and err_c.count("\n") == 1 and "Traceback" not in err_c and out_c == ""
    assert err_c == err_r  # the same line (the run's duration is not part of any of them)


def test_a_signal_that_starts_after_the_run_is_refused_as_a_tone_is(capsys, tmp_path):
    """A played signal starting at 5 s of a 2 s run would play nothing, silently (a tone starting
    there was already refused)."""
    path = _scene_file(tmp_path, OPEN, f'signals = [{SINE}]\nplay = [{{signal = "a", channel = 2, start = 5.0}}]')
    code, out, err = run_cli(capsys, "check", path)
    assert code == 2 and out == "" and err.count("\n") == 1
    assert "stimulus.play.0.start = 5.0: after the end of the run (2 s)" in err, err


def test_check_passes_good_signals_and_the_bundled_scenes(capsys, tmp_path):
    """The check refuses only what the run refuses: a good chirp, sequence and product pass."""
    body = (f'signals = [{SINE}, {{name = "c", type = "chirp", freq = 100.0, freq_end = 200.0, duration = 0.1}}, '
            '{name = "e", type = "asr", attack = 0.01, sustain = 0.05, release = 0.01}, '
            '{name = "p", type = "product", of = ["a", "e"]}, {name = "s", type = "sequence", of = ["p", "c"]}]\n'
            'play = [{signal = "s", channel = 1}]')
    code, out, err = run_cli(capsys, "check", _scene_file(tmp_path, OPEN, body))
    assert code == 0 and "valid" in out and err == ""
    for name in scene.bundled():
        code, _, err = run_cli(capsys, "check", name)
        assert code == 0, err
