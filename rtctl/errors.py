"""Domain exceptions (after python-control's ``exception.py``).

Each subclasses the builtin a caller would expect, and each message names the cause and,
where there is one, the fix. The CLI turns any of them into one line and exit status 2.
"""


class RtctlError(Exception):
    """Base class of every error rtctl raises on purpose."""


class SceneError(RtctlError, ValueError):
    """A scene file or a ``--set`` override is invalid: names the key, the value and what is allowed."""


class ModelError(RtctlError, ValueError):
    """A physical model cannot be built or is numerically unsafe (e.g. ill-conditioned)."""


class DeviceError(RtctlError, OSError):
    """A hardware backend cannot be opened or failed while running."""


class RunAborted(RtctlError, RuntimeError):
    """The loop stopped on a fault after ramping the outputs to zero."""


class TraceError(RtctlError, ValueError):
    """A trace directory's layout or records cannot be read as an rtctl trace."""
