"""Self-sensing: transfer-matrix bimorph model and segmented-electrode observers (issue 4).

Shares no model code with :mod:`rtctl.plant`, whose finite-element bimorph is the truth the
observers are judged against.
"""
