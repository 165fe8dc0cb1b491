"""The command line as a new user meets it: --help everywhere, what the run report and plot say
about binary pins, idle channels and a finger that touches nothing, a reused --out, Ctrl-C."""

import argparse
import contextlib
import io
import json
import math
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from rtctl.cli import _parser, main


def _call(args):
    """``main(args)`` as the shell sees it: exit status (returned or raised), stdout, stderr."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(list(args))
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    return code, out.getvalue(), err.getvalue()


def _command_paths(parser, path=()):
    """Every command of the parser tree, subcommands of subcommands included."""
    yield path
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _command_paths(sub, path + (name,))


PATHS = list(_command_paths(_parser()))


def _required_positionals(usage: str, prog: str) -> list[str]:
    """The words of a usage text outside [...] after the program name: what must be given."""
    body = " ".join(usage.split())[len("usage: ") + len(prog):]
    while True:
        stripped = re.sub(r"\[[^\[\]]*\]", "", body)
        if stripped == body:
            break
        body = stripped
    return [w for w in body.split() if w != "..."]


def test_the_walk_sees_the_nested_tools():
    assert {("run",), ("render",), ("selfsense",), ("emulate",), ("bench",)} <= set(PATHS)
    assert {("bench", "numerics"), ("bench", "render"), ("emulate", "audio"), ("emulate", "serial")} <= set(PATHS)


@pytest.mark.parametrize("path", PATHS, ids=lambda p: " ".join(p) or "rtctl")
def test_help_and_missing_argument_at_every_level(path):
    prog = " ".join(("rtctl",) + path)
    for flag in ("--help", "-h"):
        code, out, err = _call([*path, flag])
        assert code == 0, (flag, err)
        assert out.startswith(f"usage: {prog}"), (flag, out[:200], err)
        assert "Traceback" not in err
    usage = out.split("\n\n")[0]
    needed = _required_positionals(usage, prog)
    if not needed:  # e.g. `rtctl scenes`: nothing can be missing
        return
    code, out, err = _call(path)
    assert code == 2, (needed, out, err)
    assert err.startswith(f"usage: {prog}"), err
    lines = err.strip().splitlines()
    errors = [ln for ln in lines if ": error:" in ln]
    assert errors == [lines[-1]] and lines[-1].startswith(f"{prog}: error: "), err
    assert "required" in lines[-1] and "Traceback" not in err


@pytest.mark.parametrize("args, words", [
    (["selfsense", "--json", "no-such-scene"], ["no-such-scene", "no such scene"]),
    (["render", "--method", "roi", "/no/such.png"], ["/no/such.png", "no such file"]),
], ids=["selfsense", "render"])
def test_tool_options_before_positionals_reach_the_tool(args, words):
    code, _, err = _call(args)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and re.match(r"rtctl( \w+)?: error: ", lines[0]), err
    for w in words:
        assert w in lines[0]


# --- one solenoid-3x3 run shared by the report tests ---------------------------------------------

@pytest.fixture(scope="module")
def solenoid_run(tmp_path_factory):
    """``rtctl run solenoid-3x3`` with plot.png, the figure that was saved, the printed table."""
    import matplotlib.figure

    out_dir = tmp_path_factory.mktemp("solenoid")
    saved = []
    original = matplotlib.figure.Figure.savefig

    def capture(self, *a, **k):
        saved.append(self)
        return original(self, *a, **k)

    matplotlib.figure.Figure.savefig = capture
    try:
        code, out, err = _call(["run", "solenoid-3x3", "--duration", "0.2", "--out", str(out_dir), "--quiet"])
    finally:
        matplotlib.figure.Figure.savefig = original
    assert code == 0, err
    summary = json.loads((out_dir / "summary.json").read_text())
    return {"dir": out_dir, "summary": summary, "figures": saved, "table": out}


def test_plot_shows_the_driven_pins_first_and_says_how_many(solenoid_run):
    (fig,) = solenoid_run["figures"]  # the figure plot.png was saved from
    titles = [ax.get_title(loc="left") for ax in fig.axes]
    panels = [t.split()[0] for t in titles if t]
    assert panels[:3] == ["pins.0", "pins.4", "pins.8"] and len(panels) == 8, panels
    assert "340 Hz" in titles[[t.split()[0] if t else "" for t in titles].index("pins.8")]
    assert "8 of 9 channels shown (driven first)" in fig.get_suptitle()
    assert (solenoid_run["dir"] / "plot.png").stat().st_size > 10_000
    from rtctl.engine.report import plot_channels

    rows = solenoid_run["summary"]["channels"]
    assert len(rows) == 9
    chosen, caption = plot_channels(rows)
    assert len(chosen) == 8 and 8 in chosen  # the 340 Hz pin
    assert chosen[:3] == [0, 4, 8]  # driven first, the idle pins after
    assert caption == "8 of 9 channels shown (driven first)"


def test_plot_caption_is_empty_when_every_channel_fits():
    from rtctl.engine.report import plot_channels

    rows = [{"v_peak": v, "freq_hz": None} for v in (0.0, 3.0, 0.0)]
    assert plot_channels(rows) == ([0, 1, 2], "")


def test_end_stop_pins_have_no_amplitude_target(solenoid_run):
    rows = {r["name"]: r for r in solenoid_run["summary"]["channels"]}
    for name in ("pins.0", "pins.4", "pins.8"):
        r = rows[name]
        assert r["threshold_um"] is not None and r["true_um"] > 50  # driven into the stops
        assert r["target_um"] is None and r["error_pct"] is None, r
    table = {ln.split()[0]: ln.split() for ln in solenoid_run["table"].splitlines() if ln.startswith("pins.")}
    # channel receptor freq V-peak true thresh target error settle felt
    for name in ("pins.0", "pins.4", "pins.8"):
        assert table[name][6:9] == ["-", "-", "-"], table[name]
        assert table[name][9] == "yes"


def _run_json(tmp_path, scene, *extra):
    code, out, err = _call(["run", scene, "--duration", "0.2", "--out", str(tmp_path), "--no-plot", "--quiet", *extra])
    assert code == 0, err
    return json.loads((tmp_path / "summary.json").read_text()), out


def test_nothing_is_felt_without_contact(tmp_path):
    # bimodal-4x4 has a normal and a lateral group: finger.contact is one switch for both
    s, table = _run_json(tmp_path / "free", "bimodal-4x4", "--set", "finger.contact=false")
    rows = s["channels"]
    assert {r["group"] for r in rows} == {"normal", "lateral"}
    driven = [r for r in rows if r["threshold_um"] is not None]
    assert {r["group"] for r in driven} == {"normal", "lateral"}
    assert any(r["true_um"] >= r["threshold_um"] for r in driven)  # the tips do move that far
    felt = {ln.split()[0]: ln.split()[9] for ln in table.splitlines() if ln.split() and ln.split()[0] in
            {r["name"] for r in driven}}
    assert set(felt.values()) == {"NO"}, felt
    assert all(r["felt"] is False for r in rows)
    s, _ = _run_json(tmp_path / "touching", "bimodal-4x4")
    felt = {r["name"]: r["felt"] for r in s["channels"] if r["threshold_um"] is not None}
    assert felt and all(felt.values()), felt  # with contact the same channels are felt


def test_a_run_into_an_earlier_runs_out_leaves_none_of_its_files(tmp_path):
    code, _, err = _call(["run", "solenoid-3x3", "--duration", "0.1", "--out", str(tmp_path), "--quiet"])
    assert code == 0, err
    assert (tmp_path / "plot.png").exists()
    (tmp_path / "notes.txt").write_text("mine")
    s, _ = _run_json(tmp_path, "line-bimorph-5")
    assert s["scene"] == "line-bimorph-5"
    assert not (tmp_path / "plot.png").exists()  # the solenoid plot is gone, not left beside the new summary
    assert (tmp_path / "notes.txt").read_text() == "mine"  # files a run never writes are left alone
    from rtctl.trace import TraceReader

    assert TraceReader(tmp_path / "trace").layout["meta"]["scene"]["scene"]["name"] == "line-bimorph-5"
    code, help_, _ = _call(["run", "--help"])
    assert "plot.png" in " ".join(help_.split()), help_


def test_ctrl_c_says_how_long_the_run_went_and_where_its_trace_is(tmp_path):
    out_dir = tmp_path / "x"
    # a shell that started this test in the background may have left SIGINT ignored: the child
    # must get the default disposition for Python to turn SIGINT into KeyboardInterrupt
    p = subprocess.Popen([sys.executable, "-m", "rtctl.cli", "run", "line-bimorph-5", "--duration", "30",
                          "--realtime", "--no-plot", "--quiet", "--out", str(out_dir)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        blocks_file = out_dir / "trace" / "blocks.bin"
        t0 = time.monotonic()
        while not (blocks_file.exists() and blocks_file.stat().st_size > 0):
            assert p.poll() is None, p.communicate()
            assert time.monotonic() - t0 < 180, "the run never started writing its trace"
            time.sleep(0.05)
        time.sleep(0.5)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()
    assert p.returncode == 130, err
    m = re.search(r"^rtctl: interrupted after ([0-9.]+) s \((\d+) blocks\); trace and summary in (.+)$", err,
                  re.MULTILINE)
    assert m, err
    assert "Traceback" not in err
    s = json.loads((out_dir / "summary.json").read_text())
    blocks = round(s["duration_s"] * s["fs"] / s["block"])
    assert s["interrupted"] is True
    assert 0 < blocks < 30 * s["fs"] / s["block"]
    assert int(m.group(2)) == blocks
    assert float(m.group(1)) == pytest.approx(s["duration_s"], abs=0.006)
    assert os.path.samefile(m.group(3), out_dir)
    from rtctl.trace import TraceReader

    # every run block, the 30 ms raised-cosine release (45 blocks), then 0 V while the tips settle
    assert s["stop"]["by"] == "interrupt" and s["stop"]["fade"] == "raised cosine"
    tail = round(s["stop"]["settle_s"] * s["fs"] / s["block"])
    assert TraceReader(out_dir / "trace").n_blocks == blocks + 45 + tail and tail > 0


# --- outputs that cannot be written, images that are not files ------------------------------------

def _unwritable(tmp_path):
    """Paths no run can write into, with the words its one line must hold."""
    a_file = tmp_path / "a-file"
    a_file.write_text("x")
    fifo = tmp_path / "a-fifo"
    os.mkfifo(fifo)
    cases = {"regular-file": (a_file, "is a regular file, not a directory"),
             "under-a-file": (a_file / "sub", "cannot create the directory (Not a directory)"),
             "fifo": (fifo, "is a FIFO (named pipe), not a directory"),
             "proc": ("/proc/x", "cannot create the directory")}
    if os.path.isdir("/sys"):
        cases["sys"] = ("/sys/x", "cannot create the directory")
    return cases


def test_an_unwritable_out_is_refused_before_the_rig_is_built(tmp_path, monkeypatch):
    import rtctl.engine.rig

    built = []
    original = rtctl.engine.rig.build
    monkeypatch.setattr(rtctl.engine.rig, "build", lambda *a, **k: built.append(1) or original(*a, **k))
    for name, (out, words) in _unwritable(tmp_path).items():
        code, out_text, err = _call(["run", "line-bimorph-5", "--duration", "0.05", "--quiet", "--no-plot",
                                     "--out", str(out)])
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1, (name, err)
        assert lines[0].startswith(f"rtctl: error: --out {out}: ") and words in lines[0], (name, lines)
        assert "give --out a directory you can write to" in lines[0]
        assert out_text == "" and not built, name
    assert (tmp_path / "a-file").read_text() == "x"  # the file given as --out is left as it was
    # the same check passes a writable directory, and the run goes on to build its rig
    code, _, err = _call(["run", "line-bimorph-5", "--duration", "0.02", "--quiet", "--no-plot",
                          "--out", str(tmp_path / "new" / "dir")])
    assert code == 0 and built, err
    assert not [p for p in (tmp_path / "new" / "dir").iterdir() if p.name.startswith(".rtctl-probe")]


def test_a_trace_name_taken_by_a_file_is_refused(tmp_path):
    (tmp_path / "trace").write_text("not a trace")
    code, _, err = _call(["run", "line-bimorph-5", "--duration", "0.02", "--quiet", "--out", str(tmp_path)])
    assert code == 2 and "trace there is a regular file, where this writes a directory" in err, err
    assert (tmp_path / "trace").read_text() == "not a trace"


def test_unwritable_calibration_and_render_outputs_are_one_line(tmp_path):
    code, _, err = _call(["calibrate", "line-bimorph-5", "--out", str(tmp_path)])
    assert code == 2 and err.count("\n") == 1 and "is a directory, not a regular file" in err, err
    code, _, err = _call(["calibrate", "line-bimorph-5", "--out", "/proc/x/cal.json"])
    assert code == 2 and err.count("\n") == 1 and "cannot create its directory /proc/x" in err, err
    from matplotlib import cbook

    hopper = cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)
    for name, (out, words) in _unwritable(tmp_path).items():
        code, _, err = _call(["render", str(hopper), "--out", str(out)])
        assert code == 2 and err.count("\n") == 1 and words in err, (name, err)


def test_a_fifo_or_a_device_given_as_an_image_is_named_as_such(tmp_path):
    fifo = tmp_path / "pipe.png"
    os.mkfifo(fifo)
    for path, kind in ((fifo, "a FIFO (named pipe)"), ("/dev/null", "a character device")):
        code, _, err = _call(["render", str(path)])
        assert code == 2 and err == f"rtctl: error: {path}: is {kind}, not an image file; give a regular image file\n"


# --- values that run but leave a model's validity range -------------------------------------------

def test_a_beam_shorter_than_thick_is_refused_naming_the_key_and_the_range(tmp_path):
    code, out, err = _call(["run", "line-bimorph-5", "--duration", "0.02", "--quiet", "--out", str(tmp_path),
                            "--set", "actuator.lateral.beam.length=1e-4"])
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and out == "", err
    assert "actuator.lateral.beam.length = 0.0001 m is 0.167 times the beam's thickness 0.6 mm" in lines[0]
    assert "Euler-Bernoulli" in lines[0] and "length / thickness >= 2.5 to run" in lines[0]
    assert not (tmp_path / "trace").exists()


def test_a_stubby_beam_runs_with_a_warning_in_the_summary(tmp_path):
    code, out, err = _call(["run", "line-bimorph-5", "--duration", "0.02", "--quiet", "--no-plot", "--out",
                            str(tmp_path), "--set", "actuator.lateral.beam.length=3e-3"])
    assert code == 0, err
    # Timoshenko's first-order shift of the first cantilever mode, computed here from its closed
    # form: (1.8751 h / L)^2 (1 + 2 (1 + 0.3) / (5/6)) / 24 at L / h = 5
    shift = (1.875104 / 5) ** 2 * (1 + 2 * 1.3 / (5 / 6)) / 24
    assert f"by about {100 * shift:.2g} %" == "by about 2.4 %"
    warned = [ln for ln in err.splitlines() if ln.startswith("rtctl: warning: actuator.lateral.beam.length")]
    assert len(warned) == 1 and "is 5 times the beam's thickness" in warned[0] and "by about 2.4 %" in warned[0]
    s = json.loads((tmp_path / "summary.json").read_text())
    assert any("Euler-Bernoulli" in w for w in s["warnings"])
    # a slender beam (25 x its thickness, the bundled one) says nothing
    code, _, err = _call(["check", "line-bimorph-5"])
    assert code == 0 and "warning" not in err, err


def test_the_thresholds_sit_where_the_estimate_crosses_1_and_10_percent():
    from rtctl.validity import BEAM_NU, REFUSE, WARN, _ratio_at, shear_error

    for err in (WARN, REFUSE):
        r = _ratio_at(err, BEAM_NU)
        assert shear_error(1.875104 / r, BEAM_NU) == pytest.approx(err, rel=1e-12)
    # the Kirchhoff plate: a 2 cm glass plate keeping modes to 4 kHz warns, 8 cm is refused
    code, _, err = _call(["check", "pvdf-6x8", "--set", "actuator.cells.plate.thickness=0.02"])
    assert code == 0 and "rtctl: warning: actuator.cells.plate.thickness = 0.02 m" in err and "Kirchhoff" in err
    code, _, err = _call(["check", "pvdf-6x8", "--set", "actuator.cells.plate.thickness=0.05",
                          "--set", "actuator.cells.plate.max_mode_hz=20000"])
    assert code == 2 and err.count("\n") == 1 and "lower max_mode_hz or thin the plate" in err, err


def test_an_sma_prestrain_past_full_transformation_is_refused():
    from types import SimpleNamespace

    from rtctl.errors import SceneError
    from rtctl.plant.sma import SmaTaxel
    from rtctl.validity import SMA_SHEAR_MAX, _sma

    t = SmaTaxel()
    limit = SMA_SHEAR_MAX * math.pi * t.D ** 2 * t.N / (2 * t.d)  # closed-coil spring: gamma = d x / (pi D^2 N)
    _sma("s.toml", "actuator.pins", SimpleNamespace(prestrain=0.99 * limit))
    with pytest.raises(SceneError, match=r"actuator.pins.sma.prestrain = .* shear strain of 7\S* % at full "
                                         r"travel, beyond the 6.9 %"):
        _sma("s.toml", "actuator.pins", SimpleNamespace(prestrain=1.01 * limit))


@pytest.mark.parametrize("sets, shunt_below, fs_below", [
    (["timing.fs=192000"], "52.3", "100000"),
    (["actuator.lateral.beam.length=1.0"], "3.14", "1500"),
], ids=["fs-192k", "beam-1m"])
def test_a_shunt_the_user_never_set_is_named_by_its_key(tmp_path, sets, shunt_below, fs_below):
    args = ["run", "line-bimorph-5", "--duration", "0.02", "--quiet", "--no-plot", "--out", str(tmp_path)]
    code, _, err = _call(args + [a for s in sets for a in ("--set", s)])
    assert code == 2 and err.count("\n") == 1, err
    assert "actuator.lateral.sense.shunt = 100 ohm is too large" in err
    assert f"set actuator.lateral.sense.shunt below {shunt_below} ohm, or timing.fs below {fs_below} Hz" in err
    # the values it names are the way out: each one alone makes the scene run
    for fix in (f"actuator.lateral.sense.shunt={shunt_below}", f"timing.fs={fs_below}"):
        code, _, err = _call(args + [a for s in sets + [fix] for a in ("--set", s)] + ["--duration", "0.05"])
        assert code == 0, (fix, err)


# --- how a run ends: a requested stop releases smoothly and waits for the tips, a fault is quick ----

def test_the_end_of_a_run_releases_smoothly_and_the_trace_runs_until_the_tips_settle(tmp_path):
    from rtctl.trace import TraceReader

    s, _ = _run_json(tmp_path, "line-bimorph-5", "--set", "timing.stop_fade=0.04")
    fs, block = s["fs"], s["block"]
    run = round(s["duration_s"] * fs)
    fade = round(0.04 * fs)
    r = TraceReader(tmp_path / "trace")
    drive, tip = r.signal("drive"), r.signal("tip_um")
    assert s["stop"] == {"by": "end", "fade": "raised cosine", "fade_s": 0.04, "settle_s": s["stop"]["settle_s"]}
    # the release: each channel's drive is its tone x under g = (1 + cos(pi k / N)) / 2; a step
    # of x g is at most x's largest step plus max|x| pi / (2 N), where a one-block fade stepped
    # up to 140 V / 32 = 4.4 V
    steps = np.abs(np.diff(drive[:, run - 1:run + fade], axis=1)).max(axis=1)
    before = drive[:, run - fade:run]
    bound = np.abs(np.diff(before, axis=1)).max(axis=1) + np.abs(before).max(axis=1) * np.pi / (2 * fade)
    assert np.all(steps <= bound * (1 + 1e-9)), (steps, bound)
    assert steps.max() < 0.5
    assert np.all(drive[:, run + fade - 1:] == 0.0)
    # the window itself: each tone, fitted (least squares, its own frequency) to the 10 ms before
    # the stop and carried on, times the raised cosine, is what the limiter let out
    t = np.arange(run + fade) / fs
    k = np.arange(1, fade + 1)
    g = np.where(k < fade, 0.5 * (1 + np.cos(np.pi * k / fade)), 0.0)
    for c, row in enumerate(s["channels"]):
        w = 2 * np.pi * row["freq_hz"]
        basis = np.column_stack([np.sin(w * t), np.cos(w * t)])
        coef, *_ = np.linalg.lstsq(basis[run - 480:run], drive[c, run - 480:run], rcond=None)
        np.testing.assert_allclose(drive[c, run:run + fade], (basis[run:] @ coef) * g,
                                   atol=1e-6 * row["v_peak"], err_msg=row["name"])
    # the settle criterion is the model's (60 dB below its slowest free oscillation); the
    # simulated truth shows the tips really are still by then: within 60 dB of their peak
    tail = r.n_blocks * block - run - fade
    assert tail == round(s["stop"]["settle_s"] * fs / block) * block and tail > 0
    peak = np.abs(tip[:, :run]).max(axis=1)
    last = np.abs(tip[:, -block:]).max(axis=1)
    assert np.all(last <= 1e-3 * peak), last / peak
    assert np.any(np.abs(tip[:, run + fade:run + fade + block]).max(axis=1) > 1e-2 * peak)  # not still at 0 V


def test_a_fault_keeps_the_one_block_fade_and_ends_the_trace_there(tmp_path):
    from rtctl.trace import TraceReader

    sets = ["actuator.lateral.limits.temperature=25.0001", "actuator.lateral.limits.thermal_tau=0.001",
            "actuator.lateral.limits.loss_tangent=0.5"]
    code, _, err = _call(["run", "line-bimorph-5", "--duration", "0.3", "--quiet", "--no-plot", "--out", str(tmp_path),
                          *[a for s in sets for a in ("--set", s)]])
    assert code == 1 and "over temperature" in err, err
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["stop"] == {"by": "fault", "fade": "linear", "fade_s": s["block"] / s["fs"], "settle_s": 0.0}
    r = TraceReader(tmp_path / "trace")
    run = round(s["duration_s"] * s["fs"] / s["block"])
    assert r.n_blocks == run + 1
    drive = r.signal("drive")
    assert np.all(drive[:, -1] == 0.0) and np.any(drive[:, -s["block"] - 1] != 0.0)
