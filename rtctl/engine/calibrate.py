"""On-device calibration: measure each bimorph group's segment currents per volt with the finger
lifted, fit the model's factors, write them to a file the rig's models then take.

``rtctl calibrate SCENE`` (:func:`calibrate`), ``control.calibration = "FILE"`` (:func:`scene_calibration`,
read by the rig) and ``control.calibrate = "auto"`` (:func:`auto`, called by the run before it
builds its rig). docs/control.md, "Calibration".

The measurement is an ordinary open-loop run of the scene's backend (the engine's ``run``, its
trace in a temporary directory): every channel of every bimorph group plays the same set of
tones (:func:`rtctl.selfsense.calibrate.lines`) at a small amplitude the limiter never touches,
the switch-on transient is let ring out, and the drive and the sensed currents over a window of
whole periods of every line give each segment's current per commanded volt. Calibration sees the
device only through what a backend delivers, on ``sim`` exactly as on ``audio`` or ``daq``.

The finger must be lifted (with it the fit is 17x worse conditioned, docs/selfsense.md Sec. 6):
the excitation runs with ``finger.contact = false``, which on ``sim`` lifts the simulated
finger, as the user lifts theirs from a real display when asked to.
"""

from __future__ import annotations

import datetime
import json
import math
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import ModelError, RtctlError, SceneError

__all__ = ["Calibration", "FORMAT", "auto", "calibratable", "calibrate", "default_path", "document", "excitation",
           "lifted", "measure", "model_changes", "model_of", "plan", "read", "scene_calibration", "summary_of", "write"]

#: The calibration file's format tag (a reader refuses any other).
FORMAT = "rtctl-calibration-1"
#: Seconds of the analysis window: lines on a grid of its inverse (2 Hz), each whole periods in it.
WINDOW_S = 0.5
#: Share of each of the limiter's bounds (max_voltage, slew, current) the excitation may use at
#: most, and of the sense chain's full scale: far inside, so nothing ever clips or limits.
DRIVE_SHARE = 0.2
#: The switch-on transient must decay to this fraction before the window opens.
SETTLE_DECAY = 1e-5
#: A fit is refused beyond these: the rms residual of the currents, % (fits of free beams leave
#: 0.03-0.13 % at 60 dB of current noise; a finger left on the display, 8 %), the condition
#: number of d log I / d log p (35-112 for a free beam; a finger resting, 1e12), and any factor
#: farther from 1 than this ratio (a device off its model by more is no tolerance but a wrong
#: scene: a wrong material, a channel unconnected).
MAX_RESIDUAL_PCT = 1.0
MAX_COND = 1e4
MAX_FACTOR = 3.0


@dataclass
class GroupPlan:
    """The excitation of one bimorph group: its channels (first global index, count), the lines
    (Hz), the amplitude per line (V), the nominal free first resonance (Hz) and what the drive
    uses of each bound."""

    name: str
    first: int
    n: int
    lines: list
    volts: float
    f1_hz: float
    ring_s: float
    use: dict = field(default_factory=dict)


def calibratable(scene) -> None:
    """Refuse, in one line, a scene with nothing to calibrate (no bimorph group): before the
    measurement, and by ``rtctl check`` for ``control.calibrate = "auto"``."""
    if not _groups(scene):
        raise SceneError(f"{scene.source}: nothing to calibrate: the scene has no bimorph group")


def _groups(scene) -> list:
    """``(group, first global channel)`` of every bimorph group."""
    from ..models import n_channels

    out, ch0 = [], 0
    for g in scene.actuator:
        if g.type == "bimorph":
            out.append((g, ch0))
        ch0 += n_channels(g)
    return out


def _derived(scene, changes: dict):
    """``scene`` with ``changes`` (dotted keys of plain values) applied and validated again: the
    same scene (backend settings and all) but for what the calibration needs different."""
    from ..scene import Scene, validate

    data = scene.to_dict()
    for key, value in changes.items():
        node = data
        *path, last = key.split(".")
        for part in path:
            node = node.setdefault(part, {})
        node[last] = value
    return Scene(validate(data, scene.source), scene.source, scene.overrides)


def lifted(scene):
    """The scene as the calibration plays it: finger lifted, open loop, no observer, no events,
    no calibration of its own."""
    return _derived(scene, {"finger.contact": False, "control.mode": "open", "control.observe": False,
                            "control.calibrate": "off", "control.calibration": "", "events": []})


def plan(scene) -> tuple[list, float]:
    """Per bimorph group its :class:`GroupPlan`, and the settle time (s) before the window.

    The lines: 24 log-spaced from 20 Hz to max(3 kHz, 2 f1) (at most fs / 4) and 9 within
    +-15 % of the nominal free first resonance ``f1``, on the 2 Hz grid of the window. The
    amplitude per line: :data:`DRIVE_SHARE` of the tightest of max_voltage (the sum of the
    lines' amplitudes bounds the peak whatever their phases), slew (sum of ``2 pi f A``), current
    (the model's capacitance times that slew) and the sense chain's full scale (the nominal
    model's current, summed over the lines, counted double for a device that is off its model).
    The settle time: the nominal lifted beam's ring time (its slowest mode's ``1/sigma``),
    doubled for a damping as low as half the nominal, times ``ln(1 / SETTLE_DECAY)``.
    """
    from ..models import Models
    from ..selfsense.calibrate import NEAR_RESONANCE, Currents, lines
    from ..selfsense.identify import BeamParams

    s = lifted(scene)
    models = Models(s)
    fs = float(s.timing.fs)
    plans, settle = [], 0.0
    for g, ch0 in _groups(s):
        params = BeamParams.from_fe(models.beam(g))
        f1 = float(params.beam().natural_frequencies(1)[0])
        f_hi = min(max(3000.0, 2.0 * f1), fs / 4.0)
        near = tuple(x for x in NEAR_RESONANCE if x * f1 < fs / 4.0)
        fr = lines(f1, 1.0 / WINDOW_S, 20.0, f_hi, near=near)
        n = fr.size
        cap = models.drive_load(g)[0]
        slew_per_volt = float(sum(2.0 * math.pi * fr))
        current = Currents(params)(fr)
        full_scale = g.sense.full_scale / g.sense.shunt if s.io.backend == "sim" else float(s.io.amps_per_fs)
        sensed_per_volt = float(abs(current).sum(axis=0).max())
        bounds = {"max_voltage": (float(n), g.max_voltage), "slew": (slew_per_volt, g.limits.slew),
                  "current": (cap * slew_per_volt, g.limits.current), "sense": (sensed_per_volt, full_scale)}
        margin = {"sense": 2.0}  # the sensed current is the model's: room for a device off its model
        volts = DRIVE_SHARE * min(limit / (per_volt * margin.get(k, 1.0)) for k, (per_volt, limit) in bounds.items())
        use = {k: {"used": volts * per_volt, "bound": limit, "share": volts * per_volt / limit}
               for k, (per_volt, limit) in bounds.items()}
        ring = models.ring_time(g)
        settle = max(settle, 2.0 * ring * math.log(1.0 / SETTLE_DECAY))
        plans.append(GroupPlan(g.name, ch0, g.grid[0] * g.grid[1], [float(f) for f in fr], float(volts), f1,
                               float(ring), use))
    block = int(s.timing.block)
    settle = math.ceil(max(settle, 0.05) * fs / block) * block / fs
    return plans, settle


#: Blocks the excitation runs on after the window, so that the currents answering its last drive
#: block are in the trace: they follow by the backend's latency (sim 1, audio and daq 2 blocks).
TAIL_BLOCKS = 4


def excitation(scene, plans, settle: float):
    """The scene that plays the excitation: :func:`lifted`, every channel of each planned group
    with its lines, for the settle time, the window and :data:`TAIL_BLOCKS` (or
    ``io.latency_blocks`` + 1) blocks."""
    tones = [{"actuator": p.name, "channel": c, "freq": f, "voltage": p.volts, "receptor": "auto"}
             for p in plans for c in range(p.n) for f in p.lines]
    block, fs = int(scene.timing.block), float(scene.timing.fs)
    tail = max(TAIL_BLOCKS, int(scene.io.latency_blocks) + 1)
    duration = settle + WINDOW_S + tail * block / fs
    return _derived(lifted(scene), {"stimulus.kind": "tones", "stimulus.method": "tones", "stimulus.tones": tones,
                                    "timing.duration": duration})


@dataclass
class Measurement:
    """What :func:`measure` returns: per group its plan and the sensed current per commanded
    volt, ``(n_channels, n_lines, n_seg)`` complex; how long it took."""

    groups: list
    currents: dict
    settle_s: float
    excitation_s: float
    wall_s: float
    latency_blocks: int
    fs: float
    block: int


def _say(say, text):
    if say is not None:
        say(text)


def measure(scene, run, say=None) -> Measurement:
    """Play the excitation through the scene's backend and read the currents per volt from the
    trace.

    Parameters
    ----------
    scene : rtctl.scene.Scene
    run : callable
        The engine's run (:func:`rtctl.engine.run.run`), handed in because a run itself calls
        this for ``control.calibrate = "auto"``.
    say : callable, optional
        Where the messages for the user go (one line each).

    Raises
    ------
    SceneError
        No bimorph group; the limiter acted, a sensor clipped or the run faulted (the
        measurement is then void).
    """
    import numpy as np

    from .. import safety
    from ..selfsense.calibrate import phasors
    from ..trace import TraceReader

    calibratable(scene)
    plans, settle = plan(scene)
    exc = excitation(scene, plans, settle)
    if scene.io.backend == "sim":
        _say(say, "sim: the excitation runs with finger.contact = false on the simulated device "
                  "(the user lifting the finger)")
    else:  # the user must hear this one, whatever else is silenced
        (say or (lambda text: print(f"rtctl: {text}", file=sys.stderr)))("lift the finger from the display")
        if sys.stdin.isatty():
            input("press Enter when no finger touches the display ")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="rtctl-calibrate-") as tmp:
        result = run(exc, out_dir=tmp, plot=False, report=False)
        if result.interrupted:
            raise KeyboardInterrupt
        if result.summary["faults"]:
            raise SceneError(f"{scene.source}: calibration: the excitation ended on a fault: "
                             f"{'; '.join(result.summary['faults'])}")
        reader = TraceReader(Path(tmp) / "trace")
        fs, block = reader.fs, reader.block
        n0, n = round(settle * fs / block) * block, round(WINDOW_S * fs)
        # blocks from a drive block to the sensed block answering it, as the run's backend said
        latency = int(reader.layout["meta"].get("latency_blocks") or scene.io.latency_blocks or 1)
        shift = latency * block
        st = np.asarray(reader.status, dtype=np.int64)
        # the limiter must never act; a clipped reading or a dropped block matters in the window
        window = st[n0 // block:(n0 + shift + n) // block + 1]
        bad = int(np.bitwise_or.reduce(st, initial=0)) & (safety.LIMIT_VOLTAGE | safety.LIMIT_SLEW
                                                          | safety.LIMIT_DC | safety.LIMIT_DUTY)
        bad |= int(np.bitwise_or.reduce(window, initial=0)) & (safety.SENSOR_SATURATED | safety.IO_XRUN)
        if bad:
            raise SceneError(f"{scene.source}: calibration: {', '.join(safety.describe(bad))} during the "
                             "excitation: the measurement is void (lower the drive or check the sense chain)")
        if reader.n_blocks * block < n0 + shift + n:
            raise SceneError(f"{scene.source}: calibration: the excitation's trace is short "
                             f"({reader.n_blocks} blocks)")
        rows = {name: i for i, name in enumerate(reader.layout["meta"]["sensed_rows"])}
        drive = reader.signal("drive")
        sensed = reader.signal("sensed")
        currents = {}
        for p in plans:
            g = scene.group(p.name)
            n_seg = len(g.beam.segments)
            d = phasors(drive[p.first:p.first + p.n, n0:n0 + n], fs, p.lines)  # (n_ch, n_f)
            idx = [rows[f"{p.name}.{c}.seg{j}"] for c in range(p.n) for j in range(n_seg)]
            s = phasors(sensed[idx, n0 + shift:n0 + shift + n], fs, p.lines).reshape(p.n, n_seg, -1)
            currents[p.name] = (s / d[:, None, :]).transpose(0, 2, 1)
        del reader  # its file map, before the directory goes
    wall = time.perf_counter() - t0
    return Measurement(plans, currents, settle, float(exc.timing.duration), wall, latency, fs, block)


def calibrate(scene, run, say=None) -> dict:
    """Measure (:func:`measure`) and fit (:func:`document`) every bimorph group: the calibration
    document (what ``rtctl calibrate --json`` prints and the file holds)."""
    return document(scene, measure(scene, run, say), say)


def document(scene, m: Measurement, say=None) -> dict:
    """Fit every group of measurement ``m`` of ``scene``; anchor the scale on ``beam.mass`` where
    given; the calibration document. ``say`` hears of a fit that takes long."""
    import numpy as np

    from ..models import Models
    from ..selfsense.calibrate import anchored, beam_mass, fit, scale_uncertainty_pct, warps_with_E
    from ..selfsense.frontend import FrontEnd
    from ..selfsense.identify import BeamParams

    t0 = time.perf_counter()
    models = Models(lifted(scene))
    groups = {}
    warnings = []
    for p in m.groups:
        g = scene.group(p.name)
        params = BeamParams.from_fe(models.beam(g))
        # 20 images a side: the rest moves no factor by more than 1e-5 (40 would cost twice the time)
        front = FrontEnd(m.fs, g.amplifier.bandwidth, g.sense.aa_cutoff, g.sense.aa_order, n_images=20)
        cur = m.currents[p.name]
        if not warps_with_E(params.support):
            _say(say, f"fitting group {p.name!r}: its root is on springs, so the fit solves the beam "
                      "for every E it tries (tens of seconds)")
        try:
            # currents that fit no beam drive the factors to absurd values (a damping of 1e-37):
            # let the model's infinities run into the checks below rather than into warnings
            with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
                r = fit(params, front, p.lines, cur)
        except (ModelError, ValueError, ArithmeticError) as e:
            raise RtctlError(f"calibration refused: group {p.name!r}: the currents fit no free beam of this "
                             f"scene ({e}){_HINT}") from None
        _check(p.name, r)
        b = g.beam
        factors, anchor = dict(r.factors), None
        if b.mass > 0:
            nominal = beam_mass(params)
            s = b.mass / nominal
            factors = anchored(r.factors, s)
            anchor = {"mass_kg": b.mass, "nominal_mass_kg": nominal, "scale": s, "mass_tolerance": b.mass_tolerance}
            if abs(s - 1.0) > 3.0 * max(b.tolerance, b.mass_tolerance):
                warnings.append(f"{p.name}: beam.mass is {100 * (s - 1):+.1f} % off the nominal beam's "
                                f"{nominal * 1e6:.4g} mg, more than beam.tolerance explains: is it the mass of "
                                "the free length alone?")
        unc = scale_uncertainty_pct(b.tolerance, b.mass_tolerance if anchor else None)
        mean = cur.mean(axis=0)
        groups[p.name] = {
            "channels": p.n,
            "model": model_of(scene, g),
            "factors": factors,
            "fitted": dict(r.factors),
            "sd": r.sd,
            "anchor": anchor,
            "tolerance": b.tolerance,
            "uncertainty_pct": unc,
            "residual_pct": r.residual_pct,
            "channel_residual_pct": list(r.residual_each),
            "cond": r.cond,
            "singular_values": list(r.singular_values),
            "f1_nominal_hz": p.f1_hz,
            "f1_fitted_hz": p.f1_hz * math.sqrt(factors.get("E", 1.0) / factors.get("rho", 1.0)),
            "lines_hz": p.lines,
            "volts_per_line": p.volts,
            "limits_used": p.use,
            "current_per_volt": [[[c.real, c.imag] for c in row] for row in mean.tolist()],
        }
    fit_s = time.perf_counter() - t0
    return {
        "format": FORMAT,
        "scene": scene.scene.name,
        "source": scene.source,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "backend": scene.io.backend,
        "fs": m.fs,
        "block": m.block,
        "excitation": {"finger": "lifted" + (" (finger.contact = false on the simulated device)"
                                             if scene.io.backend == "sim" else ""),
                       "settle_s": m.settle_s, "window_s": WINDOW_S, "duration_s": m.excitation_s,
                       "latency_blocks": m.latency_blocks, "wall_s": m.wall_s, "limiter_acted": False},
        "fit_s": fit_s,
        "groups": groups,
        "warnings": warnings,
    }


#: The sense chain's keys the model (and so the fit) depends on; its noise, bits and full scale
#: only set how well the currents are read.
_SENSE_MODEL = ("shunt", "aa_cutoff", "aa_order")
#: The keys of a carrying ``em`` group that make a ``support.type = "actuator"`` root
#: (``EMPlant.support_spec``).
_CARRIER_MODEL = ("lateral_stiffness", "tilt_stiffness", "armature_mass", "armature_inertia")


def model_of(scene, group) -> dict:
    """What a group's fitted factors multiply: the scene's beam (geometry, layers, damping,
    mass and tolerances), support, amplifier, the sense chain's filter, and the properties of the
    materials its layers use. A calibration applies only to the model it was fitted on: recorded
    with the factors, checked when a run reads them (:func:`read`). Non-finite values (a rigid
    support's ``k = inf``) as strings, so the file stays JSON."""
    import dataclasses

    from ..jsonsafe import strict
    from ..models import materials

    mats = materials(scene)
    used = sorted({layer.material for layer in group.beam.layers})
    # beam.modes is the simulated device's (its plant's truncation), no part of the fitted model
    beam = {k: v for k, v in group.beam.to_dict().items() if k != "modes"}
    support = group.support.to_dict()
    if group.support.type == "actuator":
        # the root is the carrier's suspension and armature (Models.carrier): a change there moves
        # the beam's resonances as much as a change of the beam's own support would
        em = scene.group(group.support.actuator).em
        support["carrier"] = {k: em[k] for k in _CARRIER_MODEL}
    model = {"beam": beam, "support": support,
             "amplifier": group.amplifier.to_dict(), "sense": {k: group.sense[k] for k in _SENSE_MODEL},
             "materials": {n: dataclasses.asdict(mats[n]) for n in used}}
    return strict(model, repr)


def model_changes(recorded, now, at: str = "") -> list[str]:
    """Where ``recorded`` (a calibration's ``model``, as read from its file: any JSON) differs from
    ``now`` (:func:`model_of`), as ``"beam.length 0.015 -> 0.025"``; a few at most."""
    if isinstance(now, dict):
        if not isinstance(recorded, dict):
            return [f"{at or 'model'}: {_short(recorded, 40)}, not a table"]
        out = []
        for k in sorted(set(now) | set(recorded)):
            where = f"{at}.{k}" if at else k
            if k not in recorded or k not in now:
                out.append(f"{where} {'not recorded' if k not in recorded else 'not in the scene'}")
            else:
                out += model_changes(recorded[k], now[k], where)
        return out
    if isinstance(now, list):
        if not isinstance(recorded, list) or len(recorded) != len(now):
            return [f"{at} {_short(recorded, 40)} -> {_short(now, 40)}"]
        return [x for i, (a, b) in enumerate(zip(recorded, now)) for x in model_changes(a, b, f"{at}.{i}")]
    return [] if _same(recorded, now) else [f"{at} {_short(recorded, 40)} -> {_short(now, 40)}"]


def _same(a, b) -> bool:
    """Equal JSON leaves: numbers by value (a file may hold 2.0 for 2), anything else (bools,
    strings, null) only of the same type too (``True == 1`` is no match)."""
    number = (int, float)
    if isinstance(a, number) and isinstance(b, number) and not isinstance(a, bool) and not isinstance(b, bool):
        return a == b
    return type(a) is type(b) and a == b


_HINT = ("; was a finger on the display during the excitation, a segment unconnected, or the scene's "
         "beam or material not the device's?")


def _check(name: str, r) -> None:
    """Refuse a fit the currents do not support (:data:`MAX_RESIDUAL_PCT`, :data:`MAX_COND`,
    :data:`MAX_FACTOR`): an observer built on it would be worse than the uncalibrated model."""
    bad = []
    if not r.residual_pct <= MAX_RESIDUAL_PCT:
        bad.append(f"residual {r.residual_pct:.3g} % of the currents (> {MAX_RESIDUAL_PCT:g} %)")
    if not r.cond <= MAX_COND:
        bad.append(f"condition number {r.cond:.3g} (> {MAX_COND:g})")
    off = {k: v for k, v in r.factors.items() if not (1.0 / MAX_FACTOR <= v <= MAX_FACTOR)}
    if off:
        bad.append("factors " + ", ".join(f"{k} x{v:.3g}" for k, v in off.items())
                   + f" (beyond x{1 / MAX_FACTOR:.2g} ... x{MAX_FACTOR:g})")
    if bad:
        raise RtctlError(f"calibration refused: group {name!r}: " + "; ".join(bad) + _HINT)


def write(doc: dict, path) -> Path:
    """Write the calibration document to ``path`` (directories made), JSON."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(doc, indent=1, allow_nan=False))
    return p


def default_path(scene) -> Path:
    return Path("out") / scene.scene.name / "calibration.json"


# --- using a calibration ------------------------------------------------------------------------

@dataclass(frozen=True)
class Calibration:
    """A calibration in use, from ``path``: per group its factors and what it says of the group's
    amplitude (``uncertainty_pct``); ``factors`` the one set every group shares (None where the
    groups' fits differ: each group's models then take its own, :meth:`models`)."""

    path: str
    factors: dict | None
    groups: dict

    @property
    def group_factors(self) -> dict:
        return {g: v["factors"] for g, v in self.groups.items()}

    def models(self, scene):
        """The rig's :class:`~rtctl.models.Models` of ``scene`` under this calibration."""
        from ..models import Models

        if self.factors is not None:
            return Models(scene, factors=self.factors)
        return Models(scene, group_factors=self.group_factors)

    def uncertainty_pct(self, group: str):
        """The bound on the amplitude scale of ``group`` the currents cannot see, %."""
        g = self.groups.get(group)
        return None if g is None else g["uncertainty_pct"]

    def tone_uncertainty_pct(self, group: str, gain: float):
        """The bound on a tone's calibrated amplitude, %: the scale's (:meth:`uncertainty_pct`)
        plus what the observer makes of the fit's misfit of the currents. The fitted model
        predicts the currents no better than its rms residual (``residual_pct``), and the
        observer turns a relative current error into ``gain`` times as large a tip error
        (:attr:`rtctl.selfsense.observer.ObserverMatrix.gain`: 10-13 on the bundled 15 mm beam,
        185-271 at 700 Hz-1 kHz on a 30 mm one, above its first loaded resonance, where the
        motional current is a fraction of a percent of the reading). Bounds add. A file without
        a residual (written by hand) gives the scale's alone."""
        g = self.groups.get(group)
        if g is None:
            return None
        res = g.get("residual_pct")
        return g["uncertainty_pct"] + (0.0 if res is None else float(gain) * res)


def _resolve(scene, value: str) -> Path:
    """``control.calibration`` as a path: relative to the scene file, else to the working
    directory."""
    p = Path(value)
    if p.is_absolute():
        candidates = [p]
    else:
        candidates = [Path(scene.source).resolve().parent / p, Path.cwd() / p]
    for c in candidates:
        try:
            if c.is_file():
                return c
        except OSError as e:  # a name too long for the file system: is_file raises rather than says False
            raise SceneError(f"{scene.source}: control.calibration = {_short(value)}: cannot read it "
                             f"({e.strerror})") from None
    where = " or ".join(str(c) for c in candidates)
    raise SceneError(f"{scene.source}: control.calibration = {value!r}: no such file ({where})")


def read(path, scene) -> Calibration:
    """The calibration at ``path`` for ``scene``: refused in one line (SceneError) when the file
    is not a calibration, is another scene's, or names a group the scene has no bimorph group of."""
    from ..models import FACTORS

    where = f"{scene.source}: control.calibration = {str(path)!r}"
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"{where}: cannot read it: {e}") from None
    except (ValueError, RecursionError) as e:  # RecursionError: arrays nested thousands deep
        raise SceneError(f"{where}: not a calibration file (not JSON: {_short(str(e), 120)})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise SceneError(f"{where}: not a calibration file (format {_short(got)}, expected {FORMAT!r})")
    name = scene.scene.name
    if doc.get("scene") != name:
        raise SceneError(f"{where}: a calibration of scene {_short(doc.get('scene'))}, not of {name!r}")
    groups = doc.get("groups")
    if not isinstance(groups, dict) or not groups:
        raise SceneError(f"{where}: not a calibration file (no groups)")
    bimorph = [g.name for g, _ in _groups(scene)]
    out = {}
    for gname, entry in groups.items():
        if gname not in bimorph:
            raise SceneError(f"{where}: group {_short(gname)} is no bimorph group of this scene "
                             f"(bimorph groups: {', '.join(bimorph) or 'none'})")
        try:
            factors = {str(k): float(v) for k, v in entry["factors"].items()}
            unc = float(entry["uncertainty_pct"])
            res = None if entry.get("residual_pct") is None else float(entry["residual_pct"])
        except (KeyError, TypeError, ValueError, AttributeError, OverflowError):  # Overflow: 10**400
            raise SceneError(f"{where}: group {gname!r}: not a calibration (needs factors and "
                             "uncertainty_pct; residual_pct a number if given)") from None
        if res is not None and not (math.isfinite(res) and res >= 0.0):
            raise SceneError(f"{where}: group {gname!r}: residual_pct = {res!r} is not a finite number >= 0")
        bad = [k for k, v in factors.items() if k not in FACTORS or not (math.isfinite(v) and v > 0)]
        if bad or not math.isfinite(unc):
            raise SceneError(f"{where}: group {gname!r}: factors {_short(bad)} unknown or not finite and > 0 "
                             f"(allowed: {', '.join(FACTORS)})")
        if "model" in entry:  # files written by hand may leave it out; rtctl calibrate writes it
            changes = model_changes(entry["model"], model_of(scene, scene.group(gname)))
            if changes:
                more = f" and {len(changes) - 3} more" if len(changes) > 3 else ""
                raise SceneError(f"{where}: group {gname!r} was calibrated on another model of the actuator "
                                 f"({'; '.join(changes[:3])}{more}): its factors do not apply to this one; "
                                 "calibrate again (rtctl calibrate)")
        out[gname] = {"factors": factors, "uncertainty_pct": unc, "residual_pct": res}
    missing = [g for g in bimorph if g not in out]
    if missing:
        raise SceneError(f"{where}: has no calibration of group {missing[0]!r}")
    sets = {json.dumps(v["factors"], sort_keys=True) for v in out.values()}
    shared = next(iter(out.values()))["factors"] if len(sets) == 1 else None
    return Calibration(str(path), shared, out)


def scene_calibration(scene):
    """The :class:`Calibration` ``control.calibration`` names, or None without one (the rig's
    models then take the scene's nominal values)."""
    value = scene.control.calibration
    if not value:
        return None
    return read(_resolve(scene, value), scene)


def auto(scene, out_dir, run, say=None):
    """``control.calibrate = "auto"``: measure and fit now, write ``calibration.json`` into
    ``out_dir`` (a temporary file without one), and return ``(the scene with control.calibration
    naming it, the document)``; the run then builds its rig on it."""
    doc = calibrate(scene, run, say)
    ex = doc["excitation"]
    _say(say, f"calibrated in {ex['wall_s'] + doc['fit_s']:.1f} s ({ex['duration_s']:.2f} s of excitation, "
              f"{ex['wall_s']:.1f} s to run it, {doc['fit_s']:.1f} s to fit)")
    if out_dir is not None:
        path = write(doc, Path(out_dir) / "calibration.json")
    else:
        fd = tempfile.NamedTemporaryFile(prefix="rtctl-calibration-", suffix=".json", delete=False)
        fd.close()
        path = write(doc, fd.name)
    return _derived(scene, {"control.calibrate": "off", "control.calibration": str(Path(path).resolve())}), doc


def summary_of(calibration, doc=None) -> dict | None:
    """What a run's summary says of the calibration it used (None: uncalibrated)."""
    if calibration is None:
        return None
    out = {"file": calibration.path, "factors": calibration.factors,
           **({} if calibration.factors is not None else {"group_factors": calibration.group_factors}),
           "uncertainty_pct": {g: v["uncertainty_pct"] for g, v in calibration.groups.items()}}
    if doc is not None:
        ex = doc["excitation"]
        out.update({"measured": True, "excitation_s": ex["duration_s"], "wall_s": ex["wall_s"], "fit_s": doc["fit_s"]})
    return out


def _short(v, n: int = 60) -> str:
    """``repr(v)`` cut to ``n`` characters, for one-line messages about what a file holds."""
    r = repr(v)
    return r if len(r) <= n else r[: n - 3] + "..."
