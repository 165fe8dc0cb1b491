"""`rtctl check` refuses what `rtctl run` refuses before it runs, by the run's own checks, in the
run's one line (exit 2): closed loop and observing on what they cannot hold, calibration with
nothing to calibrate or a bad file, a backend's groups, an image file, and a component the run
cannot have (its JSON then says invalid, as its exit status does)."""

import json
import sys

import pytest
from test_cli import run_cli

from rtctl import scene
from rtctl.errors import SceneError

REFUSED = [  # (scene, --set overrides, words the one line holds)
    ("dot-4x4", ["control.mode=closed"], "needs stimulus.kind = 'tones'"),
    ("solenoid-3x3", ["control.mode=closed"], "no tone to hold at a target"),
    ("pvdf-6x8", ["control.mode=closed"], "no tone to hold at a target"),
    ("dot-4x4", ["control.observe=true"], "control.observe needs stimulus.kind = 'tones'"),
    ("line-bimorph-5", ["control.mode=closed", "stimulus.tones.0.shape=square", "stimulus.tones.1.shape=square",
                        "stimulus.tones.2.shape=square", "stimulus.tones.3.shape=square",
                        "stimulus.tones.4.shape=square"], "a square or pulse tone, which it does not hold"),
    ("line-bimorph-5-closed", ["stimulus.tones=[{channel = 0, freq = 250, voltage = 1, target_um = 1}, "
                               "{channel = 0, freq = 250, voltage = 1, target_um = 2}]", "events=[]"],
     "channel lateral.0 plays 250 Hz in more than one tone"),
    ("line-bimorph-5-closed", ["stimulus.tones=[{channel = 0, freq = 250, beat = 30, voltage = 1, target_um = 1}, "
                               "{channel = 0, freq = 265, voltage = 1, target_um = 2}]", "events=[]"],
     "channel lateral.0 plays 265 Hz in more than one tone"),
    ("line-bimorph-5-closed", ['stimulus.signals=[{name = "c", type = "sine", freq = 120.0, amp = 12.0}]',
                               "stimulus.play=[{signal = 'c', channel = 3, start = 0.1}]", "events=[]"],
     "channel lateral.3 plays 120 Hz in a tone and in a played voice"),
    ("solenoid-3x3", ["control.calibrate=auto"], "nothing to calibrate"),
    ("line-bimorph-5", ["io.backend=serial"], "drives exactly one actuator group of type dot or sma"),
    ("line-bimorph-5", ["control.calibration=cal/none.json"], "no such file"),
    ("line-bimorph-5", ["stimulus.kind=image", "stimulus.method=roi", "stimulus.image=/no/such.png"],
     "/no/such.png: no such file"),
    ("line-bimorph-5", ["control.calibrate=auto", "control.calibration=cal.json"],
     "control.calibrate = 'auto'"),
]


def _sets(overrides):
    return [x for o in overrides for x in ("--set", o)]


@pytest.mark.parametrize("name, overrides, words", REFUSED, ids=[f"{n}:{w}" for n, _, w in REFUSED])
def test_check_refuses_what_the_run_refuses(capsys, name, overrides, words):
    code, out, err = run_cli(capsys, "check", name, *_sets(overrides))
    assert code == 2 and out == "", (code, out)
    assert words in err and err.count("\n") == 1 and "Traceback" not in err, err


CALIBRATIONS = [("[]", "not a calibration file"), ("[" * 100000 + "]" * 100000, "not a calibration file"),
                ('{"format": "rtctl-calibration-1"}', "a calibration of scene None")]


@pytest.mark.parametrize("text, words", CALIBRATIONS, ids=["list", "deep", "other-scene"])
def test_check_reads_the_calibration_file_as_the_run_does(capsys, tmp_path, text, words):
    f = tmp_path / "cal.json"
    f.write_text(text)
    code, out, err = run_cli(capsys, "check", "line-bimorph-5", "--set", f"control.calibration={f}")
    assert code == 2 and out == "" and words in err and err.count("\n") == 1, err
    from rtctl.engine.calibrate import scene_calibration

    s = scene.load("line-bimorph-5", [f"control.calibration={f}"])
    with pytest.raises(SceneError) as e:
        scene_calibration(s)  # the rig's reader: the same line
    assert err == f"rtctl: error: {e.value}\n"


def test_a_calibration_name_too_long_is_one_line(capsys):
    code, out, err = run_cli(capsys, "check", "line-bimorph-5", "--set", "control.calibration=" + "a" * 5000)
    assert code == 2 and out == "" and "cannot read it" in err and err.count("\n") == 1, err[:300]


def test_closed_loop_refusals_are_the_rigs(capsys, tmp_path):
    """The run refuses each closed-loop scene in the line check gave, before compiling anything."""
    for name in ("dot-4x4", "pvdf-6x8"):
        _, _, err_c = run_cli(capsys, "check", name, "--set", "control.mode=closed")
        code, _, err_r = run_cli(capsys, "run", name, "--set", "control.mode=closed", "--out", str(tmp_path / name),
                                 "--no-plot", "--quiet")
        assert code == 2 and err_r == err_c, (err_r, err_c)


def test_calibrate_auto_with_a_file_is_refused_by_the_run_too(capsys, tmp_path):
    with pytest.raises(SceneError, match="control.calibrate = 'auto'.*control.calibration = 'cal.json'"):
        scene.load("line-bimorph-5", ["control.calibrate=auto", "control.calibration=cal.json"])


def test_unavailable_component_is_invalid_in_the_json_too(capsys):
    code, out, err = run_cli(capsys, "check", "line-bimorph-5", "--set", "io.backend=replay", "--json")
    d = json.loads(out)
    assert code == 2 and d["valid"] is False and d["unavailable"] == ["io.replay"]
    assert "io.replay" in err and err.count("\n") == 1
    code, out, _ = run_cli(capsys, "check", "line-bimorph-5", "--json")
    assert code == 0 and json.loads(out)["valid"] is True and json.loads(out)["unavailable"] == []


def test_daq_without_nidaqmx_is_unavailable(capsys, monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "nidaqmx", None)  # as if not installed
    code, out, err = run_cli(capsys, "check", "line-bimorph-5", "--set", "io.backend=daq", "--json")
    d = json.loads(out)
    assert code == 2 and d["valid"] is False and d["unavailable"] == ["io.daq"]
    assert "nidaqmx is not installed" in err and "rtctl[daq]" in err and err.count("\n") == 1
    code, _, err_r = run_cli(capsys, "run", "line-bimorph-5", "--set", "io.backend=daq", "--set", "io.device=Dev1",
                             "--out", str(tmp_path / "run"), "--no-plot", "--quiet")
    assert code == 2 and err_r.endswith(err.split("rtctl: error: ", 1)[1])
