import os
import sys

# Single-threaded BLAS, as the rtctl command sets it: the models' matrices are small, and two
# BLAS threads on a busy 2-core machine made one discretization 100x slower (9.5 s vs 0.085 s).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

# tests/naive.py and friends are imported as plain modules by the tests.
sys.path.insert(0, os.path.dirname(__file__))

# Never let a test's PortAudio/libjack start a JACK server of its own: HIL tests start theirs.
os.environ.setdefault("JACK_NO_START_SERVER", "1")


def pytest_terminal_summary(terminalreporter):
    """Say plainly when hardware-in-the-loop tests did not run, and why (they are real tests: a
    skipped HIL test means the audio or serial path went unchecked on this machine)."""
    skipped = [r for r in terminalreporter.stats.get("skipped", []) if "hil" in getattr(r, "keywords", {})]
    if skipped:
        reasons = sorted({str(r.longrepr[-1]) if isinstance(r.longrepr, tuple) else str(r.longrepr)
                          for r in skipped})
        terminalreporter.write_line(f"HIL: {len(skipped)} hardware-in-the-loop test(s) SKIPPED: "
                                    + "; ".join(reasons), yellow=True, bold=True)
