"""``rtctl selfsense``: JSON contract, files written, one-line errors."""

import json

import pytest

from rtctl.selfsense.cli import main


@pytest.mark.slow
def test_json_sweep_and_plot(tmp_path, capsys):
    rc = main(["line-bimorph-5", "--out", str(tmp_path), "--json", "--freqs", "250", "--beat", "10",
               "--no-mismatch"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    g = res["groups"]["lateral"]
    assert len(g["tmm_natural_frequencies_hz"]) == 4 and len(g["tmm_loaded_natural_frequencies_hz"]) == 4
    keys = {"freq_hz", "load", "snr_db", "mismatch_pct", "amp_err_pct", "phase_err_deg", "force_err_pct", "cond"}
    assert g["cases"] and all(keys <= set(c) for c in g["cases"])
    assert {c["load"] for c in g["cases"]} == {"50g", "2g", "none"}
    assert max(c["amp_err_pct"] for c in g["cases"]) < 1.0
    assert (tmp_path / "selfsense_lateral.png").stat().st_size > 10000
    assert json.loads((tmp_path / "selfsense_lateral.json").read_text())["cases"] == g["cases"]


def test_unknown_scene_is_one_line(tmp_path, capsys):
    assert main(["no-such-scene", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "error" in err
