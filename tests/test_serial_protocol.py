"""The serial pin-frame protocol (rtctl.io.protocol), against references we did not write:
``binascii.crc_hqx`` and the CRC catalogue's check value, the published COBS examples, and
plain loops."""

import binascii

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rtctl.io import protocol as P

# --- CRC -------------------------------------------------------------------------------------


def test_crc_check_value_of_the_catalogue():
    # CRC-16/CCITT-FALSE in Greg Cook's CRC catalogue: check = 0x29B1 for b"123456789"
    assert P.crc16(b"123456789") == 0x29B1


@given(st.binary(max_size=300))
def test_crc_matches_binascii_crc_hqx(data):
    assert P.crc16(data) == binascii.crc_hqx(data, 0xFFFF)


@given(st.binary(max_size=300), st.binary(max_size=300))
def test_crc_residue_and_continuation(a, b):
    # The catalogue's residue is 0x0000: a packet followed by its CRC (big endian) checks to 0.
    assert P.crc16(a + P.crc16(a).to_bytes(2, "big")) == 0x0000
    # The start value continues a CRC over pieces (how the docs' worked example is tabulated).
    assert P.crc16(b, P.crc16(a)) == P.crc16(a + b)


# --- COBS ------------------------------------------------------------------------------------

# The examples of the COBS article (Cheshire & Baker 1999, as tabulated on Wikipedia's
# "Consistent Overhead Byte Stuffing" page), without the trailing delimiter.
_R = bytes(range(1, 255))  # 01 .. FE, 254 bytes
COBS_EXAMPLES = [
    ("one-zero", b"\x00", b"\x01\x01"),
    ("two-zeros", b"\x00\x00", b"\x01\x01\x01"),
    ("zero-11-zero", b"\x00\x11\x00", b"\x01\x02\x11\x01"),
    ("11-22-00-33", b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
    ("no-zero", b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
    ("trailing-zeros", b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
    ("254-nonzero", _R, b"\xff" + _R),
    ("zero-then-254", b"\x00" + _R, b"\x01\xff" + _R),
    ("255-nonzero", _R + b"\xff", b"\xff" + _R + b"\x02\xff"),
    ("254-then-zero", bytes(range(2, 256)) + b"\x00", b"\xff" + bytes(range(2, 256)) + b"\x01\x01"),
    ("253-zero-01", bytes(range(3, 256)) + b"\x00\x01", b"\xfe" + bytes(range(3, 256)) + b"\x02\x01"),
]


@pytest.mark.parametrize("raw,enc", [(r, e) for _, r, e in COBS_EXAMPLES], ids=[i for i, _, _ in COBS_EXAMPLES])
def test_cobs_published_examples(raw, enc):
    assert P.cobs_encode(raw) == enc
    assert P.cobs_decode(enc) == raw


@given(st.binary(max_size=700))
def test_cobs_round_trip_has_no_zero(data):
    enc = P.cobs_encode(data)
    assert 0 not in enc
    assert len(enc) <= len(data) + len(data) // 254 + 1
    assert P.cobs_decode(enc) == data


@pytest.mark.parametrize("bad", [b"\x05\x11", b"\x00", b"\x03\x11\x00"], ids=["short", "zero-code", "zero-inside"])
def test_cobs_rejects_malformed(bad):
    with pytest.raises(P.ProtocolError):
        P.cobs_decode(bad)


# --- pin packing -----------------------------------------------------------------------------


@given(st.lists(st.integers(0, 3), min_size=1, max_size=P.MAX_PINS))
def test_pack_pins_matches_a_loop(codes):
    packed = P.pack_pins(codes)
    naive = bytearray((len(codes) + 3) // 4)
    for i, c in enumerate(codes):
        naive[i // 4] |= c << (2 * (i % 4))
    assert packed == bytes(naive)
    assert P.unpack_pins(packed, len(codes)).tolist() == codes


# --- every message type round trips ------------------------------------------------------------

seqs = st.integers(0, 254)
pin_lists = st.lists(st.sampled_from([P.OFF, P.UP, P.DOWN]), min_size=1, max_size=P.MAX_PINS)


def _one(wire):
    d = P.Decoder()
    frames = d.feed(wire)
    assert len(frames) == 1 and frames[0].error is None, frames
    assert wire[0] == 0 and wire[-1] == 0 and 0 not in wire[1:-1]
    return frames[0]


@settings(max_examples=60)
@given(seqs, st.floats(0.001, 10.0), pin_lists, st.sampled_from(["dot", "sma"]),
       st.sampled_from(list(P.REASONS)))
def test_every_message_round_trips(seq, keepalive, codes, display, reason):
    f = _one(P.hello(seq, keepalive))
    assert (f.kind, f.seq) == (P.HELLO, seq)
    v, ka = P.parse_hello(f.body)
    assert v == P.PROTOCOL_VERSION and ka == pytest.approx(round(keepalive * 1e3) * 1e-3)

    f = _one(P.ident(seq, display, len(codes), (2, 7), 4 * keepalive))
    assert (f.kind, f.seq) == (P.IDENT, seq)
    idn = P.parse_ident(f.body)
    assert (idn.display, idn.n_pins, idn.firmware) == (display, len(codes), (2, 7))
    assert idn.watchdog_s == pytest.approx(round(4e3 * keepalive) * 1e-3)

    for kind, wire in ((P.PINS, P.pins(seq, codes)), (P.ACK, P.ack(seq, codes))):
        f = _one(wire)
        assert (f.kind, f.seq) == (kind, seq)
        assert P.unpack_pins(f.body, len(codes)).tolist() == codes

    f = _one(P.all_off(seq))
    assert (f.kind, f.seq, f.body) == (P.ALL_OFF, seq, b"")
    f = _one(P.nack(seq, reason))
    assert (f.kind, f.seq, f.body) == (P.NACK, seq, bytes([reason]))
    assert _one(P.nack(None, reason)).seq == P.SEQ_UNKNOWN


# --- the streaming decoder -----------------------------------------------------------------------


def _stream():
    frames = [P.hello(0, 0.05), P.pins(1, [P.UP, P.DOWN] * 8), P.ack(1, [P.UP] * 16),
              P.all_off(2), P.nack(3, P.BAD_FRAME)]
    return frames, b"".join(frames)


def _good(frames):
    return [(f.kind, f.seq, f.body) for f in frames if f.error is None]


def test_split_reads_at_every_byte_boundary():
    frames, wire = _stream()
    expect = _good(P.Decoder().feed(wire))
    assert len(expect) == len(frames)
    for i in range(len(wire) + 1):
        for j in range(i, len(wire) + 1, 7):
            d = P.Decoder()
            got = d.feed(wire[:i]) + d.feed(wire[i:j]) + d.feed(wire[j:])
            assert _good(got) == expect and d.bad == 0, (i, j)
    d = P.Decoder()
    assert _good([f for b in wire for f in d.feed(bytes([b]))]) == expect


@given(st.binary(min_size=1, max_size=200))
def test_resync_after_random_garbage(garbage):
    frames, wire = _stream()
    d = P.Decoder()
    got = d.feed(garbage + wire)
    # the leading delimiter of the first frame cuts the garbage off: every frame survives
    assert _good(got) == _good(P.Decoder().feed(wire))
    # the garbage is rejected (counted), never taken for a frame of ours
    assert d.garbage <= len(garbage)
    assert d.frames + sum(1 for f in got if f.error) == len(got)


def test_dropped_byte_spoils_only_its_frame():
    frames, _ = _stream()
    hit = frames[1]
    expect = _good(P.Decoder().feed(frames[0] + frames[2]))
    for pos in range(1, len(hit) - 1):  # every byte between the delimiters
        spoiled = hit[:pos] + hit[pos + 1:]
        d = P.Decoder()
        got = d.feed(frames[0] + spoiled + frames[2])
        assert _good(got) == expect and d.bad == 1, pos


def test_corrupted_checksum_is_rejected_with_its_sequence_number():
    wire = bytearray(P.pins(42, [P.UP] * 16))
    wire[-3] ^= 0x01  # the first CRC byte, 0x4c -> 0x4d
    (f,) = P.Decoder().feed(bytes(wire))
    assert f.error == "bad CRC" and f.seq == 42 and f.kind == P.PINS


def test_corrupted_frame_gets_a_nack_from_the_firmware():
    from rtctl import scene
    from rtctl.emulate.serial import Firmware

    fw = Firmware(scene.load("dot-4x4"))
    wire = bytearray(P.pins(42, [P.UP] * 16))
    wire[4] ^= 0x04  # a pin byte
    (f,) = P.Decoder().feed(bytes(wire))
    (answer,) = P.Decoder().feed(fw.on_frame(f, 0.0))
    assert (answer.kind, answer.seq, answer.body) == (P.NACK, 42, bytes([P.BAD_FRAME]))
    assert not fw.commands.any()  # the spoiled command was not applied
    (answer,) = P.Decoder().feed(fw.on_frame(P.Decoder().feed(P.pins(43, [P.UP] * 16))[0], 0.0))
    assert (answer.kind, answer.seq) == (P.ACK, 43) and (fw.commands == P.UP).all()


def test_over_long_run_is_dropped_and_memory_stays_bounded():
    d = P.Decoder()
    junk = bytes(np.random.default_rng(0).integers(1, 256, 20_000, dtype=np.uint8))
    got = []
    for k in range(0, len(junk), 1000):
        got += d.feed(junk[k:k + 1000])
        assert len(d._buf) <= P.MAX_ENCODED + 1000
    got += d.feed(P.all_off(9))
    assert _good(got) == [(P.ALL_OFF, 9, b"")]
    assert d.garbage == len(junk)


def test_encode_refuses_what_does_not_fit():
    with pytest.raises(P.ProtocolError):
        P.encode(P.PINS, 256)
    with pytest.raises(P.ProtocolError):
        P.encode(P.PINS, 1, bytes(P.MAX_PACKET))
    with pytest.raises(P.ProtocolError):
        P.unpack_pins(b"\x00", 16)


def test_docstring_examples():
    import doctest

    res = doctest.testmod(P, optionflags=doctest.ELLIPSIS)
    assert res.attempted >= 4 and res.failed == 0
