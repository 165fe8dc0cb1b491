"""Transfer-matrix facts of a scene's bimorph group, for ``rtctl model --json``."""

from __future__ import annotations

from rtctl.selfsense.tmm import TMMBeam

__all__ = ["tmm_facts"]


def tmm_facts(fe, finger=None, n=4) -> dict:
    """Natural frequencies of the TMM twin of a finite-element beam.

    Parameters
    ----------
    fe : BeamFE
        The beam on its support (its spec and support are used, not its matrices).
    finger : MaxwellLoad, optional
        The finger for the loaded frequencies (``|s| / 2 pi`` of the damped roots, as
        :func:`rtctl.plant.facts.loaded_natural_frequencies`); None: same as unloaded.
    n : int

    Returns
    -------
    dict
        ``tmm_natural_frequencies_hz`` and ``tmm_loaded_natural_frequencies_hz`` (lists of n
        floats, Hz).

    Examples
    --------
    >>> from rtctl.plant.beam import BeamSpec, Layer, build_beam
    >>> from rtctl.plant.materials import BUILTIN
    >>> pzt = BUILTIN["PZT-5A"]
    >>> fe = build_beam(BeamSpec(15e-3, 1.5e-3, (Layer(pzt, 0.3e-3), Layer(pzt, 0.3e-3)),
    ...                          "parallel", (0.5, 0.5), 0.01))
    >>> [round(f) for f in tmm_facts(fe, n=2)["tmm_natural_frequencies_hz"]]
    [1208, 7572]
    """
    beam = TMMBeam.from_fe(fe)
    free = [float(f) for f in beam.natural_frequencies(n)]
    loaded = free if finger is None else [float(f) for f in beam.loaded_frequencies(finger, n)]
    return {"tmm_natural_frequencies_hz": free, "tmm_loaded_natural_frequencies_hz": loaded}
