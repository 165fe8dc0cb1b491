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

    fe = beam_model(g, _materials(scene), scene)
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


def em_plant(scene, g):
    """The electromagnetic perpendicular actuator of group ``g`` (bimodal display)."""
    from .plant.em import EMPlant
    from .rig import finger_load

    p = g.em
    finger = finger_load(scene, g)
    kw = dict(resistance=p.resistance, inductance=p.inductance, force_constant=p.force_constant,
              armature_mass=p.armature_mass, payload_mass=p.payload_mass, stiffness=p.stiffness,
              damping=p.damping, lateral_stiffness=p.lateral_stiffness, tilt_stiffness=p.tilt_stiffness,
              armature_inertia=p.armature_inertia, preload=p.preload if finger is not None else 0.0)
    return EMPlant(**kw, finger=finger)


def dot_pin(scene, g):
    """The latching Dot Braille pin of group ``g``."""
    from .plant.dot import DotPin
    from .rig import finger_load

    p = g.dot
    finger = finger_load(scene, g)
    return DotPin(supply=p.supply, travel=p.travel, resistance=p.resistance, inductance=p.inductance,
                  force_constant=p.force_constant, mass=p.mass, damping=p.damping,
                  latch_force=p.latch_force, finger=finger,
                  preload=p.preload if finger is not None else 0.0)


def _em(scene, g, gi, fs, block):
    from .plant.em import EMGroup

    return EMGroup(em_plant(scene, g), fs, g.grid[0] * g.grid[1], max_block=max(block, 1))


def _dot(scene, g, gi, fs, block):
    from .plant.dot import DotGroup

    return DotGroup(dot_pin(scene, g), fs, g.grid[0] * g.grid[1], up=g.dot.up, max_block=max(block, 1))


def _solenoid(scene, g, gi, fs, block):
    from .plant.solenoid import SolenoidGroup, SolenoidPin
    from .rig import finger_load

    p = g.solenoid
    finger = finger_load(scene, g)
    pin = SolenoidPin(resistance=p.resistance, inductance=p.inductance, force_constant=p.force_constant,
                      mass=p.mass, spring=p.spring, spring_preload=p.spring_preload, damping=p.damping,
                      stroke=p.stroke, stop_stiffness=p.stop_stiffness,
                      stop_damping_ratio=p.stop_damping_ratio, finger=finger,
                      preload=p.preload if finger is not None else 0.0)
    return SolenoidGroup(pin, fs, g.grid[0] * g.grid[1], max_block=max(block, 1), substeps=p.substeps,
                         levels=p.levels)


#: actuator type -> builder(scene, group, group index, fs, block)
BUILDERS = {"bimorph": _bimorph, "sma": _sma, "pvdf": _pvdf, "em": _em, "dot": _dot,
            "solenoid": _solenoid}


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

        return beam_model(g, _materials(scene), scene).capacitance(), 0.0
    if g.type == "em":
        return 0.0, g.em.resistance
    if g.type == "solenoid":
        return 0.0, g.solenoid.resistance
    if g.type == "dot":
        return 0.0, g.dot.resistance
    if g.type == "pvdf":
        return pvdf_plate(scene, g).capacitance, 0.0
    if g.type == "sma":
        return 0.0, sma_taxel(g).resistance
    raise SceneError(f"actuator.{g.name}: the limiter needs the electrical load of a {g.type!r} "
                     "actuator, which this version cannot model yet")
