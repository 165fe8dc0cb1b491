"""Scene actuator groups -> models: beam, finger, plant, observer design and limiter load, and the
rows a run senses. Built once per group and shared by everything that asks for them (the rig, the
simulated device, the emulators, ``rtctl model``, ``rtctl selfsense``), so an observed bimorph
group builds its beam once, and every reader derives a group's segment count from one place.

Nothing here simulates: :mod:`rtctl.io.sim` wraps these models into simulated groups. A device
that differs from its model is ``Models(scene, factors)``: relative factors on the scene's values
(:data:`FACTORS`), which the caller chooses; nothing here decides who gets them.
"""

from __future__ import annotations

import math

from .errors import ModelError, SceneError

#: ``beam.modes = 0``: the simulated bimorph keeps every mode up to this many times fs ...
MODE_FOLDS = 1.5
#: ... and at least this many ...
MIN_MODES = 4
#: ... and every mode (with all below it) that lies near the drive's images at 2 fs ... this many
#: times fs, where the staircase's images of the tones land (``k fs +- f``). On an elastic root
#: (k 2e4 N/m, k_rot 0.5 N m/rad) under the finger, the observer read a plant without its mode at
#: 4 fs (192 kHz) 1.9 % off (0.06 % with it), and at 5 or 6 fs 0.21 and 0.12 % (0.19 and 0.10 %
#: with it); on the clamped 15 mm beam a mode at 3-8 fs moved it by at most 0.03 % ...
IMAGE_FOLDS = 4
#: ... of tones up to this share of fs (3 kHz at 48 kHz: above the skin's band) ...
IMAGE_TONES = 1.0 / 16.0
#: ... widened by this many of the mode's half-power half-widths (``zeta f``): a mode a few
#: widths off an image still answers it several-fold
IMAGE_WIDTHS = 3.0

#: Largest condition number of the in-loop observer's inversion: the two-segment designs of the
#: bundled beams sit at 5-8; beyond 1e4 the current noise would dominate the estimate.
OBSERVER_MAX_COND = 1e4

#: How far a real finger's static stiffness may lie from the scene's, either way, where the
#: amplitude controller asks which loaded modes may ring beside a tone (the devices it is held
#: to have finger k0 x0.3 ... x3; under the bundled 200 g set at k0 / 3 the first loaded mode
#: moves from 631 to 585 Hz, and a device with E x0.9 put it at 568 Hz)
FINGER_SPREAD = 3.0


def image_modes(freqs_hz, zeta: float, fs: float) -> int:
    """How many of a beam's modes (``freqs_hz``, ascending) a plant must keep for every mode near
    the images of its tones: one plus the index of the last mode within :data:`IMAGE_WIDTHS`
    half-widths (``zeta f``) of a band ``k fs +- IMAGE_TONES fs``, ``2 <= k <= IMAGE_FOLDS``;
    0 when none is.

    Examples
    --------
    >>> image_modes([1e3, 60e3, 95e3, 150e3], 0.01, 48000.0)   # 95 kHz: on the 2 fs band
    3
    >>> image_modes([1e3, 60e3, 120e3], 0.01, 48000.0)         # 120 kHz: between 2 and 3 fs
    0
    """
    import numpy as np

    f = np.asarray(freqs_hz, dtype=float)
    k = np.arange(2, IMAGE_FOLDS + 1)[:, None]
    near = np.abs(f[None, :] - k * fs) <= IMAGE_TONES * fs + IMAGE_WIDTHS * zeta * f[None, :]
    hit = np.flatnonzero(near.any(axis=0))
    return int(hit[-1]) + 1 if hit.size else 0


def materials(scene) -> dict:
    """The materials the scene's bimorph layers use: built-ins, or the scene's tables."""
    from .plant.materials import BUILTIN, material

    names = {layer.material for a in scene.actuator if a.type == "bimorph" for layer in a.beam.layers}
    out = {}
    for name in names:
        table = scene.materials.get(name)
        out[name] = material(name, dict(table) if table else None) if (table or name not in BUILTIN) else BUILTIN[name]
    return out


def n_segments(group) -> int:
    """Segment electrodes per bimorph channel (the sensed rows of each of its channels); 0 for
    actuator types that sense nothing."""
    return len(group.beam.segments) if group.type == "bimorph" else 0


def n_channels(group) -> int:
    return group.grid[0] * group.grid[1]


def sensed_layout(scene):
    """Sensed rows on hardware: each bimorph channel's segment currents, channel-major (the rows
    the simulated bimorph writes); other actuator types sense nothing. Returns ``(row names,
    drive channel of each row)``."""
    rows, owner, ch0 = [], [], 0
    for g in scene.actuator:
        n, n_seg = n_channels(g), n_segments(g)
        rows += [f"{g.name}.{i}.seg{j}" for i in range(n) for j in range(n_seg)]
        owner += [ch0 + i for i in range(n) for _ in range(n_seg)]
        ch0 += n
    return rows, owner


def finger_params(scene, direction: str):
    """The finger's Maxwell parameter table for ``direction``: ``finger.lateral``/``normal``, or
    with ``finger.subject`` set, that subject's set in ``direction`` whose preload is nearest
    ``finger.preload`` (nearest on a log scale: loads scale roughly with preload ratios).
    Returns ``(table, where)``, ``where`` naming the set for reports."""
    f = scene.finger
    if not f.subject:
        return f[direction], f"finger.{direction}"
    sets = [(i, s) for i, s in enumerate(f.subjects) if s.name == f.subject and s.direction == direction]
    if not sets:
        have = sorted({f"{s.name}/{s.direction}" for s in f.subjects}) or ["none"]
        raise SceneError(f"{scene.source}: finger.subject = {f.subject!r} has no {direction} set in "
                         f"finger.subjects (have {', '.join(have)})")
    p = max(f.preload, 1e-6)
    i, best = min(sets, key=lambda t: abs(math.log(max(t[1].preload, 1e-6) / p)))
    return best, f"finger.subjects.{i} ({best.name}, {direction}, {best.preload:g} N)"


def finger_load(scene, group):
    """The generalized Maxwell finger on ``group``'s tips, or None without contact."""
    from .plant.finger import MaxwellLoad

    if not scene.finger.contact:
        return None
    f, _ = finger_params(scene, group.direction)
    return MaxwellLoad(f.mass, f.k0, tuple((b.k, b.tau) for b in f.branches))


#: Relative factors :class:`Models` can apply on top of the scene's values, and what each scales.
FACTORS = {
    "thickness": "every layer thickness of every bimorph beam",
    "E": "Young's modulus of every material a bimorph layer uses",
    "d31": "d31 of every material a bimorph layer uses",
    "eps33T": "relative permittivity of every material a bimorph layer uses",
    "rho": "density of every material a bimorph layer uses",
    "damping": "every bimorph beam's modal damping ratio",
    "finger_k0": "the finger's static stiffness k0, on every group",
    "finger_mass": "the finger's skin mass, on every group",
    "finger_branches": "the stiffness k_i of every Maxwell branch of the finger, on every group",
}


class Models:
    """The models of one scene's actuator groups, each built on first use and kept.

    Parameters
    ----------
    scene : rtctl.scene.Scene
    factors : dict, optional
        Relative factors on the scene's values, keys of :data:`FACTORS` (missing keys: 1): the
        models of a device that differs from the scene by them. Factors of exactly 1 change no
        bit (``x * 1.0 == x``).
    group_factors : dict, optional
        ``{group name: factors}``: for those groups' models, factors in place of ``factors``
        (a calibration fits each bimorph group on its own; a material two groups share may then
        carry a different factor in each group's beam).
    """

    def __init__(self, scene, factors=None, group_factors=None):
        self.scene = scene
        self.factors = self._checked(factors)
        self.group_factors = {str(g): self._checked(f) for g, f in (group_factors or {}).items()}
        self._cache: dict = {}

    @staticmethod
    def _checked(factors) -> dict:
        out = {k: float(v) for k, v in (factors or {}).items()}
        unknown = sorted(set(out) - set(FACTORS))
        bad = [k for k, v in out.items() if not (math.isfinite(v) and v > 0.0)]
        if unknown or bad:
            raise ModelError(f"Models factors: unknown {unknown} (allowed: {', '.join(FACTORS)}), "
                             f"or not finite and > 0: {bad}")
        return out

    def factors_of(self, group=None) -> dict:
        """The factors ``group``'s models take (the scene-wide ones without a group of its own)."""
        if group is not None and group.name in self.group_factors:
            return self.group_factors[group.name]
        return self.factors

    def _factor(self, name: str, group=None) -> float:
        return self.factors_of(group).get(name, 1.0)

    def _get(self, key, build):
        if key not in self._cache:
            self._cache[key] = build()
        return self._cache[key]

    def plant_modes(self, group) -> int:
        """Modes the simulated plant of bimorph ``group`` keeps: ``beam.modes``, or with 0 every
        mode of the beam up to :data:`MODE_FOLDS` x ``timing.fs``, at least :data:`MIN_MODES`,
        and up to the last mode near an image band (:func:`image_modes`).

        Why up to 1.5 fs: the DAC's staircase puts images of each tone at fs +- f, and a mode
        near them answers with a current that the ADC folds back onto f itself. The observer's
        model (the continuum) has every mode; a plant without them is not the device it reads.
        Observer error against the plant's truth, 10 Hz ... 1 kHz at 48 kHz (the bundled
        section, docs/selfsense.md): a 15 mm beam 0.56 % with 4 modes, 0.06 % with 5 (its 5th
        at 69 kHz); a 25 mm beam 7.4 % with 6 (to 37 kHz), 1.9 % with 7 (52 kHz), 0.6 % with 8
        (69 kHz); a 30 mm beam 13 % with 4, 4.5 % with 8 (48 kHz), 0.7 % with 9 (61 kHz).
        The images at 2 fs +- f and beyond are as real: on an elastic root (k 2e4 N/m, k_rot
        0.5 N m/rad) under the finger, the 7th mode sits at 96.3 kHz, and without it the
        observer read the plant up to 5.2 % off (0.04 % with it); with E x 1.1 its 8th and
        9th sit at 141.9 and 190.0 kHz, near 3 and 4 fs, and without them a closed loop held the
        tips 0.5-1.1 % off (within 0.14 % with them)."""
        n = int(group.beam.modes)
        return n if n > 0 else self.auto_modes(group)

    def auto_modes(self, group) -> int:
        """The modes ``beam.modes = 0`` keeps for bimorph ``group`` (:meth:`plant_modes`)."""
        def build():
            import numpy as np

            beam = self.beam(group)
            f, _ = beam.modes()
            fs = float(self.scene.timing.fs)
            n = max(MIN_MODES, int(np.count_nonzero(f <= MODE_FOLDS * fs)))
            finger = self.finger(group)
            for b in (beam,) if finger is None else (beam, beam.with_tip(finger.mass, finger.k0)):
                n = max(n, image_modes(b.modes()[0], beam.spec.damping, fs))
            return int(min(f.size, n))

        return self._get(("modes", group.name), build)

    def materials(self, group=None) -> dict:
        """The scene's bimorph materials under the factors (``group``'s own, where it has them)."""
        own = group is not None and group.name in self.group_factors

        def build():
            from dataclasses import replace

            mats, factors = materials(self.scene), self.factors_of(group if own else None)
            if not factors:  # the built-in objects themselves
                return mats
            f = factors.get
            return {name: replace(m, E=m.E * f("E", 1.0), d31=m.d31 * f("d31", 1.0),
                                  eps33T=m.eps33T * f("eps33T", 1.0), rho=m.rho * f("rho", 1.0))
                    for name, m in mats.items()}

        return self._get(("materials", group.name) if own else "materials", build)

    def finger(self, group):
        """The finger on ``group``'s tips (:func:`finger_load`), or None without contact."""
        def build():
            load = finger_load(self.scene, group)
            return None if load is None else self._factored(load, group)

        return self._get(("finger", group.name), build)

    def _factored(self, load, group):
        """``load`` (a MaxwellLoad) under the finger factors of ``group``."""
        from .plant.finger import MaxwellLoad

        f = lambda k: self._factor(k, group)  # noqa: E731
        return MaxwellLoad(load.mass * f("finger_mass"), load.k0 * f("finger_k0"),
                           tuple((k * f("finger_branches"), tau) for k, tau in load.branches))

    def beam(self, group):
        """The finite-element beam of a bimorph group (no finger). A ``support.type = "actuator"``
        root sits on the moving part of the ``em`` group named by ``support.actuator`` (the
        bimodal display), whose suspension and armature give an elastic root with its mass."""
        def build():
            from .plant.beam import BeamSpec, Layer, SupportSpec, build_beam

            b, mats = group.beam, self.materials(group)
            f = lambda k: self._factor(k, group)  # noqa: E731
            layers = tuple(Layer(mats[layer.material], layer.thickness * f("thickness")) for layer in b.layers)
            spec = BeamSpec(b.length, b.width, layers, b.connection, tuple(b.segments), b.damping * f("damping"),
                            b.elements)
            sup = group.support
            if sup.type == "actuator":
                return build_beam(spec, self.carrier(group).support_spec())
            return build_beam(spec, SupportSpec(sup.type, sup.k, sup.k_rot))

        return self._get(("beam", group.name), build)

    def carrier(self, group):
        """The electromagnetic actuator a bimorph group rides on (seed 000 Sec. 3.3, R_m)."""
        scene, name = self.scene, group.support.actuator
        where = f"actuator.{group.name}.support.actuator"
        carrier = scene.group(name)  # a SceneError naming the groups there are
        if carrier.type != "em":
            raise SceneError(f"{scene.source}: {where} = {name!r} is a {carrier.type!r} group; a bimorph can "
                             "ride on an electromagnetic ('em') actuator")
        if tuple(carrier.grid) != tuple(group.grid):
            raise SceneError(f"{scene.source}: {where} = {name!r}: grids differ ({list(carrier.grid)} vs "
                             f"{list(group.grid)}); each bimorph rides on its own carrier pin")
        return self.em(carrier)

    def em(self, group):
        """The electromagnetic perpendicular actuator of an ``em`` group (bimodal display)."""
        def build():
            from .plant.em import EMPlant

            p, finger = group.em, self.finger(group)
            return EMPlant(resistance=p.resistance, inductance=p.inductance, force_constant=p.force_constant,
                           armature_mass=p.armature_mass, payload_mass=p.payload_mass, stiffness=p.stiffness,
                           damping=p.damping, lateral_stiffness=p.lateral_stiffness,
                           tilt_stiffness=p.tilt_stiffness, armature_inertia=p.armature_inertia,
                           preload=p.preload if finger is not None else 0.0, finger=finger)

        return self._get(("em", group.name), build)

    def dot(self, group):
        """The latching Dot Braille pin of a ``dot`` group."""
        def build():
            from .plant.dot import DotPin

            p, finger = group.dot, self.finger(group)
            return DotPin(supply=p.supply, travel=p.travel, resistance=p.resistance, inductance=p.inductance,
                          force_constant=p.force_constant, mass=p.mass, damping=p.damping,
                          latch_force=p.latch_force, finger=finger,
                          preload=p.preload if finger is not None else 0.0)

        return self._get(("dot", group.name), build)

    def solenoid(self, group):
        """The polarized solenoid pin of a ``solenoid`` group."""
        def build():
            from .plant.solenoid import SolenoidPin

            p, finger = group.solenoid, self.finger(group)
            return SolenoidPin(resistance=p.resistance, inductance=p.inductance, force_constant=p.force_constant,
                               mass=p.mass, spring=p.spring, spring_preload=p.spring_preload, damping=p.damping,
                               stroke=p.stroke, stop_stiffness=p.stop_stiffness,
                               stop_damping_ratio=p.stop_damping_ratio, finger=finger,
                               preload=p.preload if finger is not None else 0.0)

        return self._get(("solenoid", group.name), build)

    def pvdf(self, group):
        """The PVDF plate of a ``pvdf`` group with the scene's finger on ``plate.finger_cell``."""
        def build():
            from .plant.pvdf import PvdfPlate

            p, finger = group.plate, self.finger(group)
            pc = tuple(p.probe_cells)
            return PvdfPlate(rows=group.grid[0], cols=group.grid[1], plate_length=p.length, plate_width=p.width,
                             plate_thickness=p.thickness, plate_E=p.E, plate_nu=p.nu, plate_rho=p.rho,
                             gap=p.gap, film_thickness=p.film_thickness, zeta=p.damping,
                             max_mode_hz=p.max_mode_hz, amplifier_bandwidth_hz=group.amplifier.bandwidth,
                             finger=finger, finger_cell=tuple(p.finger_cell),
                             preload=self.scene.finger.preload if finger is not None else 0.0,
                             probe_cells=(pc[:2], pc[2:]))

        return self._get(("pvdf", group.name), build)

    def sma(self, group):
        """The SMA taxel model of an ``sma`` group (no simulation state: also the limiter's load)."""
        def build():
            from .plant.sma import SmaTaxel

            p = group.sma
            return SmaTaxel(prestrain=p.prestrain, h_still=p.h_still, h_forced=p.h_forced, cooling=group.cooling,
                            t_ambient=group.limits.ambient, t_max=p.t_max, t_cut=p.t_cut)

        return self._get(("sma", group.name), build)

    def ring_time(self, group) -> float:
        """Time constant of the slowest decaying oscillation of a bimorph group under its finger
        (the loaded modes' ``1 / sigma``), s: how long a switch-on transient rings."""
        _, tau = self.loaded_modes(group, self.finger(group))
        return float(tau.max()) if tau.size else 0.0

    def loaded_modes(self, group, finger):
        """``(f Hz, tau s)`` of the decaying oscillations of a bimorph group's simulated plant
        under ``finger`` (a load, or None: lifted), amplifier and sense chain included."""
        def build():
            import numpy as np

            from .plant.bimorph import BimorphPlant
            from .plant.frontend import Amplifier, CurrentSense

            plant = BimorphPlant(self.beam(group), Amplifier(group.amplifier.bandwidth),
                                 CurrentSense(group.sense.shunt, group.sense.aa_cutoff, group.sense.aa_order),
                                 finger,
                                 n_modes=self.plant_modes(group))
            ev = np.linalg.eigvals(plant.sys.A)
            osc = ev[(ev.imag > 1e-6 * np.abs(ev)) & (ev.real < 0)]
            return osc.imag / (2.0 * np.pi), -1.0 / osc.real

        return self._get(("modes", group.name, finger), build)

    def spread_loads(self, group) -> list:
        """Every load a closed loop of bimorph ``group`` allows for: :meth:`finger`,
        :meth:`other_fingers` (None: lifted), each finger also with its static stiffness
        :data:`FINGER_SPREAD` times softer and stiffer (the scene's finger is a guess)."""
        from .plant.finger import MaxwellLoad

        loads = []
        for load in [self.finger(group), *self.other_fingers(group)]:
            loads.append(load)
            if load is not None:
                loads += [MaxwellLoad(load.mass, load.k0 * x, load.branches)
                          for x in (1.0 / FINGER_SPREAD, FINGER_SPREAD)]
        return loads

    def _spread_modes(self, group):
        """``(f Hz, tau s)`` of every loaded mode under the loads of :meth:`nearest_modes`."""
        import numpy as np

        modes = [self.loaded_modes(group, load) for load in self.spread_loads(group)]
        return tuple(np.concatenate(x) for x in zip(*modes))

    def lowest_mode(self, group) -> float:
        """The lowest loaded mode of bimorph ``group`` under any load of :meth:`nearest_modes`,
        Hz (inf: none)."""
        fm, _ = self._spread_modes(group)
        return float(fm.min()) if fm.size else float("inf")

    def nearest_modes(self, group, freqs):
        """Per frequency (Hz), the loaded mode of bimorph ``group`` nearest to it under any load
        its observer may read (:meth:`finger`, :meth:`other_fingers`), each also with its static
        stiffness :data:`FINGER_SPREAD` times softer and stiffer (the scene's finger is a guess:
        a softer one pulls a loaded mode 50-100 Hz down): ``(|f_mode - f| Hz, tau s)``, each of
        the shape of ``freqs`` (inf and 0 where the plant has no such mode)."""
        import numpy as np

        f = np.asarray(freqs, dtype=float)
        fm, tm = self._spread_modes(group)
        if not fm.size:
            return np.full(f.shape, np.inf), np.zeros(f.shape)
        near = np.abs(fm - f[..., None]).argmin(axis=-1)
        return np.abs(fm[near] - f), tm[near]

    def drive_load(self, group) -> tuple[float, float]:
        """``(capacitance F, resistance ohm)`` a channel of ``group`` drives (one of them is 0): what
        the limiter's current bound needs, whatever the backend (current = C dV/dt or V / R)."""
        t = group.type
        if t == "bimorph":
            return self.beam(group).capacitance(), 0.0
        if t == "pvdf":
            return self.pvdf(group).capacitance, 0.0
        if t == "em":
            return 0.0, group.em.resistance
        if t == "solenoid":
            return 0.0, group.solenoid.resistance
        if t == "dot":
            return 0.0, group.dot.resistance
        if t == "sma":
            return 0.0, self.sma(group).resistance
        raise SceneError(f"actuator.{group.name}: the limiter needs the electrical load of a {t!r} "
                         "actuator, which this version cannot model yet")

    def observer(self, group, freqs, fs: float, block: int, wave=None, window=None, hop=None,
                 lstsq=False, prefilter=None, rows=None):
        """The self-sensing observer of a bimorph group on ``freqs`` (Hz, ``(n_channels, width)``,
        0 for an unused slot): the transfer-matrix beam under the finger, the front end of the
        group's amplifier and sense chain; the rebuilt tip wave goes into ``wave``; ``window``,
        ``hop``, ``lstsq``, ``prefilter`` and ``rows`` (default all) as for
        :class:`~rtctl.selfsense.rt.Observer` (one window for all channels or one per channel;
        default :func:`~rtctl.selfsense.rt.block_window`). An
        ill-conditioned tone is refused (ModelError)."""
        from .selfsense.observer import N_EST
        from .selfsense.rt import Observer

        return Observer(self.observer_beam(group), freqs, fs, block, self.frontend(group, fs),
                        window=window, image_load=self.finger(group), max_cond=OBSERVER_MAX_COND, wave=wave,
                        hop=hop, lstsq=lstsq, image_loads=self.other_fingers(group), prefilter=prefilter,
                        rows=N_EST if rows is None else rows)

    def observer_beam(self, group):
        """The transfer-matrix twin of ``group``'s beam the observer is designed on."""
        from .selfsense.tmm import TMMBeam

        return TMMBeam.from_fe(self.beam(group))

    def frontend(self, group, fs: float):
        """The drive and sense chain the observer of bimorph ``group`` reads through at ``fs``."""
        from .selfsense.frontend import FrontEnd

        return FrontEnd(fs, group.amplifier.bandwidth, group.sense.aa_cutoff, group.sense.aa_order)

    def other_fingers(self, group) -> list:
        """The loads ``group``'s tips may see besides :meth:`finger`: none (the finger lifted) and
        every other set of the scene's finger subject in the group's direction, under the factors.
        The observer reads its currents through whichever of them its residual favours (the
        aliased images see the tip's load at tens of kHz; :class:`~rtctl.selfsense.rt.Observer`)."""
        from .plant.finger import MaxwellLoad

        first = self.finger(group)
        fi = self.scene.finger
        sets = [s for s in fi.subjects if s.name == fi.subject and s.direction == group.direction] if fi.subject else []
        if first is None and not sets:
            sets = [fi[group.direction]]
        out = [] if first is None else [None]
        for s in sets:
            load = self._factored(MaxwellLoad(s.mass, s.k0, tuple((b.k, b.tau) for b in s.branches)), group)
            if load != first and load not in out:
                out.append(load)
        return out
