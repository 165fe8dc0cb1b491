"""``rtctl sweep`` on the command line: one-line refusals before anything is computed, the
directory it writes (Parquet and CSV tables, plots), resuming it, and what the other commands
leave alone (``rtctl run`` never imports Dask)."""

import ast
import csv
import json
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from test_import_graph import import_graph

import rtctl
from rtctl.cli import main

PACKAGE = Path(rtctl.__file__).parent
LENGTH = "actuator.lateral.beam.length"


def sweep_cli(capsys, *args):
    code = main(["sweep", *args])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("args, words", [
    (["line-bimorph-5", "--vary", f"{LENGTH}=0.01:0.02"], ["a:b:n or a:b:n:log"]),
    (["line-bimorph-5", "--vary", "actuator.lateral.beam.lenght=0.01:0.02:3"],
     ["point 0", "lenght=0.01", "did you mean 'actuator.lateral.beam.length'"]),
    (["line-bimorph-5", "--vary", f"{LENGTH}=-0.01:0.01:3"], ["point 0 (actuator.lateral.beam.length=-0.01)",
                                                             "(0, 1] m"]),
    (["line-bimorph-5", "--vary", "stimulus.tones.9.freq=[1, 2]"], ["point 0", "index 9 out of range"]),
    (["line-bimorph-5", "--vary", f"{LENGTH}=[0.01]", "--what", "modal"], ["--what 'modal'", "model, reach"]),
    (["line-bimorph-5", "--vary", f"{LENGTH}=[0.01]", "--workers", "2", "--scheduler", "tcp://127.0.0.1:8786"],
     ["--workers", "--scheduler"]),
    (["line-bimorph-5", "--vary", f"{LENGTH}=[0.01]", "--scheduler", "nonsense:xx"], ["not a scheduler address"]),
    (["line-bimorph-5", "--vary", f"{LENGTH}=[0.01]", "--workers", "-1"], ["--workers must be >= 0"]),
    (["solenoid-3x3", "--vary", "finger.preload=[0.1, 0.2]", "--what", "reach"],
     ["point 0", "reach needs a sine tone"]),
    (["line-bimorph-5", "--vary", "io.backend=[sim, audio]", "--what", "run"], ["point 1", "simulated rig"]),
    (["no-such-scene", "--vary", f"{LENGTH}=[0.01]"], ["no-such-scene", "no such scene"]),
    # one key under two spellings (the group's name, its index): the later would set every point
    (["line-bimorph-5", "--vary", f"{LENGTH}=[0.015, 0.02]", "--vary", "actuator.0.beam.length=[0.03]"],
     ["actuator.0.beam.length is already varied", LENGTH]),
    (["line-bimorph-5", "--vary", "stimulus.tones.4.freq,stimulus.tones.-1.freq=[300]"],
     ["stimulus.tones.-1.freq is already varied"]),
], ids=["spec", "unknown-key", "out-of-range", "index", "what", "workers-and-scheduler", "address", "workers",
        "no-tone", "run-on-hardware", "scene", "alias-name", "alias-negative-index"])
def test_bad_input_is_one_line_and_status_2(capsys, tmp_path, args, words):
    code, out, err = sweep_cli(capsys, *args, "--out", str(tmp_path / "s"))
    assert code == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rtctl: error: "), err
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert not (tmp_path / "s" / "points.jsonl").exists()  # refused before anything was computed


@pytest.mark.parametrize("args, words", [
    (["line-bimorph-5"], ["--vary"]),
    (["line-bimorph-5", "--vary", f"{LENGTH}=[0.01]", "--workers", "two"], ["--workers", "'two'"]),
], ids=["no-vary", "workers-not-int"])
def test_usage_errors_are_argparse_s_usage_and_one_error_line(capsys, tmp_path, args, words):
    # as every rtctl command (tests/test_cli_newuser.py): the usage, then one line naming the error
    code, out, err = sweep_cli(capsys, *args, "--out", str(tmp_path / "s"))
    lines = err.strip().splitlines()
    assert code == 2 and lines[0].startswith("usage: rtctl sweep") and "Traceback" not in err
    assert lines[-1].startswith("rtctl sweep: error: ") and [ln for ln in lines if ": error:" in ln] == [lines[-1]]
    for w in words:
        assert w in lines[-1], (w, lines[-1])
    assert not (tmp_path / "s").exists()


def test_in_process_sweep_writes_tables_and_plots_and_resumes(capsys, tmp_path):
    out = tmp_path / "s"
    thick = "actuator.lateral.beam.layers.0.thickness,actuator.lateral.beam.layers.1.thickness"
    # keys varied together may be written with spaces; the column is named without them
    spaced = thick.replace(",", ", ")
    args = ["line-bimorph-5", "--vary", f"{LENGTH}=10e-3:20e-3:3", "--vary", f"{spaced}=[0.2e-3, 0.3e-3]",
            "--what", "model,reach", "--workers", "0", "--out", str(out)]
    code, text, err = sweep_cli(capsys, *args)
    assert code == 0, err
    assert "6 points (--what model,reach): 6 computed on this process" in text
    assert "beam.length" in text and "layers.0.thickness+1" in text and "ruffini.margin_db" in text
    rows = pq.read_table(out / "table.parquet").to_pylist()
    assert [r["point"] for r in rows] == list(range(6))
    assert [(r[LENGTH], r[thick]) for r in rows[:3]] == [(0.01, 0.0002), (0.01, 0.0003), (0.015, 0.0002)]
    assert all(r["error"] is None for r in rows)
    with open(out / "table.csv") as f:
        table = list(csv.DictReader(f))
    assert len(table) == 6 and float(table[3]["lateral.f1_hz"]) == pytest.approx(rows[3]["lateral.f1_hz"], rel=1e-12)
    # the designer's plots: metric against each key, and the heat map of the two
    for name in ("lateral.f1_loaded_hz", "ruffini.margin_db", "pacinian.margin_db"):
        assert (out / f"plot_{name}.png").stat().st_size > 10_000
    # resumed: nothing recomputed, the same table; a wider --vary computes only its new points
    code, text, _ = sweep_cli(capsys, *args, "--json", "--no-plot")
    doc = json.loads(text)
    assert code == 0 and doc["summary"]["reused"] == 6 and doc["summary"]["computed"] == 0
    assert pq.read_table(out / "table.parquet").to_pylist() == rows
    wider = [a.replace("10e-3:20e-3:3", "10e-3:20e-3:5") for a in args]
    code, text, _ = sweep_cli(capsys, *wider, "--json", "--no-plot")
    doc = json.loads(text)
    assert code == 0 and doc["summary"]["reused"] == 6 and doc["summary"]["computed"] == 4
    again = {(r[LENGTH], r[thick]): r for r in pq.read_table(out / "table.parquet").to_pylist()}
    assert all(again[(r[LENGTH], r[thick])] | {"point": r["point"]} == r for r in rows)
    # another --what in the same directory is refused, not mixed in
    code, _, err = sweep_cli(capsys, *args[:-6], "--what", "reach", "--workers", "0", "--out", str(out))
    assert code == 2 and "holds a sweep with another what" in err


def test_another_vary_in_the_same_directory_leaves_no_plot_of_the_first(capsys, tmp_path):
    out = tmp_path / "s"
    base = ["line-bimorph-5", "--what", "reach", "--workers", "0", "--out", str(out)]
    code, _, err = sweep_cli(capsys, *base, "--vary", "finger.preload=[0.49, 1.0]")
    assert code == 0 and (out / "plot_ruffini.margin_db.png").is_file(), err
    # one preload: no key varies, so no figure; the two-point figures are not this table's
    code, _, err = sweep_cli(capsys, *base, "--vary", "finger.preload=[0.49]")
    assert code == 0 and len(pq.read_table(out / "table.parquet").to_pylist()) == 1, err
    assert sorted(p.name for p in out.glob("plot_*")) == []
    # and --no-plot on a plotted directory leaves none behind either
    sweep_cli(capsys, *base, "--vary", "finger.preload=[0.49, 1.0]")
    assert any(out.glob("plot_*.png"))
    code, _, _ = sweep_cli(capsys, *base, "--vary", "finger.preload=[0.49, 1.0]", "--no-plot")
    assert code == 0 and sorted(p.name for p in out.glob("plot_*")) == []


def test_failed_points_are_rows_and_a_resume_retries_them(capsys, tmp_path):
    out = tmp_path / "s"
    # a 1e-7 electrode segment is a valid scene that the beam model refuses (ill-conditioned)
    args = ["line-bimorph-5", "--vary", "actuator.lateral.beam.segments=[[0.5, 0.5], [1e-7, 0.9999999]]",
            "--what", "model", "--workers", "0", "--out", str(out), "--no-plot"]
    code, text, err = sweep_cli(capsys, *args)
    assert code == 1 and "1 of 2 points failed; first: point 1: BeamFE mass matrix is numerically unsafe" in err
    rows = pq.read_table(out / "table.parquet").to_pylist()
    assert rows[0]["error"] is None and rows[1]["error"].startswith("BeamFE mass matrix")
    assert rows[1]["lateral.f1_hz"] is None
    assert [r["actuator.lateral.beam.segments"] for r in rows] == ["[0.5, 0.5]", "[1e-07, 0.9999999]"]
    code, text, err = sweep_cli(capsys, *args, "--json")
    assert code == 1 and json.loads(text)["summary"]["computed"] == 1  # only the failed one again


def test_a_killed_sweep_keeps_its_finished_points(capsys, tmp_path):
    # points.jsonl is appended point by point; a half-written last line (the sweep killed while
    # writing it) is skipped on resume and the point computed again
    out = tmp_path / "s"
    args = ["line-bimorph-5", "--vary", f"{LENGTH}=10e-3:20e-3:4", "--what", "reach", "--workers", "0",
            "--out", str(out), "--no-plot", "--json"]
    assert sweep_cli(capsys, *args)[0] == 0
    lines = (out / "points.jsonl").read_text().splitlines()
    (out / "points.jsonl").write_text("\n".join(lines[:2]) + "\n" + lines[2][: len(lines[2]) // 2])
    code, text, _ = sweep_cli(capsys, *args)
    assert code == 0 and json.loads(text)["summary"]["reused"] == 2 and json.loads(text)["summary"]["computed"] == 2


def test_run_does_not_import_dask_or_pyarrow(tmp_path):
    code = ("import sys; from rtctl.cli import main; "
            "c = main(['run', 'line-bimorph-5', '--duration', '0.02', '--no-plot', '--quiet', '--out', "
            f"{str(tmp_path)!r}]); "
            "print(c, sorted({m.split('.')[0] for m in sys.modules} & {'dask', 'distributed', 'pyarrow'}))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip().splitlines()[-1] == "0 []"


def test_only_the_sweep_engine_imports_dask_and_only_the_command_line_imports_the_sweep():
    dask_users = set()
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 else [])
            if any(n.split(".")[0] in ("dask", "distributed") for n in names):
                dask_users.add(path.relative_to(PACKAGE).as_posix())
    assert dask_users == {"sweep/engine.py"}
    graph = import_graph(PACKAGE, "rtctl")
    users = {m for m, targets in graph.items() if not m.startswith("rtctl.sweep")
             for t in targets if t.startswith("rtctl.sweep")}
    assert users == {"rtctl.cli"}
