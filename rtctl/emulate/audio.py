"""``rtctl emulate audio SCENE``: the scene's simulated plant as a JACK client, the hardware an
``audio`` run drives when no hardware is there (hardware-in-the-loop through a real audio server).

The client (``rtctl-emulator``) has one input port per drive channel (named like the channel,
``lateral.0``; port value x ``io.volts_per_fs`` = volts) and one output port per sensed row
(``lateral.0.seg1``; amperes / ``io.amps_per_fs``): exactly the sensed rows an audio run has
(``rtctl.models.sensed_layout``), matched by name to the simulated groups' rows. Each JACK period it
converts the drive ports into a preallocated float64 block, advances the simulated groups (the
``sim`` backend's kernels and their contract, :mod:`rtctl.io.sim`) and writes that block's
currents to its output ports: no latency of its own, as an analog amplifier and current sense
have none. The process callback is C (a numba ``cfunc`` handed to ``jack_set_process_callback``,
no Python and no GIL per period) where it can be built, else Python (``RTCTL_AUDIO_CFUNC=0``).

It waits for an rtctl run's PortAudio client (ports ``rtctl:out_N`` / ``rtctl:in_N``, client
name matching ``--connect``), connects drive channel ``c`` from ``out_{io.outputs[c]}`` and sensed
row ``r`` to ``in_{io.inputs[r]}`` (the run's own channel map), disconnects anything else feeding
those inputs (``system:capture_N``), resets the plant to rest and prints ``ready``. When that
client goes - its ports go one by one, at any point of the connection - it waits for the next
one: a run's end is never an error. stdout carries exactly: ``waiting`` (own ports exist),
then ``ready`` per connected run. SIGTERM or SIGINT ends it with status 0.

With ``--truth DIR`` it also writes what only the simulated device knows, per connected run, as an
rtctl trace ``DIR/run-N`` (N = 1, 2, ... in the order of connection): ``drive`` (the volts the
plant received) and ``tip_um`` (its true tip displacement), one record per JACK period from the
plant's reset at that connection. The process callback copies both into a ring the main thread
drains into the trace; a record's ``block`` is its period's index since the reset, so periods the
main thread fell a whole ring behind on show as a gap (and in the counts on stderr at the end).
The run's own trace holds none of it: it is hardware's, and hardware has no truth to give.

The scene's ``[[events]]`` are played on the emulator's own clock: an event at ``at`` s takes
effect at the start of period ``floor(at * fs / period)`` counted from the first period a connected
run drives (any drive sample not 0) after the plant's reset, writing what it writes on ``sim``
(:meth:`rtctl.io.sim.SimDevice.event_posts`: a bimorph group's finger load, a pin's preload). The
emulator cannot see a run's block count: when it connects before the run's first block that is
the run's block 0 and the finger moves at the run's own event block, as on ``sim``; when it
connects ``k`` blocks into the run, the first period it hears counts as 0 and every event comes
``k`` blocks after the run's. A scene whose stimulus starts silent starts the clock late by the
same rule. Like a real finger, the emulated one is the device's: the run only knows the times.
"""

from __future__ import annotations

import argparse
import gc
import os
import signal
import sys
import threading
import time

import numpy as np

from ..errors import RtctlError


def _parser():
    p = argparse.ArgumentParser(prog="rtctl emulate audio",
                                description="Run the scene's simulated plant as a JACK client that an audio run "
                                            "drives (hardware in the loop). Prints 'waiting', then 'ready' per "
                                            "connected run.")
    p.add_argument("scene", metavar="SCENE", help="scene file or bundled scene name")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene key (use the run's overrides: io.outputs, io.inputs, scaling)")
    p.add_argument("--connect", default="rtctl(-[0-9]+)?", metavar="REGEX",
                   help="JACK client name of the rtctl run to serve (POSIX extended regex; default %(default)s)")
    p.add_argument("--name", default="rtctl-emulator", help="this client's JACK name (default %(default)s)")
    p.add_argument("--server", default=None, help="JACK server name (default: $JACK_DEFAULT_SERVER or 'default')")
    p.add_argument("--truth", default=None, metavar="DIR",
                   help="write each connected run's simulated drive and true tip displacement as the trace DIR/run-N")
    return p


class Plant:
    """The simulated groups of a scene on one JACK period, with their port names and channel map."""

    def __init__(self, scene, fs: float, period: int):
        from ..io.base import channel_map
        from ..io.sim import build_group, device_models
        from ..models import sensed_layout
        from ..plant import TRUTH_NAMES

        models = device_models(scene)  # the simulated hardware: io.mismatch is its secret
        # The rows an audio run senses (its Layout): the emulator publishes exactly those, by name.
        self.out_names = list(sensed_layout(scene)[0])
        self.in_names, groups, sim_rows = [], [], []
        ch0 = row0 = 0
        for gi, g in enumerate(scene.actuator):
            n = g.grid[0] * g.grid[1]
            self.in_names += [f"{g.name}.{i}" for i in range(n)]
            try:
                sim = build_group(models, g, gi, fs, period)
            except RtctlError as e:
                print(f"rtctl emulate audio: {e}; its drive channels are read, its sensed rows stay 0",
                      file=sys.stderr)
                ch0 += n
                continue
            rows = n * sim.n_sensed
            sim_rows += [f"{g.name}.{i}.{lab}" for i in range(n) for lab in sim.sensed_labels]
            groups.append((sim, slice(ch0, ch0 + n), slice(row0, row0 + rows)))
            ch0, row0 = ch0 + n, row0 + rows
        self.drive = np.zeros((ch0, period))
        self.sensed = np.zeros((row0, period))
        self.truth = np.zeros((ch0, len(TRUTH_NAMES), period))
        self.groups = [g for g, _, _ in groups]
        # [io.faults]: the emulated device misbehaving; the plant then runs on what the amplifier
        # passes (``plant_drive``), the faults' drive and readings around the groups' kernels
        from ..io import faults as fault_mod

        self.faults = None
        plant_drive = self.drive
        if fault_mod.active(scene):
            ctx = fault_mod.context(scene, fault_mod.AUDIO, n_sensed=row0, names=sim_rows)
            self.faults = fault_mod.sim_injector(scene, fault_mod.plan(scene, ctx), ctx)
            plant_drive = np.zeros_like(self.drive)
        self.rec = None  # the --truth ring (record_ring)
        # for the --truth traces: which device this was (its mismatch is the simulated device's own)
        self.meta = {"scene": scene.scene.name, "scene_source": str(scene.source), "overrides": list(scene.overrides),
                     "mismatch": dict(models.factors or {})}
        self._event_writes(scene, fs, period)
        # The simulated-group contract (rtctl.io.sim): kernel(*args, drive, sensed, truth) -> bits,
        # here writing each block's currents straight into ``sensed`` (no latency of its own).
        self.calls = [(g.kernel, (*g.args, plant_drive[ch], self.sensed[sr], self.truth[ch])) for g, ch, sr in groups]
        if self.faults is not None:
            before, after = self.faults.calls(self.drive, plant_drive, self.sensed)
            self.calls = before + self.calls + after
        for kernel, args in self.calls:  # compile (or load) now, then back to rest
            kernel(*args)
        self.reset()
        missing = [r for r in self.out_names if r not in sim_rows]
        if missing:
            print(f"rtctl emulate audio: no simulated signal for sensed rows {', '.join(missing)}: they stay 0",
                  file=sys.stderr)
        # sensed row (port) -> row of the simulated groups' block, -1 for none
        self.row_of = [sim_rows.index(r) if r in sim_rows else -1 for r in self.out_names]
        self.zeros = np.zeros(period)
        io = scene.io
        # The run's map; the device's channel count is the run's business (1024 = the schema bound).
        self.outputs = channel_map(io.outputs, ch0, 1024, "io.outputs", "drive channels")
        self.inputs = channel_map(io.inputs, len(self.out_names), 1024, "io.inputs", "sensed rows")
        self.volts_per_fs = float(io.volts_per_fs)
        self.fs_per_amp = 1.0 / float(io.amps_per_fs)

    def _event_writes(self, scene, fs: float, period: int) -> None:
        """``event_writes``: ``(period, array, row, col, value)`` per write of the scene's events
        into the simulated groups (what ``sim`` posts at the event's block), in time order, the
        period on the emulator's clock; ``clock[0]``: periods since the first driven one after the
        reset, -1 before it. ``event_initial``: the written arrays as built (reset puts them back)."""
        self.clock = np.full(1, -1, dtype=np.int64)
        self.event_writes, self.event_initial = [], []
        changed = [g.events for g in self.groups if getattr(g, "events", None) is not None]
        if not changed:
            return
        from ..events import block_of, schedule

        for e in schedule(scene):
            at = block_of(e.at, fs, period)
            self.event_writes += [(at, *w) for ev in changed for w in ev.writes.get(e.index, ())]
        self.event_initial = [(t, t.copy()) for ev in changed for t in ev.targets]

    def _events(self) -> None:
        """The events due at this period (the Python process callback's path; the C one is
        generated from the same table): the clock starts at the first driven period."""
        k = int(self.clock[0])
        if k < 0:
            if not self.drive.any():
                return
            k = 0
        for at, arr, row, col, value in self.event_writes:
            if at == k:
                arr[row, col] = value
        self.clock[0] = k + 1

    def record_ring(self, periods: int) -> None:
        """Keep each period's drive (V) and true tip displacement (m) for ``--truth``:
        ``rec[k % periods, 0]`` and ``rec[k % periods, 1]`` for the k-th recorded period
        (``E_RECORDED`` counts them). Allocated here, never in the process callback."""
        self.rec = np.zeros((max(1, int(periods)), 2, *self.drive.shape))

    def keep(self, k: int) -> None:
        """Period ``k``'s drive and true tip into the ring (the Python process callback's path)."""
        slot = self.rec[k % self.rec.shape[0]]
        slot[0] = self.drive
        slot[1] = self.truth[:, 0, :]

    def reset(self) -> None:
        """Every simulated group at rest (a new run starts from zero state, as on ``sim``)."""
        for g in self.groups:
            g.reset()
        for target, initial in self.event_initial:  # the finger the scene starts with
            target[...] = initial
        self.clock[0] = -1
        if self.faults is not None:
            self.faults.reset()
        self.drive[:] = 0.0
        self.sensed[:] = 0.0
        self.truth[:] = 0.0

    def step(self) -> int:
        """One period through every group (the Python process callback's path)."""
        if self.event_writes:
            self._events()
        status = 0
        for kernel, args in self.calls:
            status |= kernel(*args)
        return status


# --- the C process callback: JACK calls it directly, no Python, no GIL ----------------------------

#: Fields of the emulator's int64 control array (``E_RECORDED``: periods put into the --truth ring).
E_PAUSE, E_PAUSED, E_BLOCKS, E_ODD, E_SATURATED, E_ERRORS, E_RECORDED = range(7)
N_E = 7
#: Seconds of periods the --truth ring holds: the main thread drains it at least every 50 ms.
RECORD_S = 1.0

_PROCESS = """# generated by rtctl.emulate.audio; package stamp {stamp}
import numpy as np
from numba import carray, cfunc, types

from rtctl._codegen import fence, voidptr_at
from rtctl.emulate.audio import (E_BLOCKS, E_ERRORS, E_ODD, E_PAUSE, E_PAUSED, E_RECORDED, E_SATURATED,
    N_E, jack_port_get_buffer)
{imports}

SIG = types.int32(types.uint32, types.voidptr)


@cfunc(SIG, nopython=True, cache=True)
def process(nframes, arg):
    tab = carray(arg, ({n_tab},), np.int64)
    ctl = carray(voidptr_at(tab[0]), (N_E,), np.int64)
    scale = carray(voidptr_at(tab[1]), (2,), np.float64)
{arrays}
    if nframes != {period} or ctl[E_PAUSE] != 0:
        for r in range({n_out}):
            buf = carray(jack_port_get_buffer(voidptr_at({ports_out}[r]), nframes), (nframes,), np.float32)
            for i in range(nframes):
                buf[i] = 0.0
        if nframes != {period}:
            ctl[E_ODD] += 1
        ctl[E_PAUSED] = ctl[E_PAUSE]
        return 0
    ctl[E_PAUSED] = 0
    for c in range({n_in}):
        buf = carray(jack_port_get_buffer(voidptr_at({ports_in}[c]), nframes), ({period},), np.float32)
        for i in range({period}):
            {drive}[c, i] = buf[i] * scale[0]
{events}
    st = 0
    try:
{steps}
    except Exception:
        ctl[E_ERRORS] += 1
        st = -1
    if st > 0 and st & 1:
        ctl[E_SATURATED] += 1
    for r in range({n_out}):
        buf = carray(jack_port_get_buffer(voidptr_at({ports_out}[r]), nframes), ({period},), np.float32)
        row = {row_of}[r]
        for i in range({period}):
            buf[i] = {sensed}[row, i] * scale[1] if (row >= 0 and st >= 0) else 0.0
{record}
    ctl[E_BLOCKS] += 1
    return 0
"""

#: The --truth ring's part of the process callback: the period's slot, then the count (after a
#: fence, so the main thread never sees a count whose slot is not written yet).
_RECORD = """    k = ctl[E_RECORDED] % {n_rec}
    for c in range({n_ch}):
        for i in range({period}):
            {rec}[k, 0, c, i] = {drive}[c, i]
            {rec}[k, 1, c, i] = {truth}[c, 0, i]
    fence()
    ctl[E_RECORDED] += 1"""


#: The scene's events (``Plant._events``): the clock starts at the first driven period, then
#: each write is due at its period.
_EVENTS = """    k = {clock}[0]
    if k < 0:
        for c in range({n_ch}):
            for i in range({period}):
                if {drive}[c, i] != 0.0:
                    k = 0
    if k >= 0:
{writes}
        {clock}[0] = k + 1"""


def _jack_port_get_buffer():
    # By symbol name (cacheable); libjack's symbols must be visible to numba's linker.
    import ctypes.util

    import llvmlite.binding as llvm
    from numba import types

    llvm.load_library_permanently(ctypes.util.find_library("jack") or "libjack.so.0")
    return types.ExternalFunction("jack_port_get_buffer", types.voidptr(types.voidptr, types.uint32))


try:
    jack_port_get_buffer = _jack_port_get_buffer()
except Exception:  # noqa: BLE001 - no libjack: the Python process callback, or nothing, runs
    jack_port_get_buffer = None


def build_process(plant, inports, outports, ctl):
    """The emulator's JACK process callback compiled to C (a numba ``cfunc``): ports ->
    ``drive`` (volts), the simulated groups' kernels, ``sensed`` -> ports (full scale), all
    without Python. Returns ``(cfunc, keep)``; ``keep[0]`` (int64 addresses) is its ``arg``."""
    from .._numba import package_stamp
    from ..io._audio_kernels import _Table, kernel_call

    if jack_port_get_buffer is None:
        raise OSError("libjack not found")
    scale = np.array([plant.volts_per_fs, plant.fs_per_amp])
    name = _Table(ctl, scale)
    port_ptr = lambda ports: np.array([int(jack_ffi().cast("uintptr_t", p._ptr)) for p in ports] or [0],  # noqa: E731
                                      dtype=np.int64)
    p_in, p_out = port_ptr(inports), port_ptr(outports)
    row_of = np.array(list(plant.row_of) or [-1], dtype=np.int64)
    fns, imports = {}, []
    steps = "\n".join(f"        st |= {kernel_call(k, a, name, fns, imports)}" for k, a in plant.calls)
    steps = steps or "        pass"
    fields = dict(period=plant.drive.shape[1], n_in=len(inports), n_out=len(outports), ports_in=name(p_in),
                  ports_out=name(p_out), row_of=name(row_of), drive=name(plant.drive), sensed=name(plant.sensed),
                  steps=steps, imports="\n".join(imports), stamp=package_stamp().hex()[:16], record="",
                  events="")
    if plant.event_writes:
        writes = "\n".join(f"        if k == {at}:\n            {name(arr)}[{row}, {col}] = {float(value)!r}"
                           for at, arr, row, col, value in plant.event_writes)
        fields["events"] = _EVENTS.format(clock=name(plant.clock), n_ch=plant.drive.shape[0],
                                          period=fields["period"], drive=fields["drive"], writes=writes)
    if plant.rec is not None:
        fields["record"] = _RECORD.format(n_rec=plant.rec.shape[0], n_ch=plant.drive.shape[0], period=fields["period"],
                                          rec=name(plant.rec), drive=fields["drive"], truth=name(plant.truth))
    keep = (scale, p_in, p_out, row_of, *name.scalars())
    fields["arrays"] = "\n".join(name.lines)
    fields["n_tab"] = len(name.addresses)
    from .._codegen import load_generated

    module = load_generated(_PROCESS.format(**fields))
    return module.process, (np.array(name.addresses, dtype=np.int64), *keep)


def jack_ffi():
    import jack

    return jack._ffi


_clock = time.monotonic  # the connection loop's clock (a test's fake JACK server brings its own)


class RunGone(Exception):
    """A run's ports went while the emulator was connecting to them: the run ended."""


class Emulator:
    """The JACK client: ports, process callback, and the main thread's connection logic."""

    def __init__(self, client, plant: Plant, pattern: str, truth=None):
        self.client, self.plant = client, plant
        self.pattern = pattern
        self.period = client.blocksize
        self.inports = [client.inports.register(n) for n in plant.in_names]
        self.outports = [client.outports.register(n) for n in plant.out_names]
        self.reset_pending = False
        self.blocks = self.errors = self.odd = self.xruns = self.saturated = 0
        self.wake = threading.Event()
        self.stop = threading.Event()  # set by JACK's shutdown callback (a thread)
        # Set by the SIGTERM/SIGINT handler, which runs on the main thread between any two
        # bytecodes - also inside an Event's own lock, so it must not take one (Event.set would
        # deadlock there): a plain flag, seen within the loop's 50 ms wait.
        self.signalled = False
        self.server_gone = None
        self.ctl = np.zeros(N_E, dtype=np.int64)
        # --truth: the ring is the plant's (the process callback fills it), the trace the main
        # thread's; rec_from is the ring count at the plant's last reset (None until it is done)
        self.truth_dir = None if truth is None else os.fspath(truth)
        self.writer, self.runs, self.rec_from, self.rec_next, self.rec_lost = None, 0, None, None, 0
        if self.truth_dir is not None:
            plant.record_ring(round(RECORD_S * float(client.samplerate) / self.period))
        self.c_process = self._keep = None
        if os.environ.get("RTCTL_AUDIO_CFUNC", "1") != "0":
            try:
                self.c_process, self._keep = build_process(plant, self.inports, self.outports, self.ctl)
            except Exception as e:  # noqa: BLE001 - the Python process callback does the same job
                print(f"rtctl emulate audio: C process callback unavailable ({type(e).__name__}: {e}); "
                      "using Python", file=sys.stderr)
        if self.c_process is not None:
            import jack

            self._cb = jack._ffi.cast("JackProcessCallback", self.c_process.address)
            self._arg = jack._ffi.cast("void *", int(self._keep[0].ctypes.data))
            if jack._lib.jack_set_process_callback(client._ptr, self._cb, self._arg):
                raise RuntimeError("jack_set_process_callback failed")
        else:
            client.set_process_callback(self.process)
        client.set_xrun_callback(self._xrun)
        client.set_shutdown_callback(self._shutdown)
        client.set_port_registration_callback(lambda port, register: self.wake.set(), only_available=False)

    def process(self, frames):
        """JACK's real-time thread: ports -> volts, plant kernels, amperes -> ports."""
        p = self.plant
        try:
            if frames != self.period:  # the server changed its period: silence, counted
                for port in self.outports:
                    port.get_array().fill(0.0)
                self.odd += 1
                return
            if self.reset_pending:
                p.reset()
                self.rec_from = int(self.ctl[E_RECORDED])
                self.reset_pending = False
            for c, port in enumerate(self.inports):
                np.multiply(port.get_array(), p.volts_per_fs, out=p.drive[c])
            if p.step() & 1:
                self.saturated += 1
            for port, r in zip(self.outports, p.row_of):
                np.multiply(p.sensed[r] if r >= 0 else p.zeros, p.fs_per_amp, out=port.get_array(),
                            casting="same_kind")
            if p.rec is not None:
                p.keep(int(self.ctl[E_RECORDED]))
                self.ctl[E_RECORDED] += 1
            self.blocks += 1
        except Exception:  # noqa: BLE001 - never into JACK's thread; outputs silent, counted
            self.errors += 1
            for port in self.outports:
                port.get_array().fill(0.0)

    def _xrun(self, delay_usecs):
        self.xruns += 1

    def _shutdown(self, status, reason):
        self.server_gone = reason or "JACK server shut down"
        self.stop.set()
        self.wake.set()

    # --- main thread ----------------------------------------------------------------------------

    def _find_client(self) -> str | None:
        """The JACK name of an rtctl run's client (the first in order), or None.

        JACK-Client lists the names, then looks each one up again: a port of a run that is
        ending can go in between (``JackError: Port ... not available``). That is None here; the
        port-registration callback wakes the loop, which looks again."""
        import jack

        try:
            ports = self.client.get_ports(f"^({self.pattern}):out_[0-9]+$", is_audio=True, is_input=False)
        except jack.JackError:
            return None
        names = sorted({p.name.split(":", 1)[0] for p in ports} - {self.client.name, ""})
        return names[0] if names else None

    def _port(self, name):
        try:
            return self.client.get_port_by_name(name)
        except Exception:  # noqa: BLE001 - jack.JackError: not (or no longer) there
            return None

    def _wiring(self, run):
        p = self.plant
        src = [(f"{run}:out_{o}", port) for o, port in zip(p.outputs, self.inports)]
        dst = [(port, f"{run}:in_{i}") for i, port in zip(p.inputs, self.outports)]
        return src, dst

    def _reset_plant(self) -> None:
        """Plant at rest before a new run's first block. The C callback is paused around the
        (Python) reset: it outputs silence meanwhile."""
        self.rec_from = None
        if self.c_process is None:
            self.reset_pending = True
            return
        self.ctl[E_PAUSE] = 1
        t = time.monotonic()
        while not self.ctl[E_PAUSED] and time.monotonic() - t < 0.5:
            time.sleep(0.0005)
        self.plant.reset()
        self.rec_from = int(self.ctl[E_RECORDED])  # paused: nothing is recorded meanwhile
        self.ctl[E_PAUSE] = 0

    # --- --truth: the main thread's side of the ring ------------------------------------------------

    def _truth_open(self, run: str) -> None:
        """A new trace for the run just connected (``DIR/run-N``)."""
        if self.truth_dir is None:
            return
        from pathlib import Path

        from ..trace import TraceWriter

        self._truth_close()
        self.runs += 1
        p = self.plant
        n_ch, period = p.drive.shape
        signals = {"drive": ("V", n_ch), "tip_um": ("um", n_ch)}
        self.writer = TraceWriter(Path(self.truth_dir) / f"run-{self.runs}", signals, float(self.client.samplerate),
                                  period, p.in_names, meta={"source": "rtctl emulate audio", "client": run, **p.meta})
        self.rec_next = None

    def _truth_drain(self) -> None:
        """Every period recorded since the last call into the trace. Periods the process callback
        overwrote before they were read (the ring lapped this thread) are lost, counted, and leave
        a gap in the records' ``block``."""
        if self.writer is None:
            return
        if self.rec_next is None:
            if self.rec_from is None:  # the Python callback has not reset the plant yet
                return
            self.rec_next = self.rec_from
        rec = self.plant.rec
        n = rec.shape[0]
        # Period k is in slot k % n from the count k + 1 on, and is overwritten while the count
        # is k + n (the callback writes the slot, then counts): of the periods up to the count,
        # the oldest n - 1 are whole.
        end = int(self.ctl[E_RECORDED])
        first = max(self.rec_next, end - n + 1)
        ks = np.arange(first, end)
        data = rec[ks % n]  # a copy: the callback goes on writing the ring
        now = int(self.ctl[E_RECORDED])
        safe = ks > now - n  # and those it began to overwrite meanwhile are not
        self.rec_lost += (first - self.rec_next) + int(np.count_nonzero(~safe))
        for k, d in zip(ks[safe], data[safe]):
            r = self.writer.next()
            r["block"] = k - self.rec_from
            r["drive"] = d[0]
            r["tip_um"] = d[1] * 1e6
        self.rec_next = end

    def _truth_close(self) -> None:
        if self.writer is not None:
            self._truth_drain()
            self.writer.close()
            self.writer = None

    def counts(self) -> tuple:
        """(blocks, failed blocks, odd-size blocks, saturated blocks), from whichever callback ran."""
        if self.c_process is None:
            return self.blocks, self.errors, self.odd, self.saturated
        c = self.ctl
        return int(c[E_BLOCKS]), int(c[E_ERRORS]), int(c[E_ODD]), int(c[E_SATURATED])

    def _client_id(self, run) -> str | None:
        """The JACK client ``run``'s UUID (one per client instance: a new run of the same name
        has another), None when no client of that name is there (or the server does not say)."""
        import jack

        try:
            return self.client.get_uuid_for_client_name(run)
        except jack.JackError:
            return None

    def _connect(self, run) -> tuple[str, str] | None:
        """Connect to ``run``'s ports once all of them exist: ``(a port's name, the client's
        UUID)`` to watch for the run's end, or None while some ports are still missing.

        The run's ports can go at any moment (JACK removes a closing client's ports one by one),
        between the check that they exist and any call that names them: a JACK error with one
        of them gone, or with another client of that name there by now, is :class:`RunGone`
        (the run ended: the normal end of a connection); a JACK error with all of them there is
        the server's, raised as it is."""
        import jack

        src, dst = self._wiring(run)
        names = [s for s, _ in src] + [d for _, d in dst]
        ident = self._client_id(run)  # None where the server cannot say: the ports alone then
        if not names or any(self._port(n) is None for n in names):
            return None
        self._reset_plant()
        try:
            for s, port in src:
                self._link(s, port.name)
            for port, d in dst:
                for other in self._feeding(d):
                    if other != port.name:  # e.g. system:capture_N, auto-connected by PortAudio
                        self._unlink(other, d)
                self._link(port.name, d)
        except jack.JackError as e:
            if self._client_id(run) != ident or any(self._port(n) is None for n in names):
                raise RunGone(run) from e
            raise
        if self._client_id(run) != ident:  # a new run of that name, part-wired: the next call's
            raise RunGone(run)
        return names[0], ident

    def _link(self, src: str, dst: str) -> None:
        """``src`` -> ``dst``; already connected (a retry after a failure half-way) is fine."""
        import errno

        import jack

        try:
            self.client.connect(src, dst)
        except jack.JackErrorCode as e:
            if e.code != errno.EEXIST:
                raise

    def _feeding(self, dst: str) -> list[str]:
        """Names of the ports connected to ``dst``. JACK-Client looks each one up by name, and
        another client's port can go meanwhile: then list again (the run's own going is the
        caller's to judge)."""
        import jack

        for attempt in range(3):
            try:
                return [p.name for p in self.client.get_all_connections(dst)]
            except jack.JackError:
                if attempt == 2 or self._port(dst) is None:
                    raise
        return []  # pragma: no cover - the loop returns or raises

    def _unlink(self, other: str, dst: str) -> None:
        """Disconnect ``other`` -> ``dst``; ``other`` gone meanwhile is as good."""
        import jack

        try:
            self.client.disconnect(other, dst)
        except jack.JackError:
            if self._port(other) is not None and self._port(dst) is not None:
                raise

    def serve(self) -> int:
        """Connect to each rtctl run as it appears, until SIGTERM/SIGINT or the server goes.

        A run's end - its ports gone, in whatever order and at whatever point of this loop - is
        the normal end of its connection: the loop waits for the next run. A connection the
        server refuses while the run's ports are all there is retried at each wake, and an
        error once it lasts over 2 s: one line on stderr per run and error."""
        print("waiting", flush=True)
        run = watch = ident = None  # the connected run: its client name, a port of it, its UUID
        cand, since, failed, warned = None, 0.0, set(), set()  # the run being connected
        while not (self.stop.is_set() or self.signalled):
            self.wake.wait(0.05)
            self.wake.clear()
            self._truth_drain()
            if run is not None and (self._port(watch) is None or self._client_id(run) != ident):
                run = None  # that run ended: wait for the next one
                self._truth_close()
            if run is not None:
                continue
            found = self._find_client()
            if found != cand:  # another one, or none: its own first sight and messages
                cand, since, failed = found, _clock(), set()
            if cand is None:
                continue
            try:
                connected = self._connect(cand)
            except RunGone:  # it ended while being connected: its end, not an error
                cand = None
                continue
            except Exception as e:  # noqa: BLE001 - the server refused: retried, said once if it lasts
                # (JACK refuses connections to a client that registered its ports but is not
                # active yet: a moment's refusal is no error)
                if _clock() - since > 2.0 and str(e) not in failed:
                    failed.add(str(e))
                    print(f"rtctl emulate audio: connecting to {cand} failed ({e})", file=sys.stderr)
                continue
            if connected is None:  # some of its ports are not there (yet)
                if _clock() - since > 2.0 and cand not in warned:
                    warned.add(cand)
                    print(f"rtctl emulate audio: {cand} lacks ports for this scene's io.outputs/io.inputs "
                          "(does the run use the same scene and --set?)", file=sys.stderr)
                continue
            run, (watch, ident) = cand, connected
            cand = None
            warned.discard(run)
            self._truth_open(run)
            print("ready", flush=True)
        self._truth_close()
        if self.server_gone:
            print(f"rtctl emulate audio: error: JACK server gone ({self.server_gone})", file=sys.stderr)
            return 1
        return 0


def main(argv=None) -> int:
    """``rtctl emulate audio``; returns the exit status."""
    args = _parser().parse_args(argv)
    try:
        import jack
    except (ImportError, OSError) as e:
        print(f"rtctl emulate audio: error: needs the JACK-Client package and libjack ({e})", file=sys.stderr)
        return 2
    from .. import scene as scenes

    try:
        sc = scenes.load(args.scene, args.overrides)
        jack.set_error_function(lambda msg: None)  # libjack's own chatter while it looks for a server
        try:
            client = jack.Client(args.name, no_start_server=True, servername=args.server)
        except jack.JackError as e:
            print(f"rtctl emulate audio: error: no JACK server to join ({e}); start one, e.g. "
                  "jackd -d dummy -r 48000 -p 64", file=sys.stderr)
            return 2
        jack.set_error_function()
        fs, period = client.samplerate, client.blocksize
        if float(fs) != float(sc.timing.fs):
            client.close()
            print(f"rtctl emulate audio: error: the JACK server runs at {fs} Hz, the scene at "
                  f"{sc.timing.fs:g} Hz: --set timing.fs={fs} or restart jackd with -r {sc.timing.fs:g}",
                  file=sys.stderr)
            return 2
        plant = Plant(sc, float(fs), period)
    except RtctlError as e:
        print(f"rtctl emulate audio: error: {e}", file=sys.stderr)
        return 2
    emu = Emulator(client, plant, args.connect, truth=args.truth)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: setattr(emu, "signalled", True))
    # The process callback needs the GIL every period: keep cyclic-GC pauses out of its way
    # (everything built so far is long-lived) and make a GIL holder yield within ~0.3 ms.
    gc.collect()
    gc.freeze()
    sys.setswitchinterval(min(sys.getswitchinterval(), 0.25 * period / fs))
    try:
        client.activate()
    except jack.JackError as e:  # the server went between joining it and now
        client.close()
        print(f"rtctl emulate audio: error: JACK server gone ({e})", file=sys.stderr)
        return 1
    try:
        code = emu.serve()
    finally:
        client.deactivate()
        client.close()
    blocks, errors, odd, saturated = emu.counts()
    kept = f", {emu.runs} truth traces, {emu.rec_lost} periods lost from them" if emu.truth_dir is not None else ""
    print(f"rtctl emulate audio: {blocks} blocks, {emu.xruns} xruns, {errors} failed blocks, {saturated} "
          f"saturated, {'C' if emu.c_process is not None else 'Python'} process callback{kept}", file=sys.stderr)
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
