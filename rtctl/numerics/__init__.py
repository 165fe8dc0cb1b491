"""Numerics report: error against run time (work-precision) and stability on extreme cases.

``rtctl bench numerics`` runs :func:`rtctl.numerics.cli.main`. Modules: :mod:`.problems`
(registry of plants with a stated reference), :mod:`.workprecision` (the sweep), :mod:`.stability`
(extreme cases), :mod:`.runner` (any discrete LTI system through the plant kernel),
:mod:`.plot`. Nothing here is imported by the real-time path.
"""
