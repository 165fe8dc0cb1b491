"""``rtctl bench render``: the JSON contract, and the 100 us budget for a 48-pin HIA update."""

import json

import pytest

from rtctl.render.bench import main_bench

KEYS = {"hia_update_us_median", "hia_update_us_p99", "preprocess_ms"}


def test_bench_json_contract(capsys):
    assert main_bench(["--json", "--size", "256", "--n", "50"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert set(d["methods"]) == {"roi", "canny", "frequency", "beat"}
    for m in d["methods"].values():
        assert KEYS <= set(m) and m["pins"] == 48
        assert 0 < m["hia_update_us_median"] <= m["hia_update_us_p99"]


@pytest.mark.slow
def test_update_budget_on_a_2048_px_photo(capsys):
    assert main_bench(["--json", "--n", "1000"]) == 0
    d = json.loads(capsys.readouterr().out)
    for name, m in d["methods"].items():
        assert m["hia_update_us_median"] <= 100.0, (name, m)
