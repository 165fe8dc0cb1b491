"""``[io.faults]`` on the sim backend: each fault kind, injected by the simulated device, has exactly
the outcome docs/faults.md gives it, starts at its block and no earlier, and leaves a trace the
invariant checker passes. A faulted run is compared with the same run without the fault (one rig,
its plan reloaded between runs): identical before the fault's block, the fault's own signature
after it."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from rtctl import safety, scene
from rtctl.check import check_trace
from rtctl.engine.rig import build
from rtctl.engine.run import run
from rtctl.errors import SceneError
from rtctl.io import faults as F
from rtctl.trace import TraceReader

START = 60          # the fault's block: 40 ms into a 0.1 s run
N_BLOCKS = 150
SETS = ["timing.duration=0.1", "control.observe=true", "io.faults.random=1",
        "io.faults.kinds=['finger_lift', 'finger_slam']"]


@pytest.fixture(scope="module")
def rig():
    return build(scene.load("line-bimorph-5", SETS))


@pytest.fixture(scope="module")
def clean(rig, tmp_path_factory):
    return _run(rig, [], tmp_path_factory.mktemp("clean"))


def _run(rig, faults, out: Path):
    rig.device.faults.load(faults)
    res = run(scene.load("line-bimorph-5", SETS), out_dir=out, plot=False, rig=rig)
    rep = check_trace(out)
    assert rep["ok"], rep["first"]
    return res.summary, TraceReader(out / "trace")


def _sig(r, name):
    return np.asarray(r.records[name], dtype=float)   # (block, rows, samples)


def test_the_clean_run_has_no_fault_and_no_warning(clean):
    s, r = clean
    assert s["faults"] == [] and s["warnings"] == []
    assert r.n_blocks > N_BLOCKS


# what each kind must do: written here from docs/faults.md, not read from rtctl.io.faults
OUTCOME = {
    "sensed_nan": ("flag", safety.ESTIMATE_NONFINITE),
    "sensed_inf": ("flag", safety.ESTIMATE_NONFINITE),
    "adc_saturated": ("flag", safety.SENSOR_SATURATED),
    "sensed_zero": ("ride", 0),
    "sensed_frozen": ("ride", 0),
    "electrode_open": ("ride", 0),
    "latency_spike": ("ride", 0),
    "block_dropped": ("flag", safety.IO_XRUN),
    "amp_clipped": ("ride", 0),
    "finger_slam": ("ride", 0),
    "finger_lift": ("ride", 0),
    "device_stopped": ("fade", safety.DEVICE_LOST),
}


@pytest.mark.parametrize("kind", sorted(OUTCOME))
def test_each_fault_has_its_documented_outcome_from_its_block_on(kind, rig, clean, tmp_path):
    value = {"latency_spike": 3.0, "amp_clipped": 0.25}.get(kind, 0.0)
    f = F.Fault(kind, START, 10, 1 if kind.startswith("sensed") or kind == "electrode_open" else -1, value)
    s, r = _run(rig, [f], tmp_path)
    s0, r0 = clean
    outcome, bit = OUTCOME[kind]
    st = r.status
    np.testing.assert_array_equal(_sig(r, "drive")[:START], _sig(r0, "drive")[:START])
    np.testing.assert_array_equal(_sig(r, "sensed")[:START], _sig(r0, "sensed")[:START])
    np.testing.assert_array_equal(st[:START], r0.status[:START])
    if outcome == "fade":
        assert len(s["faults"]) == 1 and "stopped answering" in s["faults"][0]
        assert st[START] & bit and not np.any(st[:START] & safety.FAULTS)
        assert s["duration_s"] == pytest.approx((START + 1) * 32 / 48000)
    else:
        assert s["faults"] == []
        if bit:
            assert np.all(st[START:START + 1] & bit)
            assert safety.STATUS_NAMES[bit] in s["warnings"]
        else:
            assert not np.any(st & (safety.ESTIMATE_NONFINITE | safety.SENSOR_SATURATED | safety.IO_XRUN))


def _faulted(rig, kind, tmp_path, row=1, blocks=10, value=0.0):
    return _run(rig, [F.Fault(kind, START, blocks, row, value)], tmp_path)


def test_sensed_faults_replace_the_row_with_their_signature(rig, clean, tmp_path):
    _, r0 = clean
    clean_s = _sig(r0, "sensed")
    fs = 1.0 / 100.0   # the line display's ADC: 1 V full scale over a 100 ohm shunt
    for kind, want in (("sensed_nan", np.nan), ("sensed_inf", np.inf), ("adc_saturated", fs), ("sensed_zero", 0.0)):
        _, r = _faulted(rig, kind, tmp_path / kind)
        s = _sig(r, "sensed")
        np.testing.assert_array_equal(s[START:START + 10, 1], np.full((10, 32), want, dtype=np.float32))
        np.testing.assert_array_equal(s[START:START + 10, 0], clean_s[START:START + 10, 0])  # other rows untouched
    _, r = _faulted(rig, "sensed_frozen", tmp_path / "frozen")
    s = _sig(r, "sensed")
    assert np.all(s[START:START + 10, 1] == clean_s[START - 1, 1, -1])
    _, r = _faulted(rig, "electrode_open", tmp_path / "open")
    assert np.all(_sig(r, "sensed")[START:, 1] == 0.0)   # permanent, whatever `blocks` says


def test_a_latency_spike_delivers_the_readings_of_n_blocks_before(rig, clean, tmp_path):
    _, r0 = clean
    _, r = _faulted(rig, "latency_spike", tmp_path, row=-1, blocks=10, value=3.0)
    s, c = _sig(r, "sensed"), _sig(r0, "sensed")
    np.testing.assert_array_equal(s[START:START + 10], c[START - 3:START + 7])
    np.testing.assert_array_equal(s[START + 10:START + 20], c[START + 10:START + 20])


def test_amplifier_clipping_bounds_what_the_plant_gets_not_what_the_rig_sent(rig, clean, tmp_path):
    _, r0 = clean
    _, r = _faulted(rig, "amp_clipped", tmp_path, row=-1, blocks=40, value=0.25)
    clip = 0.25 * 150.0
    drive, volt = _sig(r, "drive"), _sig(r, "voltage")   # rig's output; plant's terminal voltage
    np.testing.assert_array_equal(drive[:START + 40], _sig(r0, "drive")[:START + 40])
    assert np.abs(drive[START:START + 40]).max() > 100.0
    # a first-order amplifier fed a signal within +-clip stays within it
    assert np.abs(volt[START + 1:START + 40]).max() <= clip * (1 + 1e-6)
    assert np.abs(_sig(r0, "voltage")[START:START + 40]).max() > 100.0


def test_a_dropped_block_reaches_the_plant_as_zero_volts_for_that_block(rig, clean, tmp_path):
    _, r0 = clean
    _, r = _faulted(rig, "block_dropped", tmp_path, row=-1, blocks=1)
    assert r.status[START] & safety.IO_XRUN and not r.status[START + 1] & safety.IO_XRUN
    np.testing.assert_array_equal(_sig(r, "drive")[START], _sig(r0, "drive")[START])
    assert np.all(_sig(r, "sensed")[START] == 0.0)
    # the amplifier's output decays toward 0 V at its bandwidth (20 kHz): within a block it is
    # far below the clean run's on the 140 V channels
    v, v0 = _sig(r, "voltage")[START, :2, -1], _sig(r0, "voltage")[START, :2, -1]
    assert np.all(np.abs(v) < 0.01 * np.abs(v0))


def test_a_lifted_finger_pushes_no_more_and_a_slammed_one_pushes_harder(rig, clean, tmp_path):
    _, r0 = clean
    f0 = _sig(r0, "tip_force")
    _, r = _faulted(rig, "finger_lift", tmp_path / "lift", row=-1)
    f = _sig(r, "tip_force")
    np.testing.assert_array_equal(f[:START], f0[:START])
    assert np.all(f[START:] == 0.0) and np.abs(f0[START:]).max() > 0
    _, r = _faulted(rig, "finger_slam", tmp_path / "slam", row=-1)
    f = _sig(r, "tip_force")
    np.testing.assert_array_equal(f[:START], f0[:START])
    # 4x stiffer skin on the same tips: the force grows (the tip moves less, not 4x less)
    late = slice(START + 30, N_BLOCKS)
    assert np.abs(f[late]).max() > 1.5 * np.abs(f0[late]).max()


def test_an_xrun_burst_flags_within_the_guard_and_ends_the_run_beyond_it(tmp_path):
    # io.xrun_limit N = 5 in a window W of 100 blocks: a burst from rest fills the bucket past
    # N W at the block after N W / (W - N) = 5.26 xruns, the 6th
    sets = ["timing.duration=0.1", "io.xrun_limit=5", f"io.xrun_window={100 * 32 / 48000}"]
    sc = scene.load("line-bimorph-5", sets + ['io.faults.inject=[{kind="xrun_burst", at=0.04, blocks=5}]'])
    s = run(sc, out_dir=tmp_path / "a", plot=False).summary
    assert s["faults"] == [] and safety.STATUS_NAMES[safety.IO_XRUN] in s["warnings"]
    assert check_trace(tmp_path / "a")["ok"]
    sc = scene.load("line-bimorph-5", sets + ['io.faults.inject=[{kind="xrun_burst", at=0.04, blocks=30}]'])
    res = run(sc, out_dir=tmp_path / "b", plot=False)
    s = res.summary
    assert len(s["faults"]) == 1 and "xrun burst" in s["faults"][0]
    assert round(s["duration_s"] * 48000 / 32) == START + 6
    assert check_trace(tmp_path / "b")["ok"]


def test_bad_fault_tables_are_refused_in_one_line():
    cases = [
        ('io.faults.inject=[{kind="byte_flip", at=0.1}]', "cannot be injected on sim"),
        ('io.faults.inject=[{kind="sensed_nan", at=0.1, row=10}]', r"row = 10: the scene has 10 sensed rows"),
        ('io.faults.inject=[{kind="latency_spike", at=0.1, value=64}]', "1 to 63 whole blocks"),
        ('io.faults.inject=[{kind="amp_clipped", at=0.1, value=2}]', r"fraction of max_voltage"),
        ('io.faults.inject=[{kind="meltdown", at=0.1}]', "must be one of"),
        ("io.faults.kinds=['nope']", "must be one of"),
    ]
    for item, msg in cases:
        with pytest.raises(SceneError, match=msg) as e:
            sc = scene.load("line-bimorph-5", [item])
            F.plan(sc, F.context(sc))
        assert "\n" not in str(e.value)
    sc = scene.load("dot-4x4", ['io.faults.inject=[{kind="sensed_zero", at=0.1}]'])
    with pytest.raises(SceneError, match="no sensed rows"):
        F.plan(sc, F.context(sc))


def test_random_faults_are_drawn_from_the_seed_and_stay_within_the_run():
    sc = scene.load("line-bimorph-5", ["io.faults.random=64", "io.faults.seed=7"])
    ctx = F.context(sc)
    a, b = F.plan(sc, ctx), F.plan(sc, ctx)
    assert a == b and F.plan(sc, ctx, seed=8) != a
    many = [f for seed in range(7, 12) for f in F.plan(sc, ctx, seed=seed)]
    assert {f.kind for f in many} == {k for k in F.KINDS if ctx.can(k)}
    for f in many:
        assert 0 <= f.start < ctx.n_blocks
        if f.kind == "xrun_burst" and f.blocks > F.burst_limit(ctx):
            assert f.start + f.blocks <= ctx.n_blocks and f.blocks >= 2 * F.burst_limit(ctx)


def test_the_schema_and_the_docs_name_every_kind_with_its_outcome():
    from rtctl.schema import SCENE

    spec = SCENE.keys["io"].keys["faults"].keys["inject"].keys["kind"]
    assert set(spec.choices) == set(F.KINDS)
    doc = (Path(__file__).parent.parent / "docs" / "faults.md").read_text()
    for name, k in F.KINDS.items():
        row = re.search(rf"^\| `{name}` \|.*$", doc, re.M)
        assert row, name
        assert f"**{k.outcome}**" in row.group(0), (name, row.group(0))


def test_the_injector_kernels_against_numpy():
    rng = np.random.default_rng(3)
    ctx = F.Context("sim", 100, n_sensed=3, n_channels=2, xrun_limit=0)
    inj = F.Injector(ctx, 8, [10.0, 20.0], [0.5, 0.25, 1.0],
                     [F.Fault("sensed_nan", 2, 1, 0), F.Fault("adc_saturated", 2, 2, 2),
                      F.Fault("amp_clipped", 1, 1, 1, 0.5), F.Fault("latency_spike", 4, 2, -1, 2.0)])
    readings = []
    for k in range(7):
        x = rng.normal(size=(3, 8))
        readings.append(x.copy())
        d = 30.0 * rng.normal(size=(2, 8))
        dev = np.zeros_like(d)
        st = inj.sensed(x)
        inj.drive(d, dev)
        inj.count()
        want = readings[k].copy()
        if k == 2:
            want[0] = np.nan
        if k in (2, 3):
            want[2] = 1.0
        if k in (4, 5):
            want = readings[k - 2].copy()
        np.testing.assert_array_equal(x, want)
        assert bool(st & safety.SENSOR_SATURATED) == (k in (2, 3))
        dwant = d.copy()
        if k == 1:
            dwant[1] = np.clip(d[1], -10.0, 10.0)
        np.testing.assert_array_equal(dev, dwant)


def test_the_xrun_guard_is_a_leaky_bucket():
    ctx = F.Context("sim", 10**6, 0, 1, xrun_limit=3, xrun_window_blocks=10)
    inj = F.Injector(ctx, 4, [1.0], [])
    level, fired = 0, []
    pattern = [1, 1, 0, 1, 1, 1, 1, 0, 0, 0] * 3 + [0] * 20 + [1] * 5
    for i, x in enumerate(pattern):
        level = max(level - 3, 0) + (10 if x else 0)
        st = inj.guard(safety.IO_XRUN if x else 0)
        assert bool(st & safety.XRUN_BURST) == (level > 30), i
        fired.append(level > 30)
    assert any(fired) and not all(fired)
    assert math.isclose(F.burst_limit(ctx), 30 / 7)


def test_faults_on_one_block_combine_in_the_devices_order_not_the_plans():
    ctx = F.Context("sim", 100, n_sensed=2, n_channels=1, xrun_limit=0)
    inj = F.Injector(ctx, 4, [1.0], [1.0, 1.0],
                     [F.Fault("sensed_inf", 1, 1, 0), F.Fault("electrode_open", 0, 0, 0),
                      F.Fault("latency_spike", 1, 1, 1, 1.0), F.Fault("sensed_nan", 1, 1, 1),
                      F.Fault("block_dropped", 2, 1)])
    got = []
    for k in range(3):
        x = np.full((2, 4), float(k + 1))
        st = inj.sensed(x)
        inj.count()
        got.append((x, st))
    assert np.all(got[0][0][0] == 0.0) and np.all(got[0][0][1] == 1.0)       # open
    assert np.all(got[1][0][0] == np.inf) and np.all(np.isnan(got[1][0][1]))  # the converter's on top
    assert np.all(got[2][0] == 0.0) and got[2][1] & safety.IO_XRUN            # no block at all


def test_the_campaign_judge_catches_a_missed_fade_a_stray_fault_and_a_missing_flag():
    from rtctl.engine.bench_faults import judge

    ctx = F.Context("sim", 100, n_sensed=2, n_channels=1, observed_rows=(0, 1), xrun_limit=25,
                    xrun_window_blocks=750)
    quiet = np.zeros(101, dtype=np.int64)
    ran = {"duration_s": 101 * 32 / 48000, "fs": 48000.0, "block": 32, "faults": []}
    stop = [F.Fault("device_stopped", 40, 0)]
    assert "did not end on it" in judge(stop, ctx, quiet, ran)["problems"][0]
    st = quiet[:41].copy()
    st[40] = safety.DEVICE_LOST
    good = {**ran, "duration_s": 41 * 32 / 48000, "faults": ["I/O device lost"]}
    j = judge(stop, ctx, st, good)
    assert j["problems"] == [] and j["outcome"] == "fade" and j["injected"][0]["detected"]
    assert "no injected fault calls for" in judge([], ctx, st, good)["problems"][0]
    nan = [F.Fault("sensed_nan", 10, 2, 0)]
    assert "no 'self-sensing estimate non-finite" in judge(nan, ctx, quiet, ran)["problems"][0]
    flagged = quiet.copy()
    flagged[11] = safety.ESTIMATE_NONFINITE
    assert judge(nan, ctx, flagged, ran)["outcome"] == "flag"
    hidden = nan + [F.Fault("block_dropped", 10, 2)]   # the reading never arrived
    x = quiet.copy()
    x[10:12] = safety.IO_XRUN
    assert judge(hidden, ctx, x, ran)["problems"] == []


def test_a_short_campaign_passes_and_prints_its_table(capsys):
    from rtctl.engine.bench_faults import main

    assert main(["--runs", "3", "--scenes", "line-bimorph-5", "--duration", "0.1"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"^line-bimorph-5\s+open\s+3\s", out, re.M) and "FAIL" not in out
    assert main(["--runs", "2", "--scenes", "solenoid-3x3", "--duration", "0.1", "--json"]) == 0
    import json

    d = json.loads(capsys.readouterr().out)
    assert d["total"]["runs"] == 2 and d["total"]["samples_beyond_limits"] == 0 and d["failing"] == []


@pytest.mark.parametrize("seed", range(6))
def test_the_injector_matches_its_naive_twin_on_random_overlapping_plans(seed):
    from naive_faults import Device

    rng = np.random.default_rng(seed)
    kinds = [k for k in F.KINDS if "sim" in F.KINDS[k].where and k not in F.FINGER_KINDS]
    n_s, n_c, blk, n_b = 4, 3, 8, 60
    faults = [F.Fault(str(rng.choice(kinds)), int(rng.integers(0, n_b)), int(rng.integers(0, 12)),
                      int(rng.integers(-1, 3)), 0.0) for _ in range(12)]
    faults = [F.Fault(f.kind, f.start, f.blocks, f.row, float(rng.integers(1, 6)) if f.kind == "latency_spike"
                      else round(float(rng.uniform(0.1, 1.0)), 3) if f.kind == "amp_clipped" else 0.0)
              for f in faults]
    full, vmax = rng.uniform(0.1, 1.0, n_s), rng.uniform(10.0, 100.0, n_c)
    ctx = F.Context("sim", n_b, n_s, n_c, xrun_limit=0)
    inj = F.Injector(ctx, blk, vmax, full, faults)
    twin = Device(faults, n_s, full)
    for k in range(n_b):
        true = rng.normal(size=(n_s, blk))
        x = true.copy()
        st = inj.sensed(x)
        want, flags = twin.sensed(k, true)
        np.testing.assert_array_equal(x, want, err_msg=f"block {k}")
        assert bool(st & safety.IO_XRUN) == ("xrun" in flags)
        assert bool(st & safety.DEVICE_LOST) == ("lost" in flags)
        assert bool(st & safety.SENSOR_SATURATED) == ("saturated" in flags)
        d = 200.0 * rng.normal(size=(n_c, blk))
        dev = np.zeros_like(d)
        inj.drive(d, dev)
        inj.count()
        np.testing.assert_array_equal(dev, twin.drive(k, d, vmax), err_msg=f"block {k}")
