"""What the fuzz tests (tests/test_fuzz_*.py) share: hypothesis settings, the property every
parser keeps, a TOML writer and a hang guard.

The property: a parser given anything returns a clean result or raises one of the error types
it documents (an :class:`rtctl.errors.RtctlError`, or ``OSError`` for a file that cannot be
opened) whose message is one line that names the cause; the command line turns that into one
``rtctl: error:`` line and exit status 2. Never another exception (a traceback, or exit 3),
never a hang.

``make test`` runs a fixed set of examples (derandomized: the same cases on every run, no example
database); ``make fuzz`` sets ``RTCTL_FUZZ_EXAMPLES`` and runs that many random examples per test,
keeping failures in ``.hypothesis/`` so a rerun tries them first.
"""

import contextlib
import io
import json
import math
import os
import re
import signal
import warnings

from hypothesis import HealthCheck, settings

from rtctl.cli import main

LONG = int(os.environ.get("RTCTL_FUZZ_EXAMPLES", "0") or 0)
_QUIET = [HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much]
settings.register_profile("rtctl-fuzz-ci", deadline=None, derandomize=True, database=None,
                          suppress_health_check=_QUIET, print_blob=True)
settings.register_profile("rtctl-fuzz-long", deadline=None, derandomize=False,
                          suppress_health_check=_QUIET, print_blob=True)

#: longest message a parser may give (a key, a value, what is allowed, the fix)
MAX_MESSAGE = 600
#: an example running longer than this is a hang (a guard, not a speed test: speed is bench/'s)
HANG_S = 60


def fuzz(examples: int):
    """Settings for one fuzz test: ``examples`` fixed cases in ``make test``, ``RTCTL_FUZZ_EXAMPLES``
    random ones in ``make fuzz``."""
    if LONG:
        return settings(settings.get_profile("rtctl-fuzz-long"), max_examples=LONG)
    return settings(settings.get_profile("rtctl-fuzz-ci"), max_examples=examples)


def one_line(e: BaseException, *names: str) -> str:
    """The message of ``e``, checked: one line, not empty, not endless, naming each of ``names``."""
    msg = str(e)
    assert msg.strip(), f"{type(e).__name__} without a message"
    assert "\n" not in msg and "\r" not in msg, f"message over several lines: {msg!r}"
    assert len(msg) <= MAX_MESSAGE, f"message of {len(msg)} characters: {msg[:200]!r}..."
    for n in names:
        assert n in msg, f"{n!r} not named in {msg!r}"
    return msg


def clean_or_clear(fn, *args, errors, names=()):
    """``fn(*args)``'s result, or the error it raised if it is one of ``errors`` with a
    :func:`one_line` message; any other exception propagates (and fails the test)."""
    with hang_guard():
        try:
            return fn(*args)
        except errors as e:
            one_line(e, *names)
            return e


def run_cli(argv):
    """``rtctl ARGV`` in this process: (status, stdout, stderr). A status 2 has exactly one
    ``rtctl: error:`` line on stderr; status 3 (internal error) fails."""
    out, err = io.StringIO(), io.StringIO()
    with hang_guard(), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
            warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        status = main(list(argv))
    # a warning prints lines of its own on stderr (pytest would hide them)
    assert not caught, f"rtctl {argv!r} warned: {[str(w.message) for w in caught]}"
    lines = err.getvalue().splitlines()
    assert status != 3, f"rtctl {argv!r}: internal error: {err.getvalue()!r}"
    if status == 2:  # one line; argparse's usage errors have the usage line before it
        usage = len(lines) == 2 and lines[0].startswith("usage: rtctl")
        assert len(lines) == 1 + usage and re.match(r"rtctl( [a-z]+)*: error: ", lines[-1]), (argv, lines)
        one_line(lines[-1])
    return status, out.getvalue(), err.getvalue()


class Hang(Exception):
    pass


@contextlib.contextmanager
def hang_guard(seconds: float = HANG_S):
    """Raise :class:`Hang` in this (main) thread if the block runs longer than ``seconds``."""

    def fire(*_):
        raise Hang(f"still running after {seconds} s")

    old = signal.signal(signal.SIGALRM, fire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


# ----------------------------------------------------------------------------- TOML out


def toml_dumps(doc: dict) -> str:
    """``doc`` as TOML, one ``key = value`` line per top-level key with inline tables below, so
    any nesting and any value (NaN, inf, huge integers, unicode, mixed arrays) is written as is."""
    return "".join(f"{_key(k)} = {_value(v)}\n" for k, v in doc.items())


def _key(k) -> str:
    return json.dumps(str(k), ensure_ascii=False)


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)  # TOML basic strings escape as JSON does
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(type(v))
