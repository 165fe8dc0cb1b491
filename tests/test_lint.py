"""The source is ruff-clean: ``ruff check rtctl tests bench`` with the rules of pyproject.toml
([tool.ruff]), so ``make test`` catches a lint regression like any other failure."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PATHS = ("rtctl", "tests", "bench")

if importlib.util.find_spec("ruff") is None:
    pytest.skip("ruff is not installed: pip install -e '.[test]' (or pip install 'ruff>=0.6')",
                allow_module_level=True)


def test_ruff_check_is_clean():
    # --no-cache: nothing written into the shared working tree, no stale results
    r = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise", *PATHS],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    if r.returncode != 0:
        pytest.fail(f"ruff check {' '.join(PATHS)} (exit {r.returncode}):\n{r.stdout}{r.stderr}", pytrace=False)
