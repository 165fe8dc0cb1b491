"""Copy/scale kernels of the audio callback: device frames (float32, frames x channels) <-> the
rig's blocks (float64, rows x samples), through the scene's channel map.

One call per direction and block, whatever the channel count: a numba call costs about a
microsecond of dispatch, a numpy call per channel would cost that per channel.
"""

from __future__ import annotations

import numpy as np
from numba.core import types

from .._codegen import kernel_call, load_generated, voidptr_at  # noqa: F401 - voidptr_at: generated code
from .._numba import kernel
from ..safety import _FADE_FROM, _V, DEVICE_LOST, FADE_COSINE, FADE_LINEAR, FAULTS, IO_XRUN, XRUN_BURST, fade_length


@kernel
def frames_to_rows(frames, channel, scale, rows):
    """``rows[r, i] = frames[i, channel[r]] * scale``.

    Parameters
    ----------
    frames : ndarray float32, shape (block, n_device_inputs)
        Device input block as PortAudio delivers it (interleaved).
    channel : ndarray int64, shape (n_rows,)
        Device input channel of each row.
    scale : float
        Amperes at input full scale (``io.amps_per_fs``).
    rows : ndarray float64, shape (n_rows, block)
        The rig's ``sensed``, overwritten.
    """
    n_rows, n = rows.shape
    for r in range(n_rows):
        c = channel[r]
        for i in range(n):
            rows[r, i] = frames[i, c] * scale


@kernel
def rows_to_frames(rows, channel, scale, frames, last):
    """``frames[i, channel[r]] = clip(rows[r, i] * scale, -1, 1)``; unmapped device channels 0.

    Parameters
    ----------
    rows : ndarray float64, shape (n_rows, block)
        The rig's ``out`` (volts, after the limiter).
    channel : ndarray int64, shape (n_rows,)
        Device output channel of each row.
    scale : float
        ``1 / io.volts_per_fs``.
    frames : ndarray float32, shape (block, n_device_outputs)
        Device output block, overwritten.
    last : ndarray float64, shape (n_rows,)
        Receives the last volts sent per row (where a fault fade starts from).

    Returns
    -------
    int
        Samples clipped at digital full scale (a non-finite value counts and becomes 0).
    """
    n_rows, n = rows.shape
    frames[:, :] = 0.0
    clipped = 0
    for r in range(n_rows):
        c = channel[r]
        for i in range(n):
            v = rows[r, i] * scale
            if v > 1.0:
                v = 1.0
                clipped += 1
            elif v < -1.0:
                v = -1.0
                clipped += 1
            elif v != v:  # NaN (the limiter replaces them; a second guard costs nothing)
                v = 0.0
                clipped += 1
            frames[i, c] = v
        last[r] = frames[n - 1, c] / scale
    return clipped


@kernel
def fade_frames(last, channel, scale, frames):
    """A linear fade from ``last`` (volts per row) to 0 over the block; ``last`` is zeroed.

    The callback's own way to zero the outputs when the block step cannot be trusted (it raised):
    the limiter is bypassed, so the fade is as gentle as one block allows.
    """
    n = frames.shape[0]
    frames[:, :] = 0.0
    for r in range(last.shape[0]):
        c = channel[r]
        v0 = last[r] * scale
        if not (v0 == v0):
            v0 = 0.0
        for i in range(n):
            frames[i, c] = v0 * (1.0 - (i + 1) / n)
        last[r] = 0.0


@kernel
def _any_nonzero(a):
    """Whether any element of the 2-D ``a`` is not exactly 0 (stops at the first)."""
    for r in range(a.shape[0]):
        for i in range(a.shape[1]):
            if a[r, i] != 0.0:
                return True
    return False


@kernel
def io_guard(ctl, sensed, out, xrun, state, params, fade, block):
    """The device thread's own faults, checked after every block's step; returns status bits.

    * **Xrun bursts** (``XRUN_BURST``): a leaky bucket, ``XRUN_ADD`` (W, the window in blocks) in
      per flagged block and ``XRUN_LEAK`` (N, the xruns allowed in it) out per block; more than
      ``XRUN_CAP`` (N W) in the bucket means more than about N flagged blocks within W.
    * **Silent inputs** (``DEVICE_LOST``): every sensed sample exactly 0 while some output is
      driven, for ``SILENT_LIMIT`` blocks, after the inputs have once been live. A converter
      always carries noise; digital silence means nothing feeds the inputs any more (a sense
      chain unplugged; under JACK, the plant's client gone, its ports disconnected).

    On any fault (these or the block step's, ``step_status``) the shutdown fade starts here, in
    the device thread, so the next block already fades: the engine thread learns of it later.
    ``xrun`` holds the block step's status bits too (the caller ORs them in).

    Called after the step and before the block is counted in ``ctl[DONE]``, it also marks the
    block in which a stop's fade has reached 0 V (``ctl[FADE_END]``): the engine thread ends the
    run on that count, never on the limiter's state, which it would see change mid-block (the
    fade done, the block that did it not yet counted) and so stop one block short.
    """
    st = 0
    if ctl[XRUN_ADD] > 0:
        lvl = ctl[XRUN_LEVEL] - min(ctl[XRUN_LEVEL], ctl[XRUN_LEAK])
        if xrun & IO_XRUN:
            lvl += ctl[XRUN_ADD]
        ctl[XRUN_LEVEL] = lvl
        if lvl > ctl[XRUN_CAP]:
            st |= XRUN_BURST
            if ctl[GUARD] == 0:
                ctl[GUARD] = GUARD_XRUNS
    if ctl[SILENT_LIMIT] > 0 and sensed.shape[0] > 0:
        if _any_nonzero(sensed):
            ctl[LIVE] = 1
            ctl[SILENT] = 0
        elif ctl[LIVE] != 0:
            if _any_nonzero(out):  # driving
                ctl[SILENT] += 1
            if ctl[SILENT] >= ctl[SILENT_LIMIT]:
                st |= DEVICE_LOST
                if ctl[GUARD] == 0:
                    ctl[GUARD] = GUARD_SILENT
    # a fault fades over one block, and cuts short a requested stop's slower fade
    if (st | xrun) & FAULTS and (ctl[STOP_BEGUN] == 0 or fade[2] == FADE_COSINE):
        ctl[STOP_BEGUN] = 1
        limiter_shutdown(state, params, fade, block, False)
    if ctl[FADE_END] == 0 and ctl[STOP_BEGUN] != 0 and fade_done(state, fade):
        ctl[FADE_END] = ctl[DONE] + 1
    return st


@kernel
def fade_done(state, fade):
    """:attr:`rtctl.safety.Limiter.done` over the limiter's arrays: a shutdown fade has run its
    length and every output is at 0 V."""
    if fade[1] <= 0 or fade[0] < fade[1]:
        return False
    for c in range(state.shape[1]):
        if state[_V, c] != 0.0:
            return False
    return True


@kernel
def limiter_shutdown(state, params, fade, n_samples, smooth):
    """:meth:`rtctl.safety.Limiter.shutdown` over the limiter's arrays, callable from the device
    thread without Python: fade from the last outputs to 0 V over ``n_samples`` (longer where
    the slew bound needs it), a raised cosine if ``smooth``. Returns the fade length."""
    need = 1 if smooth else fade_length(state, params)
    for c in range(state.shape[1]):
        state[_FADE_FROM, c] = state[_V, c]
    fade[0] = 0
    fade[1] = max(n_samples, need, 1)
    fade[2] = FADE_COSINE if smooth else FADE_LINEAR
    return fade[1]


# --- the C callback (numba cfunc): PortAudio calls it directly, no Python, no GIL -------------

#: Fields of the int64 control array shared by the device thread and the engine thread.
#: ``FADE_END``: the blocks served up to and including the one in which the stop's fade reached
#: 0 V (0 until then), written by the device thread before it counts that block in ``DONE``.
(DONE, BUSY, HALT, FAILED, STOP_REQ, STOP_BEGUN, LAST_NS, IN_UNDER, IN_OVER, OUT_UNDER, OUT_OVER,
 FIRST_XRUN, LATE, CLIPPED, ODD, MAX_GAP, TS_SEC, TS_NSEC, STOP_AT,
 XRUN_LEVEL, XRUN_ADD, XRUN_LEAK, XRUN_CAP, LIVE, SILENT, SILENT_LIMIT, GUARD, FADE_END) = range(28)
N_CTL = 28
#: ``ctl[GUARD]``: which guard ended the run
GUARD_SILENT, GUARD_XRUNS = 1, 2
PA_CONTINUE, PA_ABORT = 0, 2  # paContinue, paAbort
CLOCK_MONOTONIC = 1  # Linux; what time.perf_counter_ns reads

# The generated module. Array addresses come in through PortAudio's ``userData`` (an int64 table:
# ctl, then every array), so the code depends only on shapes, dtypes and the kernels called, and
# numba caches it on disk like any kernel (named by a hash that includes the package stamp).
_MODULE = """# generated by rtctl.io._audio_kernels.build_callback; package stamp {stamp}
import numpy as np
from numba import carray, cfunc, types

from rtctl.io._audio_kernels import (BUSY, CLIPPED, CLOCK_MONOTONIC, DONE, FAILED, FIRST_XRUN, HALT,
    IN_UNDER, LAST_NS, LATE, MAX_GAP, ODD, PA_ABORT, PA_CONTINUE, STOP_AT, STOP_BEGUN, STOP_REQ, TS_NSEC, TS_SEC,
    N_CTL, clock_gettime, fade_frames, frames_to_rows, io_guard, limiter_shutdown, rows_to_frames, voidptr_at)
{imports}

SIG = types.int32(types.voidptr, types.voidptr, types.uint64, types.voidptr, types.uint64, types.voidptr)


@cfunc(SIG, nopython=True, cache=True)
def callback(inp, outp, frames, time_info, flags, user):
    tab = carray(user, ({n_tab},), np.int64)
    ctl = carray(voidptr_at(tab[0]), (N_CTL,), np.int64)
    scale = carray(voidptr_at(tab[1]), (2,), np.float64)
    ctl[BUSY] = 1
    fo = carray(outp, (frames, {n_out}), np.float32)
    if frames != {block} or ctl[HALT] != 0 or ctl[FAILED] != 0:
        for i in range(frames):
            for j in range({n_out}):
                fo[i, j] = 0.0
        if frames != {block}:
            ctl[ODD] += 1
        ctl[BUSY] = 0
        return PA_ABORT if ctl[FAILED] != 0 else PA_CONTINUE
    clock_gettime(CLOCK_MONOTONIC, voidptr_at(tab[0] + 8 * TS_SEC))
    t0 = ctl[TS_SEC] * 1000000000 + ctl[TS_NSEC]
    st = 0
    if flags & 15:
        if ctl[FIRST_XRUN] < 0:
            ctl[FIRST_XRUN] = ctl[DONE]
        for b in range(4):
            if (flags >> b) & 1:
                ctl[IN_UNDER + b] += 1
        st = {io_xrun}
{arrays}
    try:
        if (ctl[STOP_REQ] != 0 or ctl[DONE] >= ctl[STOP_AT]) and ctl[STOP_BEGUN] == 0:
            ctl[STOP_BEGUN] = 1
            limiter_shutdown({lim_state}, {lim_params}, {lim_fade}, {stop_fade}, True)
{read}
{steps}
        ctl[CLIPPED] += rows_to_frames({out}, {outputs}, scale[1], fo, {last})
        st |= io_guard(ctl, {sensed}, {out}, st, {lim_state}, {lim_params}, {lim_fade}, {block})
        k = ctl[DONE]
        slot = k % {ring}
        {snapshot}
    except Exception:
        ctl[FAILED] = 1
        fade_frames({last}, {outputs}, scale[1], fo)
        ctl[BUSY] = 0
        return PA_CONTINUE
    clock_gettime(CLOCK_MONOTONIC, voidptr_at(tab[0] + 8 * TS_SEC))
    t1 = ctl[TS_SEC] * 1000000000 + ctl[TS_NSEC]
    if t1 - t0 > {period_ns}:
        ctl[LATE] += 1
    if ctl[LAST_NS] > 0 and t0 - ctl[LAST_NS] > ctl[MAX_GAP]:
        ctl[MAX_GAP] = t0 - ctl[LAST_NS]
    {status}[slot] = st
    {compute}[slot] = (t1 - t0) * 1e-3
    ctl[LAST_NS] = t1
    ctl[DONE] = k + 1
    ctl[BUSY] = 0
    return PA_CONTINUE
"""


# By symbol name, not a ctypes pointer: code using it can be cached (a pointer cannot).
clock_gettime = types.ExternalFunction("clock_gettime", types.int32(types.int32, types.voidptr))


class _Table:
    """Numbers the arrays the generated code reaches: each becomes ``carray(voidptr_at(tab[i]),
    SHAPE, DTYPE)`` over the same memory; ``addresses`` is the table PortAudio passes along."""

    def __init__(self, ctl, scale):
        self.addresses = [ctl.ctypes.data, scale.ctypes.data, 0, 0]  # 2, 3: float and int scalars
        self.lines, self._names = [], {}
        self.floats, self.ints = [], []

    def scalars(self):
        """The scalar arguments as two arrays (to keep alive); fills their table slots."""
        f = np.array(self.floats + [0.0], dtype=np.float64)
        i = np.array(self.ints + [0], dtype=np.int64)
        self.addresses[2], self.addresses[3] = f.ctypes.data, i.ctypes.data
        self.lines.insert(0, f"    fsc = carray(voidptr_at(tab[2]), ({f.size},), np.float64)")
        self.lines.insert(1, f"    isc = carray(voidptr_at(tab[3]), ({i.size},), np.int64)")
        return f, i

    def __call__(self, a) -> str:
        if isinstance(a, (bool, np.bool_)):
            self.ints.append(int(a))
            return f"(isc[{len(self.ints) - 1}] != 0)"
        if isinstance(a, (int, np.integer)):
            self.ints.append(int(a))
            return f"isc[{len(self.ints) - 1}]"
        if isinstance(a, (float, np.floating)):
            self.floats.append(float(a))
            return f"fsc[{len(self.floats) - 1}]"
        if not isinstance(a, np.ndarray):
            raise TypeError(f"a block-step argument of type {type(a).__name__}")
        key = (a.__array_interface__["data"][0], a.shape, a.dtype.str)
        if key not in self._names:
            if not (a.flags.c_contiguous and a.flags.aligned) or a.dtype.hasobject:
                raise TypeError("a block-step argument that is not a C-contiguous numeric array")
            name = f"a{len(self._names)}"
            dt = "bool_" if a.dtype == np.bool_ else a.dtype.name
            shape = "(" + "".join(f"{n}, " for n in a.shape) + ")"
            self.lines.append(f"    {name} = carray(voidptr_at(tab[{len(self.addresses)}]), {shape}, np.{dt})")
            self.addresses.append(key[0])
            self._names[key] = name
        return self._names[key]


def build_callback(*, calls, snapshot, ctl, inputs, in_scale, sensed, outputs, out_scale, out, last,
                   limiter, status, compute, n_in, n_out, block, fs, io_xrun, stop_fade=None):
    """A PortAudio stream callback compiled to C (a numba ``cfunc``) that runs the whole block:
    frames -> ``sensed``, the block step's kernels, ``out`` -> frames, the snapshot, counters.

    Parameters
    ----------
    calls : list of (dispatcher, tuple of arrays)
        The block step as kernel calls, in order; their int results are ORed into the status.
        Each kernel must be importable by name from its module.
    snapshot : (dispatcher, tuple of arrays)
        The snapshot kernel and its arguments before ``slot`` (appended).
    ctl : ndarray int64, shape (N_CTL,)
        Shared counters and flags (the field constants of this module).
    limiter : tuple
        The limiter's ``(state, params, fade)`` arrays.
    stop_fade : int, optional
        Samples of a requested stop's raised-cosine fade (default one block).
    status, compute : ndarray, shape (ring,)
        The snapshot ring's status (int64) and compute time (float64, us) per slot.

    Returns
    -------
    (cfunc, table)
        ``cfunc.address`` is the PaStreamCallback; ``table`` (int64 addresses) is its userData.
        Every array must stay alive and unmoved while the callback can run; so must ``table``.

    Raises
    ------
    TypeError
        An argument the generated code cannot reach (not a C-contiguous numeric array).
    """
    from .._numba import package_stamp

    scale = np.array([in_scale, out_scale])
    name = _Table(ctl, scale)
    imports, fns = [], {}

    def call(fn, args):
        return kernel_call(fn, args, name, fns, imports)

    steps = "\n".join(f"        st |= {call(fn, args)}" for fn, args in calls)
    snap = call(*snapshot)[:-1] + ", slot)"
    read = f"        frames_to_rows(carray(inp, ({block}, {n_in}), np.float32), {name(inputs)}, scale[0], " \
           f"{name(sensed)})" if n_in else ""
    fields = dict(n_out=n_out, block=block, io_xrun=io_xrun, stop_fade=int(stop_fade or block),
                  lim_state=name(limiter[0]),
                  lim_params=name(limiter[1]), lim_fade=name(limiter[2]), read=read, steps=steps,
                  sensed=name(sensed),
                  out=name(out), outputs=name(outputs), last=name(last), ring=status.shape[0], snapshot=snap,
                  period_ns=int(block / fs * 1e9), status=name(status), compute=name(compute),
                  stamp=package_stamp().hex()[:16])
    fields["imports"] = "\n".join(imports)
    keep = (scale, *name.scalars())
    fields["arrays"] = "\n".join(name.lines)  # after every name() call
    fields["n_tab"] = len(name.addresses)
    module = load_generated(_MODULE.format(**fields), "rtctl_audio_cb")
    table = np.array(name.addresses, dtype=np.int64)
    return module.callback, (table, *keep)
