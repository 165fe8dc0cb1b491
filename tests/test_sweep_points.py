"""The metrics of one sweep point against the package's own single-point paths (``rtctl model``'s
facts, the transfer-matrix response the controller uses, ``rtctl selfsense``'s case, a run) and
against closed forms (Euler-Bernoulli, Smits & Choi, a cantilever on a tip spring and mass)."""

import math

import numpy as np
import pytest
from closed_forms import closed_forms, loaded_root

from rtctl import scene
from rtctl.model_report import model_facts
from rtctl.models import Models
from rtctl.perception import RECEPTORS
from rtctl.plant.beam import BeamSpec, Layer
from rtctl.plant.materials import BUILTIN
from rtctl.sweep import points
from rtctl.sweep.job import sweep
from rtctl.sweep.spec import parse, product

THICK = "actuator.lateral.beam.layers.0.thickness,actuator.lateral.beam.layers.1.thickness"
GRID = [parse("actuator.lateral.beam.length=8e-3:24e-3:3"), parse(f"{THICK}=[0.15e-3, 0.3e-3]")]


def spec_of(s) -> BeamSpec:
    """The scene's beam as the closed forms read it (two equal PZT-5A layers)."""
    b = s.actuator[0].beam
    pzt = BUILTIN["PZT-5A"]
    return BeamSpec(b.length, b.width, tuple(Layer(pzt, x.thickness) for x in b.layers), b.connection,
                    tuple(b.segments), b.damping, b.elements)


def test_model_metrics_are_rtctl_model_facts_point_by_point():
    for p in product(GRID):
        s = scene.load("line-bimorph-5", list(p.overrides))
        m = points.metrics(s, ["model"])
        f = model_facts(s)["lateral"]  # `rtctl model`'s own path, transfer-matrix check included
        assert [m[f"lateral.f{i}_hz"] for i in range(1, 5)] == f["natural_frequencies_hz"]
        assert [m[f"lateral.f{i}_loaded_hz"] for i in range(1, 5)] == f["loaded_natural_frequencies_hz"]
        for k in ("static_compliance_m_per_n", "deflection_per_volt_m", "blocked_force_per_volt_n", "capacitance_f"):
            assert m[f"lateral.{k}"] == f[k]
        # and the finite-element first modes agree with the transfer-matrix twin (another model)
        assert m["lateral.f1_hz"] == pytest.approx(f["tmm_natural_frequencies_hz"][0], rel=1e-6)
        assert m["lateral.f1_loaded_hz"] == pytest.approx(f["tmm_loaded_natural_frequencies_hz"][0], rel=1e-5)


def test_model_metrics_against_euler_bernoulli_and_smits_choi():
    for p in product(GRID):
        s = scene.load("line-bimorph-5", list(p.overrides))
        m = points.metrics(s, ["model"])
        cf = closed_forms(spec_of(s))
        # f1 = 1.8751^2 / (2 pi L^2) sqrt(EI / rho A): 24 Hermite elements are 2.6e-8 high
        # (docs/physics.md 1.11), whatever the beam's length and thickness
        assert m["lateral.f1_hz"] == pytest.approx(cf["frequencies_hz"][0], rel=1e-6)
        assert m["lateral.f2_hz"] == pytest.approx(cf["frequencies_hz"][1], rel=1e-5)
        # Smits & Choi (parallel): static tip values are nodally exact in Hermite elements
        assert m["lateral.static_compliance_m_per_n"] == pytest.approx(cf["table"][1, 1], rel=1e-9)
        assert m["lateral.deflection_per_volt_m"] == pytest.approx(abs(cf["table"][1, 2]), rel=1e-9)
        assert m["lateral.blocked_force_per_volt_n"] == pytest.approx(abs(cf["blocked_force"]), rel=1e-9)
        assert m["lateral.capacitance_f"] == pytest.approx(cf["capacitance"], rel=1e-9)


def test_loaded_frequency_against_the_tip_spring_and_mass_equation():
    # A finger that is a pure spring k0 with the skin mass m (no Maxwell branches) on an undamped
    # beam: the cantilever's characteristic equation with tip spring K = k0 L^3/EI and tip mass
    # mu = m / (rho A L) (docs/references.md), l^2 / (2 pi L^2) sqrt(EI / rho A).
    sets = ["finger.lateral.branches=[]", "finger.lateral.k0=2000", "finger.lateral.mass=2e-4",
            "actuator.lateral.beam.damping=0"]
    for p in product(GRID):
        s = scene.load("line-bimorph-5", [*sets, *p.overrides])
        m = points.metrics(s, ["model"])
        cf = closed_forms(spec_of(s))
        L = s.actuator[0].beam.length
        lam = loaded_root(K=2000 * L**3 / cf["EI"], mu=2e-4 / (cf["rhoA"] * L))
        f1 = lam**2 / (2 * math.pi * L**2) * math.sqrt(cf["EI"] / cf["rhoA"])
        assert m["lateral.f1_loaded_hz"] == pytest.approx(f1, rel=1e-5)


def test_reach_at_0p1_hz_is_the_static_tip_on_the_finger_spring():
    # 0.1 Hz, far below every resonance: the tip on a spring k0 moves V d / (1 + c k0) (Smits &
    # Choi's free deflection d per volt and compliance c), up to (f / f1)^2 < 2e-7 of dynamics
    # (f1 >= 230 Hz on this grid); 0.1 Hz is a Ruffini tone (0-15 Hz, 300 um)
    sets = ["finger.lateral.branches=[]", "stimulus.tones.0.freq=0.1"]
    for p in product(GRID):
        s = scene.load("line-bimorph-5", [*sets, *p.overrides])
        m = points.metrics(s, ["reach"])
        cf = closed_forms(spec_of(s))
        vmax, k0 = s.actuator[0].max_voltage, s.finger.lateral.k0
        x = vmax * abs(cf["table"][1, 2]) / (1.0 + cf["table"][1, 1] * k0)
        assert m["ruffini.reach_um"] == pytest.approx(x * 1e6, rel=1e-6)
        thr = RECEPTORS["ruffini"][2]
        assert m["ruffini.threshold_um"] == pytest.approx(thr * 1e6)
        assert m["ruffini.margin_db"] == pytest.approx(20 * math.log10(x / thr), abs=1e-4)
        assert m["ruffini.felt"] == (x >= thr)
        assert m["ruffini.needed_v"] == pytest.approx(vmax * thr / x, rel=1e-6)
        assert m["ruffini.freq_hz"] == 0.1 and m["ruffini.channel"] == "lateral.0"


def test_reach_at_2_hz_is_the_static_tip_on_the_maxwell_finger():
    # The scene's 2 Hz Ruffini tone under its generalized Maxwell finger, whose stiffness at w is
    # K = k0 + sum k_i j w tau_i / (1 + j w tau_i) - m w^2 (docs/physics.md): the tip moves
    # |V d / (1 + c K)|, up to (f / f1)^2 < 2.3e-5 of beam dynamics on this grid (loaded f1 >= 420 Hz).
    # docs/sweep.md's worked example rests on this form.
    w = 2 * math.pi * 2.0
    for p in product(GRID):
        s = scene.load("line-bimorph-5", list(p.overrides))
        f = s.finger.lateral
        K = f.k0 + sum(b.k * 1j * w * b.tau / (1 + 1j * w * b.tau) for b in f.branches) - f.mass * w**2
        cf = closed_forms(spec_of(s))
        x = abs(s.actuator[0].max_voltage * cf["table"][1, 2] / (1.0 + cf["table"][1, 1] * K))
        assert points.metrics(s, ["reach"])["ruffini.reach_um"] == pytest.approx(x * 1e6, rel=3e-5)


def test_reach_agrees_with_the_transfer_matrix_response_under_the_maxwell_finger():
    # The controller's model (transfer-matrix beam under the finger, amplifier pole: rig.py) is
    # another model of the same beam: both must give the same tip per volt at every tone.
    from rtctl.selfsense.tmm import TMMBeam

    for over in ([], ["actuator.lateral.beam.length=0.02", "finger.preload=1.96"]):
        s = scene.load("line-bimorph-5", over)
        m = points.metrics(s, ["reach"])
        g = s.actuator[0]
        models = Models(s)
        beam = TMMBeam.from_fe(models.beam(g))
        best = {}
        for t in s.stimulus.tones:
            amplifier = abs(1 + 1j * t.freq / g.amplifier.bandwidth)
            tip = abs(beam.response([t.freq], models.finger(g))["tip"][0]) / amplifier
            best[t.receptor] = max(best.get(t.receptor, 0.0), tip * g.max_voltage * 1e6)
        assert set(best) == {"ruffini", "merkel", "meissner", "pacinian"}
        for r, um in best.items():
            assert m[f"{r}.reach_um"] == pytest.approx(um, rel=1e-4), r
        # meissner has two tones (40, 120 Hz): the larger one is reported
        assert m["meissner.freq_hz"] in (40.0, 120.0)


def test_reach_of_a_beat_pair_and_without_contact():
    s = scene.load("line-bimorph-5", ["stimulus.tones.4.beat=20"])
    m = points.metrics(s, ["reach"])
    g = s.actuator[0]
    from rtctl.plant.bimorph import BimorphPlant
    from rtctl.plant.frontend import Amplifier, CurrentSense

    models = Models(s)
    plant = BimorphPlant(models.beam(g), Amplifier(g.amplifier.bandwidth), CurrentSense(100.0, 20e3),
                         models.finger(g), n_modes=g.beam.modes)
    h = np.abs(plant.frequency_response([240.0, 260.0])[:, 0])
    # two tones of half the voltage each, in phase at the envelope's peak
    assert m["pacinian.reach_um"] == pytest.approx(1e6 * g.max_voltage / 2 * h.sum(), rel=1e-12)
    lifted = points.metrics(scene.load("line-bimorph-5", ["finger.contact=false"]), ["reach"])
    assert lifted["pacinian.reach_um"] > 0.08 and lifted["pacinian.felt"] is False  # in air: felt by no one


def test_a_failing_point_is_a_row_with_its_error():
    text = scene.resolve("line-bimorph-5").read_text()
    task = {"text": text, "origin": "line-bimorph-5.toml", "set": [], "what": ("model",), "runner": None,
            "points": [[0, ["actuator.lateral.beam.length=0.015"]], [1, ["actuator.lateral.beam.length=-1"]],
                       # valid, but the beam model refuses it (ModelError: ill-conditioned mass matrix)
                       [2, ["actuator.lateral.beam.segments=[1e-7, 0.9999999]"]]]}
    rows = points.compute(task)
    assert [r["index"] for r in rows] == [0, 1, 2]
    assert rows[0]["error"] is None and rows[0]["metrics"]["lateral.f1_hz"] > 0
    assert rows[1]["metrics"] == {} and "actuator.lateral.beam.length = -1" in rows[1]["error"]
    assert rows[2]["metrics"] == {} and "numerically unsafe" in rows[2]["error"] and "\n" not in rows[2]["error"]


def test_check_refuses_what_a_scene_cannot_answer():
    from rtctl.errors import RtctlError

    with pytest.raises(RtctlError, match="needs a bimorph"):
        points.check(scene.load("solenoid-3x3"), ["model"])
    with pytest.raises(RtctlError, match="reach needs a sine tone"):
        points.check(scene.load("solenoid-3x3"), ["reach"])
    with pytest.raises(RtctlError, match="simulated rig"):
        points.check(scene.load("line-bimorph-5", ["io.backend=audio"]), ["run"])
    points.check(scene.load("line-bimorph-5"), points.WHATS)


@pytest.mark.slow
def test_selfsense_and_run_points_are_their_single_point_paths(tmp_path):
    # one point each, in this process: the observer's case (rtctl selfsense's run_case) and a
    # whole run through the engine's run, handed over as the command line does
    from rtctl.engine.run import run
    from rtctl.selfsense.sweep import run_case, truth_modes

    sets = ["timing.duration=0.2", "stimulus.tones=[{channel = 0, freq = 250.0, voltage = 1.0, "
            "receptor = \"pacinian\"}]"]
    res = sweep("line-bimorph-5", ["actuator.lateral.beam.length=[0.015]"], "selfsense,run", sets,
                out=tmp_path / "s", workers=0, runner=run, plot=False)
    assert not res.failed, res.failed
    row = res.rows[0]
    s = scene.load("line-bimorph-5", [*sets, "actuator.lateral.beam.length=0.015"])
    g = s.actuator[0]
    models = Models(s)
    fe = models.beam(g)
    case = run_case(fe, models.finger(g), [250.0], [10.0], fs=s.timing.fs, block=s.timing.block,
                    amplifier_hz=g.amplifier.bandwidth, aa_cutoff_hz=g.sense.aa_cutoff, aa_order=g.sense.aa_order,
                    shunt=g.sense.shunt, n_modes=truth_modes(fe, s.timing.fs, g.beam.modes))
    assert row["lateral.amp_err_pct"] == case["amp_err_pct"]
    assert row["lateral.force_err_pct"] == case["force_err_pct"]
    summary = run(s, out_dir=tmp_path / "r", plot=False).summary
    ch = summary["channels"][0]
    assert row["lateral.0.true_um"] == ch["true_um"] and row["lateral.0.felt"] == ch["felt"]
    assert row["faults"] == 0 and row["fault"] is None
