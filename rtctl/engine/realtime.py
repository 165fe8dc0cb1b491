"""What a real-time loop asks of the OS, asked for the loop thread alone and given back after.

Every paced run: the garbage collector frozen (a collection started by any thread stops every
thread that wants the GIL: the loop allocates no garbage, the other thread may), the thread's
timer slack at 1 ns (a normal thread's sleeps may otherwise end up to 50 us late, to batch
wake-ups), a short GIL switch interval (a thread that wants the GIL waits at most this long for
another thread's Python) and the shortest scheduler slice (0.1 ms; Linux 6.12+: a woken normal
thread with a shorter slice than the running one preempts it rather than waiting for that
thread's slice to end). These need no permission.

With ``--realtime`` also (scene keys ``timing.priority``, ``timing.cpu``):

- ``SCHED_FIFO`` at ``timing.priority`` (0: stay ``SCHED_OTHER``): no normal process preempts
  the loop. Needs ``CAP_SYS_NICE`` or an ``RLIMIT_RTPRIO`` of at least the priority.
- ``mlockall(MCL_CURRENT | MCL_FUTURE)``: no page of the process is paged out, or faulted in
  later, during the run. Needs ``CAP_IPC_LOCK`` or an ``RLIMIT_MEMLOCK`` above the process size.
- the loop thread on CPU ``timing.cpu`` (-1: anywhere), and every other thread of the run off it.
- ``/dev/cpu_dma_latency`` held at 0 (as cyclictest does): no CPU enters an idle state it takes
  long to wake from. Needs write access to that file (root).

A request that is refused leaves one line in :attr:`Session.notes` saying which and how to
permit it, and the run goes on without it. Linux only; elsewhere every request is a note.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
import resource
import struct
import sys
from dataclasses import dataclass, field

MCL_CURRENT, MCL_FUTURE = 1, 2
PR_SET_TIMERSLACK, PR_GET_TIMERSLACK = 29, 30
#: GIL switch interval during a paced run, s (CPython's default is 5 ms).
SWITCH_INTERVAL = 1e-4
#: The PM QoS file whose 0, held open, keeps every CPU out of deep idle states.
DMA_LATENCY = "/dev/cpu_dma_latency"


def _libc():
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    except OSError:
        return None


@dataclass
class Session:
    """What was asked and what was granted; :meth:`restore` gives it all back (idempotent)."""

    granted: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    _undo: list = field(default_factory=list)

    def restore(self) -> None:
        while self._undo:
            try:
                self._undo.pop()()
            except OSError:  # nothing more to give back than we can
                pass

    def summary(self) -> dict:
        """What was granted and, as ``refused``, the notes; empty when nothing was asked."""
        return {**self.granted, "refused": list(self.notes)} if self.granted or self.notes else {}


def enter(paced: bool, realtime: bool, priority: int = 80, cpu: int = -1) -> Session:
    """Ask for what the calling thread (the loop's) needs; see the module docstring."""
    s = Session()
    if not paced:
        return s
    _freeze_gc(s)
    _switch_interval(s)
    libc = _libc()
    _timer_slack(s, libc)
    _short_slice(s, libc)
    if not realtime:
        return s
    if cpu >= 0:
        _affinity(s, cpu)
    _mlockall(s, libc)
    _dma_latency(s)
    if priority > 0:
        _fifo(s, priority)
    else:
        s.granted["sched"] = "SCHED_OTHER (timing.priority = 0)"
    return s


def _freeze_gc(s: Session) -> None:
    was = gc.isenabled()
    gc.collect()
    gc.freeze()  # what exists now is never scanned again; nothing is collected during the run
    gc.disable()

    def undo():
        gc.unfreeze()
        if was:
            gc.enable()

    s._undo.append(undo)
    s.granted["gc_frozen"] = True


def _switch_interval(s: Session) -> None:
    old = sys.getswitchinterval()
    sys.setswitchinterval(SWITCH_INTERVAL)
    s._undo.append(lambda: sys.setswitchinterval(old))


def _timer_slack(s: Session, libc) -> None:
    if libc is None or not sys.platform.startswith("linux"):
        return
    old = libc.prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0)
    if old > 0 and libc.prctl(PR_SET_TIMERSLACK, 1, 0, 0, 0) == 0:
        s._undo.append(lambda: libc.prctl(PR_SET_TIMERSLACK, old, 0, 0, 0))
        s.granted["timer_slack_ns"] = 1


#: sched_setattr / sched_getattr system call numbers by machine.
_SCHED_ATTR_CALLS = {"x86_64": (314, 315), "aarch64": (274, 275)}
#: struct sched_attr (version 0): size, policy, flags, nice, priority, runtime, deadline, period.
_SCHED_ATTR = struct.Struct("IIQiIQQQ")
SLICE_NS = 100_000


def _short_slice(s: Session, libc) -> None:
    calls = _SCHED_ATTR_CALLS.get(os.uname().machine) if hasattr(os, "uname") else None
    if calls is None or not hasattr(libc, "syscall") or not sys.platform.startswith("linux"):
        return
    set_call, get_call = calls
    buf = ctypes.create_string_buffer(_SCHED_ATTR.size)
    if libc.syscall(get_call, 0, buf, _SCHED_ATTR.size, 0) != 0:
        return
    old = _SCHED_ATTR.unpack(buf.raw)
    if old[1] != 0:  # not SCHED_OTHER: the slice is the fair class's, nothing to do
        return
    new = ctypes.create_string_buffer(_SCHED_ATTR.pack(_SCHED_ATTR.size, *old[1:5], SLICE_NS, *old[6:]))
    if libc.syscall(set_call, 0, new, 0) != 0:  # an older kernel: it has no slice to ask for
        return
    keep = ctypes.create_string_buffer(_SCHED_ATTR.pack(_SCHED_ATTR.size, *old[1:]))
    s._undo.append(lambda: libc.syscall(set_call, 0, keep, 0))
    s.granted["slice_us"] = SLICE_NS / 1000


def _affinity(s: Session, cpu: int) -> None:
    if not hasattr(os, "sched_setaffinity"):
        s.notes.append(f"timing.cpu = {cpu}: this OS has no CPU affinity; the loop runs on any CPU")
        return
    old = os.sched_getaffinity(0)
    if cpu not in old:
        s.notes.append(f"timing.cpu = {cpu}: this process may run on CPUs {_cpus(old)} only; the loop runs "
                       "on any of them (pick one of those, or widen the process' affinity with taskset)")
        return
    try:
        os.sched_setaffinity(0, {cpu})
    except OSError as e:
        s.notes.append(f"timing.cpu = {cpu}: refused ({e.strerror}); the loop runs on any CPU")
        return
    s._undo.append(lambda: os.sched_setaffinity(0, old))
    s.granted["cpu"] = cpu


def _mlockall(s: Session, libc) -> None:
    if libc is None or not hasattr(libc, "mlockall"):
        s.notes.append("mlockall: not available here; pages may be faulted in during the run")
        return
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
        err = ctypes.get_errno()
        soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
        lim = "unlimited" if soft == resource.RLIM_INFINITY else f"{soft >> 10} KiB"
        s.notes.append(f"mlockall refused ({os.strerror(err)}; RLIMIT_MEMLOCK {lim}): pages may be faulted in "
                       "during the run; permit it with 'ulimit -l unlimited' (memlock in "
                       "/etc/security/limits.conf) or CAP_IPC_LOCK")
        return
    s._undo.append(libc.munlockall)
    s.granted["mlockall"] = True


def _dma_latency(s: Session) -> None:
    try:
        fd = os.open(DMA_LATENCY, os.O_WRONLY)
    except FileNotFoundError:  # no PM QoS interface (a container may hide it): nothing to ask
        return
    except OSError as e:
        s.notes.append(f"{DMA_LATENCY} refused ({e.strerror}): CPUs may sleep in deep idle states and wake "
                       f"late; permit it with write access to {DMA_LATENCY} (root, or a udev rule)")
        return
    try:
        os.write(fd, struct.pack("i", 0))  # held while the file stays open
    except OSError as e:
        os.close(fd)
        s.notes.append(f"{DMA_LATENCY}: writing 0 failed ({e.strerror})")
        return
    s._undo.append(lambda: os.close(fd))
    s.granted["cpu_dma_latency_us"] = 0


def _fifo(s: Session, priority: int) -> None:
    if not hasattr(os, "sched_setscheduler"):
        s.notes.append("SCHED_FIFO: not available on this OS; the loop runs at normal priority")
        return
    old = (os.sched_getscheduler(0), os.sched_getparam(0))
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as e:
        soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
        lim = "unlimited" if soft == resource.RLIM_INFINITY else str(soft)
        s.notes.append(f"SCHED_FIFO priority {priority} refused ({e.strerror}; RLIMIT_RTPRIO {lim}): the loop runs "
                       f"SCHED_OTHER; permit it with 'ulimit -r {priority}' (rtprio in /etc/security/limits.conf, "
                       "e.g. '@audio - rtprio 95') or CAP_SYS_NICE ('setcap cap_sys_nice+ep' on the interpreter)")
        s.granted["sched"] = "SCHED_OTHER"
        return
    s._undo.append(lambda: os.sched_setscheduler(0, old[0], old[1]))
    s.granted["sched"] = f"SCHED_FIFO {priority}"


def _cpus(cpus) -> str:
    return ",".join(str(c) for c in sorted(cpus))


def other_cpus(cpu: int) -> set | None:
    """The CPUs a thread that is not the loop's should use when the loop has ``cpu``: every
    allowed CPU but that one (None when there is no other, or no pinning)."""
    if cpu < 0 or not hasattr(os, "sched_getaffinity"):
        return None
    rest = os.sched_getaffinity(0) - {cpu}
    return rest or None
