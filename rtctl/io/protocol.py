"""The binary pin-frame protocol of the serial pin controllers (Dot 4x4, SMA 8x8).

Pure Python and numpy; it knows no port. The host (:mod:`rtctl.io.serial`) and the device
emulator (:mod:`rtctl.emulate.serial`) both speak it. Specification: docs/backends/serial.md.

On the wire every message is one **frame**::

    0x00  COBS(packet)  0x00          packet = type u8 | seq u8 | body | CRC-16 (big endian)

COBS (consistent overhead byte stuffing) removes every zero byte from the packet, so ``0x00``
only ever delimits frames: a receiver resynchronizes at the next zero whatever garbage came
before, without trusting a length field (a garbled length would make it wait for bytes that never
come). The leading ``0x00`` flushes line noise received before the frame into its own (bad)
chunk, so noise before a frame does not spoil it. The CRC is CRC-16/CCITT-FALSE (polynomial
0x1021, initial value 0xFFFF, no reflection, no final XOR; ``binascii.crc_hqx(data, 0xFFFF)``)
over type, seq and body.

Pins are packed 2 bits each, pin ``i`` in bits ``2 (i % 4)`` of byte ``i // 4``: commands
``OFF``/``UP``/``DOWN`` (host to device) and states ``MIDDLE``/``UP``/``DOWN`` (device to host).
"""

from __future__ import annotations

import binascii
import struct
from typing import NamedTuple

import numpy as np

PROTOCOL_VERSION = 1

# message types: host -> device below 0x80, device -> host from 0x80
HELLO, PINS, ALL_OFF = 0x01, 0x02, 0x03
IDENT, ACK, NACK = 0x81, 0x82, 0x83
TYPE_NAMES = {HELLO: "HELLO", PINS: "PINS", ALL_OFF: "ALL_OFF", IDENT: "IDENT", ACK: "ACK",
              NACK: "NACK"}

# pin commands (PINS) and pin states (ACK), 2 bits per pin
OFF, UP, DOWN = 0, 1, 2
MIDDLE = 0  # state: neither up nor down (an SMA taxel at its installed height or moving)

# display types (IDENT)
DISPLAYS = {1: "dot", 2: "sma"}
DISPLAY_CODES = {v: k for k, v in DISPLAYS.items()}

# NACK reasons
BAD_FRAME, BAD_LENGTH, BAD_TYPE, BAD_VALUE = 1, 2, 3, 4
REASONS = {BAD_FRAME: "bad frame (COBS or CRC)", BAD_LENGTH: "body length does not fit the type",
           BAD_TYPE: "unknown message type", BAD_VALUE: "a pin command is 3 (reserved)"}
#: NACK sequence number when the device could not read the rejected frame's.
SEQ_UNKNOWN = 0xFF

MAX_PINS = 1024
#: Largest packet: type, seq, a PINS/ACK body of MAX_PINS pins, CRC.
MAX_PACKET = 2 + MAX_PINS // 4 + 2
#: Largest COBS-encoded packet (one overhead byte per 254 bytes, at least one).
MAX_ENCODED = MAX_PACKET + MAX_PACKET // 254 + 1


class ProtocolError(ValueError):
    """A packet or body cannot be encoded or decoded."""


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (polynomial 0x1021, MSB first, no final XOR).

    This is ``binascii.crc_hqx(data, crc)``: the standard library's CRC-CCITT from a given start
    value, so the protocol keeps no table of its own.

    Parameters
    ----------
    data : bytes-like
    crc : int
        Start value: 0xFFFF for a whole packet, or the CRC of the bytes before ``data`` to
        continue over several pieces.

    Examples
    --------
    >>> hex(crc16(b"123456789"))    # the catalogue's check value
    '0x29b1'
    """
    return binascii.crc_hqx(data, crc)


def cobs_encode(data: bytes) -> bytes:
    """COBS-encode ``data`` (Cheshire & Baker 1999): the result has no zero byte.

    Examples
    --------
    >>> cobs_encode(bytes([0x11, 0x22, 0x00, 0x33])).hex()
    '0311220233'
    """
    out = bytearray()
    i, n = 0, len(data)
    while True:
        j = i
        while j < n and j - i < 254 and data[j] != 0:
            j += 1
        out.append(j - i + 1)
        out += data[i:j]
        if j == n:
            return bytes(out)
        # code 0xFF (254 data bytes) implies no zero; any shorter code implies the zero at j
        i = j if j - i == 254 else j + 1


def cobs_decode(data: bytes) -> bytes:
    """Inverse of :func:`cobs_encode`; raises :class:`ProtocolError` on a malformed input."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        end = i + code
        if code == 0 or end > n:
            raise ProtocolError(f"COBS code {code} at byte {i} runs past the end ({n} bytes)")
        out += data[i + 1:end]
        if 0 in data[i + 1:end]:
            raise ProtocolError("zero byte inside a COBS block")
        i = end
        if code < 0xFF and i < n:
            out.append(0)
    return bytes(out)


def encode(kind: int, seq: int, body: bytes = b"") -> bytes:
    """One wire frame: ``0x00 COBS(kind seq body crc16) 0x00``.

    Examples
    --------
    >>> encode(ALL_OFF, 7).hex()         # packet 03 07, CRC 0x38bb
    '0005030738bb00'
    """
    if not (0 <= kind <= 255 and 0 <= seq <= 255) or len(body) > MAX_PACKET - 4:
        raise ProtocolError(f"cannot encode type {kind}, seq {seq}, {len(body)}-byte body")
    packet = bytes((kind, seq)) + bytes(body)
    return b"\x00" + cobs_encode(packet + crc16(packet).to_bytes(2, "big")) + b"\x00"


class Frame(NamedTuple):
    """A received frame. ``error`` is None for a good frame, else why it was rejected; ``seq``
    is then the rejected packet's sequence number if it could be read, else None."""

    kind: int | None
    seq: int | None
    body: bytes
    error: str | None = None


def decode_packet(chunk: bytes) -> Frame:
    """Decode the bytes between two delimiters into a :class:`Frame` (good or rejected)."""
    try:
        packet = cobs_decode(chunk)
    except ProtocolError as e:
        return Frame(None, None, b"", f"bad COBS: {e}")
    if len(packet) < 4:
        return Frame(None, packet[1] if len(packet) >= 2 else None, b"",
                     f"too short ({len(packet)} bytes)")
    if crc16(packet[:-2]) != int.from_bytes(packet[-2:], "big"):
        return Frame(packet[0], packet[1], b"", "bad CRC")
    return Frame(packet[0], packet[1], packet[2:-2])


class Decoder:
    """Streaming frame decoder: feed it bytes as they arrive, in any split.

    Zero bytes delimit chunks; each non-empty chunk becomes a good or a rejected :class:`Frame`.
    A run longer than :data:`MAX_ENCODED` without a delimiter is dropped as it arrives and the
    decoder skips to the next zero, so memory stays bounded whatever the line delivers.

    Attributes
    ----------
    frames, bad : int
        Good and rejected frames so far.
    garbage : int
        Bytes skipped: those of rejected frames and of over-long runs.
    """

    def __init__(self, max_encoded: int = MAX_ENCODED):
        self.max_encoded = int(max_encoded)
        self._buf = bytearray()
        self._skipping = False
        self.frames = self.bad = self.garbage = 0

    def reset(self) -> None:
        """Forget buffered bytes (counters kept)."""
        self._buf.clear()
        self._skipping = False

    def feed(self, data: bytes) -> list:
        """Frames completed by ``data`` (good and rejected), in order."""
        out = []
        buf = self._buf
        buf += data
        while True:
            i = buf.find(0)
            if i < 0:
                if len(buf) > self.max_encoded:
                    if not self._skipping:
                        self.bad += 1
                        out.append(Frame(None, None, b"", "over-long run without a delimiter"))
                    self.garbage += len(buf)
                    self._skipping = True
                    buf.clear()
                return out
            chunk = bytes(buf[:i])
            del buf[:i + 1]
            if self._skipping:  # the tail of an over-long run
                self.garbage += len(chunk)
                self._skipping = False
                continue
            if not chunk:
                continue
            if len(chunk) > self.max_encoded:  # arrived with its delimiter in one piece: the
                self.bad += 1                  # same verdict as when it arrives byte by byte
                self.garbage += len(chunk)
                out.append(Frame(None, None, b"", "over-long run without a delimiter"))
                continue
            f = decode_packet(chunk)
            if f.error is None:
                self.frames += 1
            else:
                self.bad += 1
                self.garbage += len(chunk)
            out.append(f)


# ----------------------------------------------------------------------------- bodies


def pack_pins(codes) -> bytes:
    """Pack 2-bit codes (0..3), pin ``i`` in bits ``2 (i % 4)`` of byte ``i // 4``.

    Examples
    --------
    >>> pack_pins([UP, DOWN, OFF, UP, DOWN]).hex()
    '4902'
    """
    c = np.asarray(codes, dtype=np.uint8).ravel()
    if c.size and int(c.max()) > 3:
        raise ProtocolError("pin codes are 2 bits (0..3)")
    pad = np.zeros(-(-c.size // 4) * 4, dtype=np.uint8)
    pad[:c.size] = c
    q = pad.reshape(-1, 4)
    return (q[:, 0] | (q[:, 1] << 2) | (q[:, 2] << 4) | (q[:, 3] << 6)).astype(np.uint8).tobytes()


def unpack_pins(body: bytes, n: int, out: np.ndarray | None = None) -> np.ndarray:
    """The ``n`` 2-bit codes of ``body`` (uint8), into ``out`` if given."""
    if len(body) != -(-n // 4):
        raise ProtocolError(f"{len(body)} bytes do not hold {n} pins (need {-(-n // 4)})")
    b = np.frombuffer(body, dtype=np.uint8)
    codes = np.stack([b & 3, (b >> 2) & 3, (b >> 4) & 3, b >> 6], axis=1).ravel()[:n]
    if out is None:
        return codes.copy()
    out[:] = codes
    return out


def pins_bytes(n: int) -> int:
    """Body length of a PINS or ACK message for ``n`` pins."""
    return -(-n // 4)


def hello(seq: int, keepalive_s: float) -> bytes:
    """HELLO: protocol version, the host's keepalive in ms (the device arms a 4x watchdog)."""
    ms = min(max(int(round(keepalive_s * 1e3)), 1), 0xFFFF)
    return encode(HELLO, seq, struct.pack("<BH", PROTOCOL_VERSION, ms))


def parse_hello(body: bytes) -> tuple[int, float]:
    """``(protocol version, keepalive s)`` of a HELLO body."""
    if len(body) != 3:
        raise ProtocolError(f"HELLO body is 3 bytes, got {len(body)}")
    v, ms = struct.unpack("<BH", body)
    return v, ms * 1e-3


class Ident(NamedTuple):
    """What a device says about itself (IDENT, the answer to HELLO)."""

    version: int
    display: str
    n_pins: int
    firmware: tuple
    watchdog_s: float


_IDENT = struct.Struct("<BBHBBH")


def ident(seq: int, display: str, n_pins: int, firmware=(1, 0), watchdog_s: float = 0.2) -> bytes:
    """IDENT: protocol version, display type, pin count, firmware version, armed watchdog."""
    ms = min(max(int(round(watchdog_s * 1e3)), 1), 0xFFFF)
    return encode(IDENT, seq, _IDENT.pack(PROTOCOL_VERSION, DISPLAY_CODES[display], n_pins,
                                          firmware[0], firmware[1], ms))


def parse_ident(body: bytes) -> Ident:
    if len(body) != _IDENT.size:
        raise ProtocolError(f"IDENT body is {_IDENT.size} bytes, got {len(body)}")
    v, d, n, fa, fb, ms = _IDENT.unpack(body)
    return Ident(v, DISPLAYS.get(d, f"unknown display type {d}"), n, (fa, fb), ms * 1e-3)


def pins(seq: int, codes) -> bytes:
    """PINS: one 2-bit command per pin (OFF, UP, DOWN)."""
    return encode(PINS, seq, pack_pins(codes))


def all_off(seq: int) -> bytes:
    """ALL_OFF: every output off at once (no body)."""
    return encode(ALL_OFF, seq)


def ack(seq: int, states) -> bytes:
    """ACK of frame ``seq`` with the pins' reported states (MIDDLE, UP, DOWN)."""
    return encode(ACK, seq, pack_pins(states))


def nack(seq: int | None, reason: int) -> bytes:
    """NACK of frame ``seq`` (None: unreadable, sent as :data:`SEQ_UNKNOWN`) with a reason."""
    return encode(NACK, SEQ_UNKNOWN if seq is None else seq, bytes((reason,)))
