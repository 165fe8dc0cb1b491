"""The benches in bench/ as modules a test can import (they are scripts, not a package)."""

import importlib.util
import sys
from pathlib import Path

BENCH = Path(__file__).parents[1] / "bench"


def load(name: str):
    """``bench/<name>.py`` as the module ``name``, registered in ``sys.modules`` (the benches
    import one another by name: the oracle imports the sweep); loaded once per process."""
    path = BENCH / f"{name}.py"
    mod = sys.modules.get(name)
    if mod is not None and Path(getattr(mod, "__file__", "") or "").resolve() == path.resolve():
        return mod
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod
