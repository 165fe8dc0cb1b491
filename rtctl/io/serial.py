"""The ``serial`` backend: binary pin displays (Dot 4x4, SMA 8x8) behind a pin controller.

The rig plays Dot and SMA pins as held levels or pulse trains (:mod:`rtctl.stimulus`): ``+V``
up, ``-V`` down, ``0`` off. Once per block :meth:`SerialBackend.write` turns the block's
**last sample** of each channel into a pin command, against half the group's ``max_voltage``
(the same comparator the Dot H-bridge model uses): above ``+max_voltage/2`` UP, below
``-max_voltage/2`` DOWN, otherwise (and NaN) OFF. A PINS frame goes out when a command changes
or ``io.keepalive`` has passed since the last frame. One frame is in flight at a time: a changed
command waits for the acknowledgement of the previous frame (a pty answers in well under a
millisecond; a UART at 115200 baud in about 2 ms). A frame not acknowledged within
``io.timeout``, or refused by a NACK of its sequence number, is resent; after ``io.retries``
resends, or at once when the port fails (unplugged: the read or write raises), the backend
returns ``DEVICE_LOST`` and ``stats()["error"]`` says what happened. Protocol, timing and
firmware behaviour: docs/backends/serial.md.

pyserial opens and configures the port (``timeout=0``: non-blocking); the block path reads and
writes the non-blocking descriptor directly with ``os.read``/``os.write``, so a full output
buffer or a vanished device costs one failed system call, never a wait (pyserial's own
non-blocking write loops while the kernel answers EAGAIN).
"""

from __future__ import annotations

import os
import select
import time

import numpy as np

from .. import safety
from ..errors import DeviceError, SceneError
from . import protocol as P
from .base import Backend

DEVICE_LOST = safety.DEVICE_LOST
PIN_TYPES = ("dot", "sma")
#: a drive beyond +-this fraction of max_voltage is an up/down command; within it, off
COMMAND_THRESHOLD = 0.5
_RTT_RING = 8192
_TX_LIMIT = 1 << 16


def pin_group(scene, who: str = "io.backend = 'serial'"):
    """The scene's one actuator group a pin controller drives (type ``dot`` or ``sma``);
    ``who`` names the asker in the error.

    Raises
    ------
    SceneError
        The scene has another number of groups or another type.
    """
    groups = list(scene.actuator)
    if len(groups) != 1 or groups[0].type not in PIN_TYPES:
        have = ", ".join(f"{g.name} ({g.type})" for g in groups) or "none"
        raise SceneError(f"{scene.source}: {who} drives exactly one actuator group of type dot or sma; "
                         f"this scene has: {have}")
    return groups[0]


def _open_port(port: str, baud: int):
    import serial  # pyserial, imported where it is used

    try:
        return serial.Serial(port, baudrate=baud, timeout=0, write_timeout=0)
    except (serial.SerialException, OSError, ValueError) as e:
        why = str(e).replace("\n", " ")
        raise DeviceError(f"io.port = {port!r}: cannot open it as a serial port ({why}); run "
                          "`rtctl devices` for the ports, or `rtctl emulate serial SCENE`") from None


def _handshake(ser, port: str, baud: int, timeout: float, retries: int, keepalive: float):
    """HELLO until an IDENT answers: at most ``retries + 1`` tries of ``timeout`` each."""
    fd = ser.fileno()
    dec = P.Decoder()
    frame = P.hello(0, keepalive)
    for _ in range(retries + 1):
        _write_fd(fd, frame)
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            if not select.select([fd], [], [], left)[0]:
                continue
            try:
                data = os.read(fd, 4096)
            except BlockingIOError:
                continue
            except OSError as e:
                raise DeviceError(f"io.port = {port!r}: the device went away during HELLO ({e.strerror})") from None
            if not data:
                raise DeviceError(f"io.port = {port!r}: the port closed during HELLO (end of file)")
            for f in dec.feed(data):
                if f.error is None and f.kind == P.IDENT and f.seq == 0:
                    try:
                        return P.parse_ident(f.body), dec
                    except P.ProtocolError as e:
                        raise DeviceError(f"io.port = {port!r}: malformed IDENT answer: {e}") from None
    raise DeviceError(f"io.port = {port!r}: no answer to HELLO after {retries + 1} tries of "
                      f"{timeout * 1e3:g} ms (io.timeout, io.retries): is the controller (or `rtctl "
                      f"emulate serial SCENE`) on this port, at io.baud = {baud}?")


def _write_fd(fd: int, data: bytes) -> int:
    """Bytes written without waiting (0 when the kernel buffer is full)."""
    try:
        return os.write(fd, data)
    except BlockingIOError:
        return 0


def open_backend(scene, layout, out: np.ndarray, sensed: np.ndarray) -> SerialBackend:
    """Open ``io.port``, identify the device with HELLO and return the backend.

    Parameters
    ----------
    scene : Scene
        One actuator group of type ``dot`` or ``sma``; keys ``io.port``, ``io.baud``,
        ``io.timeout``, ``io.retries``, ``io.keepalive``.
    layout : rtctl.io.base.Layout
    out : ndarray, shape (n_channels, block)
        The rig's drive buffer (volts after the limiter), read by :meth:`SerialBackend.write`.
    sensed : ndarray, shape (0, block)
        Pin controllers sense nothing.

    Raises
    ------
    SceneError
        Wrong actuator groups, or ``io.port`` is empty.
    DeviceError
        The port cannot be opened, never answers HELLO (bounded by ``timeout * (retries + 1)``),
        or reports another display type or pin count than the scene's group.
    """
    g = pin_group(scene)
    io = scene.io
    if not io.port:
        raise SceneError(f"{scene.source}: io.port is empty: start the device emulator with `rtctl "
                         f"emulate serial {scene.source}` and pass the path it prints (--set "
                         "io.port=PATH), or name the controller's port (`rtctl devices` lists them)")
    n = g.grid[0] * g.grid[1]
    if n > P.MAX_PINS:
        raise SceneError(f"{scene.source}: actuator.{g.name}: {n} pins; the serial protocol carries "
                         f"at most {P.MAX_PINS}")
    if out.shape[0] != n or sensed.shape[0] != 0:
        raise SceneError(f"{scene.source}: io.backend = 'serial': the rig has {out.shape[0]} drive and "
                         f"{sensed.shape[0]} sensed rows; actuator.{g.name} has {n} pins and no sense")
    ser = _open_port(io.port, io.baud)
    try:
        ident, dec = _handshake(ser, io.port, io.baud, io.timeout, io.retries, io.keepalive)
        if ident.version != P.PROTOCOL_VERSION or ident.display != g.type or ident.n_pins != n:
            raise DeviceError(
                f"io.port = {io.port!r}: the device is a {ident.display} display with {ident.n_pins} "
                f"pins (protocol {ident.version}, firmware {ident.firmware[0]}.{ident.firmware[1]}); "
                f"the scene's actuator.{g.name} is {g.type} with {n} pins (protocol "
                f"{P.PROTOCOL_VERSION}): wrong port or wrong scene")
    except BaseException:
        ser.close()
        raise
    return SerialBackend(ser, io.port, ident, dec, g, layout, out, sensed, io.timeout, io.retries,
                         io.keepalive)


class _InFlight:
    __slots__ = ("seq", "kind", "frame", "t_tx", "resends")

    def __init__(self, seq, kind, frame, t_tx):
        self.seq, self.kind, self.frame, self.t_tx, self.resends = seq, kind, frame, t_tx, 0


class SerialBackend(Backend):
    """A pin controller behind a serial port (a polled backend; see :mod:`rtctl.io.base`).

    Build it with :func:`open_backend`.

    Attributes
    ----------
    callback, paced, truth
        ``False``, ``True`` (the engine sleeps to the wall clock), ``None`` (hardware knows no
        truth).
    states : ndarray of uint8, shape (n_pins,)
        The pin states the last ACK reported (:data:`~rtctl.io.protocol.MIDDLE`, ``UP``,
        ``DOWN``).
    commands : ndarray of uint8, shape (n_pins,)
        The commands derived from the last block (``OFF``, ``UP``, ``DOWN``).
    probe_names : list of (str, str)
        Rows of ``probe`` the rig traces as ``io.NAME``.
    probe : ndarray, shape (6, block)
        Per block, held: reported pins up, reported pins down, frames sent, frames
        acknowledged, resends, last round trip (s).
    ident : rtctl.io.protocol.Ident
        What the device said in answer to HELLO.
    error : str or None
        Why the link died (None while it lives).
    """

    callback = False
    paced = True
    truth = None
    commands_only = COMMAND_THRESHOLD  # the firmware pulses the coils: the limiter sees commands
    probe_names = [("pins_up", ""), ("pins_down", ""), ("frames_sent", ""), ("frames_acked", ""),
                   ("resends", ""), ("rtt", "s")]

    def __init__(self, ser, port, ident, decoder, group, layout, out, sensed, timeout, retries,
                 keepalive):
        self._ser, self._fd, self.port, self.ident = ser, ser.fileno(), port, ident
        self._poller = select.poll()
        self._poller.register(self._fd, select.POLLIN | select.POLLERR | select.POLLHUP)
        self._dec = decoder
        self.out, self.sensed = out, sensed
        self.n = out.shape[0]
        self.threshold = COMMAND_THRESHOLD * float(group.max_voltage)
        self.timeout, self.retries, self.keepalive = float(timeout), int(retries), float(keepalive)
        self.commands = np.zeros(self.n, dtype=np.uint8)
        self.states = np.zeros(self.n, dtype=np.uint8)
        self._up = np.zeros(self.n, dtype=bool)
        self._down = np.zeros(self.n, dtype=bool)
        self.probe = np.zeros((len(self.probe_names), out.shape[1]))
        self._rtt = np.zeros(_RTT_RING)
        self._tx = bytearray()     # bytes the kernel buffer had no room for yet
        self._seq = 1              # 0 was HELLO
        self._inflight = None
        self.error = None
        self._lost = self._closed = self._off_sent = False
        self._port_ok = True
        self.reset()

    # --- the block path: never blocks, never raises ---------------------------------------------

    def read(self) -> int:
        """Take in what the device sent (ACKs, NACKs); ``DEVICE_LOST`` once the link died."""
        if self._lost or self._closed:
            return DEVICE_LOST
        try:
            self._poll(time.perf_counter())
        except Exception as e:  # a bug must not escape into the engine: end the run instead
            self._fail(f"io.port {self.port}: internal error while reading: {type(e).__name__}: {e}")
        return DEVICE_LOST if self._lost else 0

    def write(self) -> int:
        """Send the block's pin commands if they changed or the keepalive is due; resend on
        timeout. Returns 0, or ``DEVICE_LOST`` (sticky; ALL_OFF is then sent once, if the port
        still works)."""
        if self._closed:
            return DEVICE_LOST
        try:
            if not self._lost:
                now = time.perf_counter()
                self._poll(now)
                self._derive()
                if not self._lost:
                    self._tick(now)
            if self._lost and not self._off_sent:
                self._off_sent = True
                if self._port_ok:
                    self._send_raw(P.all_off(self._next_seq()))
            self._fill_probe()
        except Exception as e:
            self._fail(f"io.port {self.port}: internal error while writing: {type(e).__name__}: {e}")
        return DEVICE_LOST if self._lost else 0

    def _derive(self) -> None:
        last = self.out[:, -1]
        np.greater(last, self.threshold, out=self._up)
        np.less(last, -self.threshold, out=self._down)
        c = self.commands
        c[:] = self._up
        c += self._down
        c += self._down

    def _tick(self, now: float) -> None:
        f = self._inflight
        if f is not None:
            if now - f.t_tx >= self.timeout:
                self.timeouts += 1
                self._resend_or_fail(now, "no acknowledgement")
            return  # one frame in flight at a time
        body = P.pack_pins(self.commands)
        if body != self._last_body or now - self._last_tx >= self.keepalive:
            self._last_body = body
            seq = self._next_seq()
            self._inflight = _InFlight(seq, P.PINS, P.encode(P.PINS, seq, body), now)
            self._send_raw(self._inflight.frame)
            if not self.frames_sent:
                self._t_first = now
            self.frames_sent += 1

    def _resend_or_fail(self, now: float, why: str) -> None:
        f = self._inflight
        if f.resends >= self.retries:
            self._fail(f"io.port {self.port}: {why} for frame {f.seq} after {f.resends} resends "
                       f"(io.timeout = {self.timeout * 1e3:g} ms, io.retries = {self.retries}): the "
                       "device stopped answering")
            return
        f.resends += 1
        f.t_tx = now
        self.resends += 1
        self._send_raw(f.frame)

    def _poll(self, now: float) -> None:
        for _ in range(8):  # drain what is there, boundedly
            # Ask first: with VMIN = VTIME = 0 (pyserial's setting) an empty read means "nothing
            # yet", so only a read after readiness that returns nothing is an end of file.
            if not self._poller.poll(0):
                return
            try:
                data = os.read(self._fd, 4096)
            except BlockingIOError:
                return
            except OSError as e:
                self._port_ok = False
                self._fail(f"io.port {self.port}: the device went away (read failed: {e.strerror}): "
                           "unplugged, powered off, or the emulator ended")
                return
            if not data:
                self._port_ok = False
                self._fail(f"io.port {self.port}: the device went away (end of file): unplugged, "
                           "powered off, or the emulator ended")
                return
            for fr in self._dec.feed(data):
                self._handle(fr, now)
            if len(data) < 4096:
                return

    def _handle(self, fr, now: float) -> None:
        if fr.error is not None:
            return  # counted by the decoder; the timeout resends what it spoiled
        f = self._inflight
        if fr.kind == P.ACK:
            if f is None or fr.seq != f.seq:
                self.stale += 1  # the answer to an earlier copy of a resent frame
                return
            try:
                P.unpack_pins(fr.body, self.n, self.states)
            except P.ProtocolError:
                self.stale += 1
                return
            self._rtt[self.frames_acked % _RTT_RING] = now - f.t_tx
            self.frames_acked += 1
            self._t_last_ack = now
            self._inflight = None
        elif fr.kind == P.NACK:
            self.nacks += 1
            if f is not None and fr.seq == f.seq:
                reason = P.REASONS.get(fr.body[0] if fr.body else 0, "no reason")
                self._resend_or_fail(now, f"NACK ({reason})")

    def _send_raw(self, frame: bytes) -> None:
        if len(self._tx) > _TX_LIMIT:
            self._fail(f"io.port {self.port}: {len(self._tx)} bytes wait to be sent: the device "
                       "does not read (flow control held, or the emulator is stopped)")
            return
        self._tx += frame
        try:
            n = _write_fd(self._fd, bytes(self._tx))
        except OSError as e:
            self._port_ok = False
            self._fail(f"io.port {self.port}: the device went away (write failed: {e.strerror}): "
                       "unplugged, powered off, or the emulator ended")
            return
        del self._tx[:n]
        self._last_tx = time.perf_counter()

    def _next_seq(self) -> int:
        s = self._seq
        self._seq = (s + 1) & 0xFF
        if self._seq == P.SEQ_UNKNOWN:  # never used: a NACK of an unreadable frame carries it
            self._seq = 0
        return s

    def _fail(self, msg: str) -> None:
        self._lost = True
        if self.error is None:
            self.error = msg

    def _fill_probe(self) -> None:
        p = self.probe
        p[0].fill(np.count_nonzero(self.states == P.UP))
        p[1].fill(np.count_nonzero(self.states == P.DOWN))
        p[2].fill(self.frames_sent)
        p[3].fill(self.frames_acked)
        p[4].fill(self.resends)
        p[5].fill(self._rtt[(self.frames_acked - 1) % _RTT_RING] if self.frames_acked else 0.0)

    # --- between runs --------------------------------------------------------------------------

    def compile(self) -> None:
        """Nothing to compile: no kernel runs here; HELLO already checked the link."""

    def reset(self) -> None:
        """Zero the counters and the probe; the next :meth:`write` sends the commands afresh."""
        self.frames_sent = self.frames_acked = self.resends = self.nacks = 0
        self.timeouts = self.stale = 0
        self._dec.frames = self._dec.bad = self._dec.garbage = 0
        self._last_body = None
        self._last_tx = 0.0
        self._t_first = self._t_last_ack = 0.0
        self.probe[:] = 0.0

    def close(self) -> None:
        """ALL_OFF (acknowledged within ``timeout * (retries + 1)``, if the link is alive), then
        release the port. Idempotent; never raises."""
        if self._closed:
            return
        self._closed = True
        try:
            if not self._lost and self._port_ok:
                self._inflight = None
                seq = self._next_seq()
                frame = P.all_off(seq)
                for _ in range(self.retries + 1):
                    self._send_raw(frame)
                    if self._await_ack(seq, time.monotonic() + self.timeout):
                        break
        except Exception:
            pass
        try:
            self._ser.close()
        except Exception:
            pass

    def _await_ack(self, seq: int, deadline: float) -> bool:
        while (left := deadline - time.monotonic()) > 0 and self._port_ok:
            if not select.select([self._fd], [], [], left)[0]:
                continue
            try:
                data = os.read(self._fd, 4096)
            except BlockingIOError:
                continue
            except OSError:
                return False
            if not data:
                return False
            for fr in self._dec.feed(data):
                if fr.error is None and fr.kind == P.ACK and fr.seq == seq:
                    P.unpack_pins(fr.body, self.n, self.states)
                    return True
        return False

    def stats(self) -> dict:
        """Link counters for ``summary["io"]`` (JSON-able)."""
        k = min(self.frames_acked, _RTT_RING)
        rtt = self._rtt[:k] * 1e3
        span = self._t_last_ack - self._t_first  # first frame sent .. last one acknowledged
        return {
            "backend": "serial",
            "port": self.port,
            "display": self.ident.display,
            "pins": self.ident.n_pins,
            "firmware": f"{self.ident.firmware[0]}.{self.ident.firmware[1]}",
            "watchdog_s": self.ident.watchdog_s,
            "frames_sent": self.frames_sent,
            "frames_acked": self.frames_acked,
            "resends": self.resends,
            "timeouts": self.timeouts,
            "nacks": self.nacks,
            "stale_acks": self.stale,
            "bad_frames": self._dec.bad,
            "garbage_bytes": self._dec.garbage,
            "frame_rate_hz": self.frames_acked / span if span > 0 else 0.0,
            "rtt_ms": {"median": float(np.median(rtt)) if k else None,
                       "p99": float(np.percentile(rtt, 99)) if k else None,
                       "max": float(rtt.max()) if k else None},
            "pins_up": int(np.count_nonzero(self.states == P.UP)),
            "error": self.error,
        }
