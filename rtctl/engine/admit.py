"""What ``rtctl run`` refuses of a scene before anything runs, checked without running it.

:func:`admit` calls the very checks the run's path calls (the stimulus compiled, an image's file
read, what observing and closed loop need, the calibration file read, what a backend drives), so
``rtctl check`` refuses each in the run's one line, without building plants or kernels, opening
a device or measuring. Components the scene needs that this rtctl or machine lacks are not
refused here: :attr:`rtctl.needs.Needs.unavailable` lists them, and ``rtctl check`` reports them.
"""

from __future__ import annotations


def admit(scene) -> None:
    """Refuse ``scene`` (SceneError, one line) where ``rtctl run`` would, short of a device that
    is absent or refuses, a fit that fails, or what rendering finds in an image's pixels.

    Raises
    ------
    SceneError
    """
    from ..stimulus import check

    check(scene)  # the stimulus as the run compiles it; observing and closed loop on it
    if scene.control.calibrate == "auto":
        from .calibrate import calibratable

        calibratable(scene)
    elif scene.control.calibration:
        from .calibrate import scene_calibration

        scene_calibration(scene)  # the rig's reader: a missing or foreign file refused as run refuses it
    if scene.io.backend == "serial":
        from ..io.serial import pin_group

        pin_group(scene)
