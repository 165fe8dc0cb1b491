"""The block loop in one room: the rig (buffers and an ordered list of stages), the composer that
makes one compiled block function of them, the parameter queue, the run loop, trace and summary.

Lower rooms (``dsp``, ``plant``, ``selfsense``, ``render``, ``io``, ``control``) never import
from here; docs/engine.md explains the stage contract and how to add a stage.
"""
