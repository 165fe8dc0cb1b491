"""rtctl.dsp as a package: its imports, its exports, NaN visibility for the safety limiter."""

import ast
from pathlib import Path

import numpy as np

import rtctl.dsp as dsp
from rtctl.dsp import _kernels as K


def test_imports_only_numpy_and_numba():
    """Read the import statements (numba itself pulls scipy into sys.modules, so look at ours)."""
    allowed = {"numpy", "numba", "math", "fractions", "rtctl._numba", "rtctl.dsp"}
    for path in Path(dsp.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module] if isinstance(node, ast.ImportFrom) else [])
            for name in names:
                assert any(name == ok or name.startswith(ok + ".") for ok in allowed), f"{path.name} imports {name}"


def test_exports():
    for name in ("OscillatorBank", "PulseTrain", "LockIn", "Ramp", "Fade",
                 "osc_bank_process", "pulse_process", "lockin_process"):
        assert hasattr(dsp, name), name


def test_nan_target_reaches_the_output():
    """fastmath without nnan: a NaN written into pending by the loop must show up in the block,
    where the limiter can see it, instead of being optimized into a number."""
    bank = dsp.OscillatorBank(1, [0], 48000.0, 100.0, 1.0, ramp=4)
    bank.pending[K.P_AMP, 0] = np.nan
    bank.pending[K.P_FLAG, 0] = 1.0
    out = np.zeros((1, 8))
    dsp.osc_bank_process(*bank.args, out)
    assert np.isnan(out).all()
    lock = dsp.LockIn(1, [[100.0]], 48000.0, 32, hop=32)
    assert np.isnan(lock.process(np.full((1, 32), np.nan))).all()
