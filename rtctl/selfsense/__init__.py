"""Self-sensing: transfer-matrix bimorph model and segmented-electrode observers.

Shares no model code with :mod:`rtctl.plant`, whose finite-element bimorph is the truth the
observers are judged against.
"""
