"""``rtctl replay``: resim finds exactly the differences planted in a recording (their block,
signal, channel and size, checked against a plain numpy comparison) and tells a last-bit
difference from a real one; plant mode gives back a simulated recording's currents and names the
size of a device's mismatch; observer mode reproduces the recorded estimates and commands."""

import json
import re
import shutil

import numpy as np
import pytest

from rtctl import scene as scenes
from rtctl.cli import main
from rtctl.engine.replay.resim import compare
from rtctl.engine.run import run
from rtctl.trace import TraceReader, TraceWriter


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    d = tmp_path_factory.mktemp("rec")
    run(scenes.load("line-bimorph-5", ["timing.duration=0.2"]), out_dir=d, plot=False)
    return d


def rewritten(src, dst, change):
    """A copy of trace ``src`` at ``dst`` whose records went through ``change(records)``: a
    recording that differs from what its scene gives in known places (checksums made anew)."""
    r = TraceReader(src)
    recs = np.array(r.records)
    change(recs)
    names = r.dtype.names[3:]
    sig = {n: (r.units[n], r.dtype[n].shape[0], 0) if n in r.layout["per_block"] else (r.units[n], r.dtype[n].shape[0])
           for n in names}
    w = TraceWriter(dst, sig, r.fs, r.block, r.channels, meta=r.meta)
    w.append(recs)
    w.close()
    return dst


def replay(capsys, *argv):
    code = main(["replay", *map(str, argv), "--json"])
    out = capsys.readouterr()
    return code, (json.loads(out.out) if out.out.strip() else None), out.err


def test_resim_of_an_untouched_recording_is_bitwise(recorded, capsys):
    code, rep, _ = replay(capsys, recorded)
    assert code == 0 and rep["verdict"] == "bitwise" and rep["first"] is None, rep
    assert rep["blocks_compared"] == TraceReader(recorded / "trace").n_blocks
    assert rep["provenance_match"] and "same package source, libraries and machine" in rep["line"]


def test_resim_names_the_first_planted_difference_and_its_size(recorded, tmp_path, capsys):
    def change(recs):
        recs["sensed"][40, 3, 7] *= 1.01       # block 40, sensed row 3, +1 %
        recs["drive"][90, 1, 0] += 0.5         # later, elsewhere
    t = rewritten(recorded / "trace", tmp_path / "trace", change)
    rec, orig = TraceReader(t), TraceReader(recorded / "trace")
    # what a plain comparison finds, independent of the replay's
    bad = [np.flatnonzero((np.asarray(rec.records[n]) != np.asarray(orig.records[n])).reshape(rec.n_blocks, -1)
                          .any(axis=1)) for n in ("drive", "sensed")]
    assert [list(b) for b in bad] == [[90], [40]]
    code, rep, _ = replay(capsys, t)
    assert code == 1 and rep["verdict"] == "differs"
    f = rep["first"]
    assert (f["block"], f["signal"], f["channel"]) == (40, "sensed", rec.meta["sensed_rows"][3])
    want = float(orig.records["sensed"][40, 3, 7])
    assert f["replayed"] == want and f["recorded"] == float(np.float32(want * np.float32(1.01)))
    assert f["abs"] == pytest.approx(abs(want) * 0.01, rel=1e-5)
    assert rep["blocks_differing"] == 2 and rep["values_differing"] == 2
    line = rep["line"]
    assert "block 40" in line and "sensed" in line and rec.meta["sensed_rows"][3] in line


def test_a_difference_of_one_float32_ulp_is_reported_as_last_bit(recorded, tmp_path, capsys):
    def change(recs):
        x = recs["tip_um"][55, 2, 3]
        recs["tip_um"][55, 2, 3] = np.nextafter(x, np.float32(np.inf), dtype=np.float32)
    t = rewritten(recorded / "trace", tmp_path / "trace", change)
    code, rep, _ = replay(capsys, t)
    assert code == 0 and rep["verdict"] == "last-bit", rep["line"]
    assert rep["max_ulps"] == 1 and rep["first"]["block"] == 55 and rep["first"]["signal"] == "tip_um"
    assert "1 float32 ulps" in rep["line"] and "reassociation" in rep["line"]


def test_ulps_count_float32_steps_across_zero():
    from rtctl.engine.replay.resim import _ulps

    a = np.array([1.0, 0.0, -np.float32(1e-45)], dtype=np.float32)
    b = np.array([np.nextafter(np.float32(1), np.float32(2)), np.float32(1e-45), np.float32(1e-45)], dtype=np.float32)
    np.testing.assert_array_equal(_ulps(a, b), [1, 1, 2])


def test_timing_fields_are_not_compared(recorded, tmp_path):
    def change(recs):
        recs["compute_us"] += 100.0
    t = rewritten(recorded / "trace", tmp_path / "trace", change)
    rec, orig = TraceReader(t), TraceReader(recorded / "trace")
    assert compare(rec, orig, rec.n_blocks)["first"] is None


def test_resim_refuses_a_hardware_trace_in_one_line(recorded, tmp_path, capsys):
    shutil.copytree(recorded / "trace", tmp_path / "trace")
    layout = json.loads((tmp_path / "trace" / "trace.json").read_text())
    layout["meta"]["backend"] = "audio"
    (tmp_path / "trace" / "trace.json").write_text(json.dumps(layout))
    code = main(["replay", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "use --mode plant" in err


def test_plant_replay_of_a_simulated_recording(recorded, tmp_path, capsys):
    code, rep, _ = replay(capsys, recorded, "--mode", "plant", "--out", tmp_path)
    assert code == 0 and rep["latency_blocks"] == rep["recorded_latency_blocks"] == 1
    # the recording's sensor noise is all that differs (the model's currents carry none)
    assert rep["residual_pct"] < 1.0 and rep["gain"] == pytest.approx(1.0, abs=2e-3), rep["line"]
    assert rep["tip_residual_pct"] < 1e-3  # same plant, same drive (float32-rounded)
    assert (tmp_path / "plant.png").stat().st_size > 0 and (tmp_path / "residual.csv").exists()


def test_plant_replay_of_a_settle_tail_is_the_sensor_noise_not_a_device_difference(recorded, tmp_path, capsys):
    # past 0.25 s of a 0.2 s run the drive is 0 V and the tips settle: the recorded currents are
    # the sensor's noise (1e-6 V over 100 ohm), the model's (noiseless) under one ADC step. The
    # residual is then the noise over the recorded rms, computed here from the trace alone.
    code, rep, _ = replay(capsys, recorded, "--mode", "plant", "--skip", 0.25, "--out", tmp_path)
    assert code == 0 and rep["residual_pct"] > 90, rep["line"]
    rec = np.asarray(TraceReader(recorded / "trace").records["sensed"], dtype=float)
    k0 = round(0.25 * 48000 / 32) + rep["latency_blocks"]
    want = 100 * 1e-6 / 100 / np.sqrt(np.mean(rec[k0:] ** 2))
    assert rep["noise_floor_pct"] == pytest.approx(want, rel=1e-3)
    assert rep["residual_pct"] == pytest.approx(want, rel=0.05)
    assert "differs" not in rep["line"] and "cannot tell the model from the device" in rep["line"], rep["line"]


def test_plant_replay_does_not_name_an_idle_channels_noise_as_the_worst_row(tmp_path, capsys):
    # lateral.4 plays nothing: its recorded currents are the sensor's noise, the model's zero
    run(scenes.load("line-bimorph-5", ["timing.duration=0.1", "stimulus.tones.4.voltage=0"]), out_dir=tmp_path / "r",
        plot=False)
    code, rep, _ = replay(capsys, tmp_path / "r", "--mode", "plant", "--out", tmp_path / "p")
    rows = {r["row"]: r for r in rep["rows"]}
    rec = np.asarray(TraceReader(tmp_path / "r" / "trace").records["sensed"], dtype=float)[rep["latency_blocks"]:]
    i = TraceReader(tmp_path / "r" / "trace").meta["sensed_rows"].index("lateral.4.seg0")
    assert rows["lateral.4.seg0"]["residual_pct"] == pytest.approx(100, abs=0.1)
    assert rows["lateral.4.seg0"]["noise_floor_pct"] == pytest.approx(100 * 1e-8 / np.sqrt(np.mean(rec[:, i] ** 2)),
                                                                      rel=1e-3)
    assert code == 0 and "matches" in rep["line"] and "worst lateral.4" not in rep["line"], rep["line"]


def test_plant_replay_names_a_permittivity_mismatch(tmp_path, capsys):
    # the device's eps33T 10 % above the model's: the clamped capacitance, and with it the
    # capacitive current C dV/dt that dominates a segment's current, is 10 % larger
    run(scenes.load("line-bimorph-5", ["timing.duration=0.3", "io.mismatch.eps33T=1.1"]), out_dir=tmp_path / "r",
        plot=False)
    code, rep, _ = replay(capsys, tmp_path / "r", "--mode", "plant")
    assert code == 0 and rep["gain"] == pytest.approx(1.10, abs=0.005), rep["line"]
    assert 8.0 < rep["residual_pct"] < 10.5, rep["line"]
    m = re.search(r"its currents are ([0-9.]+) x the model's \(\+([0-9.]+) %\)", rep["line"])
    assert m and float(m.group(1)) == pytest.approx(1.10, abs=0.01) and 9.0 < float(m.group(2)) < 11.0, rep["line"]


@pytest.mark.slow
def test_observer_replay_reproduces_a_closed_loop_recording(tmp_path, capsys):
    run(scenes.load("line-bimorph-5-closed"), out_dir=tmp_path / "r", plot=False)
    code, rep, _ = replay(capsys, tmp_path / "r", "--mode", "observer")
    assert code == 0
    for row in rep["channels"]:
        # inputs are the trace's float32 copies of the float64 the live run used
        assert row["estimate_max_rel"] < 1e-5 and row["command_max_rel"] < 1e-4, row


def test_observer_replay_needs_an_observer(recorded, capsys):
    code = main(["replay", str(recorded), "--mode", "observer"])
    err = capsys.readouterr().err
    assert code == 2 and "--set control.observe=true" in err and err.count("\n") == 1


def _ulp_then_growth(recs):
    x = recs["drive"][50, 4, 3]
    recs["drive"][50, 4, 3] = np.nextafter(x, np.float32(np.inf), dtype=np.float32)  # 1 ulp first
    recs["drive"][120, 4, :] *= 1.02  # then more, as a closed loop carries a difference on


def test_a_last_bit_start_that_grows_is_last_bit_with_the_same_code(recorded, tmp_path, capsys):
    t = rewritten(recorded / "trace", tmp_path / "trace", _ulp_then_growth)
    code, rep, _ = replay(capsys, t)
    assert code == 0 and rep["verdict"] == "last-bit", rep["line"]
    assert rep["first"]["block"] == 50 and rep["first"]["ulps"] == 1
    assert rep["largest"]["block"] == 120 and rep["largest"]["signal"] == "drive"
    assert "grow to" in rep["line"] and "block 120" in rep["line"]


def test_the_same_difference_under_other_code_is_a_failure(recorded, tmp_path, capsys):
    t = rewritten(recorded / "trace", tmp_path / "trace", _ulp_then_growth)
    layout = json.loads((t / "trace.json").read_text())
    layout["meta"]["rtctl"]["package_sha256"] = "0" * 64  # recorded by other code
    (t / "trace.json").write_text(json.dumps(layout))
    code, rep, _ = replay(capsys, t)
    assert code == 1 and rep["verdict"] == "differs" and not rep["provenance_match"], rep["line"]
    assert "package_sha256: 000000000000 ->" in rep["line"]
