"""What the audio backend's tests take from sounddevice, for machines without PortAudio.

sounddevice cannot be imported where its C library is missing (it raises ``OSError``), yet most of
the backend's logic (copy kernels, the Python and C callbacks driven by a fake stream, device
matching) needs no audio library at all. This stand-in gives those tests the same objects
sounddevice 0.5 gives them: callback buffers made exactly as its callback wrapper makes them
(``np.frombuffer`` over cffi memory, reshaped to (frames, channels)), its flag bits (PortAudio's
``paInputUnderflow`` ... ``paOutputOverflow`` values from portaudio.h), ``CallbackFlags``,
``CallbackAbort``, ``PortAudioError``, and a cffi with the ``PaStreamCallback`` signature.
"""

from __future__ import annotations

import types

import cffi
import numpy as np

_ffi = cffi.FFI()
_ffi.cdef("""
typedef unsigned long PaStreamCallbackFlags;
typedef double PaTime;
typedef struct PaStreamCallbackTimeInfo {
    PaTime inputBufferAdcTime; PaTime currentTime; PaTime outputBufferDacTime;
} PaStreamCallbackTimeInfo;
typedef int PaStreamCallback(const void *input, void *output, unsigned long frameCount,
                             const PaStreamCallbackTimeInfo *timeInfo, PaStreamCallbackFlags statusFlags,
                             void *userData);
""")

# portaudio.h: PaStreamCallbackFlags
_lib = types.SimpleNamespace(paInputUnderflow=0x1, paInputOverflow=0x2, paOutputUnderflow=0x4,
                             paOutputOverflow=0x8, paPrimingOutput=0x10)


class PortAudioError(Exception):
    pass


class CallbackAbort(Exception):
    pass


class CallbackFlags:
    """The status argument of a stream callback: flag bits with sounddevice's property names."""

    def __init__(self, flags=0x0):
        self._flags = int(flags)

    def __bool__(self):
        return bool(self._flags)

    def _has(self, bit):
        return bool(self._flags & bit)

    input_underflow = property(lambda self: self._has(_lib.paInputUnderflow))
    input_overflow = property(lambda self: self._has(_lib.paInputOverflow))
    output_underflow = property(lambda self: self._has(_lib.paOutputUnderflow))
    output_overflow = property(lambda self: self._has(_lib.paOutputOverflow))
    priming_output = property(lambda self: self._has(_lib.paPrimingOutput))


def _buffer(ptr, frames, channels, samplesize):
    return _ffi.buffer(ptr, frames * channels * samplesize)


def _array(buffer, channels, dtype):
    return np.frombuffer(buffer, dtype=dtype).reshape(-1, channels)
