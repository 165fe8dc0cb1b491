"""Faults the simulated hardware injects: ``[io.faults]`` (backend ``sim``, ``rtctl emulate audio``,
``rtctl emulate serial``), one vocabulary for all three.

A fault is the *device* misbehaving: the simulated device (or emulator) injects it on its side of
the block contract and the rig is never told. What the rig does about it is what it would do on
hardware: ride through, flag (a status bit in the trace and a warning in the summary), or fade
every output to 0 V and end the run (exit 1). Each kind's required outcome is written in
:data:`KINDS` and in docs/faults.md; ``rtctl bench faults`` checks it over many seeded runs.

The plan (:class:`Fault` list, :func:`plan`) is the scene's ``io.faults.inject`` table plus
``io.faults.random`` faults drawn with ``io.faults.seed``. The injector (:class:`Injector`) holds it
in preallocated arrays that its kernels read once per block; :meth:`Injector.load` replaces the
plan between runs without a rebuild (what the fault campaign does).
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass

import numpy as np

from .._numba import kernel
from ..errors import SceneError
from ..safety import DEVICE_LOST, ESTIMATE_NONFINITE, IO_XRUN, SENSOR_SATURATED, XRUN_BURST


@dataclass(frozen=True)
class Kind:
    """One fault kind: its code in the injector's plan, where it can be injected, what the run
    must do (``ride``: the run goes on within every limit, no fault; ``flag``: as ride, and the
    status ``bit`` marks the blocks it hit; ``fade``: ``bit`` ends the run, outputs faded to 0 V,
    exit 1), and what it is."""

    code: int
    where: tuple
    outcome: str
    bit: int
    doc: str


SIM, AUDIO, SERIAL = "sim", "emulate audio", "emulate serial"
_SENSE = (SIM, AUDIO)

#: The vocabulary. The outcome of ``sensed_nan``/``sensed_inf`` is ``flag`` where a self-sensing
#: observer reads the row (``ESTIMATE_NONFINITE``), ``ride`` where nothing does; ``xrun_burst``
#: flags (``IO_XRUN``) a burst within ``io.xrun_limit`` and fades (``XRUN_BURST``) a longer one
#: (:func:`expected`).
KINDS = {
    "sensed_nan": Kind(0, _SENSE, "flag", ESTIMATE_NONFINITE,
                       "sensed current reads NaN (a driver or converter bug)"),
    "sensed_inf": Kind(1, _SENSE, "flag", ESTIMATE_NONFINITE, "sensed current reads +inf"),
    "adc_saturated": Kind(2, _SENSE, "flag", SENSOR_SATURATED,
                          "the current ADC pinned at full scale (the simulated ADC reports its clip, as the "
                          "plant's own saturation does)"),
    "sensed_zero": Kind(3, _SENSE, "ride", 0, "a sensed row stuck at 0"),
    "sensed_frozen": Kind(4, _SENSE, "ride", 0, "a sensed row frozen at its last value"),
    "electrode_open": Kind(5, _SENSE, "ride", 0,
                           "a segment electrode open: its current reads 0 from then on (permanent)"),
    "block_dropped": Kind(6, (SIM, AUDIO), "flag", IO_XRUN,
                          "one block lost both ways: the plant gets 0 V, the readings are 0 (the device "
                          "counts an xrun)"),
    "latency_spike": Kind(7, _SENSE, "ride", 0,
                          "the readings arrive `value` blocks late (1-63) for `blocks` blocks"),
    "xrun_burst": Kind(8, (SIM,), "flag", IO_XRUN,
                       "`blocks` dropped blocks in a row, each an xrun: more than the io.xrun_limit bucket "
                       "takes ends the run (XRUN_BURST)"),
    "amp_clipped": Kind(9, (SIM, AUDIO), "ride", 0,
                        "the amplifier clips at `value` x max_voltage (default 0.5): the plant gets less "
                        "than the rig sent"),
    "finger_slam": Kind(10, (SIM,), "ride", 0,
                        "the finger presses `value` x finger.preload (default 4) from one sample to the next"),
    "finger_lift": Kind(11, (SIM,), "ride", 0, "the finger leaves the display from one sample to the next"),
    "device_stopped": Kind(12, (SIM, AUDIO, SERIAL), "fade", DEVICE_LOST,
                           "the device stops answering (sim: no block comes back; audio: its inputs go "
                           "digitally silent; serial: frames go unanswered)"),
    "byte_flip": Kind(13, (SERIAL,), "ride", 0, "one bit flipped in a fraction `value` of the answers' bytes"),
    "byte_drop": Kind(14, (SERIAL,), "ride", 0, "a fraction `value` of the host's bytes lost"),
    "byte_dup": Kind(15, (SERIAL,), "ride", 0, "a fraction `value` of the answers' bytes sent twice"),
}
CODE = {k.code: name for name, k in KINDS.items()}
_K = {name: k.code for name, k in KINDS.items()}
SENSED_KINDS = ("sensed_nan", "sensed_inf", "adc_saturated", "sensed_zero", "sensed_frozen", "electrode_open",
                "latency_spike")
FINGER_KINDS = ("finger_slam", "finger_lift")
#: the kinds that last to the end of the run whatever ``blocks`` says
PERMANENT = ("electrode_open", "device_stopped", "finger_slam", "finger_lift")
#: blocks of history the latency spike reads from (its ``value`` is at most one less)
HISTORY = 64
#: most faults one run holds (the plan's rows)
MAX_FAULTS = 64
_END = 2**62

# plan columns
_KIND, _START, _STOP, _ROW, _N = range(5)
# control array: block count, xrun bucket level, in per xrun, out per block, cap
_BLK, _XLEVEL, _XADD, _XLEAK, _XCAP = range(5)


@dataclass(frozen=True)
class Fault:
    """One fault of a run: ``kind``, first block ``start``, blocks ``blocks`` (0: to the end),
    ``row`` (-1: every row/channel), ``value`` (the kind's parameter; 0: its default)."""

    kind: str
    start: int
    blocks: int = 1
    row: int = -1
    value: float = 0.0

    @property
    def stop(self) -> int:
        return _END if self.blocks == 0 or self.kind in PERMANENT else self.start + self.blocks

    def to_dict(self) -> dict:
        return {"kind": self.kind, "start": self.start, "blocks": self.blocks, "row": self.row, "value": self.value}


@dataclass(frozen=True)
class Context:
    """What the plan needs to know of the rig: rows and channels, which sensed rows an observer
    reads, and the xrun guard's bucket."""

    where: str
    n_blocks: int
    n_sensed: int
    n_channels: int
    observed_rows: tuple = ()
    fingers: bool = False
    xrun_limit: int = 0
    xrun_window_blocks: int = 1
    #: the device's sensed row names (``group.channel.label``), where it senses more than the
    #: bimorph segments hardware does (a simulated coil's current): () for the hardware layout
    sensed_names: tuple = ()

    def can(self, kind: str) -> bool:
        if self.where not in KINDS[kind].where:
            return False
        if kind in SENSED_KINDS:
            return self.n_sensed > 0
        if kind in FINGER_KINDS:
            return self.fingers
        return True


def context(scene, where: str = SIM, n_sensed: int | None = None, names=None) -> Context:
    """The :class:`Context` of ``scene`` run on ``where`` (``n_sensed``, ``names``: the device's
    sensed rows, and their names, where they are more than the bimorph segments a scene's
    hardware senses: a simulated coil's current comes before a later group's segments)."""
    from ..events import block_of, duration_blocks
    from ..models import n_channels, sensed_layout

    rows = list(names) if names is not None else sensed_layout(scene)[0]
    fs, blk = float(scene.timing.fs), int(scene.timing.block)
    observed = ()
    if scene.control.observe or scene.control.mode == "closed":
        observed = tuple(i for i, name in enumerate(rows)
                         if scene.group(name.split(".")[0]).type == "bimorph")
    fingers = any(g.type == "bimorph" or g.type in ("em", "dot", "solenoid") for g in scene.actuator)
    return Context(where, duration_blocks(scene.timing.duration, fs, blk),
                   len(rows) if n_sensed is None else int(n_sensed),
                   sum(n_channels(g) for g in scene.actuator), observed, fingers and bool(scene.finger.contact),
                   int(scene.io.xrun_limit), max(1, block_of(scene.io.xrun_window, fs, blk)),
                   tuple(names) if names is not None else ())


def burst_limit(ctx: Context) -> float:
    """Consecutive xrun blocks from rest the guard's bucket takes before it ends the run: with N =
    ``io.xrun_limit`` and W the window in blocks it fills by W - N per xrun block and holds N W, so
    N W / (W - N); inf with the guard off."""
    n, w = ctx.xrun_limit, ctx.xrun_window_blocks
    return math.inf if n <= 0 or w <= n else n * w / (w - n)


def xrun_blocks(faults) -> set:
    """The blocks the device flags ``IO_XRUN`` (dropped blocks and xrun bursts; a stopped device
    counts none)."""
    return {k for f in faults if f.kind in ("block_dropped", "xrun_burst")
            for k in range(f.start, f.start + max(1, f.blocks))}


def xrun_fault_block(faults, ctx: Context) -> int | None:
    """The block the xrun guard ends the run at for these faults, by the documented rule (a
    leaky bucket: W in per flagged block, N out per block, more than N W in it ends the run; N
    = ``io.xrun_limit``, W its window in blocks); None when it never does."""
    blocks = xrun_blocks(faults)
    n, w = ctx.xrun_limit, ctx.xrun_window_blocks
    if not blocks or n <= 0 or w <= n:
        return None
    level = 0
    for k in range(min(blocks), max(blocks) + 1):
        level = max(level - n, 0) + (w if k in blocks else 0)
        if level > n * w:
            return k
    return None


def expected(f: Fault, ctx: Context) -> tuple[str, int]:
    """``(outcome, status bit)`` the run must show for fault ``f`` (see :data:`KINDS`)."""
    k = KINDS[f.kind]
    if f.kind in ("sensed_nan", "sensed_inf"):
        hit = ctx.observed_rows if f.row < 0 else tuple(r for r in ctx.observed_rows if r == f.row)
        return ("flag", k.bit) if hit else ("ride", 0)
    if f.kind == "xrun_burst":
        return ("fade", XRUN_BURST) if f.blocks > burst_limit(ctx) else ("flag", IO_XRUN)
    return k.outcome, k.bit


def plan(scene, ctx: Context, seed: int | None = None, random_n: int | None = None) -> list[Fault]:
    """The faults of one run: ``io.faults.inject``, then ``io.faults.random`` drawn ones (``seed``
    and ``random_n`` replace the scene's seed and count).

    Raises
    ------
    SceneError
        A kind this backend or scene cannot take, a row it does not have, a value out of range.
    """
    spec = scene.io.faults
    src = f"{scene.source}: io.faults"
    fs, blk = float(scene.timing.fs), int(scene.timing.block)
    from ..events import block_of

    out = []
    for i, item in enumerate(spec.inject):
        where = f"{src}.inject.{i}"
        if not ctx.can(item.kind):
            raise SceneError(f"{where}.kind = {item.kind!r}: {_why_not(item.kind, ctx)}")
        f = Fault(item.kind, block_of(item.at, fs, blk), int(item.blocks), int(item.row), float(item.value))
        _check(f, ctx, where)
        out.append(f)
    n = spec.random if random_n is None else random_n
    if n:
        pool = [k for k in (spec.kinds or KINDS) if ctx.can(k)]
        if not pool:
            raise SceneError(f"{src}.random = {n}: none of the kinds "
                             f"{', '.join(spec.kinds or KINDS)} can be injected on {ctx.where} with this scene")
        rng = random.Random(spec.seed if seed is None else seed)
        out += [draw(rng, pool, ctx) for _ in range(n)]
    if len(out) > MAX_FAULTS:
        raise SceneError(f"{src}: {len(out)} faults in one run; at most {MAX_FAULTS}")
    return out


def _why_not(kind: str, ctx: Context) -> str:
    if ctx.where not in KINDS[kind].where:
        return f"cannot be injected on {ctx.where} (only on {', '.join(KINDS[kind].where)})"
    if kind in SENSED_KINDS:
        return "the scene has no sensed rows (bimorph segment currents)"
    return "needs a finger on a bimorph or pin group (finger.contact = true)"


def _check(f: Fault, ctx: Context, where: str) -> None:
    rows = ctx.n_channels if f.kind == "amp_clipped" else ctx.n_sensed
    if f.row >= rows and (f.kind in SENSED_KINDS or f.kind == "amp_clipped"):
        what = "drive channels" if f.kind == "amp_clipped" else "sensed rows"
        raise SceneError(f"{where}.row = {f.row}: the scene has {rows} {what} (0..{rows - 1}, or -1 for all)")
    if f.kind == "latency_spike" and not (f.value == 0 or 1 <= f.value < HISTORY and f.value.is_integer()):
        raise SceneError(f"{where}.value = {f.value:g}: a latency spike is 1 to {HISTORY - 1} whole blocks")
    if f.kind == "amp_clipped" and f.value > 1:
        raise SceneError(f"{where}.value = {f.value:g}: the clip level is a fraction of max_voltage, in (0, 1]")
    if f.kind.startswith("byte_") and f.value > 1:
        raise SceneError(f"{where}.value = {f.value:g}: the fraction of bytes hit is in (0, 1]")


def draw(rng: random.Random, pool, ctx: Context) -> Fault:
    """One random fault of a kind in ``pool``: it starts within the first 80 % of the run (after
    its first 10 %), lasts a few blocks to a few tens, hits one row or all of them."""
    kind = rng.choice(sorted(pool))
    start = rng.randint(ctx.n_blocks // 10, max(ctx.n_blocks // 10, (8 * ctx.n_blocks) // 10))
    blocks, row, value = rng.randint(1, 20), -1, 0.0
    if kind in SENSED_KINDS and rng.random() < 0.5:
        row = rng.randrange(ctx.n_sensed)
    if kind == "latency_spike":
        value, blocks = float(rng.randint(1, 8)), rng.randint(5, 50)
    elif kind == "block_dropped":
        blocks = rng.randint(1, 3)
    elif kind == "xrun_burst":  # clearly within the guard's bucket, or clearly beyond it (and within the run)
        lim = burst_limit(ctx)
        big = math.isfinite(lim) and rng.random() < 0.5 and ctx.n_blocks > math.ceil(2 * lim)
        if big:
            blocks = rng.randint(math.ceil(2 * lim), min(math.ceil(3 * lim), ctx.n_blocks - 1))
            start = min(start, ctx.n_blocks - blocks)
        else:
            blocks = rng.randint(1, max(1, ctx.xrun_limit // 2) if ctx.xrun_limit else 20)
    elif kind == "amp_clipped":
        value, blocks = round(rng.uniform(0.2, 0.8), 3), rng.randint(10, 200)
        if rng.random() < 0.5:
            row = rng.randrange(ctx.n_channels)
    elif kind.startswith("byte_"):  # a frame of ~10 bytes hit one time in 10 to 100, for 0.1-2 s of frames
        value, blocks = round(rng.uniform(0.001, 0.01), 4), rng.randint(100, 2000)
    if kind in PERMANENT:
        blocks = 0
    return Fault(kind, start, blocks, row, value)


# --- the injector: kernels over preallocated arrays ----------------------------------------------

@kernel
def _rows(row, n):
    if row < 0:
        return 0, n
    r = row % n if n > 0 else 0
    return r, r + 1


@kernel
def _phase(kind):
    """The order of the sensed faults within a block (see :func:`inject_sensed`); -1: not one."""
    if kind == 7:
        return 0
    if kind == 3 or kind == 4 or kind == 5:
        return 1
    if kind == 0 or kind == 1 or kind == 2:
        return 2
    if kind == 6 or kind == 8 or kind == 12:
        return 3
    return -1


@kernel
def inject_sensed(plan, value, ctl, sensed, hist, last, full_scale):
    """Block ``ctl[_BLK]``'s readings as the faulty device delivers them, in place; returns the
    status bits the device itself reports (its ADC's clip, an xrun, no answer)."""
    k = ctl[_BLK]
    n_s, nb = sensed.shape
    h = hist.shape[0]
    if h > 0 and n_s > 0:
        hist[k % h] = sensed
    st = 0
    # in the order a device makes them, whatever the plan's order: which block's readings arrive
    # (latency), what the sense chain gives (stuck, frozen, open), what the converter outputs
    # (NaN, inf, full scale), and no block at all (dropped, xrun, stopped)
    for phase in range(4):
        for f in range(plan.shape[0]):
            kind = plan[f, _KIND]
            if kind < 0 or k < plan[f, _START] or k >= plan[f, _STOP] or _phase(kind) != phase:
                continue
            r0, r1 = _rows(plan[f, _ROW], n_s)
            if phase == 3:  # dropped block, xrun burst, device stopped
                sensed[:, :] = 0.0
                st |= DEVICE_LOST if kind == 12 else IO_XRUN
                continue
            for r in range(r0, r1):
                for i in range(nb):
                    if kind == 0:
                        sensed[r, i] = math.nan
                    elif kind == 1:
                        sensed[r, i] = math.inf
                    elif kind == 2:
                        sensed[r, i] = full_scale[r]
                    elif kind == 3 or kind == 5:
                        sensed[r, i] = 0.0
                    elif kind == 4:
                        sensed[r, i] = last[r]
                    elif kind == 7:
                        j = k - plan[f, _N]
                        sensed[r, i] = hist[j % h, r, i] if j >= 0 and h > 0 else 0.0
            if kind == 2:
                st |= SENSOR_SATURATED
    for r in range(n_s):
        last[r] = sensed[r, nb - 1]
    return st


@kernel
def inject_drive(plan, value, ctl, drive, dev, vmax):
    """What the plant receives of block ``ctl[_BLK]``'s drive ``drive`` (the rig's limited
    output, left as it is) into ``dev``. Returns 0."""
    k = ctl[_BLK]
    n_c, nb = drive.shape
    dev[:, :] = drive
    for f in range(plan.shape[0]):
        kind = plan[f, _KIND]
        if kind < 0 or k < plan[f, _START] or k >= plan[f, _STOP]:
            continue
        if kind == 6 or kind == 8 or kind == 12:
            dev[:, :] = 0.0
        elif kind == 9:
            r0, r1 = _rows(plan[f, _ROW], n_c)
            for c in range(r0, r1):
                lim = value[f] * vmax[c]
                for i in range(nb):
                    dev[c, i] = min(max(dev[c, i], -lim), lim)
    return 0


@kernel
def count_block(ctl):
    """The device's block is done: the next one starts. Returns 0."""
    ctl[_BLK] += 1
    return 0


@kernel
def inject_finger(plan, ctl, target, col, lift, slam):
    """A finger fault starting at block ``ctl[_BLK]``: ``target[:, col]`` (a simulated group's
    load index or pin preloads) becomes ``lift`` or ``slam``. Returns 0."""
    k = ctl[_BLK]
    for f in range(plan.shape[0]):
        kind = plan[f, _KIND]
        if (kind == 10 or kind == 11) and plan[f, _START] == k:
            v = slam if kind == 10 else lift
            for r in range(target.shape[0]):
                target[r, col] = v
    return 0


@kernel
def xrun_guard(ctl, status):
    """The sim backend's xrun guard (the audio backend's leaky bucket): ``XRUN_BURST`` once more
    than about ``io.xrun_limit`` blocks within ``io.xrun_window`` were flagged ``IO_XRUN``."""
    if ctl[_XADD] <= 0:
        return 0
    lvl = ctl[_XLEVEL] - min(ctl[_XLEVEL], ctl[_XLEAK])
    if status & IO_XRUN:
        lvl += ctl[_XADD]
    ctl[_XLEVEL] = lvl
    return XRUN_BURST if lvl > ctl[_XCAP] else 0


class Injector:
    """A run's fault plan in arrays, and the calls that inject it.

    Parameters
    ----------
    ctx : Context
    block : int
    vmax : array_like (n_channels,)
        max_voltage per drive channel (``amp_clipped``'s reference).
    full_scale : array_like (n_sensed,)
        Each sensed row's ADC full scale, A (``adc_saturated``).
    faults : list of Fault
    """

    def __init__(self, ctx: Context, block: int, vmax, full_scale, faults=()):
        self.ctx = ctx
        self.plan = np.full((MAX_FAULTS, 5), -1, dtype=np.int64)
        self.value = np.zeros(MAX_FAULTS)
        self.ctl = np.zeros(5, dtype=np.int64)
        if ctx.xrun_limit > 0 and ctx.xrun_window_blocks > ctx.xrun_limit:
            self.ctl[_XADD], self.ctl[_XLEAK] = ctx.xrun_window_blocks, ctx.xrun_limit
            self.ctl[_XCAP] = ctx.xrun_limit * ctx.xrun_window_blocks
        self.hist = np.zeros((HISTORY if ctx.n_sensed else 0, ctx.n_sensed, block))
        self.last = np.zeros(ctx.n_sensed)
        self.full_scale = np.ascontiguousarray(full_scale, dtype=float).reshape(ctx.n_sensed)
        self.vmax = np.ascontiguousarray(vmax, dtype=float).reshape(ctx.n_channels)
        self.faults: list[Fault] = []
        self.load(faults)

    def load(self, faults) -> None:
        """Replace the plan (between runs)."""
        self.faults = list(faults)
        self.plan[:] = -1
        self.value[:] = 0.0
        for i, f in enumerate(self.faults):
            v = f.value
            if f.kind == "amp_clipped" and v == 0:
                v = 0.5
            n = int(f.value) if f.kind == "latency_spike" and f.value else 1
            self.plan[i] = (_K[f.kind], f.start, f.stop, f.row, n)
            self.value[i] = v
        self.reset()

    def reset(self) -> None:
        self.ctl[_BLK] = 0
        self.ctl[_XLEVEL] = 0
        self.hist[:] = 0.0
        self.last[:] = 0.0

    def sensed(self, sensed) -> int:
        return inject_sensed(self.plan, self.value, self.ctl, sensed, self.hist, self.last, self.full_scale)

    def drive(self, drive, dev) -> int:
        return inject_drive(self.plan, self.value, self.ctl, drive, dev, self.vmax)

    def calls(self, drive, dev, sensed) -> tuple[list, list]:
        """``(before, after)`` kernel calls ``[(kernel, args)]`` around a device's own for one
        block, for a device whose block runs as compiled calls (the audio emulator): the drive the
        plant gets, before; the readings it gives and the block count, after."""
        return ([(inject_drive, (self.plan, self.value, self.ctl, drive, dev, self.vmax))],
                [(inject_sensed, (self.plan, self.value, self.ctl, sensed, self.hist, self.last, self.full_scale)),
                 (count_block, (self.ctl,))])

    def count(self) -> int:
        return count_block(self.ctl)

    def guard(self, status: int) -> int:
        return xrun_guard(self.ctl, status)

    def finger(self, target, col, lift, slam) -> int:
        return inject_finger(self.plan, self.ctl, target, col, lift, slam)

    def describe(self) -> list:
        return [f.to_dict() for f in self.faults]


def slam_factor(scene) -> float:
    """The finger_slam force factor the simulated finger is built for: the first injected
    finger_slam's value, else 4."""
    for item in scene.io.faults.inject:
        if item.kind == "finger_slam" and item.value:
            return float(item.value)
    return 4.0


def wants_fingers(scene) -> bool:
    """Whether the scene's faults may hit the finger (the simulated groups then carry the lifted
    and the slammed finger as extra load states)."""
    f = scene.io.faults
    return any(i.kind in FINGER_KINDS for i in f.inject) or (
        f.random > 0 and any(k in FINGER_KINDS for k in (f.kinds or KINDS)))


def active(scene) -> bool:
    """Whether the scene injects any fault."""
    return bool(scene.io.faults.inject) or scene.io.faults.random > 0


def sim_injector(scene, faults, ctx: Context) -> Injector:
    """The :class:`Injector` of ``scene``'s simulated device with the plan ``faults``; a sensed row
    of no bimorph (a PVDF cell's or a coil's current) has a full scale of 1 A."""
    from ..models import n_channels, sensed_layout

    vmax = []
    for g in scene.actuator:
        vmax += [float(g.max_voltage)] * n_channels(g)
    full = []
    for name in ctx.sensed_names or sensed_layout(scene)[0]:
        g = scene.group(name.split(".")[0])
        full.append(float(g.sense.full_scale) / float(g.sense.shunt) if g.type == "bimorph" else 1.0)
    full = (full + [1.0] * ctx.n_sensed)[:ctx.n_sensed]
    return Injector(ctx, int(scene.timing.block), vmax, full, faults)
