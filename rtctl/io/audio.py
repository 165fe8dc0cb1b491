"""The ``audio`` backend: drive channels out and current-sense channels in through one full-duplex
sounddevice (PortAudio) stream, with the rig's block step running in the device's callback.

Per callback (the device thread): device input frames -> ``rig.sensed`` (amps, via ``io.inputs``
and ``io.amps_per_fs``), the rig's block step (synthesis, limiter, observers: ``nogil`` kernels),
``rig.out`` -> device output frames (via ``io.outputs`` and ``io.volts_per_fs``, clipped at full
scale, unmapped device outputs 0), a snapshot of the block into a ring the engine's thread reads.
:meth:`AudioBackend.run` is that engine thread: it hands completed blocks to ``on_block`` in order
(trace, schedule) and decides when to stop. A stop always fades the outputs through the limiter;
a device that stops calling back (unplugged, audio server gone) is noticed within
``LOSS_TIMEOUT`` and reported as ``DEVICE_LOST``.

The callback is C where it can be: a numba ``cfunc`` with PortAudio's callback signature that
runs the whole block (:func:`rtctl.io._audio_kernels.build_callback`), so the audio thread never
waits for Python's GIL; a Python callback does the same job where the cfunc cannot be built (or
with ``RTCTL_AUDIO_CFUNC=0``). Both share the int64 control array ``ctl`` with the engine thread.
bench/hil_audio.py measures the difference.

Devices are opened by name and host API (PortAudio's indices change when devices come and go).
Under JACK the stream's client is named ``rtctl`` (``rtctl-01``... when taken), its ports
``rtctl:in_N`` / ``rtctl:out_N`` (N = device channel, 0-based) exist while :meth:`run` runs;
``JACK_DEFAULT_SERVER`` picks the server, as for every libjack client. PortAudio is initialized
(devices rescanned) when a backend opens and terminated when the last one closes: a PortAudio
still attached to a JACK server that goes away aborts the process at exit. After a device loss
it can be neither closed nor terminated (both block or abort): the process keeps it and refuses
further audio backends with a one-line error.
"""

from __future__ import annotations

import ctypes
import gc
import math
import os
import sys
import threading
import time

import numpy as np

from ..errors import DeviceError
from ..safety import DEVICE_LOST, IO_XRUN
from . import _audio_kernels as K
from .base import Backend, Snapshots, channel_map  # noqa: F401 - channel_map is part of this module's API

#: JACK client name of the stream (PortAudio keeps the pointer: this object must live).
CLIENT_NAME = ctypes.create_string_buffer(b"rtctl")
#: No callback for this long (s) while running: the device is lost. (A JACK server that dies is
#: noticed sooner: PortAudio marks the stream inactive within milliseconds.)
LOSS_TIMEOUT = 0.1
#: The first callback may take this long (s) after start.
START_TIMEOUT = 2.0
#: Snapshot ring length (blocks the engine thread may fall behind before trace blocks are lost).
RING = 512

_open_streams = 0  # PortAudio is re-initialized (device rescan) only while this is 0
_poisoned = None   # why PortAudio cannot be used again in this process (its audio server died)


def _sounddevice():
    """Import sounddevice (PortAudio) or say in one line why not."""
    os.environ.setdefault("JACK_NO_START_SERVER", "1")  # libjack must not start a server of its own
    try:
        import sounddevice as sd
    except (ImportError, OSError) as e:
        raise DeviceError(f"io.backend = 'audio' needs PortAudio and the sounddevice package ({e}); "
                          "install them (Debian: apt-get install libportaudio2; pip install sounddevice)") from None
    return sd


def rescan(sd) -> None:
    """Re-initialize PortAudio (under the JACK client name ``rtctl``) so that devices and audio
    servers started after ``import sounddevice`` are seen. Skipped while a stream is open."""
    if _poisoned:
        raise DeviceError(f"{_poisoned}; PortAudio cannot be restarted in this process: run rtctl again")
    if _open_streams:
        return
    try:  # PaJack_SetClientName exists where PortAudio was built with JACK
        ctypes.CDLL(sd._libname).PaJack_SetClientName(CLIENT_NAME)
    except (OSError, AttributeError):
        pass
    release(sd)
    sd._initialize()


def release(sd) -> None:
    """Terminate PortAudio (closing its JACK client) unless a backend's stream is open.

    Done when the last backend closes: a PortAudio still connected to a JACK server that later
    goes away aborts the whole process at exit (an assertion in PortAudio's JACK host API).
    """
    if _open_streams or _poisoned:
        return
    while sd._initialized > 0:
        sd._terminate()


def describe_devices(devices, hostapis) -> str:
    """``'NAME' (HOST API, X in, Y out)`` for every device, comma-separated."""
    if not devices:
        return "none"
    return ", ".join(f"{d['name']!r} ({hostapis[d['hostapi']]['name']}, {d['max_input_channels']} in, "
                     f"{d['max_output_channels']} out)" for d in devices)


def find_device(devices, hostapis, name: str, host_api: str = "") -> int:
    """Index of the one device whose name contains ``name`` on a host API containing ``host_api``
    (case-insensitive; an exact name wins over longer ones).

    Parameters
    ----------
    devices : list of dict
        As ``sounddevice.query_devices()``: ``name``, ``hostapi``, ``max_input_channels``,
        ``max_output_channels``.
    hostapis : list of dict
        As ``sounddevice.query_hostapis()``: ``name``.

    Raises
    ------
    DeviceError
        Nothing or several devices match; the message lists the devices there are.

    Examples
    --------
    >>> apis = [{"name": "ALSA"}, {"name": "JACK Audio Connection Kit"}]
    >>> devs = [{"name": "system", "hostapi": 1, "max_input_channels": 8, "max_output_channels": 8},
    ...         {"name": "HDA Intel: system", "hostapi": 0, "max_input_channels": 2, "max_output_channels": 2}]
    >>> find_device(devs, apis, "system", "jack")
    0
    """
    devices = list(devices)
    have = describe_devices(devices, hostapis)
    if not name:
        raise DeviceError(f"io.device is empty: name the audio device (have: {have})")
    api = host_api.lower()
    hits = [i for i, d in enumerate(devices)
            if name.lower() in d["name"].lower() and api in hostapis[d["hostapi"]]["name"].lower()]
    exact = [i for i in hits if devices[i]["name"].lower() == name.lower()]
    if len(exact) == 1:
        return exact[0]
    where = f"io.device = {name!r}" + (f", io.host_api = {host_api!r}" if host_api else "")
    if not hits:
        raise DeviceError(f"{where}: no such audio device (have: {have}); is the audio server running?")
    if len(hits) > 1:
        which = describe_devices([devices[i] for i in hits], hostapis)
        raise DeviceError(f"{where} matches {len(hits)} devices: {which}; "
                          "give more of the name or set io.host_api")
    return hits[0]


def open_backend(scene, layout, out, sensed) -> AudioBackend:
    """Open the scene's audio device for the rig's buffers (the stream is created, not started).

    Parameters
    ----------
    scene : rtctl.scene.Scene
        ``io.device``, ``io.host_api``, ``io.outputs``, ``io.inputs``, ``io.volts_per_fs``,
        ``io.amps_per_fs``.
    layout : rtctl.io.base.Layout
    out : ndarray, shape (n_channels, block)
        The rig's drive volts (read by the callback after the block step).
    sensed : ndarray, shape (n_sensed, block)
        The rig's sensed currents (written by the callback before the block step).

    Raises
    ------
    DeviceError
        No PortAudio, no or several matching devices, a channel the device lacks, an unsupported
        sample rate, or PortAudio refusing the stream.
    """
    sd = _sounddevice()
    io = scene.io
    rescan(sd)
    devices, apis = list(sd.query_devices()), list(sd.query_hostapis())
    idx = find_device(devices, apis, io.device, io.host_api)
    dev = devices[idx]
    outputs = channel_map(io.outputs, layout.n_channels, dev["max_output_channels"], "io.outputs", "drive channels")
    inputs = channel_map(io.inputs, layout.n_sensed, dev["max_input_channels"], "io.inputs", "sensed rows")
    return AudioBackend(sd, idx, dev, apis[dev["hostapi"]]["name"], layout, out, sensed, outputs, inputs,
                        float(io.volts_per_fs), float(io.amps_per_fs),
                        guard=(float(io.silence_ms), int(io.xrun_limit), float(io.xrun_window)))


class AudioBackend(Backend):
    """A full-duplex PortAudio stream serving one rig; see the module docstring.

    ``callback = True``: the engine calls :meth:`run`, not ``read``/``write``. The stream exists
    from :meth:`run` to its end. Its callback is C where it can be (``cfunc``: a numba-compiled
    PaStreamCallback that runs the whole block without Python or the GIL), else Python
    (``RTCTL_AUDIO_CFUNC=0`` forces Python). Both share one int64 control array ``ctl``
    (fields in :mod:`rtctl.io._audio_kernels`) with the engine thread.
    """

    callback = True
    paced = True
    truth = None
    probes = ()
    #: Blocks from a drive block to the sensed block that answers it, for the observer: one for
    #: the callback's own cycle plus one for the server's (measured through JACK: 2.00 blocks at
    #: blocks 32 and 64, bench/hil_audio.py). An interface with converter delays differs:
    #: ``io.latency_blocks`` overrides it.
    latency_blocks = 2

    def __init__(self, sd, index, dev, host_api, layout, out, sensed, outputs, inputs, volts_per_fs, amps_per_fs,
                 guard=(50.0, 25, 0.5)):
        self._sd, self._index = sd, index
        self.device = f"{dev['name']} ({host_api})"
        self.fs, self.block = float(layout.fs), int(layout.block)
        self._out, self._sensed = out, sensed
        self._outputs, self._inputs = outputs, inputs
        self._out_scale, self._in_scale = 1.0 / volts_per_fs, amps_per_fs
        self._last = np.zeros(len(outputs))
        self._period_ns = self.block / self.fs * 1e9
        # the device thread's guards (_audio_kernels.io_guard): silent inputs after ms, more than
        # n xruns within a window of s; 0 switches either off
        silence_ms, n_xruns, window_s = guard
        self._silent_limit = math.ceil(silence_ms * 1e-3 * self.fs / self.block) if silence_ms > 0 else 0
        w = max(1, round(window_s * self.fs / self.block))
        self._xrun_bucket = (w, n_xruns, n_xruns * w) if n_xruns > 0 else (0, 0, 0)
        self._guard_text = (silence_ms, n_xruns, window_s)
        self.snaps = Snapshots(RING, layout.n_channels, layout.n_sensed, self.block)
        self.ctl = np.zeros(K.N_CTL, dtype=np.int64)
        self._n_out = int(outputs.max()) + 1 if outputs.size else 1
        self._n_in = int(inputs.max()) + 1 if inputs.size else 0
        try:
            if self._n_in:
                sd.check_input_settings(device=index, channels=self._n_in, dtype="float32", samplerate=self.fs)
            sd.check_output_settings(device=index, channels=self._n_out, dtype="float32", samplerate=self.fs)
        except sd.PortAudioError as e:
            raise DeviceError(f"{self.device}: {self.fs:g} Hz, float32 not supported ({e}); set timing.fs "
                              "to a rate the device runs at (under JACK: the server's rate, jackd -r)") from None
        self._stream = None
        self._latency = (math.nan, math.nan)
        self._closed = False
        self._rig = None
        self._cfunc = self._cfunc_keep = None
        self._cfunc_note = None
        self.reset()

    def _open_stream(self, c_callback) -> None:
        """Open the stream with the C callback (a cfunc) or the Python one (None)."""
        global _open_streams
        sd = self._sd
        kw = dict(samplerate=self.fs, blocksize=self.block, dtype="float32", latency="low",
                  clip_off=True, dither_off=True)
        dev = (self._index, self._index) if self._n_in else self._index
        ch = (self._n_in, self._n_out) if self._n_in else self._n_out
        try:
            if c_callback is not None:
                user = sd._ffi.cast("void *", int(self._cfunc_keep[0].ctypes.data))
                self._stream = sd._StreamBase("duplex" if self._n_in else "output", device=dev, channels=ch,
                                              callback=c_callback.address, userdata=user, wrap_callback=None, **kw)
            elif self._n_in:
                self._stream = sd.Stream(device=dev, channels=ch, callback=self._callback, **kw)
            else:
                self._stream = sd.OutputStream(device=dev, channels=ch, callback=self._callback_out, **kw)
        except sd.PortAudioError as e:
            raise DeviceError(f"{self.device}: PortAudio cannot open the stream ({e})") from None
        _open_streams += 1
        if self._stream.samplerate != self.fs:
            raise DeviceError(f"{self.device}: runs at {self._stream.samplerate:g} Hz, the scene at "
                              f"{self.fs:g} Hz; set timing.fs = {self._stream.samplerate:g}")
        self._latency = self._stream.latency

    # --- the device thread (Python callback; the C one does the same in _audio_kernels) -----------

    def _callback_out(self, outdata, frames, time_info, status):
        self._callback(None, outdata, frames, time_info, status)

    def _callback(self, indata, outdata, frames, time_info, status):
        """PortAudio's thread, once per block. Never lets an exception out: a failure fades the
        outputs over this block, zeroes the next one and only then aborts the stream."""
        ctl = self.ctl
        ctl[K.BUSY] = 1
        try:
            abort = self._serve(indata, outdata, frames, status)
        except BaseException as e:  # noqa: BLE001 - nothing may escape into the audio thread
            abort = self._fail(e, outdata)
        ctl[K.BUSY] = 0
        if abort:
            raise self._sd.CallbackAbort

    def _serve(self, indata, outdata, frames, status) -> bool:
        ctl = self.ctl
        if frames != self.block or ctl[K.HALT] or ctl[K.FAILED]:
            outdata.fill(0.0)
            if frames != self.block:  # PortAudio promises fixed blocks; never step on a partial one
                ctl[K.ODD] += 1
            return bool(ctl[K.FAILED])
        t0 = time.perf_counter_ns()
        st = self._count_flags(status) if status else 0
        if (ctl[K.STOP_REQ] or ctl[K.DONE] >= ctl[K.STOP_AT]) and not ctl[K.STOP_BEGUN]:
            ctl[K.STOP_BEGUN] = 1
            K.limiter_shutdown(*self._lim, self._stop_fade, True)
        if self._n_in:
            K.frames_to_rows(indata, self._inputs, self._in_scale, self._sensed)
        st |= self._step()
        ctl[K.CLIPPED] += K.rows_to_frames(self._out, self._outputs, self._out_scale, outdata, self._last)
        st |= K.io_guard(ctl, self._sensed, self._out, st, *self._lim, self.block)
        snaps = self.snaps
        k = int(ctl[K.DONE])
        slot = k % snaps.n
        self._snapshot(snaps, slot)
        t1 = time.perf_counter_ns()
        if t1 - t0 > self._period_ns:
            ctl[K.LATE] += 1
        if ctl[K.LAST_NS] and t0 - ctl[K.LAST_NS] > ctl[K.MAX_GAP]:
            ctl[K.MAX_GAP] = t0 - ctl[K.LAST_NS]
        snaps.status[slot] = st
        snaps.compute_us[slot] = (t1 - t0) * 1e-3
        ctl[K.LAST_NS] = t1
        ctl[K.DONE] = k + 1
        return False

    def _count_flags(self, status) -> int:
        """Count PortAudio's under/overflow flags; ``IO_XRUN`` if any is set."""
        f = (status.input_underflow, status.input_overflow, status.output_underflow, status.output_overflow)
        if not any(f):
            return 0
        ctl = self.ctl
        if ctl[K.FIRST_XRUN] < 0:
            ctl[K.FIRST_XRUN] = ctl[K.DONE]
        for i in range(4):
            ctl[K.IN_UNDER + i] += f[i]
        return IO_XRUN

    def _fail(self, e, outdata) -> bool:
        abort = bool(self.ctl[K.FAILED])
        if not abort:
            self.ctl[K.FAILED] = 1
            self._error = f"the audio callback failed at block {self.ctl[K.DONE]} ({type(e).__name__}: {e})"
        try:
            if abort:
                outdata.fill(0.0)
            else:
                K.fade_frames(self._last, self._outputs, self._out_scale, outdata)
        except BaseException:  # noqa: BLE001
            try:
                outdata.fill(0.0)
            except BaseException:  # noqa: BLE001
                pass
            abort = True
        return abort

    # --- the engine thread ----------------------------------------------------------------------

    def compile(self) -> None:
        """Compile (or load) the copy kernels for the exact array types the callback sees:
        sounddevice hands over ``np.frombuffer`` views, C-contiguous float32 (frames, channels)."""
        fin = np.frombuffer(bytearray(4 * self.block * max(self._n_in, 1)), dtype=np.float32)
        fin = fin.reshape(-1, max(self._n_in, 1))  # a view: fin is C-contiguous, never copied
        fout = np.frombuffer(bytearray(4 * self.block * self._n_out), dtype=np.float32)
        fout = fout.reshape(-1, self._n_out)  # a view, as above
        K.frames_to_rows(fin, self._inputs, self._in_scale, np.zeros_like(self._sensed))
        last = np.zeros_like(self._last)
        K.rows_to_frames(np.zeros_like(self._out), self._outputs, self._out_scale, fout, last)
        K.fade_frames(last, self._outputs, self._out_scale, fout)
        st, par, fade = np.zeros((5, 1)), np.ones((13, 1)), np.zeros(3, dtype=np.int64)
        K.limiter_shutdown(st, par, fade, self.block, True)
        ctl = np.zeros(K.N_CTL, dtype=np.int64)
        K.io_guard(ctl, np.zeros_like(self._sensed), np.zeros_like(self._out), 0, st, par, fade, self.block)

    def reset(self) -> None:
        """Zero the counters and the snapshot ring (the rig resets its own state)."""
        self.ctl[:] = 0
        self.ctl[K.FIRST_XRUN] = -1
        self.ctl[K.STOP_AT] = 2**62
        self.ctl[K.XRUN_ADD], self.ctl[K.XRUN_LEAK], self.ctl[K.XRUN_CAP] = self._xrun_bucket
        self.ctl[K.SILENT_LIMIT] = self._silent_limit
        self._error = None
        self._lost_ms = None
        self._last[:] = 0.0
        self.snaps.done = self.snaps.overrun = 0

    def bind(self, rig) -> None:
        """Serve ``rig`` (its ``step``, ``snapshot`` and ``limiter``) from the callback, and
        compile the C callback for it (unless ``RTCTL_AUDIO_CFUNC=0`` or it cannot be built)."""
        self._rig, self._step, self._snapshot = rig, rig.step, rig.snapshot
        self._lim = rig.limiter.args[:3]  # state, params, fade
        self._stop_fade = int(getattr(rig, "stop_fade", self.block))  # a requested stop's fade, samples
        rig.snapshot(self.snaps, self.snaps.n - 1)  # compiles it now if nothing did (not in a callback)
        for a in (self.snaps.out, self.snaps.sensed, self.snaps.temperature, self.snaps.status,
                  self.snaps.compute_us, self.ctl):
            np.add(a, 0, out=a)  # write every page now: no page faults in the device thread's first pass
        self._cfunc = None
        if os.environ.get("RTCTL_AUDIO_CFUNC", "1") == "0":
            self._cfunc_note = "off (RTCTL_AUDIO_CFUNC=0)"
            return
        try:
            calls, snap = list(rig.kernel_calls()), rig.snapshot_call(self.snaps)
            t = time.perf_counter()
            self._cfunc, self._cfunc_keep = K.build_callback(
                calls=calls, snapshot=snap, ctl=self.ctl, inputs=self._inputs, in_scale=self._in_scale,
                sensed=self._sensed, outputs=self._outputs, out_scale=self._out_scale, out=self._out,
                last=self._last, limiter=self._lim, status=self.snaps.status, compute=self.snaps.compute_us,
                n_in=self._n_in, n_out=self._n_out, block=self.block, fs=self.fs, io_xrun=IO_XRUN,
                stop_fade=self._stop_fade)
            self._cfunc_note = f"compiled in {time.perf_counter() - t:.2f} s"
        except Exception as e:  # noqa: BLE001 - the Python callback does the same job
            self._cfunc_note = f"unavailable ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"

    def run(self, rig, n_blocks: int, on_block) -> int:
        """Run ``n_blocks`` blocks on the device; return the OR of every block's status bits.

        ``on_block(k, slot) -> bool`` is called here, in order, for every completed block ``k``
        (its data in ``self.snaps`` slot ``slot``); True asks to stop. Any stop (``n_blocks``
        done, ``on_block``, Ctrl-C, device loss) fades the outputs to 0 V through the limiter,
        still delivering the fade's blocks to ``on_block``. Ctrl-C is re-raised after the fade.
        A lost device adds ``DEVICE_LOST``; ``stats()["error"]`` says what happened.
        """
        self.bind(rig)
        self._open_stream(self._cfunc)
        snaps, ctl = self.snaps, self.ctl
        ctl[K.STOP_AT] = n_blocks  # the device thread fades after that many, however far behind this thread is
        nap = min(0.002, 0.5 * self.block / self.fs)
        status = 0
        k_read = 0
        end = None  # blocks to deliver once the fade is done (the device runs on, silent)
        held = False  # the controllers hold their commands (a requested stop began)
        interrupted = False
        # A Python callback needs the GIL once per block: no cyclic-GC pause (can be
        # milliseconds) while running, and a holder of the GIL yields it within a quarter block.
        # The C callback needs neither.
        gc_was, switch = gc.isenabled(), sys.getswitchinterval()
        if self._cfunc is None:
            gc.collect()
            gc.disable()
            sys.setswitchinterval(min(switch, 0.25 * self.block / self.fs))
        t_start = time.perf_counter_ns()
        try:
            self._stream.start()
        except self._sd.PortAudioError as e:
            self._restore(gc_was, switch)
            raise DeviceError(f"{self.device}: cannot start the stream ({e})") from None
        try:
            while True:
                try:
                    done = snaps.done = int(ctl[K.DONE])
                    if done - k_read > snaps.n:  # the engine fell a whole ring behind
                        snaps.overrun += done - k_read - snaps.n
                        k_read = done - snaps.n
                    while k_read < (done if end is None else min(done, end)):
                        k, slot = k_read, k_read % snaps.n
                        k_read += 1  # first: a Ctrl-C inside on_block must not deliver k twice
                        status |= int(snaps.status[slot])
                        stop = on_block(k, slot)
                        if (stop or k_read >= n_blocks) and not ctl[K.STOP_REQ]:
                            ctl[K.STOP_REQ] = 1
                    if not held and ctl[K.STOP_BEGUN] and rig.limiter.smooth_stop:
                        # a requested stop began in the device thread: the controllers hold their
                        # commands from here (a block or two into the release, as this thread
                        # trails the device's), so feedback does not answer the release
                        held = True
                        getattr(rig, "hold_control", lambda: None)()
                    if end is None and ctl[K.FADE_END]:
                        # the device thread counted the fade's last block (not rig.limiter.done:
                        # that turns true inside the block's step, before ctl[DONE] counts the
                        # block); after a requested stop's fade the device runs on silent until
                        # the model's tips have settled
                        end = int(ctl[K.FADE_END]) + (int(getattr(rig, "settle_blocks", 0))
                                                      if rig.limiter.smooth_stop else 0)
                    if end is not None and k_read >= end:
                        break
                    why = self._lost(t_start)
                    if why:
                        status |= DEVICE_LOST | self._finish_without_device(rig, on_block, why)
                        break
                    time.sleep(nap)
                except KeyboardInterrupt:
                    interrupted = True
                    ctl[K.STOP_REQ] = 1
        finally:
            self._stop_stream()
            self._restore(gc_was, switch)
            snaps.done = int(ctl[K.DONE])
        if interrupted:
            raise KeyboardInterrupt
        return status

    @staticmethod
    def _restore(gc_was: bool, switch: float) -> None:
        sys.setswitchinterval(switch)
        if gc_was:
            gc.enable()

    def _lost(self, t_start: int) -> str | None:
        """Why the device counts as lost now, or None."""
        ctl = self.ctl
        now = time.perf_counter_ns()
        if ctl[K.FAILED] and not self._stream.active:
            if self._error is None:  # the C callback caught an exception in the block step
                self._error = f"the audio callback failed at block {ctl[K.DONE]} (an exception in the block step)"
            return self._error
        last = int(ctl[K.LAST_NS])
        if last == 0:
            if now - t_start > START_TIMEOUT * 1e9:
                return f"no callback {START_TIMEOUT:g} s after the stream started"
            return None
        gap = (now - last) * 1e-9
        if gap > LOSS_TIMEOUT or not self._stream.active:
            self._lost_ms = gap * 1e3
            how = "the stream stopped" if not self._stream.active else "no callback"
            return f"{how} for {gap * 1e3:.0f} ms after block {ctl[K.DONE]}"
        return None

    def _finish_without_device(self, rig, on_block, why: str) -> int:
        """The device stopped calling back: fade the rig's outputs here, for the trace and the
        limiter's state (the hardware outputs stopped with the device), deliver those blocks."""
        ctl = self.ctl
        ctl[K.HALT] = 1
        t = time.perf_counter()
        while ctl[K.BUSY] and time.perf_counter() - t < 0.1:
            time.sleep(0.0005)  # a callback may still be returning
        if self._error is None:
            self._error = f"audio device {self.device} lost: {why}"
        if ctl[K.BUSY]:  # stuck inside the rig: stepping it here too would race
            self._error += " (a callback is stuck; the trace ends without the fade)"
            return 0
        if not ctl[K.STOP_BEGUN]:
            ctl[K.STOP_BEGUN] = 1
            rig.limiter.shutdown(self.block)
        snaps, status = self.snaps, 0
        self._sensed[:] = 0.0
        for _ in range(100000):  # bounded: a fade is a few blocks
            if rig.limiter.done:
                break
            st = rig.step() | DEVICE_LOST
            k = int(ctl[K.DONE])
            slot = k % snaps.n
            rig.snapshot(snaps, slot)
            snaps.status[slot], snaps.compute_us[slot] = st, 0.0
            ctl[K.DONE] = snaps.done = k + 1
            status |= st
            on_block(k, slot)
        return status

    def _stop_stream(self) -> None:
        """Stop the stream. If the run ended another way than by its fade (an exception in
        ``on_block``), fade first. A lost device's stream is left alone: PortAudio's stop, abort
        and close block forever once the JACK server is gone."""
        s, ctl = self._stream, self.ctl
        if s is None or ctl[K.HALT]:
            return
        if not (ctl[K.FAILED] or self._rig is None):
            ctl[K.STOP_REQ] = 1
            t = time.perf_counter()
            while not (ctl[K.FADE_END] and ctl[K.DONE] >= ctl[K.FADE_END]) and time.perf_counter() - t < 0.5:
                if not s.active:
                    break
                time.sleep(0.002)
        _bounded(s.abort if ctl[K.FAILED] else s.stop)

    # --- reporting and release --------------------------------------------------------------------

    def stats(self) -> dict:
        """JSON-able counters for ``summary["io"]``."""
        lat = self._latency
        lat_in, lat_out = lat if isinstance(lat, tuple) else (math.nan, lat)
        c = [int(x) for x in self.ctl]
        return {
            "backend": "audio",
            "device": self.device,
            "blocks": c[K.DONE],
            "input_underflow": c[K.IN_UNDER], "input_overflow": c[K.IN_OVER],
            "output_underflow": c[K.OUT_UNDER], "output_overflow": c[K.OUT_OVER],
            "xruns": sum(c[K.IN_UNDER:K.OUT_OVER + 1]),
            "first_xrun_block": c[K.FIRST_XRUN] if c[K.FIRST_XRUN] >= 0 else None,
            "late_blocks": c[K.LATE],
            "inputs_live": bool(c[K.LIVE]) if self._n_in else None,
            "max_callback_gap_us": c[K.MAX_GAP] * 1e-3,
            "clipped_samples": c[K.CLIPPED],
            "odd_size_blocks": c[K.ODD],
            "trace_overrun": self.snaps.overrun,
            "latency_in_s": lat_in, "latency_out_s": lat_out,
            "loss_detected_after_ms": self._lost_ms,
            "cfunc": self._cfunc is not None,
            "cfunc_note": self._cfunc_note,
            "error": self._error or self._guard_error(),
        }

    def _guard_error(self) -> str | None:
        """What the device thread's guard (``_audio_kernels.io_guard``) stopped the run for."""
        why = int(self.ctl[K.GUARD])
        silence_ms, n_xruns, window_s = self._guard_text
        if why == K.GUARD_SILENT:
            return (f"every input sample exactly 0 for {silence_ms:g} ms while driving, after the inputs "
                    "were live: nothing feeds them any more (the sense chain unplugged; under JACK, the "
                    "plant's client gone)")
        if why == K.GUARD_XRUNS:
            n_all = int(sum(self.ctl[K.IN_UNDER:K.OUT_OVER + 1]))
            return f"more than {n_xruns} xruns within {window_s:g} s ({n_all} in all)"
        return None

    def close(self) -> None:
        """Stop and release the stream (and PortAudio with the last one); idempotent, never raises."""
        global _open_streams, _poisoned
        if self._closed:
            return
        self._closed = True
        if self._stream is None:
            return
        _open_streams = max(0, _open_streams - 1)
        try:
            s = self._stream
            # After a loss the stream may be dead (its JACK server gone: inactive), or stalled.
            gone = bool(self.ctl[K.HALT]) and not s.active
            if gone or not _bounded(lambda: (s.abort(), s.close())):
                # PortAudio's close blocks and its termination would abort the process at exit:
                # leave both, for good.
                _poisoned = self._error or f"audio device {self.device} lost"
                self._sd._initialized = 0
                return
            _bounded(lambda: release(self._sd))
        except BaseException:  # noqa: BLE001
            pass


def _bounded(fn, timeout: float = 0.5) -> bool:
    """Call ``fn`` on a daemon thread; give up waiting after ``timeout`` s; swallow errors.
    Returns whether it finished."""
    def call():
        try:
            fn()
        except BaseException:  # noqa: BLE001 - releasing a device must not raise
            pass

    t = threading.Thread(target=call, daemon=True)
    t.start()
    t.join(timeout)
    return not t.is_alive()
