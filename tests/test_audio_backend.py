"""The audio backend without an audio server: device matching, channel maps and scaling, the copy
kernels against plain numpy, and the callback and engine thread driven by a fake PortAudio stream
that hands over arrays made exactly as sounddevice makes them (``np.frombuffer`` over cffi memory).
None of them needs PortAudio: where sounddevice cannot be imported they take its callback types
from ``portaudio_standin``.
"""

import threading
import time
import tracemalloc

import numpy as np
import pytest

from rtctl.errors import DeviceError, SceneError
from rtctl.io import _audio_kernels as K
from rtctl.io import audio
from rtctl.io.base import Layout
from rtctl.safety import DEVICE_LOST, IO_XRUN, Limiter

try:
    import sounddevice as sd
except (ImportError, OSError):  # no PortAudio on this machine: none of these tests needs it
    import portaudio_standin as sd
else:
    # Importing sounddevice initialized PortAudio, whose JACK host joins a running JACK server: these
    # tests need none, and a pytest process holding one may not join another (test_hil_audio.py).
    audio.release(sd)

FS, BLOCK = 48000.0, 64


@pytest.fixture(autouse=True)
def _module_state(monkeypatch):
    """Backends built here on a fake PortAudio must not change the real one's bookkeeping."""
    monkeypatch.setattr(audio, "_open_streams", audio._open_streams)
    monkeypatch.setattr(audio, "_poisoned", audio._poisoned)
APIS = [{"name": "ALSA"}, {"name": "JACK Audio Connection Kit"}]
DEVS = [
    {"name": "system", "hostapi": 1, "max_input_channels": 8, "max_output_channels": 8},
    {"name": "HDA Intel PCH: ALC3246 Analog (hw:0,0)", "hostapi": 0, "max_input_channels": 2, "max_output_channels": 2},
    {"name": "Scarlett 18i20 USB: Audio (hw:1,0)", "hostapi": 0, "max_input_channels": 18, "max_output_channels": 20},
    {"name": "Scarlett 2i2 USB: Audio (hw:2,0)", "hostapi": 0, "max_input_channels": 2, "max_output_channels": 2},
]


# --- device names and channel maps -------------------------------------------------------------

@pytest.mark.parametrize("name, api, want", [
    ("system", "", 0), ("SYSTEM", "jack", 0), ("18i20", "", 2), ("scarlett 2i2", "ALSA", 3), ("ALC3246", "", 1),
], ids=["exact", "case-and-api", "substring", "api-filter", "middle"])
def test_find_device_by_name_and_host_api(name, api, want):
    assert audio.find_device(DEVS, APIS, name, api) == want


@pytest.mark.parametrize("name, api, words", [
    ("Fireface", "", ["'Fireface'", "no such audio device", "'system' (JACK Audio Connection Kit, 8 in, 8 out)",
                      "Scarlett 18i20"]),
    ("Scarlett", "", ["matches 2 devices", "18i20", "2i2", "io.host_api"]),
    ("system", "ALSA", ["io.host_api = 'ALSA'", "no such audio device"]),
    ("", "", ["io.device is empty", "'system'"]),
], ids=["none", "several", "wrong-api", "empty"])
def test_find_device_errors_list_what_exists(name, api, words):
    with pytest.raises(DeviceError) as e:
        audio.find_device(DEVS, APIS, name, api)
    msg = str(e.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, (w, msg)


def test_channel_map_default_explicit_and_errors():
    assert audio.channel_map((), 4, 8, "io.outputs", "drive channels").tolist() == [0, 1, 2, 3]
    assert audio.channel_map((7, 0), 2, 8, "io.outputs", "drive channels").tolist() == [7, 0]
    with pytest.raises(SceneError, match=r"io.inputs has 3 entries but the scene has 2 sensed rows"):
        audio.channel_map((0, 1, 2), 2, 8, "io.inputs", "sensed rows")
    with pytest.raises(SceneError, match=r"io.outputs = \[1, 1\]: device channel 1 is given twice"):
        audio.channel_map((1, 1), 2, 8, "io.outputs", "drive channels")
    with pytest.raises(DeviceError, match=r"io.outputs = \[0, 8\]: the device has channels 0..7, not 8"):
        audio.channel_map((0, 8), 2, 8, "io.outputs", "drive channels")
    with pytest.raises(DeviceError, match=r"io.inputs .* channels 0..1, not 2"):
        audio.channel_map((), 3, 2, "io.inputs", "sensed rows")


def test_missing_portaudio_is_one_line(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "sounddevice", None)  # import raises ImportError
    with pytest.raises(DeviceError) as e:
        audio._sounddevice()
    assert "PortAudio" in str(e.value) and "libportaudio2" in str(e.value) and "\n" not in str(e.value)


# --- copy kernels vs plain numpy ---------------------------------------------------------------

def sd_array(frames, channels, values=None):
    """A float32 (frames, channels) array made the way sounddevice's callback wrapper makes it."""
    buf = sd._ffi.new("float[]", frames * channels)
    a = sd._array(sd._buffer(buf, frames, channels, 4), channels, "float32")
    if values is not None:
        a[...] = values
    return a, buf


@pytest.mark.parametrize("seed", range(5))
def test_kernels_match_numpy(seed):
    rng = np.random.default_rng(seed)
    n_dev, n_rows = rng.integers(3, 12), rng.integers(1, 3)
    chans = rng.permutation(n_dev)[:n_rows].astype(np.int64)
    frames, keep = sd_array(BLOCK, n_dev, rng.uniform(-1, 1, (BLOCK, n_dev)))
    rows = np.empty((n_rows, BLOCK))
    K.frames_to_rows(frames, chans, 0.02, rows)
    np.testing.assert_array_equal(rows, frames[:, chans].T.astype(np.float64) * 0.02)

    volts = rng.uniform(-200, 200, (n_rows, BLOCK))
    volts[0, 3] = np.nan
    outf, keep2 = sd_array(BLOCK, n_dev, 7.0)  # stale garbage in the device buffer
    last = np.zeros(n_rows)
    clipped = K.rows_to_frames(volts, chans, 1 / 150.0, outf, last)
    want = np.zeros((BLOCK, n_dev), np.float32)
    v = np.nan_to_num(volts / 150.0, nan=0.0)
    want[:, chans] = np.clip(v, -1, 1).T
    np.testing.assert_allclose(outf, want, rtol=1e-7, atol=1e-9)
    assert clipped == np.sum(np.abs(volts / 150.0) > 1) + 1  # the NaN counts too
    np.testing.assert_allclose(last, want[-1, chans] * 150.0, rtol=1e-6)

    K.fade_frames(last.copy(), chans, 1 / 150.0, outf)
    ramp = 1.0 - np.arange(1, BLOCK + 1) / BLOCK
    np.testing.assert_allclose(outf[:, chans], (want[-1, chans][None, :] * ramp[:, None]), rtol=1e-6, atol=1e-9)
    assert not np.any(outf[:, np.setdiff1d(np.arange(n_dev), chans)])
    assert np.all(outf[-1] == 0.0)


# --- a fake PortAudio and a tiny rig -----------------------------------------------------------

class FakeStream:
    """Calls the callback at the block rate on a thread, like PortAudio; ``lose_after`` blocks
    later it stops calling (a device unplugged: PortAudio marks the stream inactive)."""

    def __init__(self, channels, callback, samplerate, blocksize, lose_after=None, stall=False, flags=None, **kw):
        self.channels, self.callback = channels, callback
        self.samplerate, self.blocksize, self.latency = samplerate, blocksize, (0.0015, 0.0027)
        self.lose_after, self.stall, self.flags = lose_after, stall, flags or {}
        self.active = False
        self.calls = 0
        self.indata = None
        self._thread = None

    def start(self):
        self.active = True
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self):
        n_in, n_out = self.channels
        period = self.blocksize / self.samplerate
        t = time.perf_counter()
        while self.active:
            if self.lose_after is not None and self.calls >= self.lose_after:
                self.active = self.stall  # a stalled device: still "active", no more callbacks
                self.t_lost = time.perf_counter()
                return
            ind, k1 = sd_array(self.blocksize, n_in, 0.0 if self.indata is None else self.indata)
            outd, k2 = sd_array(self.blocksize, n_out, 5.0)
            flags = sd.CallbackFlags(self.flags.get(self.calls, 0))
            try:
                self.callback(ind, outd, self.blocksize, None, flags)
            except sd.CallbackAbort:
                self.active = False
            self.last_out = outd.copy()
            self.calls += 1
            t += period
            time.sleep(max(0.0, t - time.perf_counter()))

    def stop(self):
        self.active = False
        if self._thread:
            self._thread.join(1)

    abort = stop

    def close(self):
        self.stop()


class FakeSD:
    PortAudioError = sd.PortAudioError
    CallbackAbort = sd.CallbackAbort

    def __init__(self, **stream_kw):
        self.stream_kw = stream_kw
        self.stream = None
        self.rates = {48000.0}

    def check_input_settings(self, device, channels, dtype, samplerate):
        if samplerate not in self.rates:
            raise sd.PortAudioError("Invalid sample rate")

    check_output_settings = check_input_settings

    def Stream(self, device, channels, callback, samplerate, blocksize, **kw):  # noqa: N802
        self.stream = FakeStream(channels, callback, samplerate, blocksize, **self.stream_kw)
        return self.stream


class TinyRig:
    """Two drive channels (sines through the real limiter), three sensed rows."""

    def __init__(self, amp=(100.0, 40.0), fail_at=None):
        self.block = BLOCK
        self.out = np.zeros((2, BLOCK))
        self.sensed = np.zeros((3, BLOCK))
        self.limiter = Limiter(FS, max_voltage=[150.0, 150.0], slew=[1e9, 1e9], current=[1.0, 1.0],
                               capacitance=[1e-9, 1e-9], temperature=[80.0, 80.0], ambient=[25.0, 25.0],
                               loss_tangent=[0.0, 0.0], thermal_resistance=[1.0, 1.0], thermal_tau=[10.0, 10.0])
        self.amp = np.array(amp)
        self.k = 0
        self.fail_at = fail_at
        self.seen_sensed = []

    def step(self):
        if self.fail_at is not None and self.k == self.fail_at:
            raise FloatingPointError("a bug in the block step")
        n = np.arange(self.k * BLOCK, (self.k + 1) * BLOCK)
        self.out[:] = self.amp[:, None] * np.sin(2 * np.pi * 375.0 * n / FS)[None, :]
        self.k += 1
        return self.limiter.process(self.out)

    def snapshot(self, snaps, slot):
        snaps.out[slot] = self.out
        snaps.sensed[slot] = self.sensed


LAYOUT = Layout(FS, BLOCK, ("g.0", "g.1"), ("g", "g"), ("bimorph", "bimorph"), ("g.0.seg0", "g.0.seg1", "g.1.seg0"),
                (0, 0, 1))


def backend(fake, outputs=(5, 2), inputs=(1, 0, 3), vpf=150.0, apf=0.01, fs=FS):
    lay = Layout(fs, BLOCK, *[getattr(LAYOUT, f) for f in
                              ("channel_names", "channel_groups", "channel_types", "sensed_names", "sensed_channel")])
    dev = {"name": "fake", "max_input_channels": 8, "max_output_channels": 8}
    out, sensed = np.zeros((2, BLOCK)), np.zeros((3, BLOCK))
    be = audio.AudioBackend(fake, 0, dev, "Fake API", lay, out, sensed,
                            audio.channel_map(outputs, 2, 8, "io.outputs", ""),
                            audio.channel_map(inputs, 3, 8, "io.inputs", ""), vpf, apf)
    return be


def rig_for(be, **kw):
    rig = TinyRig(**kw)
    be._out, be._sensed = rig.out, rig.sensed  # the rig's buffers, as open_backend receives them
    return rig


def test_unsupported_rate_is_a_device_error():
    with pytest.raises(DeviceError, match=r"fake \(Fake API\): 44100 Hz, float32 not supported .*timing.fs"):
        backend(FakeSD(), fs=44100.0)


def test_callback_maps_and_scales_both_ways():
    fake = FakeSD()
    be = backend(fake)
    rig = rig_for(be)
    be.bind(rig)
    be.compile()
    n_in, n_out = be._n_in, be._n_out
    assert (n_in, n_out) == (4, 6)  # up to the highest mapped channel
    rng = np.random.default_rng(0)
    ind, k1 = sd_array(BLOCK, n_in, rng.uniform(-1, 1, (BLOCK, n_in)))
    outd, k2 = sd_array(BLOCK, n_out, 9.0)
    be._callback(ind, outd, BLOCK, None, sd.CallbackFlags(0))
    # sensed row r <- device input io.inputs[r], times amps per full scale
    np.testing.assert_allclose(rig.sensed, ind[:, [1, 0, 3]].T * 0.01, rtol=1e-7)
    # drive channel c -> device output io.outputs[c], divided by volts per full scale
    np.testing.assert_allclose(outd[:, 5], rig.out[0] / 150.0, rtol=1e-6)
    np.testing.assert_allclose(outd[:, 2], rig.out[1] / 150.0, rtol=1e-6)
    assert not np.any(outd[:, [0, 1, 3, 4]])
    assert be.ctl[K.DONE] == 1 and np.array_equal(be.snaps.out[0], rig.out)
    # status flags: counted and marked on the block
    be._callback(ind, outd, BLOCK, None, sd.CallbackFlags(sd._lib.paOutputUnderflow | sd._lib.paInputOverflow))
    s = be.stats()
    assert (s["output_underflow"], s["input_overflow"], s["xruns"], s["first_xrun_block"]) == (1, 1, 2, 1)
    assert be.snaps.status[1] & IO_XRUN and not be.snaps.status[0] & IO_XRUN


def test_callback_allocates_no_arrays_and_compiles_nothing():
    fake = FakeSD()
    be = backend(fake)
    be.bind(rig_for(be))
    be.compile()
    sigs = [len(k.signatures) for k in (K.frames_to_rows, K.rows_to_frames)]
    ind, k1 = sd_array(BLOCK, 4)
    outd, k2 = sd_array(BLOCK, 6)
    flags = sd.CallbackFlags(0)
    for _ in range(20):
        be._callback(ind, outd, BLOCK, None, flags)
    assert [len(k.signatures) for k in (K.frames_to_rows, K.rows_to_frames)] == sigs
    be._snapshot = lambda snaps, slot: None  # the tiny rig's step allocates; time only the backend
    be._step = lambda: 0
    # tracemalloc counts every thread's allocations (a daemon thread left by an earlier test, the
    # garbage collector): the callback's own would show in every repetition, so take the least
    peaks = []
    tracemalloc.start()
    try:
        for _ in range(5):
            base = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            for _ in range(200):
                be._callback(ind, outd, BLOCK, None, flags)
            peaks.append(tracemalloc.get_traced_memory()[1] - base)
    finally:
        tracemalloc.stop()
    assert min(peaks) < 400, peaks  # a few Python ints; one block of float64 would be 1 KiB


def test_failing_step_fades_then_aborts_without_raising_into_portaudio():
    fake = FakeSD()
    be = backend(fake)
    rig = rig_for(be, fail_at=3)
    be.bind(rig)
    ind, k1 = sd_array(BLOCK, 4)
    outd, k2 = sd_array(BLOCK, 6)
    for _ in range(3):
        be._callback(ind, outd, BLOCK, None, sd.CallbackFlags(0))
    last = outd[-1, [5, 2]].copy()
    assert np.all(np.abs(last) > 0)
    be._callback(ind, outd, BLOCK, None, sd.CallbackFlags(0))  # step raises: a fade, no exception
    ramp = 1.0 - np.arange(1, BLOCK + 1) / BLOCK
    np.testing.assert_allclose(outd[:, [5, 2]], last[None, :] * ramp[:, None], rtol=1e-5, atol=1e-7)
    with pytest.raises(sd.CallbackAbort):  # next block: zeros, then the abort
        be._callback(ind, outd, BLOCK, None, sd.CallbackFlags(0))
    assert not np.any(outd)
    assert "FloatingPointError: a bug in the block step" in be.stats()["error"]


def run_backend(fake, n_blocks, stop_at=None, **rig_kw):
    be = backend(fake)
    rig = rig_for(be, **rig_kw)
    be.compile()
    got = []

    def on_block(k, slot):
        got.append((k, be.snaps.out[slot].copy(), int(be.snaps.status[slot])))
        return stop_at is not None and k + 1 >= stop_at

    status = be.run(rig, n_blocks, on_block)
    return be, rig, got, status, time.perf_counter()


def test_run_delivers_every_block_in_order_then_fades_to_zero():
    be, rig, got, status, _ = run_backend(FakeSD(), 60)
    ks = [k for k, _, _ in got]
    assert ks == list(range(len(ks))) and len(ks) > 60  # the fade blocks come after the 60
    assert np.all(got[-1][1][:, -1] == 0.0) and rig.limiter.done  # the fade's last block ends at 0 V
    assert np.max(np.abs(got[59][1])) > 50  # still playing at the last requested block
    assert status & DEVICE_LOST == 0
    assert be.stats()["blocks"] >= len(ks) and be.stats()["error"] is None
    be.close()
    be.close()  # idempotent


def test_a_slow_engine_thread_does_not_stretch_the_run():
    """The device thread fades after n_blocks itself; the engine, at half speed, catches up."""
    be = backend(FakeSD())
    rig = rig_for(be)
    be.compile()
    got = []

    def on_block(k, slot):
        time.sleep(2 * BLOCK / FS)
        got.append((k, be.snaps.out[slot].copy()))
        return False

    t = time.perf_counter()
    be.run(rig, 40, on_block)
    assert time.perf_counter() - t < 2.0
    assert rig.limiter.done and [k for k, _ in got] == list(range(len(got)))
    playing = [k for k, out in got if np.any(out)]
    assert max(playing) <= 41  # the fade ends within a block or two of block 40
    assert len(got) >= max(playing) + 1  # every played block reached the engine


def test_on_block_stop_request_fades():
    be, rig, got, status, _ = run_backend(FakeSD(), 10_000, stop_at=20)
    assert 20 < len(got) < 40 and np.all(got[-1][1][:, -1] == 0.0)


@pytest.mark.parametrize("stall", [False, True], ids=["stream-stopped", "no-callbacks"])
def test_device_loss_ends_the_run_quickly_with_zero_outputs(stall):
    fake = FakeSD(lose_after=40, stall=stall)
    be, rig, got, status, t_end = run_backend(fake, 10_000)
    assert status & DEVICE_LOST
    # a stream that stops ends the run within 100 ms; a device that just goes quiet, LOSS_TIMEOUT later
    assert t_end - fake.stream.t_lost < (audio.LOSS_TIMEOUT + 0.05 if stall else 0.1)
    assert np.all(got[-1][1][:, -1] == 0.0) and rig.limiter.done
    assert all(s & DEVICE_LOST for _, _, s in got[40:]) and len(got) > 40
    err = be.stats()["error"]
    assert "audio device fake (Fake API) lost" in err and ("the stream stopped" in err or "no callback" in err)


# --- the C callback (numba cfunc) against the Python one -----------------------------------------

def rig_backend(scene, cfunc: bool, monkeypatch):
    from rtctl.engine.rig import build

    monkeypatch.setenv("RTCTL_AUDIO_CFUNC", "1" if cfunc else "0")
    rig = build(scene)
    n, m = rig.n_channels, rig.sensed.shape[0]
    lay = Layout(rig.fs, rig.block, tuple(rig.channel_names), tuple(rig.channel_groups), ("bimorph",) * n,
                 tuple(rig.sensed_names), tuple(range(m)))
    dev = {"name": "fake", "max_input_channels": 16, "max_output_channels": 16}
    be = audio.AudioBackend(FakeSD(), 0, dev, "Fake API", lay, rig.out, rig.sensed,
                            audio.channel_map((), n, 16, "io.outputs", ""),
                            audio.channel_map((), m, 16, "io.inputs", ""),
                            150.0, 0.01)
    be.compile()
    rig.apply_schedule(0)
    be.bind(rig)
    return rig, be


def c_call(be, ind, outd, flags=0):
    fn = sd._ffi.cast("PaStreamCallback *", be._cfunc.address)
    user = sd._ffi.cast("void *", int(be._cfunc_keep[0].ctypes.data))
    return fn(sd._ffi.from_buffer(ind), sd._ffi.from_buffer(outd), ind.shape[0], sd._ffi.NULL, flags, user)


@pytest.mark.parametrize("observe", ["false", "true"], ids=["tones", "tones+observer"])
def test_c_callback_gives_the_python_callbacks_blocks(observe, monkeypatch):
    from rtctl import scene as scenes

    sc = scenes.load("line-bimorph-5", ["timing.block=64", f"control.observe={observe}"])
    rig_c, be_c = rig_backend(sc, True, monkeypatch)
    rig_p, be_p = rig_backend(sc, False, monkeypatch)
    assert be_c._cfunc is not None, be_c.stats()["cfunc_note"]
    assert be_p._cfunc is None and be_p.stats()["cfunc_note"].startswith("off")
    rng = np.random.default_rng(1)
    n_in, n_out = be_c._n_in, be_c._n_out
    fade_end = None
    for k in range(60):
        frames = rng.normal(0, 1e-3, (BLOCK, n_in))
        ind_c, a = sd_array(BLOCK, n_in, frames)
        ind_p, b = sd_array(BLOCK, n_in, frames)
        out_c, c = sd_array(BLOCK, n_out, 3.0)
        out_p, d = sd_array(BLOCK, n_out, 3.0)
        flags = 6 if k == 7 else 0  # input overflow + output underflow
        if k == 30:
            be_c.ctl[K.STOP_REQ] = be_p.ctl[K.STOP_REQ] = 1
        assert c_call(be_c, ind_c, out_c, flags) == K.PA_CONTINUE
        be_p._callback(ind_p, out_p, BLOCK, None, sd.CallbackFlags(flags))
        if rig_p.limiter.done and fade_end is None:
            fade_end = k + 1
        np.testing.assert_allclose(out_c, out_p, rtol=1e-6, atol=1e-9)
        slot = k % be_c.snaps.n
        for f in ("out", "sensed", "estimated", "temperature"):
            np.testing.assert_allclose(getattr(be_c.snaps, f)[slot], getattr(be_p.snaps, f)[slot], rtol=1e-9,
                                       atol=1e-15, err_msg=f)
        assert be_c.snaps.status[slot] == be_p.snaps.status[slot]
    assert np.max(np.abs(be_c.snaps.out[25])) > 10  # it played, then faded
    assert rig_c.limiter.done and rig_p.limiter.done
    # both mark the block in which the fade reached 0 V, the first after which the limiter is done
    assert be_c.ctl[K.FADE_END] == be_p.ctl[K.FADE_END] == fade_end
    sc_, sp = be_c.stats(), be_p.stats()
    for key in ("blocks", "input_overflow", "output_underflow", "xruns", "first_xrun_block", "clipped_samples"):
        assert sc_[key] == sp[key], key
    assert sc_["blocks"] == 60 and sc_["xruns"] == 2 and sc_["first_xrun_block"] == 7


@__import__("numba").njit(cache=False)
def boom(flag, out):
    if flag[0]:
        raise ValueError("boom")
    out[:, :] = 40.0
    return 0


def test_c_callback_catches_a_failing_step_fades_then_aborts():
    from rtctl.engine.kernels import snapshot as _snapshot

    out, sensed = np.zeros((2, BLOCK)), np.zeros((3, BLOCK))
    est, amp, temp = np.zeros((2, BLOCK)), np.zeros(2), np.zeros(2)
    flag = np.zeros(1, dtype=np.int64)
    snaps = audio.Snapshots(4, 2, 3, BLOCK)
    ctl = np.zeros(K.N_CTL, dtype=np.int64)
    lim = (np.zeros((3, 2)), np.ones((8, 2)), np.zeros(2, dtype=np.int64))
    inputs, outputs, last = np.arange(3), np.array([1, 0]), np.zeros(2)  # alive while the callback runs
    cf, keep = K.build_callback(
        calls=[(boom, (flag, out))],
        snapshot=(_snapshot, (out, sensed, est, amp, temp, snaps.out, snaps.sensed, snaps.estimated,
                              snaps.estimated_amp, snaps.temperature)),
        ctl=ctl, inputs=inputs, in_scale=0.01, sensed=sensed, outputs=outputs, out_scale=1 / 80.0,
        out=out, last=last, limiter=lim, status=snaps.status, compute=snaps.compute_us, n_in=3, n_out=2,
        block=BLOCK, fs=FS, io_xrun=IO_XRUN)

    class B:  # what c_call needs
        _cfunc, _cfunc_keep = cf, keep

    ind, a = sd_array(BLOCK, 3, 0.5)
    outd, b = sd_array(BLOCK, 2, 9.0)
    assert c_call(B, ind, outd) == K.PA_CONTINUE
    np.testing.assert_allclose(outd, 0.5)  # 40 V at 80 V full scale
    np.testing.assert_allclose(sensed, 0.005)
    flag[0] = 1
    assert c_call(B, ind, outd) == K.PA_CONTINUE  # the exception stays inside: a fade
    np.testing.assert_allclose(outd[:, 0], 0.5 * (1 - np.arange(1, BLOCK + 1) / BLOCK), rtol=1e-6)
    assert ctl[K.FAILED] == 1 and ctl[K.DONE] == 1
    assert c_call(B, ind, outd) == K.PA_ABORT and not np.any(outd)  # zeros, then PortAudio stops


def test_limiter_shutdown_kernel_is_the_limiters():
    rng = np.random.default_rng(3)
    for _ in range(5):
        lim = Limiter(FS, max_voltage=[150.0] * 3, slew=rng.uniform(1e3, 1e6, 3), current=[1.0] * 3,
                      capacitance=[1e-9] * 3, temperature=[80.0] * 3, ambient=[25.0] * 3, loss_tangent=[0.0] * 3,
                      thermal_resistance=[1.0] * 3, thermal_tau=[10.0] * 3)
        lim.state[0] = rng.uniform(-150, 150, 3)
        twin = [a.copy() for a in lim.args[:3]]
        for smooth in (False, True):
            n = lim.shutdown(64, smooth)
            assert K.limiter_shutdown(*twin, 64, smooth) == n
            for a, b in zip(lim.args[:3], twin):
                np.testing.assert_array_equal(a, b)


def test_ctrl_c_fades_delivers_each_block_once_and_reraises():
    be = backend(FakeSD())
    rig = rig_for(be)
    be.compile()
    got = []

    def on_block(k, slot):
        got.append((k, be.snaps.out[slot].copy()))
        if k == 30:
            raise KeyboardInterrupt
        return False

    with pytest.raises(KeyboardInterrupt):
        be.run(rig, 10_000, on_block)
    ks = [k for k, _ in got]
    assert ks == list(range(len(ks))) and 31 < len(ks) < 60
    assert rig.limiter.done and np.all(got[-1][1][:, -1] == 0.0)


class LingeringRig(TinyRig):
    """Its step lingers (the GIL released, as in a nogil kernel) in the block where the
    limiter's fade has just reached 0 V: the engine thread then sees the limiter done while that
    block is not yet counted, every time, instead of on a rare unlucky schedule."""

    def step(self):
        st = super().step()
        if self.limiter.done and not getattr(self, "lingered", False):
            self.lingered = True
            time.sleep(0.02)  # 15 blocks: the engine thread polls many times meanwhile
        return st


@pytest.mark.parametrize("how", ["ctrl-c", "on_block", "n_blocks"])
def test_the_fade_block_is_delivered_though_the_limiter_is_done_before_the_block_is_counted(how):
    be = backend(FakeSD())
    rig = LingeringRig()
    be._out, be._sensed = rig.out, rig.sensed
    be.compile()
    got = []

    def on_block(k, slot):
        got.append((k, be.snaps.out[slot].copy()))
        if how == "ctrl-c" and k == 30:
            raise KeyboardInterrupt
        return how == "on_block" and k == 30

    if how == "ctrl-c":
        with pytest.raises(KeyboardInterrupt):
            be.run(rig, 10_000, on_block)
    else:
        be.run(rig, 31 if how == "n_blocks" else 10_000, on_block)
    ks = [k for k, _ in got]
    assert rig.lingered and ks == list(range(len(ks))) and len(ks) > 31
    assert np.max(np.abs(got[30][1])) > 50  # still playing at the stop
    # the block that ended the fade was delivered (ending at 0 V); any later one is silent
    end = int(be.ctl[K.FADE_END])
    assert 31 < end <= len(ks) and rig.limiter.done
    assert np.all(got[end - 1][1][:, -1] == 0.0) and np.any(got[end - 1][1])
    assert not any(np.any(out) for _, out in got[end:])
