"""The invariant checker catches every invariant broken on its own, passes clean traces, and
says so through ``rtctl check-trace`` with the exit statuses it documents.

The traces here are written by hand with :class:`rtctl.trace.TraceWriter` (not by the loop),
with the limits of a :class:`rtctl.safety.Limiter` built for them, so each one breaks exactly
what it is meant to."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from rtctl import safety
from rtctl.check import INVARIANTS, TraceUnreadable, check_trace
from rtctl.trace import TraceWriter

FS, BLOCK, N_CH = 48000.0, 32, 2
VMAX, SLEW = 100.0, 1e6          # V, V/s: 20.8 V per sample
STEP = SLEW / FS


def _limits(dc=np.inf, tmax=80.0):
    lim = safety.Limiter(FS, max_voltage=[VMAX] * N_CH, slew=[SLEW] * N_CH, current=[10.0] * N_CH,
                         capacitance=[1e-9] * N_CH, temperature=[tmax] * N_CH, ambient=[25.0] * N_CH,
                         loss_tangent=[0.0] * N_CH, thermal_resistance=[1.0] * N_CH, thermal_tau=[1.0] * N_CH,
                         dc_offset=[dc] * N_CH, dc_tau=[0.01] * N_CH)
    return lim.bounds()


def _clean(n_blocks=60, amp=80.0, freq=200.0):
    """A sine within every bound, faded to 0 V over the last block (linear, as the limiter's)."""
    t = np.arange(n_blocks * BLOCK) / FS
    v = np.vstack([amp * np.sin(2 * np.pi * freq * t), -amp * np.sin(2 * np.pi * freq * t)])
    last = v[:, -BLOCK - 1].copy()
    v[:, -BLOCK:] = last[:, None] * (1.0 - np.arange(1, BLOCK + 1) / BLOCK)
    return v


def _write(path, v, status=None, limits=None, temp=None, numbers=None, summary=None):
    n_b = v.shape[1] // BLOCK
    w = TraceWriter(path / "trace", {"drive": ("V", N_CH), "temperature": ("degC", N_CH, 0)}, FS, BLOCK,
                    ["a.0", "a.1"], meta={"limits": limits or _limits()})
    for k in range(n_b):
        r = w.next()
        r["drive"] = v[:, k * BLOCK:(k + 1) * BLOCK]
        r["status"] = 0 if status is None else status[k]
        r["temperature"] = 30.0 if temp is None else temp[k]
        if numbers is not None:
            r["block"] = numbers[k]
    w.close()
    if summary is not False:
        s = {"duration_s": (n_b - 1) * BLOCK / FS, "fs": FS, "block": BLOCK, "faults": [], "warnings": []}
        s.update(summary or {})
        (path / "summary.json").write_text(json.dumps(s))
    return path


def _only(rep, name):
    bad = {k for k, n in rep["violations"].items() if n}
    assert bad == {name}, rep["first"]
    assert not rep["ok"]


def test_a_clean_trace_passes(tmp_path):
    rep = check_trace(_write(tmp_path, _clean()))
    assert rep["ok"], rep["first"]
    assert rep["samples"] == 60 * BLOCK * N_CH and rep["blocks"] == 60
    assert set(rep["violations"]) == set(INVARIANTS)


def test_one_sample_beyond_max_voltage(tmp_path):
    v = _clean()
    i = int(np.argmax(v[0]))
    v[0, i] = VMAX + 0.01   # one sample, a step of < 21 V: only the voltage bound breaks
    rep = check_trace(_write(tmp_path, v))
    _only(rep, "voltage")
    assert rep["violations"]["voltage"] == 1
    assert f"block {i // BLOCK}, channel a.0, sample {i % BLOCK}" in rep["first"]["voltage"]


def test_float32_rounding_at_the_bound_is_no_violation(tmp_path):
    v = _clean(amp=VMAX)   # peaks at exactly max_voltage, stored as float32
    assert check_trace(_write(tmp_path, v))["ok"]


def test_one_step_beyond_the_slew_bound(tmp_path):
    v = _clean(amp=10.0, freq=50.0)
    v[1, 500] += 1.02 * STEP  # up, then back down by as much: two steps beyond
    rep = check_trace(_write(tmp_path, v))
    _only(rep, "slew")
    assert rep["violations"]["slew"] == 2


def test_the_first_sample_steps_from_zero(tmp_path):
    v = _clean(amp=10.0)
    v[:, 0] = 1.5 * STEP
    _only(check_trace(_write(tmp_path, v)), "slew")


def test_a_nan_drive_sample(tmp_path):
    v = _clean()
    v[0, 700] = np.nan
    rep = check_trace(_write(tmp_path, v))
    assert rep["violations"]["nonfinite"] == 1 and not rep["ok"]


def test_a_dc_offset_beyond_its_bound(tmp_path):
    # a 10 ms running mean bounded at 5 V: a 4 V offset stays inside, a 6 V one leaves it
    t = np.arange(60 * BLOCK) / FS
    for offset, ok in ((4.0, True), (6.0, False)):
        v = np.vstack([offset + 20 * np.sin(2 * np.pi * 1500 * t)] * 2)   # whole periods per block: block mean = offset
        v[:, :20] *= np.arange(20) / 20      # start from 0 V within the slew bound
        last = v[:, -BLOCK - 1].copy()
        v[:, -BLOCK:] = last[:, None] * (1.0 - np.arange(1, BLOCK + 1) / BLOCK)
        rep = check_trace(_write(tmp_path / str(offset), v, limits=_limits(dc=5.0)))
        if ok:
            assert rep["ok"], rep["first"]
        else:
            _only(rep, "mean")
            # the closed form: m_k = b (1 - (1 - A)^k) with A = 1 - exp(-32 / (48000 * 0.01)) passes
            # 5 V at the block k where (1 - A)^k < 1/6
            a = -math.expm1(-BLOCK / (FS * 0.01))
            k = math.ceil(math.log(1 - 5.0 / 6.0) / math.log(1 - a)) - 1
            assert rep["first"]["mean"].startswith(f"block {k},") or rep["first"]["mean"].startswith(f"block {k + 1},")


def test_outputs_that_do_not_fade_after_a_fault(tmp_path):
    v = _clean()
    st = np.zeros(60, dtype=np.int64)
    st[30] = safety.DEVICE_LOST
    s = {"faults": ["at 0.0200 s: I/O device lost"], "duration_s": 31 * BLOCK / FS}
    # good: the fade over block 31, then zeros
    good = v.copy()
    last = good[:, 31 * BLOCK - 1].copy()
    good[:, 31 * BLOCK:32 * BLOCK] = last[:, None] * (1.0 - np.arange(1, BLOCK + 1) / BLOCK)
    good[:, 32 * BLOCK:] = 0.0
    assert check_trace(_write(tmp_path / "good", good, st, summary=s))["ok"]
    rep = check_trace(_write(tmp_path / "bad", v, st, summary=s))   # goes on playing the sine
    _only(rep, "fade")
    st2 = st.copy()
    rep = check_trace(_write(tmp_path / "short", good[:, :31 * BLOCK], st2[:31], summary=s))
    assert rep["violations"]["fade"] == 1 and "without its fade" in rep["first"]["fade"]


def test_a_trace_that_does_not_end_at_zero(tmp_path):
    v = _clean()[:, :-BLOCK]   # cut before the fade
    _only(check_trace(_write(tmp_path, v, summary={"duration_s": 58 * BLOCK / FS})), "end")


def test_a_temperature_over_the_limit_without_its_bit(tmp_path):
    temp = np.full(60, 30.0)
    temp[40] = 81.0
    st = np.zeros(60, dtype=np.int64)
    _only(check_trace(_write(tmp_path / "a", _clean(), st, temp=temp)), "temperature")
    st[40] = safety.OVERTEMP   # flagged: the fade check then applies, and this sine does not fade
    rep = check_trace(_write(tmp_path / "b", _clean(), st, temp=temp, summary={"faults": ["over temperature"]}))
    assert rep["violations"]["temperature"] == 0 and rep["violations"]["fade"] > 0


def test_records_missing_or_out_of_order(tmp_path):
    numbers = list(range(60))
    numbers[10] = 11
    _only(check_trace(_write(tmp_path, _clean(), numbers=numbers)), "records")


def test_a_summary_that_does_not_match_the_records(tmp_path):
    st = np.zeros(60, dtype=np.int64)
    st[5] = safety.LIMIT_VOLTAGE
    rep = check_trace(_write(tmp_path / "a", _clean(), st))   # the summary does not warn of it
    _only(rep, "summary")
    assert "voltage limited" in rep["first"]["summary"]
    rep = check_trace(_write(tmp_path / "b", _clean(), summary={"faults": ["invented"]}))
    _only(rep, "summary")
    rep = check_trace(_write(tmp_path / "c", _clean(), summary={"warnings": ["voltage limited"]}))
    _only(rep, "summary")
    p = _write(tmp_path / "d", _clean())
    (p / "summary.json").write_text('{"duration_s": NaN, "fs": 48000, "block": 32, "faults": [], "warnings": []}')
    rep = check_trace(p)
    assert rep["violations"]["summary"] >= 1 and "not strict JSON" in rep["first"]["summary"]


def test_dropped_record_placeholders_are_counted_not_violations(tmp_path):
    v = _clean()
    w = TraceWriter(tmp_path / "trace", {"drive": ("V", N_CH)}, FS, BLOCK, ["a.0", "a.1"], meta={"limits": _limits()})
    for k in range(60):
        if k == 20:
            w.gap(1)
            continue
        r = w.next()
        r["drive"] = v[:, k * BLOCK:(k + 1) * BLOCK]
    w.close()
    rep = check_trace(tmp_path / "trace")
    assert rep["ok"], rep["first"]
    assert rep["dropped"] == 1


def test_unreadable_traces_are_refused(tmp_path):
    with pytest.raises(TraceUnreadable, match="not a readable rtctl trace"):
        check_trace(tmp_path)
    w = TraceWriter(tmp_path / "old", {"drive": ("V", 1)}, FS, BLOCK, ["a"])   # no meta.limits
    w.close()
    with pytest.raises(TraceUnreadable, match="holds no limits"):
        check_trace(tmp_path / "old")


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "rtctl.cli", "check-trace", *map(str, args)],
                          capture_output=True, text=True, timeout=120)


def test_the_command_exits_0_1_and_2(tmp_path):
    good = _write(tmp_path / "good", _clean())
    r = _cli(good)
    assert r.returncode == 0 and ": ok:" in r.stdout, r.stderr
    v = _clean()
    v[0, 100] = 2 * VMAX
    r = _cli(_write(tmp_path / "bad", v), "--json")
    assert r.returncode == 1
    rep = json.loads(r.stdout)
    assert rep["violations"]["voltage"] == 1 and not rep["ok"]
    r = _cli(tmp_path / "nothing-here")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "not a readable rtctl trace" in r.stderr


def test_every_bundled_scene_run_passes(tmp_path):
    from rtctl import scene
    from rtctl.engine.run import run

    for name in ("line-bimorph-5", "solenoid-3x3"):
        run(scene.load(name, ["timing.duration=0.05"]), out_dir=tmp_path / name, plot=False)
        rep = check_trace(tmp_path / name)
        assert rep["ok"], (name, rep["first"])
