"""--realtime asks the OS for the loop thread alone: SCHED_FIFO, a CPU, mlockall, the collector
frozen; every refusal is one line saying how to permit it, and the run goes on; everything is
given back after the run. The drain thread inherits none of it: it runs off the loop's CPU, at a
real-time priority below the loop's where that is permitted."""

import ctypes
import errno
import gc
import json
import os
import sys
import threading

import pytest

from rtctl import scene as scenes
from rtctl.cli import main
from rtctl.engine import loop as loopmod
from rtctl.engine import realtime
from rtctl.engine.rig import Rig
from rtctl.engine.run import run


class _Libc:
    """A libc whose mlockall is refused (the timer slack works)."""

    def __init__(self):
        self.slack = 50_000

    def prctl(self, op, value, *rest):
        if op == realtime.PR_GET_TIMERSLACK:
            return self.slack
        self.slack = value
        return 0

    def mlockall(self, flags):
        ctypes.set_errno(errno.ENOMEM)
        return -1

    def munlockall(self):
        return 0


def _refuse_fifo(*a):
    raise PermissionError(errno.EPERM, "Operation not permitted")


def test_every_refused_request_is_one_line_and_the_run_goes_on(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(realtime, "_libc", _Libc)
    monkeypatch.setattr(realtime.os, "sched_setscheduler", _refuse_fifo)
    monkeypatch.setattr(realtime, "DMA_LATENCY", str(tmp_path))  # a directory: not writable as a file
    code = main(["run", "line-bimorph-5", "--realtime", "--duration", "0.1", "--out", str(tmp_path / "o"),
                 "--quiet", "--no-plot", "--json", "--set", "timing.cpu=4095"])
    out, err = capsys.readouterr()
    assert code == 0
    lines = [ln for ln in err.splitlines() if ln.startswith("rtctl: realtime:")]
    assert len(lines) == 4 and len(err.strip().splitlines()) == 4, err
    text = "\n".join(lines)
    assert "SCHED_FIFO priority 80 refused" in text and "ulimit -r 80" in text and "CAP_SYS_NICE" in text
    assert "mlockall refused" in text and "CAP_IPC_LOCK" in text
    assert "timing.cpu = 4095" in text and str(tmp_path) in text
    s = json.loads(out)
    assert s["realtime"]["sched"] == "SCHED_OTHER" and len(s["realtime"]["refused"]) == 4
    assert s["duration_s"] == pytest.approx(0.1, abs=0.001)


def test_priority_0_stays_sched_other_without_asking(monkeypatch):
    monkeypatch.setattr(realtime.os, "sched_setscheduler", _refuse_fifo)
    monkeypatch.setattr(realtime, "_libc", _Libc)
    s = realtime.enter(True, True, priority=0)
    try:
        assert not any("SCHED_FIFO" in n for n in s.notes) and s.granted["sched"].startswith("SCHED_OTHER")
    finally:
        s.restore()


def _fifo_permitted() -> bool:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except (OSError, AttributeError):
        return False
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    return True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux scheduling")
def test_the_loop_thread_alone_gets_it_and_gives_it_back(tmp_path, monkeypatch):
    cpus = os.sched_getaffinity(0)
    cpu = min(cpus)
    before = (os.sched_getscheduler(0), os.sched_getaffinity(0), gc.isenabled(), sys.getswitchinterval())
    seen = {}
    real_advance = Rig.advance

    def advance(self):
        if "loop" not in seen:
            seen["loop"] = (os.sched_getscheduler(0), os.sched_getaffinity(0), gc.isenabled())
        return real_advance(self)

    real_init = loopmod.Loop.__init__

    def init(self, rig, writer, *a, **kw):
        real_append = writer.append

        def append(recs):
            seen.setdefault("drain", (threading.get_ident(), os.sched_getscheduler(0), os.sched_getaffinity(0)))
            seen.setdefault("drain_prio", os.sched_getparam(0).sched_priority)
            real_append(recs)

        writer.append = append
        real_init(self, rig, writer, *a, **kw)

    monkeypatch.setattr(Rig, "advance", advance)
    monkeypatch.setattr(loopmod.Loop, "__init__", init)
    res = run(scenes.load("line-bimorph-5", ["timing.duration=0.3", f"timing.cpu={cpu}"]), out_dir=tmp_path,
              realtime=True, plot=False, report=False)
    rt = res.summary["realtime"]
    assert rt["gc_frozen"] and not seen["loop"][2]
    assert seen["loop"][1] == {cpu} and rt["cpu"] == cpu
    drain_thread, drain_policy, drain_cpus = seen["drain"]
    assert drain_thread != threading.get_ident()
    if len(cpus) > 1:
        assert cpu not in drain_cpus
    if _fifo_permitted():
        assert seen["loop"][0] == os.SCHED_FIFO and rt["sched"] == "SCHED_FIFO 80"
        # the drain below the loop: preempted by nothing but the loop while it holds the GIL
        assert drain_policy == os.SCHED_FIFO and seen["drain_prio"] == 70
    else:
        assert drain_policy == os.SCHED_OTHER
    after = (os.sched_getscheduler(0), os.sched_getaffinity(0), gc.isenabled(), sys.getswitchinterval())
    assert after == before
