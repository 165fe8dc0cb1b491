"""Bad command-line values the commands refuse with one line and status 2: outputs that cannot be
written, empty paths, non-finite or out-of-range numbers, paths too long to render, unreadable
files; never a traceback, an internal error (status 3) or a quiet default."""

import pytest
from test_cli_newuser import _call


def _refused(args, *words):
    code, out, err = _call(args)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, (args, code, err)
    assert "internal error" not in err and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("run")
    code, _, err = _call(["run", "line-bimorph-5", "--duration", "0.05", "--quiet", "--no-plot", "--out", str(d)])
    assert code == 0, err
    return d


def test_trace_export_refuses_an_out_it_cannot_write(run_dir, tmp_path):
    (tmp_path / "afile").write_text("x")
    for out, words in ((tmp_path, "is a directory, not a regular file"),
                       (tmp_path / "afile" / "x.npz", "afile is a regular file, not a directory"),
                       ("/proc/x.npz", "cannot write in /proc"),
                       ("", "--out is empty")):
        _refused(["trace", "export", str(run_dir), "--out", str(out)], words, "give --out a file path")
    assert (tmp_path / "afile").read_text() == "x"


def test_selfsense_and_bench_control_refuse_a_file_as_out_before_they_compute(tmp_path, monkeypatch):
    import rtctl.engine.bench_control

    monkeypatch.setattr(rtctl.engine.bench_control, "measure", lambda *a, **k: pytest.fail("measured"))
    f = tmp_path / "afile"
    f.write_text("x")
    _refused(["selfsense", "line-bimorph-5", "--out", str(f)], "is a regular file, not a directory")
    _refused(["bench", "control", "--blocks", "32,32", "--out", str(f)], "is a regular file, not a directory")
    assert f.read_text() == "x"


@pytest.mark.parametrize("args, words", [
    (["run", "line-bimorph-5", "--duration", "0.02", "--quiet", "--out", ""], "--out is empty"),
    (["calibrate", "line-bimorph-5", "--out", ""], "--out is empty"),
    (["trace", "info", ""], "the trace path is empty"),
    (["bench", "control", "--out", ""], "--out is empty"),
    (["sweep", "line-bimorph-5", "--vary", "timing.block=[32]", "--workers", "0", "--out", ""], "--out is empty"),
], ids=["run", "calibrate", "trace-info", "bench-control", "sweep"])
def test_an_empty_path_is_refused_not_taken_for_the_default(args, words, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _refused(args, words)
    assert not list(tmp_path.iterdir())  # nothing written into the working directory or out/


@pytest.fixture(scope="module")
def image(tmp_path_factory):
    import cv2
    import numpy as np

    f = tmp_path_factory.mktemp("img") / "checker.png"
    a = np.zeros((16, 16), np.uint8)
    a[::4] = 255
    cv2.imwrite(str(f), a)
    return f


@pytest.mark.parametrize("args, words", [
    (["--at", "nan,nan"], ["--at nan", "stimulus.at allows [-1e+06, 1e+06] px"]),
    (["--at", "inf,0"], ["--at inf"]),
    (["--rate", "1e8", "--path", "raster"], ["--rate 100000000.0", "stimulus.rate allows [1, 10000] Hz"]),
    (["--rate", "nan", "--path", "raster"], ["--rate nan"]),
    (["--hia", "100000"], ["--hia 100000", "stimulus.hia allows [0, 4096] px"]),
    (["--method", "beat", "--mm-per-px", "1e300"], ["--mm-per-px 1e+300", "stimulus.px_size"]),
    (["--path", "raster", "--speed", "1e-6"],
     ["1.5e+10 render updates", "(1.5e+07 s at 1000 Hz)", "more than the 1000000 allowed"]),
    (["--path", "1,1@0;2,2@1e9"], ["1e+12 render updates", "more than the 1000000 allowed"]),
    (["--path", ""], ["--path is empty"]),
], ids=["at-nan", "at-inf", "rate-huge", "rate-nan", "hia-huge", "mm-per-px-huge", "slow-raster", "far-time",
        "empty-path"])
def test_render_refuses_values_that_would_crash_or_never_end(image, args, words):
    _refused(["render", str(image), *args], *words)


def test_a_mouse_csv_too_long_or_not_text_is_refused_by_render_and_by_a_scene(image, tmp_path):
    long = tmp_path / "long.csv"
    long.write_text("t,x,y\n0,1,1\n1e12,2,2\n")
    binary = tmp_path / "bin.csv"
    binary.write_bytes(b"\xff\xfe,\x00\n")
    _refused(["render", str(image), "--path", str(long)], "1e+15 render updates", "1000000 allowed")
    _refused(["render", str(image), "--path", str(binary)], f"{binary}: not UTF-8 text", "give a CSV of t,x,y")
    scene = ["run", "dot-4x4", "--quiet", "--no-plot", "--out", str(tmp_path / "out"), "--set", "stimulus.kind=image",
             "--set", "stimulus.method=roi", "--set", f"stimulus.image={image}"]
    _refused([*scene, "--set", f"stimulus.path={binary}"], f"{binary}: not UTF-8 text")
    _refused([*scene, "--set", f"stimulus.path={long}"], "1e+15 render updates")


@pytest.mark.parametrize("skip", ["nan", "inf", "1e9"])
def test_replay_refuses_a_skip_that_is_not_a_time_inside_the_trace(run_dir, tmp_path, skip):
    _refused(["replay", str(run_dir), "--mode", "plant", "--skip", skip, "--out", str(tmp_path)],
             f"--skip {float(skip):g}: must be >= 0 and shorter than the")


def test_replay_compares_a_tail_shorter_than_one_window(run_dir, tmp_path):
    import json

    code, out, _ = _call(["trace", "info", str(run_dir), "--json"])
    skip = json.loads(out)["duration_s"] - 0.05  # leaves about 0.05 s: half the 0.1 s window
    code, out, err = _call(["replay", str(run_dir), "--mode", "plant", "--skip", f"{skip:.4f}", "--out",
                            str(tmp_path), "--json"])
    assert code == 0, err
    rep = json.loads(out)
    assert rep["window_s"] < 0.1 and rep["blocks"] >= 1


@pytest.mark.parametrize("args, words", [
    (["bench", "realtime", "--seconds", "nan"], ["--seconds in (0, 86400]"]),
    (["bench", "realtime", "--seconds", "inf"], ["--seconds in (0, 86400]"]),
    (["bench", "realtime", "--seconds", "1", "--rounds", "1000000"],
     ["leaves 1e-06 s a round, less than one block (667 us)"]),
    (["bench", "control", "--blocks", ""], ["--blocks ''", "give block sizes like 16,32,64"]),
    (["selfsense", "line-bimorph-5", "--beat", "nan"], ["--beat nan: must be in [0, 20] Hz"]),
    (["selfsense", "line-bimorph-5", "--snr", "nan"], ["--snr nan"]),
    (["selfsense", "line-bimorph-5", "--freqs", "nan"], ["--freqs 'nan'", "finite frequencies > 0 Hz"]),
], ids=["realtime-nan", "realtime-inf", "realtime-rounds", "control-no-blocks", "selfsense-beat", "selfsense-snr",
        "selfsense-freqs"])
def test_bench_and_selfsense_refuse_numbers_they_cannot_use(args, words, tmp_path):
    if args[0] == "selfsense":
        args = [*args, "--out", str(tmp_path)]
    _refused(args, *words)


def test_a_wav_at_infinite_volts_per_full_scale_is_refused_not_written_silent(run_dir, tmp_path):
    _refused(["trace", "export", str(run_dir), "--format", "wav", "--volts-per-fs", "inf",
              "--out", str(tmp_path / "x.wav")], "volts per full scale must be a finite number > 0, not inf")
    assert not (tmp_path / "x.wav").exists()


def test_a_directory_given_as_a_scene_is_called_a_directory(tmp_path):
    line = _refused(["check", str(tmp_path)], f"{tmp_path}: is a directory, not a scene file")
    assert "no such" not in line


def test_a_gray_and_alpha_png_is_named_la_not_rgba(tmp_path):
    import numpy as np
    from PIL import Image

    f = tmp_path / "la.png"
    a = np.zeros((16, 16, 2), np.uint8)
    a[..., 1] = 255
    Image.fromarray(a, "LA").save(f)
    line = _refused(["render", str(f)], f"{f}: gray with an alpha channel (LA)", "8-bit gray without alpha")
    assert "RGBA" not in line


@pytest.mark.parametrize("args, words", [
    (["bench", "render", "--size", "0"], ["--size 0: must be in [8, 16384] px"]),
    (["bench", "render", "--size", "1000000000"], ["--size 1000000000"]),
    (["bench", "render", "--n", "0"], ["--n 0: must be in [4, 1000000] updates"]),
    (["bench", "render", "--methods", "nope"], ["--methods: 'nope' not among roi, canny, frequency, beat"]),
    (["emulate", "serial", "dot-4x4", "--settle-ms", "nan"], ["--settle-ms = nan: must be a finite number >= 0"]),
    (["emulate", "serial", "dot-4x4", "--settle-ms", "inf"], ["--settle-ms = inf"]),
], ids=["render-size-0", "render-size-huge", "render-n-0", "render-method", "serial-settle-nan", "serial-settle-inf"])
def test_render_bench_and_serial_emulator_refuse_numbers_they_cannot_use(args, words):
    _refused(args, *words)


def test_render_replay_and_sweep_refuse_an_out_they_cannot_write(run_dir, image, tmp_path, monkeypatch):
    f = tmp_path / "afile"
    f.write_text("x")
    for args in (["replay", str(run_dir), "--mode", "plant"],
                 ["sweep", "line-bimorph-5", "--vary", "timing.block=[32]", "--workers", "0"]):
        _refused([*args, "--out", str(f)], f"--out {f}: is a regular file, not a directory")
    assert f.read_text() == "x"
    monkeypatch.chdir(tmp_path)
    for args in (["render", str(image)], ["replay", str(run_dir), "--mode", "plant"]):
        _refused([*args, "--out", ""], "--out is empty")
    assert [p.name for p in tmp_path.iterdir()] == ["afile"]


def _readme_commands():
    import pathlib
    import re

    text = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()
    for cell in re.findall(r"^\| `(rtctl [^`]*)` \|", text, flags=re.M):
        yield cell.replace("\\|", "|")


def test_the_readme_writes_as_required_only_options_the_help_requires():
    from test_cli_newuser import _required_positionals

    checked = []
    for row in _readme_commands():
        cmd = []
        for w in row.split()[1:]:  # the command words: up to the first argument or option
            if not w.replace("-", "").isalpha() or w.isupper() or w.startswith("-"):
                break
            cmd.append(w)
        code, out, _ = _call([*cmd, "--help"])
        if code != 0 or not out.startswith("usage: "):
            continue
        usage = out.split("\n\n")[0]
        needed = {w for w in _required_positionals(usage, " ".join(["rtctl", *cmd])) if w.startswith("--")}
        written = {w for w in _required_positionals("usage: " + row, "rtctl") if w.startswith("--")}
        assert written <= needed, (row, written - needed, usage)
        checked.append(" ".join(cmd))
    assert "render" in checked and "sweep" in checked, checked


def test_check_and_run_refuse_an_overlap_longer_than_the_item_before(tmp_path):
    from rtctl import scene

    base = scene.resolve("line-bimorph-5").read_text().split("[stimulus]")[0]
    f = tmp_path / "overlap.toml"
    f.write_text(base + '[stimulus]\nkind = "tones"\nsignals = [\n'
                 '  {name = "a", type = "sine", freq = 200.0, duration = 0.03},\n'
                 '  {name = "ab", type = "sequence", of = ["a", "a"], gap = -0.05},\n'
                 ']\nplay = [{signal = "ab", channel = 3}]\n')
    words = (f"{f}: stimulus.signals.1.gap = -0.05: an overlap longer than 'a' (0.03 s): the item after it would "
             "start before it (signal 'ab')")
    _refused(["check", str(f)], words)
    _refused(["run", str(f), "--duration", "0.1", "--quiet", "--no-plot", "--out", str(tmp_path / "r")], words)
    assert not (tmp_path / "r").exists()  # refused before anything was written: no empty --out left
    (tmp_path / "kept").mkdir()  # a directory the user made stays, empty or not
    _refused(["run", str(f), "--duration", "0.1", "--quiet", "--no-plot", "--out", str(tmp_path / "kept")], words)
    assert (tmp_path / "kept").is_dir()
