"""Finite-element bimorph model against closed forms and published numbers.

Every expectation says where it comes from; REFERENCES = docs/references.md.
Closed forms live in tests/closed_forms.py (never in rtctl).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from closed_forms import (
    CANTILEVER_ROOTS,
    CLAMPED_PINNED_ROOT,
    EPS0,
    TIP_MASS_MU1_ROOT,
    cantilever_frequencies,
    closed_forms,
    laminate,
    loaded_root,
)

from rtctl.errors import ModelError
from rtctl.plant.beam import BeamSpec, Layer, SupportSpec, build_beam
from rtctl.plant.facts import model_facts
from rtctl.plant.materials import BUILTIN, Material, material

# rtctl poles each layer so that +V raises the tip for either sign of d31 (beam.py docstring):
# Smits & Choi's signed table maps onto the model with d31 -> |d31|, i.e. the V column and the
# charge row flip with sign(d31).


def convention(table: np.ndarray, d31: float) -> np.ndarray:
    s = math.copysign(1.0, d31)
    flip = np.array([[1.0, 1.0, s], [1.0, 1.0, s], [s, s, 1.0]])
    return table * flip


def bimorph(mat=None, L=15e-3, w=1.5e-3, h=0.6e-3, connection="parallel", segments=(1.0,),
            elements=24, damping=0.01):
    """Two identical layers of total thickness h (the scene example's beam by default)."""
    mat = BUILTIN["PZT-5A"] if mat is None else mat
    return BeamSpec(L, w, (Layer(mat, h / 2), Layer(mat, h / 2)), connection, segments,
                    damping, elements)


def rel(a, b):
    return np.abs(np.asarray(a) / np.asarray(b) - 1.0)


# ---------------------------------------------------------------------------- materials


def test_builtin_coupling_matches_datasheet_k31():
    # Derived k31 = sqrt(d31^2 E / (eps0 eps33T)) from the REFERENCES table must agree with the
    # coupling factor tabulated next to those same constants in the classic Vernitron/Morgan
    # property table (Berlincourt et al.; the origin of Erturk & Inman's Table E.1 values):
    # k31 = 0.34 (PZT-5A) and 0.39 (PZT-5H). 3 % tolerance (two-digit rounding).
    assert math.sqrt(BUILTIN["PZT-5A"].k31_sq) == pytest.approx(0.34, rel=0.03)
    assert math.sqrt(BUILTIN["PZT-5H"].k31_sq) == pytest.approx(0.39, rel=0.03)
    pvdf = BUILTIN["PVDF"]
    assert 2e9 <= pvdf.E <= 4e9 and pvdf.d31 == 23e-12 and pvdf.eps33T in (12.0, 13.0)
    m = BUILTIN["PZT-5A"]
    # e31 = d31 E; permittivity of a uniaxially stressed layer at constant strain
    # eps33S = eps0 eps33T - d31^2 / s11^E (the 1-D reduced constitutive law).
    assert m.e31 == pytest.approx(-171e-12 / 16.4e-12, rel=1e-12)
    assert m.eps33S == pytest.approx(EPS0 * 1700 - (171e-12) ** 2 / 16.4e-12, rel=1e-9)


def test_material_overrides_and_custom_tables():
    assert material("PZT-5A", {"rho": 7800}).rho == 7800.0
    assert material("PZT-5A", {"rho": 7800}).d31 == BUILTIN["PZT-5A"].d31
    assert material("PVDF", {"E": 2e9}).e31 == pytest.approx(0.046, rel=1e-12)  # Tzou's e31
    brass = material("brass", {"E": 100e9, "d31": 0.0, "eps33T": 1.0, "rho": 8500.0})
    assert not brass.is_piezo and brass.k31_sq == 0.0
    with pytest.raises(ModelError, match=r"missing keys: \['eps33T', 'rho'\]"):
        material("PZT-8", {"E": 1e11, "d31": -97e-12})
    with pytest.raises(ModelError, match="unknown keys.*'s11'"):
        material("PZT-5A", {"s11": 16e-12})
    with pytest.raises(ModelError, match="k31"):
        material("PZT-5A", {"d31": -1e-9})  # k31^2 > 1: permittivity units mixed up
    with pytest.raises(ModelError, match="rho"):
        Material(E=1e9, d31=0.0, eps33T=1.0, rho=-1.0)


# ---------------------------------------------------------------------------- frequencies


@pytest.mark.parametrize("name", ["PZT-5A", "PZT-5H", "PVDF"])
@pytest.mark.parametrize("connection", ["series", "parallel"])
def test_clamped_free_frequencies(name, connection):
    # REFERENCES (Euler-Bernoulli cantilever): f_n = l_n^2/(2 pi L^2) sqrt(EI/(rho A)),
    # homogeneous section EI = E w h^3/12, rho A = rho w h. First three within 0.1 %.
    spec = bimorph(BUILTIN[name], connection=connection, segments=(0.5, 0.5))
    f, _ = build_beam(spec).modes(4)
    cf = closed_forms(spec)
    err = rel(f, cf["frequencies_hz"])
    print(f"{name} {connection}: f = {f} Hz, error % = {100 * err}")
    assert np.all(err[:3] < 1e-3)
    assert err[3] < 5e-3  # the fourth is reported; Hermite elements give ~3e-5 at 24 elements


def test_mesh_refinement_converges_from_above_at_fourth_order():
    # Theory: Hermite cubics are conforming for the beam energy, so with the consistent mass
    # matrix the FE is a Rayleigh-Ritz method: every eigenvalue is an upper bound and nested
    # refinements decrease it monotonically, with eigenvalue error O(h^(2(p+1-m))) = O(h^4)
    # (p = 3, m = 2; Strang & Fix, An Analysis of the Finite Element Method, ch. 6).
    L = 15e-3
    f_ref = cantilever_frequencies(BUILTIN["PZT-5A"].E * 1.5e-3 * 0.6e-3**3 / 12,
                                   BUILTIN["PZT-5A"].rho * 1.5e-3 * 0.6e-3, L, 3)
    errs = []
    for n in (4, 8, 16):  # nested meshes; errors stay far above round-off (~1e-10)
        f, _ = build_beam(bimorph(segments=(0.5, 0.5), elements=n)).modes(3)
        errs.append(f / f_ref - 1.0)
    errs = np.array(errs)
    assert np.all(errs > 0.0)  # upper bounds
    assert np.all(np.diff(errs, axis=0) < 0.0)  # monotone decrease
    order = np.log2(errs[:-1] / errs[1:])
    print("observed orders (rows: 4->8, 8->16; columns: modes 1-3):", order)
    assert np.all((order > 3.6) & (order < 4.4))


# ---------------------------------------------------------------------------- Smits & Choi


@pytest.mark.parametrize("name", ["PZT-5A", "PZT-5H", "PVDF"])
@pytest.mark.parametrize("connection", ["series", "parallel"])
def test_smits_choi_table(name, connection):
    # REFERENCES, Smits & Choi 1991: all nine entries (tip rotation/deflection/charge per tip
    # moment/force/volt), blocked force and free capacitance, series as printed and parallel
    # with the V column and charge row doubled, capacitance x4. 0.5 % (Hermite FE is nodally
    # exact for these loads, so the errors are round-off).
    spec = bimorph(BUILTIN[name], connection=connection, segments=(0.5, 0.5))
    fe = build_beam(spec)
    cf = closed_forms(spec)
    d31 = spec.layers[0].material.d31
    G = fe.static_tip_matrix()
    expected = convention(cf["table"], d31)
    err = rel(G, expected)
    print(f"{name} {connection}: max table error {100 * err.max():.2e} %")
    assert np.all(err < 5e-3)
    assert fe.static_compliance() == pytest.approx(cf["table"][1, 1], rel=5e-3)
    assert fe.deflection_per_volt() == pytest.approx(abs(cf["table"][1, 2]), rel=5e-3)
    assert fe.blocked_force_per_volt() == pytest.approx(abs(cf["blocked_force"]), rel=5e-3)
    assert fe.capacitance() == pytest.approx(cf["capacitance"], rel=5e-3)
    assert np.allclose(G, G.T, rtol=1e-9, atol=0)  # Maxwell-Betti reciprocity


def test_series_and_parallel_capacitance_rules():
    # REFERENCES: parallel capacitance is 4x series (blocked and free), V column 2x.
    s = build_beam(bimorph(connection="series"))
    p = build_beam(bimorph(connection="parallel"))
    assert p.Cp.sum() / s.Cp.sum() == pytest.approx(4.0, rel=1e-12)
    assert p.capacitance() / s.capacitance() == pytest.approx(4.0, rel=1e-9)
    assert p.deflection_per_volt() / s.deflection_per_volt() == pytest.approx(2.0, rel=1e-9)
    # Blocked capacitance of a uniaxially stressed layer: eps0 eps33T (1 - k31^2) w L / h (series).
    m = BUILTIN["PZT-5A"]
    assert s.Cp.sum() == pytest.approx(EPS0 * m.eps33T * (1 - m.k31_sq) * 1.5e-3 * 15e-3 / 0.6e-3,
                                       rel=1e-9)


def test_tzou_benchmark_is_the_series_connection():
    # REFERENCES, Tzou's PVDF bimorph: L = 100 mm, b = 5 mm, t = 1 mm, E = 2 GPa,
    # e31 = 0.046 C/m^2, V = 1 V -> w = 3 e31 V L^2/(2 E t^2) = 3.45e-7 m. The voltage is
    # applied across the full thickness (the two layers in series); parallel doubles it.
    pvdf = material("PVDF", {"E": 2e9, "d31": 0.046 / 2e9})
    series = build_beam(bimorph(pvdf, L=0.1, w=5e-3, h=1e-3, connection="series"))
    parallel = build_beam(bimorph(pvdf, L=0.1, w=5e-3, h=1e-3, connection="parallel"))
    print("Tzou:", series.deflection_per_volt(), "m/V (series)")
    assert series.deflection_per_volt() == pytest.approx(3.45e-7, rel=5e-3)
    assert series.deflection_per_volt() == pytest.approx(3 * 0.046 * 0.1**2 / (2 * 2e9 * 1e-6),
                                                         rel=1e-9)
    assert parallel.deflection_per_volt() == pytest.approx(6.9e-7, rel=5e-3)


# ---------------------------------------------------------------------------- tip loads


@pytest.mark.parametrize("K", [0.3, 3.0, 30.0, 300.0, 1e4])
def test_tip_spring_frequency(K):
    # REFERENCES: l^3 (1 + cos l cosh l) + K (sin l cosh l - cos l sinh l) = 0, K = k L^3/EI,
    # solved here with brentq. FE with_tip(k) within 0.1 %.
    spec = bimorph()
    cf = closed_forms(spec)
    f_fe, _ = build_beam(spec).with_tip(k=K * cf["EI"] / spec.length**3).modes(2)
    for mode in (0, 1):
        l_n = loaded_root(K=K, which=mode)
        f_cf = l_n**2 / (2 * math.pi * spec.length**2) * math.sqrt(cf["EI"] / cf["rhoA"])
        assert f_fe[mode] == pytest.approx(f_cf, rel=1e-3)


def test_tip_spring_limit_is_clamped_pinned():
    # REFERENCES: l_1 -> 3.926602 as K -> infinity; l_1 grows monotonically with K.
    roots = [loaded_root(K=K) for K in (0.0, 1.0, 10.0, 100.0, 1e4, 1e8)]
    assert roots[0] == pytest.approx(CANTILEVER_ROOTS[0], rel=1e-9)
    assert np.all(np.diff(roots) > 0)
    assert roots[-1] == pytest.approx(CLAMPED_PINNED_ROOT, abs=2e-6)
    # The FE with a stiff tip spring approaches the clamped-pinned beam too.
    spec = bimorph()
    cf = closed_forms(spec)
    f_fe, _ = build_beam(spec).with_tip(k=1e6 * cf["EI"] / spec.length**3).modes(1)
    f_cp = CLAMPED_PINNED_ROOT**2 / (2 * math.pi * spec.length**2) * math.sqrt(cf["EI"] / cf["rhoA"])
    assert f_fe[0] == pytest.approx(f_cp, rel=1e-3)


@pytest.mark.parametrize("mu", [0.1, 1.0, 10.0])
def test_tip_mass_frequency(mu):
    # REFERENCES: 1 + cos l cosh l + mu l (cos l sinh l - sin l cosh l) = 0, mu = m/(rho A L);
    # mu = 1 gives l_1 = 1.247917. FE with_tip(mass) within 0.1 %.
    if mu == 1.0:
        assert loaded_root(mu=1.0) == pytest.approx(TIP_MASS_MU1_ROOT, abs=1e-6)
    spec = bimorph()
    cf = closed_forms(spec)
    f_fe, _ = build_beam(spec).with_tip(mass=mu * cf["rhoA"] * spec.length).modes(2)
    for mode in (0, 1):
        l_n = loaded_root(mu=mu, which=mode)
        f_cf = l_n**2 / (2 * math.pi * spec.length**2) * math.sqrt(cf["EI"] / cf["rhoA"])
        assert f_fe[mode] == pytest.approx(f_cf, rel=1e-3)


def test_model_facts_with_mass_and_spring():
    # Loaded frequencies: REFERENCES tip-spring equation with the spring's dynamic stiffness
    # k - m omega^2 (mass and spring together, closed_forms.loaded_char). Statics: Smits & Choi.
    spec = bimorph(segments=(0.5, 0.5))
    cf = closed_forms(spec)
    L = spec.length
    mass, k = 0.5 * cf["rhoA"] * L, 20.0 * cf["EI"] / L**3
    facts = model_facts(build_beam(spec), tip_mass=mass, tip_k=k, n=3)
    assert set(facts) == {
        "natural_frequencies_hz", "loaded_natural_frequencies_hz", "static_compliance_m_per_n",
        "deflection_per_volt_m", "blocked_force_per_volt_n", "capacitance_f",
    }
    scale = math.sqrt(cf["EI"] / cf["rhoA"]) / (2 * math.pi * L**2)
    loaded = [loaded_root(K=20.0, mu=0.5, which=i) ** 2 * scale for i in range(3)]
    assert np.all(rel(facts["loaded_natural_frequencies_hz"], loaded) < 1e-3)
    assert np.all(rel(facts["natural_frequencies_hz"], cf["frequencies_hz"][:3]) < 1e-3)
    assert facts["static_compliance_m_per_n"] == pytest.approx(cf["table"][1, 1], rel=5e-3)
    assert facts["deflection_per_volt_m"] == pytest.approx(abs(cf["table"][1, 2]), rel=5e-3)
    assert facts["blocked_force_per_volt_n"] == pytest.approx(abs(cf["blocked_force"]), rel=5e-3)
    assert facts["capacitance_f"] == pytest.approx(cf["capacitance"], rel=5e-3)
    assert all(type(v) is float for key, v in facts.items() if not key.endswith("_hz"))


# ---------------------------------------------------------------------------- random sweep


def _random_material(rng, piezo=True):
    E = 10 ** rng.uniform(math.log10(2e9), math.log10(200e9))
    eps33T = 10 ** rng.uniform(1, 3.7)
    rho = rng.uniform(1000, 9000)
    if not piezo:
        return Material(E=E, d31=0.0, eps33T=eps33T, rho=rho)
    k31_sq = rng.uniform(0.001, 0.5)
    d31 = rng.choice([-1.0, 1.0]) * math.sqrt(k31_sq * EPS0 * eps33T / E)
    return Material(E=E, d31=d31, eps33T=eps33T, rho=rho)


def _random_dims(rng):
    return rng.uniform(5e-3, 50e-3), rng.uniform(0.5e-3, 10e-3)


@pytest.mark.parametrize("seed", range(30), ids=lambda s: f"bimorph-{s}")
def test_random_homogeneous_bimorphs(seed):
    # Materials and geometries not in the repo (REFERENCES ranges: L 5-50 mm, w 0.5-10 mm,
    # layers 0.05-1 mm, E 2-200 GPa, d31 of either sign). Smits & Choi + cantilever roots:
    # frequencies 0.5 %, statics 1 %. The sign of d31 must not change the model (convention).
    rng = np.random.default_rng(seed)
    mat = _random_material(rng)
    L, w = _random_dims(rng)
    t = rng.uniform(0.05e-3, 1e-3)
    conn = ("series", "parallel")[seed % 2]
    spec = BeamSpec(L, w, (Layer(mat, t), Layer(mat, t)), conn, (1.0,), 0.02)
    fe = build_beam(spec)
    cf = closed_forms(spec)
    f, _ = fe.modes(4)
    assert np.all(rel(f, cf["frequencies_hz"]) < 5e-3)
    assert np.all(rel(fe.static_tip_matrix(), convention(cf["table"], mat.d31)) < 1e-2)
    assert fe.blocked_force_per_volt() == pytest.approx(abs(cf["blocked_force"]), rel=1e-2)
    flipped = Material(E=mat.E, d31=-mat.d31, eps33T=mat.eps33T, rho=mat.rho)
    fe2 = build_beam(BeamSpec(L, w, (Layer(flipped, t), Layer(flipped, t)), conn, (1.0,), 0.02))
    assert fe2.deflection_per_volt() == pytest.approx(fe.deflection_per_volt(), rel=1e-12)
    assert fe.deflection_per_volt() > 0


@pytest.mark.parametrize("seed", range(30), ids=lambda s: f"stack-{s}")
def test_random_layered_stacks(seed):
    # General stacks (2-4 layers, passive shims, mixed materials, d31 of either sign) against the
    # continuum laminate solution in closed_forms.laminate (bottom-face reference, floating
    # electrodes for series): all nine static tip entries within 1 %. Frequencies (0.5 %) from
    # the cantilever roots with EI = D - B^2/A for parallel stacks; a series stack of unequal
    # layers is stiffened by its floating electrodes, so only its statics have a closed form.
    rng = np.random.default_rng(1000 + seed)
    n_layers = int(rng.integers(2, 5))
    layers = []
    for i in range(n_layers):
        piezo = i in (0, n_layers - 1) or rng.random() < 0.5
        layers.append(Layer(_random_material(rng, piezo), rng.uniform(0.05e-3, 1e-3)))
    L, w = _random_dims(rng)
    conn = ("series", "parallel")[seed % 2]
    spec = BeamSpec(L, w, tuple(layers), conn, (1.0,), 0.0)
    fe = build_beam(spec)
    lam = laminate(spec)
    err = rel(fe.static_tip_matrix(), lam["table"])
    assert np.all(err < 1e-2), err
    if conn == "parallel":
        f, _ = fe.modes(4)
        assert np.all(rel(f, cantilever_frequencies(lam["EI"], lam["rhoA"], L)) < 5e-3)


def test_unimorph_free_capacitance_includes_axial_stretch():
    # A PZT layer on a steel shim stretches as well as bends; its stress-free capacitance
    # (closed_forms.laminate, zero axial force) is larger than the bending-only value. The model
    # condenses the (quasi-static) stretch into Cp; check against the laminate to 0.5 %.
    steel = Material(E=200e9, d31=0.0, eps33T=1.0, rho=7850.0)
    spec = BeamSpec(20e-3, 2e-3, (Layer(steel, 0.1e-3), Layer(BUILTIN["PZT-5H"], 0.2e-3)),
                    "parallel", (1.0,), 0.01)
    fe = build_beam(spec)
    lam = laminate(spec)
    assert fe.capacitance() == pytest.approx(lam["table"][2, 2], rel=5e-3)
    assert np.all(rel(fe.static_tip_matrix(), lam["table"]) < 5e-3)


def test_series_unequal_layers_voltage_division():
    # Two unequal PZT layers in series share the port voltage by charge balance of the floating
    # middle electrode (closed_forms.laminate), not 50/50; statics within 0.5 %.
    pzt = BUILTIN["PZT-5A"]
    spec = BeamSpec(15e-3, 1.5e-3, (Layer(pzt, 0.2e-3), Layer(pzt, 0.4e-3)), "series",
                    (1.0,), 0.01)
    fe = build_beam(spec)
    assert np.all(rel(fe.static_tip_matrix(), laminate(spec)["table"]) < 5e-3)
    # The thin layer takes about a third (capacitive divider 1/3, moved to ~0.35 by the
    # strain-induced charge), far from the 1/2 an equal split would give.
    f = fe.section.fractions
    assert 0.3 < f[0] < 0.4 and sum(f) == pytest.approx(1.0)


# ---------------------------------------------------------------------------- segments


def test_two_segment_columns_sum_to_single_electrode():
    # With segments [0.5, 0.5] on the same nodes, the two moment pairs cancel at the shared
    # node: the columns sum to the single-electrode Theta; the Cp add up.
    one = build_beam(bimorph(segments=(1.0,)))
    two = build_beam(bimorph(segments=(0.5, 0.5)))
    np.testing.assert_allclose(one.nodes, two.nodes, rtol=0, atol=1e-15)
    assert two.Theta.shape == (one.n_dof, 2)
    np.testing.assert_allclose(two.Theta.sum(axis=1), one.Theta[:, 0], rtol=0,
                               atol=1e-15 * np.abs(one.Theta).max())
    assert two.Cp.sum() == pytest.approx(one.Cp[0], rel=1e-12)
    # Theta spans only the segment's end slopes: zero on every w row.
    w_rows = [two.dof_of(i, "w") for i in range(1, two.nodes.size)]
    assert np.all(two.Theta[w_rows] == 0.0)


@pytest.mark.parametrize("connection", ["series", "parallel"])
def test_unequal_segments(connection):
    split = (0.2, 0.3, 0.5)
    spec = bimorph(connection=connection, segments=split)
    fe = build_beam(spec)
    L = spec.length
    bounds = np.concatenate(([0.0], np.cumsum(split))) * L
    assert np.isin(bounds, fe.nodes).all()  # every boundary is a node
    # Elements go to segments in proportion to length: 24 over (0.2, 0.3, 0.5) is 5, 7, 12,
    # so element lengths stay within 15 % of L/24 (a per-segment equal split would give 3x).
    le = np.diff(fe.nodes)
    assert le.size == 24 and le.max() / le.min() < 1.15 * 1.15
    # Blocked capacitance per segment scales with its length.
    single = build_beam(bimorph(connection=connection))
    np.testing.assert_allclose(fe.Cp / single.Cp[0], split, rtol=1e-12)
    # Tip deflection per volt on segment j alone: the free-beam curvature per volt kappa
    # (Smits & Choi: rotation per volt / L) acts only on [a, b], so
    # w_tip = kappa [(L - a)^2 - (L - b)^2] / 2 (integrate (L - x) w'' over the segment).
    cf = closed_forms(spec)
    kappa = abs(cf["table"][0, 2]) / L
    w_tip = fe.static_solve(fe.Theta)[fe.tip]
    expected = kappa * ((L - bounds[:-1]) ** 2 - (L - bounds[1:]) ** 2) / 2
    assert np.all(rel(w_tip, expected) < 5e-3)
    # Free capacitance matrix: a segment's moment pair is self-equilibrated, so on a cantilever
    # it bends only its own segment: the matrix is diagonal, each entry the free capacitance of
    # a cantilever as long as the segment (Smits & Choi with L -> segment length).
    C = fe.free_capacitance_matrix()
    diag_expected = [closed_forms(bimorph(connection=connection, L=lj))["capacitance"]
                     for lj in np.diff(bounds)]
    assert np.all(rel(np.diag(C), diag_expected) < 5e-3)
    off = C - np.diag(np.diag(C))
    assert np.abs(off).max() < 1e-9 * np.diag(C).min()
    # A tip spring makes the segments interact statically (off-diagonals appear), symmetric.
    Ck = fe.with_tip(k=10 * cf["EI"] / L**3).free_capacitance_matrix()
    assert np.abs(Ck - np.diag(np.diag(Ck))).max() > 1e-3 * np.diag(Ck).min()
    np.testing.assert_allclose(Ck, Ck.T, rtol=1e-12, atol=0)


# ---------------------------------------------------------------------------- support


def test_elastic_support_limits_and_compliance():
    spec = bimorph()
    cf = closed_forms(spec)
    EI, L = cf["EI"], spec.length
    clamped = build_beam(spec)
    f_c, _ = clamped.modes(4)
    # k, k_rot -> inf recovers the clamped beam: the frequency shift falls like the root
    # compliance relative to the beam's, 1/scale (first-order perturbation).
    shifts = []
    for scale in (1e4, 1e6, 1e8):
        stiff = build_beam(spec, SupportSpec("elastic", k=scale * EI / L**3, k_rot=scale * EI / L))
        shifts.append(rel(stiff.modes(4)[0], f_c))
        assert stiff.static_compliance() == pytest.approx(clamped.static_compliance(),
                                                          rel=10 / scale)
    assert np.all(shifts[2] < 1e-5)  # at 1e8 the shift nears the eigensolver's round-off
    ratio = shifts[0] / shifts[1]  # 100 for a first-order effect; higher modes feel 2nd order
    np.testing.assert_allclose(ratio[:2], 100.0, rtol=0.02)
    assert np.all(ratio > 50.0)
    assert build_beam(spec, SupportSpec("elastic")).modes(4)[0] == pytest.approx(f_c, rel=1e-12)
    # Finite springs: the root translates F/k and rotates F L/k_rot (statics), so the tip
    # compliance is L^3/(3 EI) + 1/k + L^2/k_rot (REFERENCES tip-force formula + rigid body).
    k, k_rot = 3 * EI / L**3, 2 * EI / L
    soft = build_beam(spec, SupportSpec("elastic", k=k, k_rot=k_rot))
    assert soft.static_compliance() == pytest.approx(L**3 / (3 * EI) + 1 / k + L**2 / k_rot,
                                                     rel=1e-6)
    # The piezo moment pair is self-equilibrated: the support carries nothing, so the deflection
    # per volt is the clamped one.
    assert soft.deflection_per_volt() == pytest.approx(clamped.deflection_per_volt(), rel=1e-6)
    # Softer support, lower frequencies (Rayleigh quotient with less stiffness), monotonically.
    prev = f_c
    for scale in (1e4, 1e2, 1.0, 1e-2):
        f, _ = build_beam(spec, SupportSpec("elastic", k=scale * EI / L**3,
                                            k_rot=scale * EI / L)).modes(4)
        assert np.all(f < prev)
        prev = f
    # Pinned root with a rotational spring: k = inf keeps only the root slope DOF.
    pinned = build_beam(spec, SupportSpec("elastic", k=math.inf, k_rot=k_rot))
    with pytest.raises(ModelError, match="fixed"):
        pinned.dof_of(0, "w")
    assert pinned.static_compliance() == pytest.approx(L**3 / (3 * EI) + L**2 / k_rot, rel=1e-6)


@pytest.mark.parametrize("k,k_rot,bad", [(0.0, 0.0, "k"), (0.0, 1.0, "k"), (1e3, 0.0, "k_rot")])
def test_mechanism_raises(k, k_rot, bad):
    with pytest.raises(ModelError, match=rf"SupportSpec\.{bad} = 0 .*mechanism"):
        build_beam(bimorph(), SupportSpec("elastic", k=k, k_rot=k_rot))


# ---------------------------------------------------------------------------- conventions


def test_sign_conventions_and_reciprocity():
    fe = build_beam(bimorph(segments=(0.5, 0.5)))
    # +V raises the tip; Theta's tip slope entry is positive (distal end of the last segment).
    assert fe.deflection_per_volt() > 0
    assert fe.Theta[fe.tip_rot, 1] > 0 and fe.Theta[fe.tip_rot, 0] == 0.0
    mid = fe.dof_of(int(fe.segment_nodes[1]), "psi")
    assert fe.Theta[mid, 0] > 0 and fe.Theta[mid, 1] < 0
    # Shorted electrodes, tip pushed up by 1 N: Q = Theta^T q > 0 and equals the deflection per
    # volt (reciprocity: Q = Theta^T K^-1 e_tip = (K^-1 Theta)_tip).
    e = np.zeros(fe.n_dof)
    e[fe.tip] = 1.0
    Q = fe.Theta.T @ fe.static_solve(e)
    assert Q.sum() > 0
    assert Q.sum() == pytest.approx(fe.deflection_per_volt(), rel=1e-12)
    assert fe.blocked_force_per_volt() > 0
    # The blocked force holds the tip at w = 0: V = 1 plus F = -F_b gives zero tip deflection.
    q = fe.static_solve(fe.Theta.sum(axis=1) - fe.blocked_force_per_volt() * e)
    assert abs(q[fe.tip]) < 1e-9 * fe.deflection_per_volt()


def test_modes_and_damping():
    fe = build_beam(bimorph(segments=(0.5, 0.5), damping=0.02))
    f, phi = fe.modes()
    assert phi.shape == (fe.n_dof, fe.n_dof) and np.all(np.diff(f) > 0)
    np.testing.assert_allclose(phi.T @ fe.M @ phi, np.eye(fe.n_dof), atol=1e-9)
    np.testing.assert_allclose(phi.T @ fe.K @ phi, np.diag((2 * np.pi * f) ** 2),
                               rtol=1e-9, atol=1e-9 * (2 * np.pi * f[-1]) ** 2)
    assert np.all(phi[fe.tip] > 0)
    # Modal damping: the state matrix [[0, I], [-M^-1 K, -M^-1 C]] has eigenvalues
    # -zeta w +- i w sqrt(1 - zeta^2), so each mode's damping ratio is -Re(s)/|s| = zeta.
    C = fe.damping_matrix()
    n = fe.n_dof
    Minv = np.linalg.inv(fe.M)
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-Minv @ fe.K, -Minv @ C]])
    s = np.linalg.eigvals(A)
    s = s[s.imag > 0]
    s = s[np.argsort(np.abs(s))][:6]
    np.testing.assert_allclose(-s.real / np.abs(s), 0.02, rtol=1e-5)
    np.testing.assert_allclose(np.abs(s) / (2 * np.pi), f[:6], rtol=1e-6)


def test_with_tip_returns_new_model():
    fe = build_beam(bimorph())
    f0, _ = fe.modes(1)
    loaded = fe.with_tip(mass=1e-4)
    assert loaded.tip_mass == 1e-4 and fe.tip_mass == 0.0
    assert fe.modes(1)[0][0] == f0[0] and loaded.modes(1)[0][0] < f0[0]
    with pytest.raises(ValueError):
        fe.K[0, 0] = 1.0  # read-only


# ---------------------------------------------------------------------------- errors


def _spec(**kw):
    base = dict(length=15e-3, width=1.5e-3,
                layers=(Layer(BUILTIN["PZT-5A"], 0.3e-3), Layer(BUILTIN["PZT-5A"], 0.3e-3)),
                connection="parallel", segments=(0.5, 0.5), damping=0.01)
    base.update(kw)
    return BeamSpec(**base)


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda: _spec(length=-1e-3), "BeamSpec.length"),
        (lambda: _spec(width=0.0), "BeamSpec.width"),
        (lambda: _spec(length=math.nan), "BeamSpec.length"),
        (lambda: Layer(BUILTIN["PZT-5A"], -0.1e-3), "Layer.thickness"),
        (lambda: _spec(segments=(0.5, 0.4)), "BeamSpec.segments must sum to 1"),
        (lambda: _spec(segments=(1.2, -0.2)), "BeamSpec.segments must be positive"),
        (lambda: _spec(segments=()), "BeamSpec.segments"),
        (lambda: _spec(connection="serial"), "BeamSpec.connection"),
        (lambda: _spec(damping=1.5), "BeamSpec.damping"),
        (lambda: _spec(elements=1), "BeamSpec.elements = 1 must be at least"),
        (lambda: _spec(elements=2.5), "BeamSpec.elements must be an integer"),
        (lambda: _spec(elements=100000), "BeamSpec.elements = 100000 exceeds"),
        (lambda: _spec(layers=()), "BeamSpec.layers"),
        (lambda: _spec(layers=(Layer(Material(1e11, 0.0, 1.0, 8000.0), 1e-4),)),
         "no piezoelectric layer"),
        (lambda: SupportSpec("hinged"), "SupportSpec.kind"),
        (lambda: SupportSpec("elastic", k=-1.0), "SupportSpec.k "),
        (lambda: SupportSpec("clamped", k_rot=5.0), "SupportSpec.k_rot"),
        # Numerically unsafe: a 1e-7 segment next to a long one, or a 1e16 x stiffer tip spring.
        (lambda: build_beam(_spec(segments=(1e-7, 1 - 1e-7))), "condition number"),
        (lambda: build_beam(_spec()).with_tip(k=1e30), "condition number"),
        (lambda: build_beam(_spec()).with_tip(mass=-1.0), "with_tip: mass"),
        (lambda: build_beam(_spec()).modes(1000), "modes: n"),
        (lambda: build_beam(_spec()).dof_of(0, "psi"), "fixed by the clamped support"),
        (lambda: build_beam(_spec()).dof_of(0, "v"), "which"),
    ],
    ids=lambda x: x if isinstance(x, str) else "",
)
def test_invalid_inputs_raise_model_error(make, match):
    with pytest.raises(ModelError, match=match):
        make()
