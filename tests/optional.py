"""Optional system libraries: tests that need one skip with one line naming what to install.

sounddevice and JACK-Client install from PyPI everywhere but load a C library at import, and raise
``OSError`` (not ``ImportError``) where it is missing, so ``pytest.importorskip`` lets them take the
whole collection down. The check runs the import in a child process with this process's
environment: that is what the ``rtctl`` processes a HIL test starts will see, and this process
stays free of PortAudio's and libjack's clients (tests/hil_jack.py).
"""

from __future__ import annotations

import functools
import os
import subprocess
import sys

import pytest

#: module -> what to install where it cannot be imported
INSTALL = {
    "sounddevice": "Debian: apt-get install libportaudio2 (PortAudio, for the sounddevice package)",
    "jack": "Debian: apt-get install jackd2 (libjack, for the JACK-Client package)",
}


@functools.cache
def import_error(module: str) -> str | None:
    """Why ``import module`` fails in a child process, or None when it works."""
    r = subprocess.run([sys.executable, "-c", f"import {module}"], capture_output=True, text=True,
                       env=os.environ.copy(), timeout=60)
    if r.returncode == 0:
        return None
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    return lines[-1] if lines else f"exit {r.returncode}"


def require(*modules: str) -> None:
    """Skip the calling test module unless every one of ``modules`` imports."""
    for m in modules:
        why = import_error(m)
        if why is not None:
            pytest.skip(f"{m} cannot be imported ({why}); {INSTALL.get(m, 'pip install ' + m)}",
                        allow_module_level=True)
