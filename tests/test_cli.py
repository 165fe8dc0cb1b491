"""The command line: one-line errors with status 2, run outputs, model facts against closed forms."""

import json
import math

import numpy as np
import pytest
from closed_forms import CANTILEVER_ROOTS, loaded_root

from rtctl.cli import main

EPS0 = 8.8541878128e-12


def run_cli(capsys, *args):
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize(
    "args, words",
    [
        (["check", "line-bimorph-5", "--set", "timing.blok=64"], ["timing.blok", "timing.block"]),
        (["run", "line-bimorph-5", "--set", "actuator.lateral.max_voltage=-1"], ["max_voltage", "-1.0", "(0, 2000] V"]),
        (["model", "no-such-scene"], ["no-such-scene", "no such scene"]),
        (["run", "line-bimorph-5", "--set", "control.mode=closed", "--set", "stimulus.kind=shape"],
         ["control.mode = closed", "stimulus.kind = 'tones'", "'shape'"]),
        (["run", "line-bimorph-5", "--set", "io.backend=replay"],
         ["io.backend = 'replay'", "not have yet", "rtctl replay TRACE"]),
        (["run", "dot-4x4", "--set", "io.backend=serial"], ["io.port", "rtctl emulate serial"]),
        (["run", "line-bimorph-5", "--set", "stimulus.kind=image", "--set", "stimulus.method=roi",
          "--set", "stimulus.image=/no/such.png"], ["/no/such.png", "no such file"]),
        (["check", "line-bimorph-5", "--set", "nonsense"], ["path.to.key=VALUE"]),
    ],
    ids=["misspelled", "out-of-range", "missing-file", "closed-loop", "replay", "serial-no-port", "image",
         "bad-set"],
)
def test_bad_input_is_one_line_and_status_2(capsys, args, words):
    code, out, err = run_cli(capsys, *args)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rtctl: error: "), err
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0], (w, lines[0])


def test_scenes_and_check_json(capsys):
    code, out, _ = run_cli(capsys, "scenes", "--json")
    assert code == 0
    assert "line-bimorph-5" in [s["name"] for s in json.loads(out)["scenes"]]
    code, out, _ = run_cli(capsys, "check", "line-bimorph-5", "--json")
    assert code == 0
    d = json.loads(out)
    needed = [n["component"] for n in d["needs"]]
    left = [n["component"] for n in d["leaves_out"]]
    assert {"plant.bimorph", "plant.finger", "dsp.oscillator", "io.sim", "safety.limiter"} <= set(needed)
    assert {"selfsense", "render", "io.audio", "dsp.lockin"} <= set(left)
    assert "cv2" not in d["modules"] and "rtctl.selfsense" not in d["modules"]


def _um(v):
    return v * 1e6


def test_run_json_summary_trace_and_plot(capsys, tmp_path):
    code, out, err = run_cli(capsys, "run", "line-bimorph-5", "--duration", "0.5", "--out", str(tmp_path), "--json")
    assert code == 0, err
    s = json.loads(out)
    assert s == json.loads((tmp_path / "summary.json").read_text())
    for key in ("fs", "block", "duration_s", "realtime_factor", "block_time_us", "deadline_misses", "faults",
                "channels"):
        assert key in s
    assert set(s["block_time_us"]) == {"p50", "p99", "p999", "max"}
    assert s["faults"] == [] and len(s["channels"]) == 5
    row = s["channels"][4]
    for key in ("name", "group", "receptor", "freq_hz", "target_um", "true_um", "estimated_um",
                "error_pct", "settle_ms", "v_peak", "limited"):
        assert key in row
    assert row["receptor"] == "pacinian" and row["freq_hz"] == 250.0
    assert row["target_um"] == pytest.approx(0.08 * 10 ** (6 / 20))
    assert row["error_pct"] == pytest.approx(100 * (row["true_um"] / row["target_um"] - 1))
    assert (tmp_path / "plot.png").stat().st_size > 10_000
    from rtctl.trace import TraceReader

    r = TraceReader(tmp_path / "trace")
    # run blocks, the requested stop's 30 ms raised-cosine release, then 0 V while the tips settle
    stop = s["stop"]
    assert stop["by"] == "end" and stop["fade"] == "raised cosine" and stop["fade_s"] == 0.03
    assert 0 < stop["settle_s"] <= 0.5
    assert r.n_blocks == math.ceil(0.5 * 48000 / 32) + 45 + round(stop["settle_s"] * 48000 / 32)
    drive = r.signal("drive")
    assert np.all(drive[:, (750 + 45) * 32 - 1:] == 0.0) and np.any(drive[:, (750 + 44) * 32] != 0.0)
    rows = r.layout["meta"]["sensed_rows"]
    assert len(rows) == r.signal("sensed").shape[0]
    assert rows[:3] == ["lateral.0.seg0", "lateral.0.seg1", "lateral.1.seg0"]


def test_run_amplitude_matches_the_continuous_model(capsys, tmp_path):
    """The whole pipeline (scene -> rig -> loop -> trace -> report) against the plant's own
    continuous frequency response, evaluated independently of the kernels."""
    from rtctl import scene
    from rtctl.models import Models
    from rtctl.plant.bimorph import BimorphPlant
    from rtctl.plant.frontend import Amplifier, CurrentSense

    code, out, _ = run_cli(capsys, "run", "line-bimorph-5", "--duration", "1.0", "--out", str(tmp_path),
                           "--json", "--no-plot")
    assert code == 0
    s = scene.load("line-bimorph-5")
    g = s.group("lateral")
    m = Models(s)
    plant = BimorphPlant(m.beam(g), Amplifier(g.amplifier.bandwidth),
                         CurrentSense(g.sense.shunt, g.sense.aa_cutoff), m.finger(g), n_modes=g.beam.modes)
    rows = json.loads(out)["channels"]
    for i in (2, 3, 4):  # 40, 120, 250 Hz: settled within the 1 s run
        t = s.stimulus.tones[i]
        h = abs(plant.frequency_response([t.freq])[0, 0])
        assert rows[i]["true_um"] == pytest.approx(_um(h * t.voltage), rel=5e-3), i


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("connection", ["series", "parallel"])
def test_model_agrees_with_closed_forms_on_unseen_beams(capsys, seed, connection):
    """Random geometry and a material defined on the command line (not in the repo): clamped-free
    frequencies within 0.5 %, Smits-Choi statics within 1 % (docs/references.md)."""
    rng = np.random.default_rng(100 + seed)
    L, w, t = rng.uniform(5e-3, 40e-3), rng.uniform(0.5e-3, 8e-3), rng.uniform(0.05e-3, 0.6e-3)
    E, d31, eps, rho = (rng.uniform(5e9, 120e9), rng.uniform(-400e-12, 400e-12), rng.uniform(200, 4000),
                        rng.uniform(1500, 9000))
    eps = max(eps, 3 * d31**2 * E / EPS0)  # a physical material: k31^2 <= 1/3
    sets = [f"materials.X.E={E!r}", f"materials.X.d31={d31!r}", f"materials.X.eps33T={eps!r}",
            f"materials.X.rho={rho!r}", f"actuator.lateral.beam.length={L!r}", f"actuator.lateral.beam.width={w!r}",
            f"actuator.lateral.beam.connection={connection}", "actuator.lateral.beam.segments=[1.0]",
            f'actuator.lateral.beam.layers=[{{material = "X", thickness = {t!r}}}, '
            f'{{material = "X", thickness = {t!r}}}]']
    args = ["model", "line-bimorph-5", "--json"] + [a for s in sets for a in ("--set", s)]
    code, out, err = run_cli(capsys, *args)
    assert code == 0, err
    f = json.loads(out)["actuators"]["lateral"]
    h = 2 * t
    s11 = 1 / E
    EI, rhoA = E * w * h**3 / 12, rho * w * h
    fn = CANTILEVER_ROOTS**2 / (2 * np.pi * L**2) * np.sqrt(EI / rhoA)
    np.testing.assert_allclose(f["natural_frequencies_hz"], fn, rtol=5e-3)
    k = 1 if connection == "series" else 2  # parallel doubles the V column and the charge row
    k31 = d31**2 * E / (EPS0 * eps)
    cap = eps * EPS0 * w * L * (1 - k31 / 4) / h * (1 if connection == "series" else 4)
    assert f["static_compliance_m_per_n"] == pytest.approx(4 * s11 * L**3 / (w * h**3), rel=1e-2)
    assert f["deflection_per_volt_m"] == pytest.approx(k * 3 * abs(d31) * L**2 / (2 * h**2), rel=1e-2)
    assert f["blocked_force_per_volt_n"] == pytest.approx(k * 3 * abs(d31) * w * h / (8 * s11 * L), rel=1e-2)
    assert f["capacitance_f"] == pytest.approx(cap, rel=1e-2)


def test_loaded_frequencies_match_the_tip_mass_and_spring_equation(capsys):
    """With the finger reduced to skin mass and a spring (no Maxwell branches), the loaded
    frequencies must solve 1 + cos l cosh l + mu l (...) + K (...) = 0 for mass and spring."""
    sets = ["finger.lateral.branches=[]", "finger.lateral.mass=5e-5", "finger.lateral.k0=800.0",
            "actuator.lateral.beam.damping=0.0"]
    code, out, _ = run_cli(capsys, "model", "line-bimorph-5", "--json", *[a for s in sets for a in ("--set", s)])
    f = json.loads(out)["actuators"]["lateral"]
    L, w, h, E, rho = 15e-3, 1.5e-3, 0.6e-3, 1 / 16.4e-12, 7750.0
    EI, rhoA = E * w * h**3 / 12, rho * w * h
    K, mu = 800.0 * L**3 / EI, 5e-5 / (rhoA * L)
    # combined tip mass + spring: the frequency equation with both terms (docs/references.md forms)
    from scipy.optimize import brentq

    def char(l):
        c, ch, s, sh = np.cos(l), np.cosh(l), np.sin(l), np.sinh(l)
        k_eff = K - mu * l**4  # a tip mass acts as a negative spring -m w^2 = -mu l^4 EI/L^3
        return l**3 * (1 + c * ch) + k_eff * (s * ch - c * sh)

    grid = np.linspace(0.5, 12, 4000)
    vals = [char(x) for x in grid]
    roots = [brentq(char, a, b) for a, b, va, vb in zip(grid, grid[1:], vals, vals[1:]) if va * vb < 0][:2]
    want = np.array(roots) ** 2 / (2 * np.pi * L**2) * np.sqrt(EI / rhoA)
    np.testing.assert_allclose(f["loaded_natural_frequencies_hz"][:2], want, rtol=1e-3)
    assert loaded_root(mu=1.0) == pytest.approx(1.247917, rel=1e-6)  # the helper itself is sane


def test_fault_ends_the_run_with_status_1_and_a_readable_trace(capsys, tmp_path):
    sets = ["actuator.lateral.limits.temperature=25.0001", "actuator.lateral.limits.thermal_tau=0.001",
            "actuator.lateral.limits.loss_tangent=0.5"]
    code, out, err = run_cli(capsys, "run", "line-bimorph-5", "--out", str(tmp_path), "--no-plot",
                             *[a for s in sets for a in ("--set", s)])
    assert code == 1
    assert "rtctl: fault:" in err and "over temperature" in err and "faded to 0 V" in err
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["duration_s"] < 0.1 and s["faults"]
    from rtctl.trace import TraceReader

    d = TraceReader(tmp_path / "trace").signal("drive")
    assert np.all(d[:, -1] == 0.0)
