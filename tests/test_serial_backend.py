"""The serial backend (rtctl.io.serial) against scripted devices on real pseudo-terminals.

A device here is a thread on the pty master that answers with rtctl.io.protocol messages as a
test scripts it (silent, NACKing, wrong type, unplugged); the firmware emulator as a separate
process is tests/test_serial_emulator.py. Every wait has a deadline."""

import contextlib
import gc
import json
import os
import pty
import select
import threading
import time
import tty

import numpy as np
import pytest

from rtctl import scene
from rtctl.errors import DeviceError, SceneError
from rtctl.io import protocol as P
from rtctl.io.base import Layout
from rtctl.io.serial import DEVICE_LOST, open_backend

pytestmark = pytest.mark.hil

TIMEOUT, RETRIES = 0.02, 3


class FakeDevice:
    """A scripted controller on a pty: ``policy(dev, frame) -> bytes or None``."""

    def __init__(self, display="dot", n=16, policy=None):
        self.master, self._slave = pty.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        self.display, self.n = display, n
        self.policy = policy or FakeDevice.answer
        self.frames = []  # (monotonic time, Frame)
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def answer(self, f):
        if f.error is not None:
            return P.nack(f.seq, P.BAD_FRAME)
        if f.kind == P.HELLO:
            return P.ident(f.seq, self.display, self.n)
        if f.kind == P.PINS:  # a perfect display: every pin is where it was told (OFF: middle)
            return P.ack(f.seq, P.unpack_pins(f.body, self.n))
        if f.kind == P.ALL_OFF:
            return P.ack(f.seq, np.zeros(self.n, np.uint8))
        return P.nack(f.seq, P.BAD_TYPE)

    def _run(self):
        dec = P.Decoder()
        while not self._stop:
            try:
                if not select.select([self.master], [], [], 0.005)[0]:
                    continue
                data = os.read(self.master, 4096)
            except OSError:
                return
            for f in dec.feed(data):
                self.frames.append((time.monotonic(), f))
                out = self.policy(self, f)
                if out:
                    os.write(self.master, out)

    def received(self, kind):
        return [(t, f) for t, f in self.frames if f.error is None and f.kind == kind]

    def unplug(self):
        self._stop = True
        self._thread.join(1.0)
        os.close(self.master)
        os.close(self._slave)

    def close(self):
        if not self._stop:
            self.unplug()


def _layout(n, block=32):
    return Layout(48000.0, block, tuple(f"g.{i}" for i in range(n)), ("g",) * n, ("dot",) * n, (), ())


@contextlib.contextmanager
def _timed():
    """A timed stretch without the collector: the bounds below are the backend's. Late in one run of
    the whole suite the HELLO bound (0.08 s) measured 0.68 s, with the scene's loading and any
    collection of the test process's heap (by then large) inside the stretch; both are now outside
    it (the paced loop freezes the collector for its run likewise)."""
    gc.collect()
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def _scene(path, *extra, name="dot-4x4"):
    return scene.load(name, [f"io.port={path}", "io.backend=serial", f"io.timeout={TIMEOUT}",
                             f"io.retries={RETRIES}", *extra])


def _open(path, *extra, name="dot-4x4", n=16, sc=None):
    """The backend on ``path`` (``sc``: a scene loaded before, so that a caller can time the
    opening alone) and its drive buffer."""
    sc = _scene(path, *extra, name=name) if sc is None else sc
    out, sensed = np.zeros((n, 32)), np.zeros((0, 32))
    return open_backend(sc, _layout(n), out, sensed), out


def _run(be, seconds, period=0.0005, until=None):
    """Call read/write like the paced engine; stop at ``until(status)``; returns the status."""
    t_end = time.monotonic() + seconds
    status = 0
    while time.monotonic() < t_end:
        status = be.read() | be.write()
        if until is not None and until(status):
            break
        time.sleep(period)
    return status


@pytest.fixture
def device():
    devs = []

    def make(**kw):
        devs.append(FakeDevice(**kw))
        return devs[-1]

    yield make
    for d in devs:
        d.close()


# --- opening ------------------------------------------------------------------------------------


def test_empty_port_says_how_to_get_one():
    with pytest.raises(SceneError, match="rtctl emulate serial") as e:
        _open("")
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("name", ["line-bimorph-5", "bimodal-4x4"])
def test_other_groups_are_refused_in_one_line(name):
    sc = scene.load(name, ["io.backend=serial", "io.port=/dev/null"])
    n = sum(g.grid[0] * g.grid[1] for g in sc.actuator)
    with pytest.raises(SceneError) as e:
        open_backend(sc, _layout(n), np.zeros((n, 32)), np.zeros((0, 32)))
    msg = str(e.value)
    assert "io.backend" in msg and "bimorph" in msg and "\n" not in msg


def test_ports_that_are_not_devices_are_refused_in_one_line(tmp_path):
    f = tmp_path / "not-a-tty"
    f.write_bytes(b"")
    for port in ("/nonexistent/ttyUSB7", "/dev/null", str(f), str(tmp_path)):
        t0 = time.monotonic()
        with pytest.raises(DeviceError) as e:
            _open(port)
        assert port in str(e.value) and "\n" not in str(e.value)
        assert time.monotonic() - t0 < 0.5


def test_a_device_that_never_answers_fails_hello_within_the_bound(device):
    dev = device(policy=lambda d, f: None)
    sc = _scene(dev.path)  # (loading the scene is not the handshake's time)
    with _timed():
        t0 = time.monotonic()
        with pytest.raises(DeviceError, match="no answer to HELLO") as e:
            _open(dev.path, sc=sc)
        elapsed = time.monotonic() - t0
    assert (RETRIES + 1) * TIMEOUT * 0.9 <= elapsed < (RETRIES + 1) * TIMEOUT + 0.1
    assert "\n" not in str(e.value)
    time.sleep(0.02)
    assert len(dev.received(P.HELLO)) == RETRIES + 1


def test_a_device_of_another_type_is_refused(device):
    dev = device(display="sma", n=64)
    with pytest.raises(DeviceError) as e:
        _open(dev.path)
    msg = str(e.value)
    assert "sma display with 64 pins" in msg and "dot with 16 pins" in msg and "\n" not in msg


# --- commands, keepalive, resends -------------------------------------------------------------------


def test_commands_come_from_the_last_sample_against_half_max_voltage(device):
    dev = device()
    be, out = _open(dev.path)
    # dot-4x4: max_voltage 5 V -> thresholds +-2.5 V; the earlier samples say the opposite
    last = [5.0, 2.6, 2.4, 0.0, -2.4, -2.6, -5.0, np.nan, 1e9, -np.inf] + [0.0] * 6
    want = [P.UP, P.UP, P.OFF, P.OFF, P.OFF, P.DOWN, P.DOWN, P.OFF, P.UP, P.DOWN] + [P.OFF] * 6
    out[:, :-1] = -np.sign(np.nan_to_num(np.array(last)))[:, None] * 5.0
    out[:, -1] = last
    assert _run(be, 1.0, until=lambda s: be.frames_acked >= 1) == 0
    (_, f), = dev.received(P.PINS)[:1]
    assert P.unpack_pins(f.body, 16).tolist() == want
    assert be.states.tolist() == want  # the fake display reports what it was told
    be.close()


def test_keepalive_and_changes(device):
    dev = device()
    keepalive = 0.02
    be, out = _open(dev.path, f"io.keepalive={keepalive}")
    out[:] = -5.0
    _run(be, 0.3)
    times = [t for t, _ in dev.received(P.PINS)]
    gaps = np.diff(times)
    # Timed on the device's side of a pty, so one late wake-up of either thread stretches one gap
    # and shortens the next: judge the bounds that matter, not single gaps to the millisecond.
    assert 0.3 / keepalive * 0.6 <= len(times) <= 0.3 / keepalive + 2  # no more often than keepalive
    assert gaps.max() < 4 * keepalive  # the device's watchdog (4x keepalive) never fires
    assert 0.9 * keepalive <= np.median(gaps) < 1.5 * keepalive
    s = be.stats()
    json.dumps(s)
    # nothing is lost; a busy machine may hold an answer past io.timeout, and the answer to its
    # resent copy then arrives stale
    assert s["frames_acked"] >= s["frames_sent"] - 1 and s["resends"] == s["stale_acks"] and s["error"] is None
    assert be.probe.shape == (len(be.probe_names), 32) and be.probe[1, 0] == 16.0  # every pin down
    be.close()


def test_a_change_goes_out_at_the_next_write_not_the_next_keepalive(device):
    dev = device()
    be, out = _open(dev.path, "io.keepalive=2.0")  # a keepalive would take seconds
    out[:] = -5.0
    _run(be, 0.1)
    n0 = len(dev.received(P.PINS))
    t0 = time.monotonic()
    out[3, -1] = 5.0
    _run(be, 1.0, until=lambda s: be.states[3] == P.UP)
    t_next, first = dev.received(P.PINS)[n0]  # the very next frame carries the change
    assert P.unpack_pins(first.body, 16)[3] == P.UP
    assert t_next - t0 < 0.5  # well before the keepalive, whatever the machine's load
    assert be.probe[0, 0] == 1.0  # pins up, as acknowledged
    be.close()


def test_a_nack_of_the_frame_in_flight_is_a_counted_resend(device):
    def nack_first_copy(dev, f):
        if f.error is None and f.kind == P.PINS and not any(
                g.seq == f.seq for _, g in dev.frames[:-1] if g.error is None and g.kind == P.PINS):
            return P.nack(f.seq, P.BAD_FRAME)
        return FakeDevice.answer(dev, f)

    dev = device(policy=nack_first_copy)
    be, out = _open(dev.path, "io.keepalive=0.01")
    assert _run(be, 0.2) == 0
    s = be.stats()
    assert s["nacks"] > 5 and s["frames_acked"] >= s["frames_sent"] - 1  # one may fly
    # every NACK is resent at once; any timeout is an answer a busy machine held late (stale after)
    assert s["resends"] == s["nacks"] + s["timeouts"] and s["timeouts"] == s["stale_acks"] and s["error"] is None
    be.close()


def test_silence_after_hello_is_device_lost_after_the_retries(device):
    dev = device(policy=lambda d, f: FakeDevice.answer(d, f) if f.kind == P.HELLO else None)
    be, out = _open(dev.path)
    with _timed():
        t0 = time.monotonic()
        status = _run(be, 1.0, until=lambda s: s & DEVICE_LOST)
        elapsed = time.monotonic() - t0
    assert status & DEVICE_LOST
    assert (RETRIES + 1) * TIMEOUT <= elapsed < (RETRIES + 1) * TIMEOUT + 0.05
    s = be.stats()
    assert s["timeouts"] == RETRIES + 1 and s["resends"] == RETRIES
    assert "no acknowledgement" in s["error"] and "\n" not in s["error"]
    seqs = [f.seq for _, f in dev.received(P.PINS)]
    assert len(seqs) == RETRIES + 1 and len(set(seqs)) == 1  # the same frame, resent
    assert be.write() & DEVICE_LOST and be.read() & DEVICE_LOST  # sticky
    time.sleep(0.02)
    assert len(dev.received(P.ALL_OFF)) == 1  # sent once, best effort
    be.close()


def test_unplugged_device_is_lost_at_the_next_call(device):
    dev = device()
    be, out = _open(dev.path, "io.keepalive=0.005")
    assert _run(be, 0.05) == 0 and be.frames_acked > 2
    dev.unplug()
    t0 = time.perf_counter()
    status = be.read() | be.write()
    assert status & DEVICE_LOST and time.perf_counter() - t0 < 0.005
    assert "went away" in be.stats()["error"]
    be.close()
    be.close()  # idempotent
    assert be.read() & DEVICE_LOST and be.write() & DEVICE_LOST  # and never raises


def test_close_sends_all_off_once(device):
    dev = device()
    be, out = _open(dev.path)
    out[:, -1] = 5.0
    _run(be, 0.05)
    be.close()
    be.close()
    offs = dev.received(P.ALL_OFF)
    assert len(offs) == 1
    assert (be.states == P.MIDDLE).all()  # the ALL_OFF's acknowledgement was read


def test_writes_never_wait_for_a_device_that_does_not_read(device):
    dev = device()
    be, out = _open(dev.path, "io.timeout=10.0")
    dev._stop = True  # the device stops reading; its pty input fills up
    dev._thread.join(1.0)
    # A write that waited would wait forever on a full pty: the writes run on a thread and must all
    # return (no wall-clock bound per write: a busy machine can preempt any single call).
    assert not os.get_blocking(be._fd)
    frame = P.pins(1, np.zeros(16, np.uint8))
    sent = []

    def write_until_error():
        for k in range(20000):
            be._send_raw(frame)
            if be.error:
                sent.append(k)  # the write that saw the error
                return
        sent.append(19999)  # ran out of frames

    t = threading.Thread(target=write_until_error, daemon=True)
    t.start()
    t.join(60.0)
    assert not t.is_alive(), "a write to a device that does not read blocked"
    assert sent and sent[0] < 19999  # it stopped on the error, not by running out of frames
    assert "does not read" in be.error
