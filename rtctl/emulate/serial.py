"""``rtctl emulate serial SCENE``: a pin controller's firmware behind a pseudo-terminal.

Opens a pty pair, prints the slave's path as the first line of stdout (the scene's ``io.port``)
once the plant is built, and then runs the firmware until SIGTERM/SIGINT:

- speaks :mod:`rtctl.io.protocol`: IDENT to HELLO, ACK (with the pins' states from the plant)
  to PINS and ALL_OFF, NACK to anything it cannot take;
- **Dot** (seed 001, one H-bridge per pin): when a pin's command changes to UP or DOWN, the
  bridge drives the coil at ``+-actuator.dot.supply`` for ``--pulse-ms`` (default 3 ms, the safe
  pulse of docs/plants/dot.md) and then shorts it; the latch holds the pin. OFF starts nothing
  (a pulse under way completes: a cut pulse leaves the pin to the latch);
- **SMA** (seed 002, crossbar controller): a taxel commanded UP has its raise spring heated,
  DOWN its lower spring, OFF neither; the crossbar scans the rows (one row line live per
  ``actuator.sma.slot``), so the firmware drives ``max_voltage * sqrt(rows)`` to deliver the
  mean heat of ``max_voltage``; a spring at ``actuator.sma.t_cut`` gets no current until it cools;
- **watchdog**: 4x the keepalive the host announced in HELLO (0.2 s before any HELLO) without
  a valid frame drops every output (commands OFF, pulses cut, heating off);
- the plant (:mod:`rtctl.plant.dot`, :mod:`rtctl.plant.sma`) advances with the wall clock in
  chunks of ``--chunk-ms`` at ``--fs``. The Dot plant is frozen while no pin is switching (no
  pulse within ``--settle-ms``): latched pins at rest do not move, and a resting finger makes the
  model cost ~40 % of a core at any rate. A chunk owed more than 0.1 s late is skipped (counted).

The emulator keeps its own descriptor of the slave open, so a host closing the port is no hangup
and a new open works. Faults for tests: ``--drop-byte-every N`` (every Nth byte from the host is
lost), ``--garbage-every N`` (random bytes before every Nth answer), ``--corrupt-every N`` (one
bit flipped in every Nth answer), ``--stall-after S`` (S seconds after the first valid frame it
stops answering and ignores frames, port open), ``--mute`` (never answers). The scene's
``[io.faults]`` (docs/faults.md) adds ``byte_flip``/``byte_dup`` (answers) and ``byte_drop`` (host
bytes), each a fraction of the bytes in its window, and ``device_stopped``, timed from the run's
first PINS frame.
"""

from __future__ import annotations

import argparse
import errno
import fcntl
import math
import os
import pty
import random
import select
import signal
import sys
import time
import tty

import numpy as np

from ..errors import RtctlError
from ..io import protocol as P
from ..schema import SCENE

FIRMWARE = (1, 0)
#: SMA pin states: up above +this height, down below -this (m): half the unpowered raised and
#: lowered heights (C, D = +-0.70 mm) of the calibrated taxel (docs/plants/sma.md).
SMA_STATE_HEIGHT = 0.35e-3
_MAX_LAG_S = 0.1


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rtctl emulate serial",
                                description="run a Dot/SMA pin controller behind a pseudo-terminal; "
                                            "prints the port path first")
    p.add_argument("scene", metavar="SCENE", help="scene file or bundled scene name (one dot or sma group)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene key (repeatable)")
    p.add_argument("--fs", type=float, default=8000.0, help="plant sample rate, Hz (default 8000)")
    p.add_argument("--chunk-ms", type=float, default=1.0, help="plant step between polls, ms (default 1)")
    p.add_argument("--pulse-ms", type=float, default=3.0, help="Dot H-bridge pulse, ms (default 3)")
    p.add_argument("--settle-ms", type=float, default=50.0,
                   help="Dot plant keeps running this long after a pulse, ms (default 50)")
    p.add_argument("--drop-byte-every", type=int, default=0, metavar="N", help="lose every Nth byte received")
    p.add_argument("--garbage-every", type=int, default=0, metavar="N", help="random bytes before every Nth answer")
    p.add_argument("--corrupt-every", type=int, default=0, metavar="N", help="flip a bit in every Nth answer")
    p.add_argument("--stall-after", type=float, default=None, metavar="S",
                   help="stop answering S seconds after the first valid frame (port stays open)")
    p.add_argument("--mute", action="store_true", help="never answer")
    p.add_argument("--seed", type=int, default=1, help="seed of the injected faults")
    p.add_argument("-v", "--verbose", action="store_true", help="log frames and events to stderr")
    return p


class Firmware:
    """The controller: protocol, H-bridge pulses or crossbar heating, watchdog, and the plant.

    Parameters
    ----------
    scene : Scene
        One actuator group of type ``dot`` or ``sma``.
    fs : float
        Plant sample rate, Hz.
    chunk_s, pulse_s, settle_s : float
        Plant step, Dot pulse length, how long the Dot plant keeps running after a pulse (s).

    Attributes
    ----------
    display : str
    n : int
        Pins.
    commands, states : ndarray of uint8, shape (n,)
        Current commands and the states an ACK reports.
    heights : ndarray, shape (n,)
        Pin heights at the end of the last chunk, m.
    """

    def __init__(self, scene, fs: float = 8000.0, chunk_s: float = 1e-3, pulse_s: float = 3e-3,
                 settle_s: float = 0.05):
        from ..io.serial import pin_group

        g = pin_group(scene, "rtctl emulate serial")
        self.display, self.name = g.type, g.name
        self.n = n = g.grid[0] * g.grid[1]
        self.fs = float(fs)
        self.B = max(1, int(round(chunk_s * self.fs)))
        if self.display == "dot":
            from ..io.sim import build_group, device_models

            self.group = build_group(device_models(scene), g, 0, self.fs, self.B)
            self.volts = float(g.dot.supply)
            self.travel = float(g.dot.travel)
        else:
            from ..io.sim import device_models
            from ..plant.sma import SmaGroup

            p = g.sma
            rows = g.grid[0]
            self.group = SmaGroup(device_models(scene).sma(g), self.fs, n, max_block=self.B,
                                  mech_fs=min(p.mech_fs, self.fs), crossbar=True, rows=rows, slot=p.slot)
            self.group.f_ext[:] = p.push
            self.volts = float(g.max_voltage) * math.sqrt(rows)
        self.pulse_n = max(1, int(round(pulse_s * self.fs)))
        self.settle_n = int(round(settle_s * self.fs))
        self.drive = np.zeros((n, self.B))
        self._sensed = np.zeros((0, self.B))
        self.truth = np.zeros((n, 4, self.B))
        self.commands = np.zeros(n, dtype=np.uint8)
        self.states = np.zeros(n, dtype=np.uint8)
        self.heights = np.zeros(n)
        self._left = np.zeros(n, dtype=np.int64)    # Dot: pulse samples still to drive
        self._sign = np.zeros(n)
        self._busy_until = 0                         # Dot: sample until which the plant runs
        self.watchdog_s = 0.2
        self.done = 0
        self.t0 = self.last_valid = time.monotonic()
        self.armed = False                           # outputs may be on: the watchdog watches
        self.counts = dict(frames=0, bad=0, nacks=0, watchdog_trips=0, pulses=0, skipped_s=0.0,
                           plant_faults=0)
        self.truth[:, 0, :] = self._rest_heights()[:, None]
        self._read_states()

    def compile(self) -> None:
        """Run one chunk (compiles or loads the kernel), then put the plant back."""
        self.group.kernel(*self.group.args, self.drive, self._sensed, self.truth)
        self.group.reset()
        self.truth[:, 0, :] = self._rest_heights()[:, None]
        self._read_states()

    # --- protocol ------------------------------------------------------------------------------

    def on_frame(self, f, now: float) -> bytes:
        """The answer to one received frame (good or rejected)."""
        if f.error is not None:
            self.counts["bad"] += 1
            return self._nack(f.seq, P.BAD_FRAME)
        self.counts["frames"] += 1
        if f.kind == P.HELLO:
            try:
                _, keepalive = P.parse_hello(f.body)
            except P.ProtocolError:
                return self._nack(f.seq, P.BAD_LENGTH)
            self.watchdog_s = 4.0 * keepalive
            self.last_valid = now
            return P.ident(f.seq, self.display, self.n, FIRMWARE, self.watchdog_s)
        if f.kind == P.PINS:
            if len(f.body) != P.pins_bytes(self.n):
                return self._nack(f.seq, P.BAD_LENGTH)
            new = P.unpack_pins(f.body, self.n)
            if np.any(new == 3):
                return self._nack(f.seq, P.BAD_VALUE)
            self.last_valid = now
            self._apply(new)
            return P.ack(f.seq, self.states)
        if f.kind == P.ALL_OFF:
            if f.body:
                return self._nack(f.seq, P.BAD_LENGTH)
            self.last_valid = now
            self.all_off()
            return P.ack(f.seq, self.states)
        return self._nack(f.seq, P.BAD_TYPE)

    def _nack(self, seq, reason: int) -> bytes:
        self.counts["nacks"] += 1
        return P.nack(seq, reason)

    def _apply(self, new: np.ndarray) -> None:
        if self.display == "dot":
            fire = (new != self.commands) & (new != P.OFF)
            if fire.any():
                self._left[fire] = self.pulse_n
                self._sign[fire] = np.where(new[fire] == P.UP, 1.0, -1.0)
                self._busy_until = self.done + self.pulse_n + self.B + self.settle_n
                self.counts["pulses"] += int(fire.sum())
        self.commands[:] = new
        self.armed = bool(new.any())

    def all_off(self) -> None:
        """Every output off now: commands OFF, pulses cut, heating off."""
        self.commands[:] = P.OFF
        self._left[:] = 0
        self.armed = False

    def watchdog(self, now: float) -> bool:
        """Drop every output after ``watchdog_s`` without a valid frame; True when it trips."""
        if self.armed and now - self.last_valid > self.watchdog_s:
            self.all_off()
            self.counts["watchdog_trips"] += 1
            return True
        return False

    # --- plant ---------------------------------------------------------------------------------

    def wait(self, now: float) -> float:
        """Seconds until the next chunk is owed (0 when late)."""
        return max(0.0, self.t0 + (self.done + self.B) / self.fs - now)

    def advance(self, now: float, max_chunks: int = 1) -> None:
        """Run the plant toward the wall clock, at most ``max_chunks`` chunks (the caller polls
        the port between calls, so an answer never waits for a long catch-up)."""
        target = int((now - self.t0) * self.fs)
        lag = target - self.done - int(_MAX_LAG_S * self.fs)
        if lag > 0:  # we were not scheduled for a while: do not try to catch up all of it
            self.done += lag
            self.counts["skipped_s"] += lag / self.fs
            self._busy_until += lag
        B = self.B
        for _ in range(max_chunks):
            if self.done + B > target:
                break
            if self.display == "dot" and self.done >= self._busy_until and not self._left.any():
                self.done += (target - self.done) // B * B   # latched pins at rest: frozen
                break
            self._fill_drive()
            s = self.group.kernel(*self.group.args, self.drive, self._sensed, self.truth)
            if s & 2:
                self.counts["plant_faults"] += 1
            self.done += B
        self._read_states()

    def _fill_drive(self) -> None:
        d = self.drive
        if self.display == "sma":
            c = self.commands
            d[:] = np.where(c == P.UP, self.volts, np.where(c == P.DOWN, -self.volts, 0.0))[:, None]
            return
        d[:] = 0.0
        for i in np.flatnonzero(self._left):
            k = int(min(self._left[i], self.B))
            d[i, :k] = self._sign[i] * self.volts
            self._left[i] -= k

    def _read_states(self) -> None:
        x = self.truth[:, 0, -1]
        self.heights[:] = x
        if self.display == "dot":
            self.states[:] = np.where(x > 0.5 * self.travel, P.UP, P.DOWN)
        else:
            self.states[:] = np.where(x > SMA_STATE_HEIGHT, P.UP,
                                      np.where(x < -SMA_STATE_HEIGHT, P.DOWN, P.MIDDLE))

    def _rest_heights(self) -> np.ndarray:
        if self.display == "dot":
            return np.where(self.group._up0, self.travel, 0.0)
        return np.zeros(self.n)


class Faults:
    """Injected line faults (all off by default): every Nth byte or answer (the options), and the
    scene's ``[io.faults]`` byte faults, each a fraction of the bytes within its time window
    (``scheduled``: ``(kind, from s, to s, fraction)``, seconds since the first valid PINS frame,
    which :func:`serve` keeps in ``now``)."""

    def __init__(self, drop_every=0, garbage_every=0, corrupt_every=0, seed=1, scheduled=()):
        self.drop_every, self.garbage_every, self.corrupt_every = drop_every, garbage_every, corrupt_every
        self.rng = random.Random(seed)
        self.rx = self.tx = 0
        self.dropped = self.garbage = self.corrupted = self.duplicated = 0
        self.scheduled = list(scheduled)
        self.now = None

    def _p(self, kind: str) -> float:
        if self.now is None:
            return 0.0
        return max((p for k, t0, t1, p in self.scheduled if k == kind and t0 <= self.now < t1), default=0.0)

    def incoming(self, data: bytes) -> bytes:
        p = self._p("byte_drop")
        if self.drop_every <= 0 and p <= 0:
            return data
        keep = bytearray()
        for b in data:
            self.rx += 1
            if (self.drop_every <= 0 or self.rx % self.drop_every) and not (p > 0 and self.rng.random() < p):
                keep.append(b)
            else:
                self.dropped += 1
        return bytes(keep)

    def outgoing(self, frame: bytes) -> bytes:
        self.tx += 1
        if self.corrupt_every > 0 and self.tx % self.corrupt_every == 0:
            b = bytearray(frame)
            i = self.rng.randrange(1, len(b) - 1)
            b[i] ^= 1 << self.rng.randrange(8)
            frame = bytes(b)
            self.corrupted += 1
        flip, dup = self._p("byte_flip"), self._p("byte_dup")
        if flip > 0 or dup > 0:
            out = bytearray()
            for x in frame:
                if flip > 0 and self.rng.random() < flip:
                    x ^= 1 << self.rng.randrange(8)
                    self.corrupted += 1
                out.append(x)
                if dup > 0 and self.rng.random() < dup:
                    out.append(x)
                    self.duplicated += 1
            frame = bytes(out)
        if self.garbage_every > 0 and self.tx % self.garbage_every == 0:
            junk = bytes(self.rng.randrange(256) for _ in range(self.rng.randrange(1, 17)))
            frame = junk + frame
            self.garbage += len(junk)
        return frame


def scene_faults(scene) -> tuple[list, float]:
    """The scene's ``[io.faults]`` as this emulator injects them: ``(byte faults as (kind, from s,
    to s, fraction of bytes), when the device stops answering (inf: never))``, seconds after the
    first valid PINS frame (the run's first block); one line (SceneError) for a kind a pin
    controller's line cannot take."""
    from ..io import faults as F

    if not F.active(scene):
        return [], math.inf
    ctx = F.context(scene, F.SERIAL)
    period = scene.timing.block / scene.timing.fs
    scheduled, stall = [], math.inf
    for f in F.plan(scene, ctx):
        t0 = f.start * period
        if f.kind == "device_stopped":
            stall = min(stall, t0)
            continue
        t1 = math.inf if f.stop >= 2**62 else f.stop * period
        scheduled.append((f.kind, t0, t1, f.value or 0.01))
    return scheduled, stall


def serve(fw: Firmware, master: int, faults: Faults, stop, stall_after=None, mute=False, log=None,
          fault_stall=math.inf) -> None:
    """The firmware's main loop until ``stop()`` is true. The scene's faults count time from the
    first valid PINS frame (a run's first block: HELLO comes while its rig is still being built);
    ``fault_stall`` is when, on that clock, the device stops answering."""
    dec = P.Decoder()
    first_valid = first_pins = None
    while not stop():
        try:  # wake for a byte or for the next plant chunk, whichever comes first
            ready, _, _ = select.select([master], [], [], min(fw.wait(time.monotonic()), 0.01))
        except InterruptedError:
            continue
        now = time.monotonic()
        if ready:
            try:
                data = os.read(master, 4096)
            except BlockingIOError:
                data = b""
            except OSError as e:
                if e.errno != errno.EIO:
                    raise
                data = b""  # no slave open: cannot happen while we hold one, but do not spin
                time.sleep(fw.B / fw.fs)
            faults.now = None if first_pins is None else now - first_pins
            for f in dec.feed(faults.incoming(data)):
                if f.error is None and first_valid is None:
                    first_valid = now
                if f.error is None and f.kind == P.PINS and first_pins is None:
                    first_pins = now
                faults.now = None if first_pins is None else now - first_pins
                stalled = mute or (stall_after is not None and first_valid is not None
                                   and now - first_valid >= stall_after) or (
                    faults.now is not None and faults.now >= fault_stall)
                if stalled:
                    continue  # hung: reads and drops, answers nothing
                answer = fw.on_frame(f, now)
                if log:
                    log(f"rx {P.TYPE_NAMES.get(f.kind, f.kind)} seq={f.seq} err={f.error} -> "
                        f"{answer.hex()}")
                try:
                    os.write(master, faults.outgoing(answer))
                except BlockingIOError:
                    pass  # nobody reads the other end: the answer is lost, as on a real line
        if fw.watchdog(now) and log:
            log("watchdog: every output off")
        fw.advance(now)


def main(argv: list[str] | None = None) -> int:
    """``rtctl emulate serial SCENE [--set K=V ...] [options]``; returns the exit status."""
    a = _parser().parse_args(argv)
    from .. import scene as scene_mod

    sc = scene_mod.load(a.scene, a.overrides)
    for name, v in (("--fs", a.fs), ("--chunk-ms", a.chunk_ms), ("--pulse-ms", a.pulse_ms)):
        if not (v > 0 and math.isfinite(v)):
            raise RtctlError(f"{name} = {v!r}: must be a positive number")
    # the plant's buffers are a chunk long (--fs 1e12 asked for 119 GiB), and a chunk is computed
    # between two polls: one longer than the lag the loop catches up would stall every answer
    fs_key = SCENE.keys["timing"].keys["fs"]
    if not fs_key.lo <= a.fs <= fs_key.hi:
        raise RtctlError(f"--fs = {a.fs!r}: must be in [{fs_key.lo:g}, {fs_key.hi:g}] Hz (the range of timing.fs)")
    if a.chunk_ms > _MAX_LAG_S * 1e3:
        raise RtctlError(f"--chunk-ms = {a.chunk_ms!r}: must be at most {_MAX_LAG_S * 1e3:g} ms")
    for name, v in (("--drop-byte-every", a.drop_byte_every), ("--garbage-every", a.garbage_every),
                    ("--corrupt-every", a.corrupt_every)):
        if v < 0:
            raise RtctlError(f"{name} = {v}: must be a count >= 0 (0: never)")
    for name, v in (("--settle-ms", a.settle_ms), ("--stall-after", a.stall_after)):
        if v is not None and not 0 <= v < math.inf:  # written so that NaN fails too
            raise RtctlError(f"{name} = {v!r}: must be a finite number >= 0")
    fw = Firmware(sc, a.fs, a.chunk_ms * 1e-3, a.pulse_ms * 1e-3, max(a.settle_ms, 0.0) * 1e-3)
    fw.compile()
    scheduled, stall = scene_faults(sc)
    faults = Faults(a.drop_byte_every, a.garbage_every, a.corrupt_every, a.seed, scheduled)
    master, slave = pty.openpty()
    tty.setraw(slave)  # no echo, no line discipline: bytes pass as they are (0x00 included)
    fcntl.fcntl(master, fcntl.F_SETFL, fcntl.fcntl(master, fcntl.F_GETFL) | os.O_NONBLOCK)
    flag = []
    old = {s: signal.signal(s, lambda *_: flag.append(1)) for s in (signal.SIGTERM, signal.SIGINT)}
    log = (lambda m: print(f"emulate serial: {m}", file=sys.stderr, flush=True)) if a.verbose else None
    try:
        print(os.ttyname(slave), flush=True)
        fw.t0 = fw.last_valid = time.monotonic()
        fw.done = 0
        serve(fw, master, faults, lambda: bool(flag), a.stall_after, a.mute, log, stall)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        os.close(master)
        os.close(slave)
    c = fw.counts
    print(f"emulate serial: {fw.display} x{fw.n}: {c['frames']} frames, {c['bad']} rejected, "
          f"{c['pulses']} pulses, {c['watchdog_trips']} watchdog trips, {c['skipped_s']:.3f} s of "
          f"plant time skipped; injected: {faults.dropped} bytes dropped, {faults.garbage} garbage "
          f"bytes, {faults.corrupted} answers corrupted, {faults.duplicated} bytes sent twice", file=sys.stderr)
    return 0


def _cli() -> int:
    try:
        return main(sys.argv[1:])
    except RtctlError as e:
        print(f"rtctl emulate serial: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    sys.exit(_cli())
