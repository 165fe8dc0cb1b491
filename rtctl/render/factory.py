"""Renderers by method name.

The factory sits above the method modules (:mod:`rtctl.render.roi`, :mod:`~rtctl.render.frequency`,
:mod:`~rtctl.render.beat`) and they above :mod:`rtctl.render.hia`, whose base class they extend:
kept in ``hia`` it would make the base module import its own subclasses.
"""

from __future__ import annotations

from rtctl.errors import SceneError
from rtctl.render.hia import METHODS, Renderer

__all__ = ["make_renderer", "METHODS"]


def make_renderer(method: str, **kw) -> Renderer:
    """A renderer by method name (``roi``, ``canny``, ``frequency``, ``beat``).

    Keyword arguments go to the method's class: :class:`~rtctl.render.roi.RoiRenderer`,
    :class:`~rtctl.render.frequency.FrequencyRenderer`, :class:`~rtctl.render.beat.BeatRenderer`.
    Each method's module (and OpenCV with it) is imported on first use only.

    Examples
    --------
    >>> r = make_renderer("roi", grid=(4, 4), hia=32)
    >>> r.cell, r.fields
    (8, ('up',))
    """
    if method in ("roi", "canny"):
        from rtctl.render.roi import RoiRenderer

        return RoiRenderer(edges=(method == "canny"), **kw)
    if method == "frequency":
        from rtctl.render.frequency import FrequencyRenderer

        return FrequencyRenderer(**kw)
    if method == "beat":
        from rtctl.render.beat import BeatRenderer

        return BeatRenderer(**kw)
    raise SceneError(f"render method {method!r} is unknown; use one of {', '.join(METHODS)}")
