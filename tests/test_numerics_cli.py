"""``rtctl bench numerics --quick``: the JSON contract, files, and the done criteria."""

import json

import pytest

from rtctl.numerics.cli import main


@pytest.mark.slow
def test_quick_report_json_and_files(tmp_path, capsys):
    status = main(["--quick", "--json", "--out", str(tmp_path)])
    rep = json.loads(capsys.readouterr().out)
    assert status == 0
    assert {"work_precision", "stability"} <= set(rep)
    for e in rep["work_precision"]:
        assert set(e) == {"plant", "method", "setting", "error", "wall_s"}
    for c in rep["stability"]:
        assert set(c) == {"case", "passed", "detail"}
        assert c["passed"] is True, c
    methods = {e["method"] for e in rep["work_precision"] if e["plant"] == "bimorph"}
    assert {"Radau", "BDF", "LSODA", "RK45", "dlsim zoh", "rtctl SimGroup zoh"} <= methods
    # equal error is reachable by our kernel and by Radau (timing itself is not asserted)
    radau = [s for s in rep["speedups"] if s["plant"] == "bimorph" and s["baseline"] == "Radau"]
    assert radau[0]["ratio"] is not None
    for name in ("numerics.json", "numerics.txt", "work_precision.png"):
        assert (tmp_path / name).stat().st_size > 0
