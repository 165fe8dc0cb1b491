"""`io.mismatch`: the simulated device differs from the rig's models by factors only it knows.

(a) no mismatch, no change, to the bit; (b) each factor moves what it should, checked against
closed forms of a uniform beam, a parallel-plate capacitor and the Maxwell finger; (c) the secret
stays in the simulated device: no other module reads it, and a rig's limiter and observer are the
same with and without it while its simulated truth is not.
"""

import ast
import math
from pathlib import Path

import numpy as np
import pytest

import rtctl
from rtctl import scene
from rtctl.engine.rig import build
from rtctl.errors import SceneError
from rtctl.io.sim import build_group, device_models
from rtctl.models import FACTORS, Models
from rtctl.plant.facts import loaded_natural_frequencies
from rtctl.plant.materials import EPS0

ALL_ONES = [f"io.mismatch.{k}=1.0" for k in FACTORS]
BIG = ["io.mismatch.thickness=1.3", "io.mismatch.E=0.7", "io.mismatch.d31=1.2", "io.mismatch.eps33T=1.5",
       "io.mismatch.rho=1.2", "io.mismatch.damping=3.0", "io.mismatch.finger_k0=2.0",
       "io.mismatch.finger_mass=2.0", "io.mismatch.finger_branches=0.5"]


def run_blocks(rig, n=120):
    """Sensed currents and true tip states of ``n`` blocks."""
    sensed, truth = [], []
    for k in range(n):
        rig.apply_schedule(k)
        rig.advance()
        sensed.append(rig.sensed.copy())
        truth.append(rig.truth.copy())
    return np.concatenate(sensed, axis=1), np.concatenate(truth, axis=2)


def device(overrides):
    s = scene.load("line-bimorph-5", overrides)
    return s, device_models(s), Models(s)


# --- (a) no mismatch: the bundled run is bitwise unchanged ---------------------------------------

def test_no_mismatch_is_bitwise_the_nominal_run(monkeypatch):
    ref = run_blocks(build(scene.load("line-bimorph-5")))
    ones = run_blocks(build(scene.load("line-bimorph-5", ALL_ONES)))
    # the factor path itself with every factor 1 (device_models would skip it): x * 1.0 == x
    monkeypatch.setattr("rtctl.io.sim.device_models", lambda s, nominal=None: Models(s, dict.fromkeys(FACTORS, 1.0)))
    forced = run_blocks(build(scene.load("line-bimorph-5")))
    monkeypatch.undo()
    # and the comparison sees a change of one part in a million
    tiny = run_blocks(build(scene.load("line-bimorph-5", ["io.mismatch.thickness=1.000001"])))
    for got in (ones, forced):
        assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])
    assert not np.array_equal(tiny[0], ref[0]) and not np.array_equal(tiny[1], ref[1])


def test_device_models_without_mismatch_are_the_rigs_own():
    s = scene.load("line-bimorph-5", ALL_ONES)
    nominal = Models(s)
    assert device_models(s, nominal) is nominal and device_models(s).factors == {}


# --- (b) each factor moves what it should --------------------------------------------------------

def f1(models, g):
    return models.beam(g).modes(1)[0][0]


def test_E_moves_the_free_frequency_by_its_square_root():
    s, dev, nom = device(["io.mismatch.E=1.1"])
    g = s.actuator[0]
    assert f1(dev, g) / f1(nom, g) == pytest.approx(math.sqrt(1.1), rel=1e-8)  # eigh's rounding: 1e-9
    # and the device's beam is the Euler-Bernoulli cantilever of the scaled modulus: f1 =
    # 1.8751^2 / (2 pi L^2) sqrt(E I / (rho A)), uniform section (both layers PZT-5A)
    b, m = g.beam, dev.materials()["PZT-5A"]
    h = sum(layer.thickness for layer in b.layers)
    beta = 1.8751040687119611  # first root of 1 + cos x cosh x = 0
    want = beta**2 / (2 * math.pi * b.length**2) * math.sqrt(m.E * h**2 / (12 * m.rho))
    assert m.E == pytest.approx(1.1 / 16.4e-12, rel=1e-15)
    assert f1(dev, g) == pytest.approx(want, rel=1e-6)  # 24 Hermite elements: 3e-9 here


def test_thickness_scales_the_frequency_and_inverts_the_capacitance():
    s, dev, nom = device(["io.mismatch.thickness=1.2"])
    g = s.actuator[0]
    assert f1(dev, g) / f1(nom, g) == pytest.approx(1.2, rel=1e-8)      # sqrt(E t^3 / (rho t)) / L^2
    # parallel plates, t -> 1.2 t: every capacitance term (blocked and motional, Theta^2 / K) ~ 1/t
    assert dev.beam(g).capacitance() / nom.beam(g).capacitance() == pytest.approx(1 / 1.2, rel=1e-9)
    assert dev.drive_load(g)[0] == dev.beam(g).capacitance()


def test_rho_scales_the_frequency_by_its_inverse_square_root():
    s, dev, nom = device(["io.mismatch.rho=1.3"])
    g = s.actuator[0]
    assert f1(dev, g) / f1(nom, g) == pytest.approx(1.3 ** -0.5, rel=1e-8)  # eigh's rounding: 1e-9


def test_d31_scales_the_deflection_per_volt():
    s, dev, nom = device(["io.mismatch.d31=0.8"])
    g = s.actuator[0]
    # moment per volt ~ d31 E; the short-circuit stiffness does not see d31
    assert dev.beam(g).deflection_per_volt() / nom.beam(g).deflection_per_volt() == pytest.approx(0.8, rel=1e-9)
    assert f1(dev, g) == f1(nom, g)


def test_eps33T_adds_its_parallel_plate_capacitance():
    s, dev, nom = device(["io.mismatch.eps33T=1.5"])
    g = s.actuator[0]
    b = g.beam
    # blocked permittivity eps0 eps33T - d31^2 E: only the first term moves; the coupling term
    # does not see eps33T. Layers in parallel, each a plate of w L / t.
    want = 0.5 * EPS0 * 1700.0 * b.width * b.length * sum(1.0 / layer.thickness for layer in b.layers)
    got = dev.beam(g).capacitance() - nom.beam(g).capacitance()
    assert got == pytest.approx(want, rel=1e-9)


def test_finger_factors_move_the_loaded_frequency_the_right_way():
    s, dev, nom = device(["io.mismatch.finger_k0=3.0"])
    g = s.actuator[0]
    base = loaded_natural_frequencies(nom.beam(g), nom.finger(g), 1)[0]
    stiffer = loaded_natural_frequencies(dev.beam(g), dev.finger(g), 1)[0]
    _, heavy, _ = device(["io.mismatch.finger_mass=10.0"])
    heavier = loaded_natural_frequencies(heavy.beam(g), heavy.finger(g), 1)[0]
    assert stiffer > base * 1.01 and heavier < base * 0.99
    # the device's beam is untouched by the finger's factors
    assert f1(dev, g) == f1(nom, g)


def test_finger_branches_scale_the_branch_stiffness_only():
    s, dev, nom = device(["io.mismatch.finger_branches=0.5"])
    g = s.actuator[0]
    w = 2 * math.pi * 40.0
    # K(w) = -m w^2 + k0 + sum k_i j w tau_i / (1 + j w tau_i): the scene's finger, by hand
    branches = [(300.0, 0.004), (150.0, 0.07), (80.0, 1.4)]
    want = -1e-4 * w**2 + 300.0 + sum(0.5 * k * 1j * w * t / (1 + 1j * w * t) for k, t in branches)
    assert complex(dev.finger(g).dynamic_stiffness(w)) == pytest.approx(want, rel=1e-12)
    assert nom.finger(g).branches == tuple(branches)


def test_damping_scales_the_simulated_plants_modal_damping_ratio():
    s, dev, nom = device(["io.mismatch.damping=4.0", "finger.contact=false"])
    g = s.actuator[0]

    def ratios(models):
        # the simulated plant's poles of its first three beam modes, -zeta w_n +- j w_n
        # sqrt(1 - zeta^2) (its other poles: amplifier, anti-alias filter)
        plant = build_group(models, g, 0, 48000.0, 32).plant
        lam = np.linalg.eigvals(plant.sys.A)
        osc = [lam[np.argmin(np.abs(np.abs(lam) - 2 * np.pi * f))] for f in plant.modes_hz[:3]]
        return np.array([-z.real / abs(z) for z in osc])

    np.testing.assert_allclose(ratios(nom), 0.01, rtol=1e-6)
    np.testing.assert_allclose(ratios(dev), 0.04, rtol=1e-6)


def test_impossible_factors_are_refused_naming_the_key():
    with pytest.raises(SceneError, match="io.mismatch.thickness"):
        scene.load("line-bimorph-5", ["io.mismatch.thickness=0"])
    with pytest.raises(SceneError, match="io.mismatch.E"):
        scene.load("line-bimorph-5", ["io.mismatch.E=-1"])
    # PZT-5A's k31^2 = 0.118: d31 x 3 would make it 1.07, a negative clamped permittivity
    with pytest.raises(SceneError, match=r"io.mismatch \(d31 = 3\).*k31\^2"):
        device_models(scene.load("line-bimorph-5", ["io.mismatch.d31=3"]))


# --- (c) the secret stays secret -----------------------------------------------------------------

ROOT = Path(rtctl.__file__).parent
#: modules that may read the scene's io.mismatch: the simulated devices, the schema, the report
SCENE_READERS = {"io/sim.py", "emulate/audio.py", "emulate/serial.py", "schema.py", "engine/report.py"}
#: (module, function) that only remove the table from a recorded scene: `rtctl replay --mode plant`
#: runs the scene's model (no secret) against what a device recorded
SCENE_ERASERS = {("engine/replay/__init__.py", "scene_of")}
#: (module, function) that may build a simulated device's models; None: anywhere in the module
DEVICE_BUILDERS = {("io/sim.py", None), ("emulate/audio.py", None), ("emulate/serial.py", None),
                   ("engine/rig.py", "_build_sim")}


def secret_refs(source: str):
    """``(what, enclosing function)`` of every reference to the scene's mismatch table and to
    ``device_models`` in ``source``."""
    tree = ast.parse(source)
    out = []

    def visit(node, fn):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            fn = node.name
        table = (  # scene.io.mismatch, scene.io["mismatch"], getattr(x, "mismatch"), "io.mismatch..."
            isinstance(node, ast.Attribute) and node.attr == "mismatch"
            or isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant)
            and node.slice.value == "mismatch" and "io" in ast.unparse(node.value).split(".")
            or isinstance(node, ast.Call) and ast.unparse(node.func) == "getattr"
            and any(isinstance(a, ast.Constant) and a.value == "mismatch" for a in node.args)
            or isinstance(node, ast.Constant) and isinstance(node.value, str) and "io.mismatch" in node.value)
        builder = (isinstance(node, ast.Name) and node.id == "device_models"
                   or isinstance(node, ast.Attribute) and node.attr == "device_models"
                   or isinstance(node, ast.alias) and node.name == "device_models"
                   or isinstance(node, ast.FunctionDef) and node.name == "device_models")
        if table:
            out.append(("mismatch", fn))
        if builder:
            out.append(("device_models", fn))
        for child in ast.iter_child_nodes(node):
            visit(child, fn)

    visit(tree, None)
    return out


def test_the_scanner_sees_every_way_in():
    for src in ("x = scene.io.mismatch.E", "x = scene.io['mismatch']", "x = getattr(s.io, 'mismatch')",
                "x = load(s, ['io.mismatch.E=2'])", "from .sim import device_models"):
        assert secret_refs(src), src
    assert not secret_refs("r = case['mismatch']\ndef f(mismatch=None):\n    return mismatch")


def test_only_the_simulated_device_reads_the_mismatch():
    seen = {}
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        for what, fn in secret_refs(path.read_text()):
            seen.setdefault(rel, set()).add((what, fn))
    def emulate(rel):  # the emulators (the device side of hardware-in-the-loop)
        return rel.startswith("emulate/")

    for rel, refs in seen.items():
        for what, fn in refs:
            if what == "mismatch":
                assert rel in SCENE_READERS or (rel, fn) in SCENE_ERASERS or emulate(rel), \
                    f"{rel} ({fn}) reads io.mismatch"
            else:
                assert (rel, None) in DEVICE_BUILDERS or (rel, fn) in DEVICE_BUILDERS or emulate(rel), \
                    f"{rel} ({fn}) builds the simulated device's models"
    assert {("mismatch", "device_models")} <= seen["io/sim.py"]     # the scan is not empty
    assert ("device_models", "_build_sim") in seen["engine/rig.py"]
    # the models take factors and do not know where they come from
    assert "mismatch" not in (ROOT / "models.py").read_text().lower()


def test_the_rig_designs_on_the_nominal_model_while_the_device_differs():
    nominal = build(scene.load("line-bimorph-5", ["control.observe=true"]))
    secret = build(scene.load("line-bimorph-5", ["control.observe=true", *BIG]))
    # what the rig designs from: the limiter's loads, the observers' matrices, the rig's models
    assert np.array_equal(secret.limiter.params, nominal.limiter.params)
    assert len(secret.observers) == len(nominal.observers) > 0
    for a, b in zip(secret.observers, nominal.observers):
        assert np.array_equal(a[1].observer.H, b[1].observer.H)
    assert secret.models.factors == {} and nominal.models.factors == {}
    # what the simulated device is: another beam under another finger
    dev, nom = secret.device.groups[0][0], nominal.device.groups[0][0]
    assert abs(dev.capacitance / nom.capacitance - 1.0) > 0.05
    assert not np.allclose(dev.plant.modes_hz, nom.plant.modes_hz, rtol=1e-3)
    assert dev.plant.finger.k0 == 2 * nom.plant.finger.k0
    s_dev, t_dev = run_blocks(secret, 60)
    s_nom, t_nom = run_blocks(nominal, 60)
    assert np.max(np.abs(t_dev[:, 0] - t_nom[:, 0])) > 0.05 * np.max(np.abs(t_nom[:, 0]))
    assert np.max(np.abs(s_dev - s_nom)) > 0.05 * np.max(np.abs(s_nom))
    # the report may know: the sim backend's summary says what the device hides
    assert secret.device.stats()["mismatch"]["thickness"] == 1.3 and "mismatch" not in nominal.device.stats()
