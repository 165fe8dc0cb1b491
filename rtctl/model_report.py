"""``rtctl model``: per actuator group, the facts of the scene's models."""

from __future__ import annotations


def model_facts(scene, tmm: bool = True) -> dict:
    """Per actuator group, the facts of :func:`rtctl.plant.facts.model_facts` with
    ``loaded_natural_frequencies_hz`` under the scene's full finger load, and the transfer-matrix
    model's frequencies of the same beam (an independent check of the finite-element values).

    ``tmm=False`` leaves the transfer-matrix frequencies out: they cost ~1 s a group against
    ~10 ms for everything else, which is what a design sweep of many beams cannot afford."""
    from .models import Models
    from .plant.facts import loaded_natural_frequencies
    from .plant.facts import model_facts as beam_facts

    models = Models(scene)
    out = {}
    for g in scene.actuator:
        if g.type != "bimorph":
            out[g.name] = {"type": g.type, "note": "no model facts for this actuator type yet"}
            continue
        fe, finger = models.beam(g), models.finger(g)
        facts = beam_facts(fe)
        if finger is not None:
            facts["loaded_natural_frequencies_hz"] = loaded_natural_frequencies(fe, finger, 4)
        else:
            facts["loaded_natural_frequencies_hz"] = list(facts["natural_frequencies_hz"])
        if tmm:
            from .selfsense.facts import tmm_facts

            facts.update(tmm_facts(fe, finger))
        out[g.name] = facts
    return out
