"""Leave out what a scene does not need; run without PortAudio; survive Ctrl-C.

Each case runs in a fresh interpreter so that ``sys.modules`` and the numba dispatchers show
exactly what that run imported and compiled.
"""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

BLOCK_OPTIONAL = """
import sys
class _Block:
    # Make the optional hardware and image packages unimportable, as on a machine without
    # PortAudio, a serial stack, NI drivers or OpenCV.
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('sounddevice', 'serial', 'nidaqmx', 'cv2', '_sounddevice'):
            raise ImportError('blocked by test: ' + name)
        return None
sys.meta_path.insert(0, _Block())
"""


def python(code: str, *args, timeout=240) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=timeout)


def test_open_loop_run_never_imports_or_compiles_what_it_leaves_out(tmp_path):
    code = """
import json, sys
from rtctl import scene
from rtctl.engine.rig import build
from rtctl.engine.run import run
r = run(scene.load('line-bimorph-5', ['timing.duration=0.05']), out_dir=sys.argv[1], plot=False)
rig = build(scene.load('line-bimorph-5', ['timing.duration=0.05']))
import rtctl.dsp as dsp
print(json.dumps({
    'modules': sorted(sys.modules),
    'stages': [s.name for s in rig.stages],
    'composed': rig.compose_note,
    'imports': [ln for ln in rig._block.source.splitlines() if ln.startswith('from ') and ' as k' in ln],
    'compiled': {k: len(getattr(dsp, k).signatures) for k in
                 ('lockin_process', 'pulse_process', 'ramp_process', 'fade_process')},
    'faults': r.summary['faults'],
}))
"""
    p = python(code, str(tmp_path))
    assert p.returncode == 0, p.stderr
    d = json.loads(p.stdout.strip().splitlines()[-1])
    mods = set(d["modules"])
    for absent in ("rtctl.selfsense", "rtctl.render", "cv2", "sounddevice", "serial", "nidaqmx",
                   "rtctl.io.audio", "rtctl.control"):
        assert absent not in mods, absent
    assert {"rtctl.plant.bimorph", "rtctl.dsp", "rtctl.io.sim"} <= mods
    # the block function is composed of exactly the stages the scene needs, and imports only
    # their kernels; the lock-in, pulse trains, ramps and fades were never compiled
    assert d["composed"] == "composed"
    # (the simulated device's read and plant inside it: SimDevice.in_block)
    assert d["stages"] == ["params", "sim read", "clear", "oscillators", "limiter", "sim group 0"]
    kernels = sorted(ln.split(" import ")[1].split(" as ")[0] for ln in d["imports"])
    assert kernels == sorted(["drain", "deliver", "clear", "osc_bank_process", "limit_block", "sim_group_process",
                              "group_status"]), kernels
    assert d["compiled"] == {"lockin_process": 0, "pulse_process": 0, "ramp_process": 0, "fade_process": 0}
    assert d["faults"] == []


def test_check_imports_no_model_at_all():
    p = python("import sys; from rtctl.cli import main; main(['check', 'line-bimorph-5']); "
               "print('|'.join(sorted(m for m in sys.modules if m.startswith(('rtctl', 'numba', 'scipy')))))")
    assert p.returncode == 0, p.stderr
    mods = set(p.stdout.strip().splitlines()[-1].split("|"))
    assert not {m for m in mods if m.startswith(("rtctl.plant", "rtctl.dsp", "rtctl.selfsense", "numba", "scipy"))}
    assert "rtctl.needs" in mods


def test_import_and_sim_run_without_portaudio_serial_or_opencv(tmp_path):
    code = BLOCK_OPTIONAL + """
import rtctl, rtctl.cli, rtctl.scene, rtctl.engine.run, rtctl.engine.rig, rtctl.io, rtctl.safety
from rtctl.cli import main
sys.exit(main(['run', 'line-bimorph-5', '--duration', '0.05', '--out', sys.argv[1], '--no-plot', '--quiet']))
"""
    p = python(code, str(tmp_path))
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "summary.json").exists()


def test_ctrl_c_fades_to_zero_and_keeps_the_trace(tmp_path):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "rtctl.cli", "run", "line-bimorph-5", "--realtime", "--duration", "60",
           "--out", str(tmp_path), "--no-plot", "--quiet"]
    # a shell that started the suite in the background leaves SIGINT ignored, and a child inherits
    # that: give it the default disposition, as a terminal's Ctrl-C finds it
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    trace = tmp_path / "trace" / "blocks.bin"
    t0 = time.time()
    while time.time() - t0 < 120 and not (trace.exists() and trace.stat().st_size > 200_000):
        time.sleep(0.1)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    from rtctl.trace import TraceReader

    r = TraceReader(tmp_path / "trace")
    assert r.n_blocks > 10
    drive = r.signal("drive")
    assert np.all(drive[:, -1] == 0.0) and np.any(drive != 0.0)
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["interrupted"] is True and 0 < s["duration_s"] < 60


def test_realtime_pacing_takes_wall_time(tmp_path):
    from rtctl import scene
    from rtctl.engine.run import run

    t0 = time.perf_counter()
    r = run(scene.load("line-bimorph-5", ["timing.duration=0.3"]), realtime=True)
    wall = time.perf_counter() - t0
    assert wall >= 0.3
    assert r.summary["realtime_factor"] == pytest.approx(1.0, abs=0.1)
