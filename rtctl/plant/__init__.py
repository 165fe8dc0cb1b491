"""Continuous-time plant models, their exact discretization, and simulated channel groups.

Public API: LTI machinery (:mod:`~rtctl.plant.lti`), the finger load, the amplifier and current
sense, the reduced bimorph channel and :class:`SimGroup`, plus the finite-element beam
(``build_fe``/``build_beam``, ``BeamSpec``, ``Layer``, ``SupportSpec``, ``BeamFE``, ``Material``,
``BUILTIN``, ``model_facts``).
"""

from rtctl.plant.bimorph import TRUTH_NAMES, BimorphPlant, SimGroup, sim_group_process
from rtctl.plant.finger import MaxwellLoad
from rtctl.plant.frontend import Amplifier, CurrentSense
from rtctl.plant.lti import ModalForm, StateSpace, augment_tones, c2d, to_modal, tone_state

__all__ = [
    "StateSpace", "c2d", "augment_tones", "tone_state", "to_modal", "ModalForm",
    "MaxwellLoad", "Amplifier", "CurrentSense", "BimorphPlant", "SimGroup", "TRUTH_NAMES",
    "sim_group_process",
    "build_fe", "build_beam", "BeamSpec", "Layer", "SupportSpec", "BeamFE", "Material",
    "BUILTIN", "model_facts",
]

_FE_NAMES = {
    "build_fe": ("rtctl.plant.beam", ("build_fe", "build_beam")),
    "build_beam": ("rtctl.plant.beam", ("build_beam",)),
    "BeamSpec": ("rtctl.plant.beam", ("BeamSpec",)),
    "Layer": ("rtctl.plant.beam", ("Layer",)),
    "SupportSpec": ("rtctl.plant.beam", ("SupportSpec",)),
    "BeamFE": ("rtctl.plant.beam", ("BeamFE",)),
    "Material": ("rtctl.plant.materials", ("Material",)),
    "BUILTIN": ("rtctl.plant.materials", ("BUILTIN",)),
    "model_facts": ("rtctl.plant.facts", ("model_facts",)),
}


def __getattr__(name):
    # The finite-element names live in modules written separately; import them on first use.
    if name in _FE_NAMES:
        import importlib

        module, candidates = _FE_NAMES[name]
        mod = importlib.import_module(module)
        for attr in candidates:
            if hasattr(mod, attr):
                value = getattr(mod, attr)
                globals()[name] = value
                return value
    raise AttributeError(f"module 'rtctl.plant' has no attribute {name!r}")
