"""What made a run: the versions and sources a replay needs to say whether it can match bitwise.

:func:`provenance` is stored in every trace's meta (``rtctl``): the package version, the SHA-256
of its source files (:func:`rtctl._numba.package_stamp`: it tells an edited tree from a clean
one, which a git revision alone does not), the git revision where the package is a git work
tree, the versions of Python, numpy, scipy and numba, the machine, and whether kernels ran
cached. Two traces whose provenance agree were made by the same code on the same kind of machine.
"""

from __future__ import annotations

import platform
import subprocess
import sys

#: The entries that must agree for a re-run to be expected bitwise equal.
BITWISE_KEYS = ("package_sha256", "python", "numpy", "numba", "scipy", "machine", "cpu")


def git_revision(path) -> str | None:
    """``HEAD`` of the git work tree holding ``path`` (with ``+dirty`` when it has uncommitted
    changes), or None when there is no git or no work tree."""
    try:
        rev = subprocess.run(["git", "-C", str(path), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=5)
        if rev.returncode:
            return None
        dirty = subprocess.run(["git", "-C", str(path), "status", "--porcelain", "--untracked-files=no", "--", "."],
                               capture_output=True, text=True, timeout=5)
        return rev.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return None


def _cpu() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or ""


def provenance() -> dict:
    import numba
    import numpy
    import scipy

    from . import __version__, _numba

    return {
        "version": __version__,
        "package_sha256": _numba.package_stamp().hex(),
        "git": git_revision(_numba.PACKAGE_DIR),
        "python": sys.version.split()[0],
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "numba": numba.__version__,
        "machine": platform.machine(),
        "cpu": _cpu(),
        "numba_cache": _numba.CACHE_NOTE or "stamped with the package",
    }


def differences(a: dict, b: dict) -> list[str]:
    """The :data:`BITWISE_KEYS` on which two provenances differ, as ``key: a -> b``."""
    def short(v):
        return v[:12] if isinstance(v, str) and len(v) == 64 else v
    return [f"{k}: {short(a.get(k))} -> {short(b.get(k))}" for k in BITWISE_KEYS if a.get(k) != b.get(k)]
