"""Domain exceptions (after python-control's ``exception.py``).

Each subclasses the builtin a caller would expect, and each message names the cause and,
where there is one, the fix. The CLI turns any of them into one line and exit status 2.
"""


class RtctlError(Exception):
    """Base class of every error rtctl raises on purpose."""


class SceneError(RtctlError, ValueError):
    """A scene file or a ``--set`` override is invalid: names the key, the value and what is allowed."""


class PatternError(RtctlError, ValueError):
    """A haptic pattern file (.ahap, .haptic) cannot be read: names the file, the item and the fix."""


class ModelError(RtctlError, ValueError):
    """A physical model cannot be built or is numerically unsafe (e.g. ill-conditioned)."""


class DeviceError(RtctlError, OSError):
    """A hardware backend cannot be opened or failed while running."""


class RunAborted(RtctlError, RuntimeError):
    """The loop stopped on a fault after ramping the outputs to zero."""


class OutputError(RtctlError, OSError):
    """An output directory or file cannot be written: names the path, the cause and the fix."""


class TraceError(RtctlError, ValueError):
    """A trace directory's layout or records cannot be read as an rtctl trace."""
