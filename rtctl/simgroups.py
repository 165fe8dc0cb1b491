"""Scene actuator groups -> simulated plant groups (the ``sim`` backend), one builder per type.

Every builder returns an object following the simulated-group contract of :mod:`rtctl.io.sim`
(``kernel``, ``args``, ``n_sensed``, ``sensed_labels``, ``probe_names``, ``probe``,
``capacitance``, ``reset``). :func:`drive_load` says what the limiter needs to know about the
load a channel drives, whatever the backend: a piezo's capacitance (current = C dV/dt) or a
coil's resistance (current = V / R).
"""

from __future__ import annotations

from .errors import SceneError


def _bimorph(scene, g, gi, fs, block):
    from .plant.bimorph import BimorphPlant, SimGroup
    from .plant.frontend import Amplifier, CurrentSense
    from .rig import _materials, beam_model, finger_load

    fe = beam_model(g, _materials(scene))
    s = g.sense
    sense = CurrentSense(s.shunt, s.aa_cutoff, s.aa_order, s.bits, s.full_scale, s.noise,
                         seed=scene.io.seed + 7919 * gi)
    plant = BimorphPlant(fe, Amplifier(g.amplifier.bandwidth), sense, finger_load(scene, g),
                         n_modes=g.beam.modes)
    return SimGroup(plant, fs, g.grid[0] * g.grid[1], max_block=max(block, 1))


def sma_taxel(g):
    """The SMA taxel model of group ``g`` (no simulation state: also the limiter's load)."""
    from .plant.sma import SmaTaxel

    p = g.sma
    return SmaTaxel(prestrain=p.prestrain, h_still=p.h_still, h_forced=p.h_forced, cooling=g.cooling,
                    t_ambient=g.limits.ambient, t_max=p.t_max, t_cut=p.t_cut)


def _sma(scene, g, gi, fs, block):
    from .plant.sma import SmaGroup

    p = g.sma
    group = SmaGroup(sma_taxel(g), fs, g.grid[0] * g.grid[1], max_block=max(block, 1), mech_fs=p.mech_fs,
                     crossbar=p.crossbar, rows=g.grid[0], slot=p.slot)
    group.f_ext[:] = p.push
    group.resistance = group.plant.resistance
    return group


def pvdf_plate(scene, g):
    """The PVDF plate of group ``g`` with the scene's finger on ``plate.finger_cell``."""
    from .plant.pvdf import PvdfPlate
    from .rig import finger_load

    p = g.plate
    finger = finger_load(scene, g)
    pc = tuple(p.probe_cells)
    return PvdfPlate(rows=g.grid[0], cols=g.grid[1], plate_length=p.length, plate_width=p.width,
                     plate_thickness=p.thickness, plate_E=p.E, plate_nu=p.nu, plate_rho=p.rho,
                     gap=p.gap, film_thickness=p.film_thickness, zeta=p.damping,
                     max_mode_hz=p.max_mode_hz, amplifier_bandwidth_hz=g.amplifier.bandwidth,
                     finger=finger, finger_cell=tuple(p.finger_cell),
                     preload=scene.finger.preload if finger is not None else 0.0,
                     probe_cells=(pc[:2], pc[2:]))


def _pvdf(scene, g, gi, fs, block):
    from .plant.pvdf import PvdfGroup

    return PvdfGroup(pvdf_plate(scene, g), fs, max_block=max(block, 1))


#: actuator type -> builder(scene, group, group index, fs, block)
BUILDERS = {"bimorph": _bimorph, "sma": _sma, "pvdf": _pvdf}


def build_group(scene, g, gi: int, fs: float, block: int):
    """The simulated group of actuator group ``g`` (index ``gi`` in the scene)."""
    try:
        builder = BUILDERS[g.type]
    except KeyError:
        raise SceneError(f"actuator.{g.name}: type {g.type!r} has no simulated plant yet") from None
    return builder(scene, g, gi, fs, block)


def drive_load(scene, g) -> tuple[float, float]:
    """``(capacitance F, resistance ohm)`` a channel of group ``g`` drives; one of them is 0."""
    if g.type == "bimorph":
        from .rig import _materials, beam_model

        return beam_model(g, _materials(scene)).capacitance(), 0.0
    if g.type == "pvdf":
        return pvdf_plate(scene, g).capacitance, 0.0
    if g.type == "sma":
        return 0.0, sma_taxel(g).resistance
    raise SceneError(f"actuator.{g.name}: the limiter needs the electrical load of a {g.type!r} "
                     "actuator, which this version cannot model yet")
