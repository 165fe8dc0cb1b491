"""The hand-made nasty inputs of tests/corpus, each with the words its one-line error must hold
(tests/corpus/README.md). Many were found by the fuzz tests (tests/test_fuzz_*.py) and guard the
fixes they led to."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from fuzzing import clean_or_clear, one_line, run_cli

from rtctl import patterns, scene
from rtctl.errors import PatternError, RtctlError, SceneError
from rtctl.io import protocol as P

CORPUS = Path(__file__).with_name("corpus")


def _expect(kind):
    return json.loads((CORPUS / kind / "expect.json").read_text(encoding="utf-8"))


def test_every_corpus_file_says_what_it_must_produce():
    for kind in ("scene", "image", "serial", "trace", "calibration", "pattern"):
        files = {p.name for p in (CORPUS / kind).iterdir() if p.name != "expect.json"}
        assert files == set(_expect(kind)), kind


def _check(result, want, *names):
    if want == "ok":
        assert not isinstance(result, Exception), result
        return
    assert isinstance(result, Exception), f"accepted, expected an error with {want}"
    for w in [*want, *names]:
        assert w in str(result), (w, str(result))


@pytest.mark.parametrize("name", sorted(_expect("scene")))
def test_scene_files(name):
    path = CORPUS / "scene" / name
    result = clean_or_clear(scene.load, path, errors=SceneError)
    _check(result, _expect("scene")[name], str(path))
    status, _, err = run_cli(["check", str(path)])
    assert status == (0 if _expect("scene")[name] == "ok" else 2), err


SETS = json.loads((CORPUS / "set.json").read_text(encoding="utf-8"))


@pytest.mark.parametrize("case", SETS, ids=[f"{i}-{c['item'][:24]}" for i, c in enumerate(SETS)])
def test_set_items(case):
    result = clean_or_clear(scene.load, case["scene"], [case["item"]], errors=SceneError)
    _check(result, case["expect"])
    status, _, _ = run_cli(["check", case["scene"], f"--set={case['item']}"])
    assert status == (0 if case["expect"] == "ok" else 2)


def test_image_files_in_bounded_memory():
    """Every corpus image through load_image in one child process that may map at most 1.5 GiB:
    a loader that believed a lying header would fail to allocate there instead of passing."""
    script = (
        "import json, resource, sys\n"
        "resource.setrlimit(resource.RLIMIT_AS, (3 << 29, 3 << 29))\n"
        "from rtctl.render.image import load_image\n"
        "from rtctl.errors import RtctlError\n"
        "out = {}\n"
        "for p in sys.argv[1:]:\n"
        "    try:\n"
        "        a = load_image(p); out[p] = ['ok', list(a.shape), str(a.dtype)]\n"
        "    except RtctlError as e:\n"
        "        out[p] = ['error', str(e)]\n"
        "    except BaseException as e:\n"
        "        out[p] = ['bug', f'{type(e).__name__}: {e}']\n"
        "print(json.dumps(out))\n"
    )
    want = _expect("image")
    paths = [str(CORPUS / "image" / n) for n in sorted(want)]
    p = subprocess.run([sys.executable, "-c", script, *paths], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    got = json.loads(p.stdout)
    for path in paths:
        kind, *rest = got[path]
        w = want[Path(path).name]
        assert kind != "bug", (path, rest)
        if w == "ok":
            assert kind == "ok" and rest[1] == "uint8", (path, rest)
        else:
            assert kind == "error", (path, rest)
            one_line(rest[0], path, *w)


@pytest.fixture(scope="module")
def firmware():
    from rtctl.emulate.serial import Firmware

    return Firmware(scene.load("dot-4x4"), chunk_s=1e-3)


def _label(wire):
    (a,) = P.Decoder().feed(wire)
    assert a.error is None
    return f"NACK:{a.body[0]}" if a.kind == P.NACK else P.TYPE_NAMES[a.kind]


@pytest.mark.parametrize("name", sorted(n for n in _expect("serial") if n.startswith("device-")))
def test_serial_streams_into_the_device(firmware, name):
    data = (CORPUS / "serial" / name).read_bytes()
    answers = [_label(firmware.on_frame(f, 0.0)) for f in P.Decoder().feed(data)]
    assert answers == _expect("serial")[name]["answers"]


@pytest.mark.parametrize("name", sorted(n for n in _expect("serial") if n.startswith("host-")))
def test_serial_streams_into_the_host(name):
    from test_fuzz_serial import _backend

    be, dev, out = _backend()
    try:
        out[:, -1] = 5.0  # every pin UP: the first write sends PINS with sequence number 1
        assert be.write() == 0 and be._inflight.seq == 1
        dev.sendall((CORPUS / "serial" / name).read_bytes())
        be.read()
        stats = be.stats()
        for key, want in _expect("serial")[name].items():
            assert stats[key] == want, (key, stats)
    finally:
        be.close()
        dev.close()


@pytest.mark.parametrize("name", sorted(_expect("trace")))
def test_trace_directories(name):
    from rtctl.trace import TraceReader

    path = CORPUS / "trace" / name
    r = clean_or_clear(TraceReader, path, errors=(RtctlError, OSError), names=[str(path)])
    want = _expect("trace")[name]
    if isinstance(want, dict):  # readable: every signal, with the records that are complete
        assert not isinstance(r, Exception), r
        assert r.n_blocks == want["n_blocks"]
        for sig in r.dtype.names[3:]:
            assert r.signal(sig).shape[1] in (r.n_blocks, r.n_blocks * r.block)
    else:
        _check(r, want)


@pytest.mark.parametrize("name", sorted(_expect("calibration")))
def test_calibration_files(name):
    from rtctl.engine.calibrate import read

    path = CORPUS / "calibration" / name
    result = clean_or_clear(read, path, scene.load("line-bimorph-5"), errors=SceneError)
    _check(result, _expect("calibration")[name], str(path))


@pytest.mark.parametrize("name", sorted(_expect("pattern")))
def test_pattern_files(name):
    path = CORPUS / "pattern" / name
    result = clean_or_clear(patterns.load, path, errors=PatternError, names=[str(path)])
    _check(result, _expect("pattern")[name])
    if _expect("pattern")[name] != "ok":  # a good one would run the whole scene
        status, _, err = run_cli(["play", str(path), "--scene", "pvdf-6x8"])
        assert status == 2, err


VARIES = json.loads((CORPUS / "vary.json").read_text(encoding="utf-8"))


@pytest.mark.parametrize("case", VARIES, ids=[f"{i}-{c['item'][:24]}" for i, c in enumerate(VARIES)])
def test_vary_specs(case):
    from rtctl.sweep.spec import parse

    _check(clean_or_clear(parse, case["item"], errors=RtctlError), case["expect"])
