"""Hardware-in-the-loop helpers: a private JACK dummy server, the plant emulator
(``rtctl emulate audio``) and an xrun counter, each a child process.

Every child runs in its own process group and is killed by group on exit, so a failing test
leaves no ``jackd`` or emulator behind. Servers get their own names (``-n rtctl-hil-N``), never
``default``, and a test uses a server only once it knows the server is its own: several test
processes (other people's suites on a shared machine) start servers at the same time, and a
``jackd`` that loses a name to another one runs for a moment before it exits. This process
itself opens no JACK client: libjack serves one server per process, and the test process may
hold PortAudio's client of another one.
"""

from __future__ import annotations

import fcntl
import os
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
JACKD = shutil.which("jackd")


def _killpg(proc: subprocess.Popen, sig=signal.SIGTERM, wait: float = 10.0) -> None:
    if proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, sig)
        proc.wait(wait)
    except (ProcessLookupError, subprocess.TimeoutExpired):
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(5)


class Lines:
    """A child's stdout read line by line on a thread, so waits can time out."""

    def __init__(self, stream):
        self.q: queue.Queue = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._pump, args=(stream,), daemon=True).start()

    def _pump(self, stream):
        for line in stream:
            self.q.put(line.rstrip("\n"))
        self.q.put(None)

    def wait_for(self, word: str, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while (left := end - time.monotonic()) > 0:
            try:
                line = self.q.get(timeout=left)
            except queue.Empty:
                return False
            if line is None:
                return False
            self.seen.append(line)
            if line.strip() == word:
                return True
        return False

    def rest(self, timeout: float = 10.0) -> list[str]:
        """Every line seen so far and the rest up to end of stream (the child has ended)."""
        end = time.monotonic() + timeout
        while (left := end - time.monotonic()) > 0:
            try:
                line = self.q.get(timeout=left)
            except queue.Empty:
                break
            if line is None:
                break
            self.seen.append(line)
        return self.seen


def _lock(name: str) -> int | None:
    """An exclusive lock on the server name ``name`` among this machine's test processes, or
    None when another one holds it. The kernel releases it when the holder exits, however."""
    fd = os.open(Path(tempfile.gettempdir()) / f"{name}.jackd.lock", os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


def _answers(name: str, env: dict) -> bool:
    """Does a JACK server of that name answer? (From a child: see the module's docstring.)"""
    return subprocess.run(["jack_lsp", "-s", name], env=env, capture_output=True, timeout=60).returncode == 0


class JackServer:
    """``jackd -n NAME -d dummy -r FS -p PERIOD`` in its own process group.

    ``env`` is the environment for clients of this server (``JACK_DEFAULT_SERVER`` set).
    """

    def __init__(self, fs: int = 48000, period: int = 64, channels: int = 16, name: str | None = None):
        self.names = [name] if name else [f"rtctl-hil-{i}" for i in range(6)]
        self.args = ["-d", "dummy", "-r", str(fs), "-p", str(period), "-C", str(channels), "-P", str(channels)]
        self.proc = None
        self.lock = None

    def start(self, timeout: float = 30.0) -> JackServer:
        """Start on the first free name of a few fixed ones. Fixed, not unique: JACK's registry
        has 8 server slots, and the slot of a server that died without unregistering (SIGKILL,
        as the unplug test does) is reclaimed only by a server of the same name. A name is free
        when no other test process holds its lock (:func:`_lock`) and no server of that name
        answers (one left behind, or started by an older copy of these tests)."""
        for name in self.names:
            self.lock = _lock(name)
            if self.lock is None:
                continue
            try:
                return self._start(name, timeout)
            except FileExistsError:
                self._unlock()
                continue
            except BaseException:
                self._unlock()
                raise
        raise RuntimeError(f"no free JACK server name among {self.names}")

    def _unlock(self) -> None:
        if self.lock is not None:
            os.close(self.lock)
            self.lock = None

    def _start(self, name: str, timeout: float) -> JackServer:
        self.name = name
        self.env = dict(os.environ, JACK_DEFAULT_SERVER=name, JACK_NO_START_SERVER="1")
        if _answers(name, self.env):
            raise FileExistsError(name)
        self.cmd = [JACKD, "-n", name, *self.args]
        # jackd's chatter (stdout: its banner and "JACK server starting"; stderr: errors, a line
        # per xrun) goes to a file: an unread pipe would fill and stall it. Append mode: jackd
        # shares the file offset with us, and reading must not move its writes.
        self.log = tempfile.TemporaryFile("a+")
        self.proc = subprocess.Popen(self.cmd, env=self.env, stdout=self.log, stderr=self.log,
                                     start_new_session=True, text=True)
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                log = self.log_text()
                self.log.close()
                if "already active" in log:  # that name is another live server's
                    raise FileExistsError(name)
                raise RuntimeError(f"jackd exited with {self.proc.returncode}: {log[-500:]}")
            # Ours only once jackd holds the name in JACK's registry (it says "JACK server
            # starting" after that, and a jackd that lost the name to a live server never does):
            # until then an answer to the probe may come from that other server.
            if "JACK server starting" in self.log_text() and _answers(name, self.env):
                if self.proc.poll() is None:
                    return self
                continue
            time.sleep(0.05)
        log = self.log_text()
        self.stop()
        raise RuntimeError(f"jackd -n {self.name} did not come up in {timeout} s: {log[-500:]}")

    def log_text(self) -> str:
        """Everything jackd wrote so far (stdout and stderr)."""
        self.log.flush()
        self.log.seek(0)
        return self.log.read()

    def kill(self) -> None:
        """SIGKILL: the audio device vanishes as if unplugged."""
        if self.proc is not None:
            _killpg(self.proc, signal.SIGKILL)

    def stop(self) -> None:
        if self.proc is not None:
            _killpg(self.proc)
            if not self.log.closed:
                self.log.close()
        self._unlock()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


def xrun_causes(log: str) -> dict:
    """What jackd's log says about its xruns: ``{"driver late": n, "<client> not started": n,
    "<client> still running": n, "<client> finished late": n}``. A client "not started" had been
    triggered but its thread was not running yet at the deadline (scheduling); "still running"
    was inside its process callback."""
    import re

    out: dict = {}
    for line in log.splitlines():
        if "JackTimedDriver::Process XRun" in line:
            key = "driver late"
        elif m := re.search(r"client = (\S+) was not finished, state = (\w+)", line):
            key = f"{m[1]} {'not started' if m[2] == 'Triggered' else 'still running'}"
        elif m := re.search(r"client (\S+) finished after current callback", line):
            key = f"{m[1]} finished late"
        else:
            continue
        out[key] = out.get(key, 0) + 1
    return out


_COUNTER = """
import sys, jack
c = jack.Client("xrun-counter", no_start_server=True, servername=sys.argv[1])
n = [0]
c.set_xrun_callback(lambda delay: n.__setitem__(0, n[0] + 1))
c.activate()
print("up", flush=True)
for line in sys.stdin:
    print(n[0], flush=True)
    n[0] = 0
c.deactivate()
c.close()
"""


class XrunCounter:
    """A child JACK client counting the server's xruns (libjack's notification thread; it does
    nothing per cycle, so it causes none). :meth:`take` returns the count since the last take."""

    def __init__(self, server: JackServer):
        self.proc = subprocess.Popen([sys.executable, "-c", _COUNTER, server.name], env=server.env, text=True,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                     start_new_session=True)
        if self.proc.stdout.readline().strip() != "up":
            raise RuntimeError("the xrun counter could not join the JACK server")

    def take(self) -> int:
        self.proc.stdin.write("n\n")
        self.proc.stdin.flush()
        return int(self.proc.stdout.readline())

    def close(self) -> None:
        try:
            self.proc.stdin.close()
            self.proc.wait(5)
        except (OSError, subprocess.TimeoutExpired):
            _killpg(self.proc, signal.SIGKILL)


CLI = [sys.executable, "-c", "import sys; from rtctl.cli import main; sys.exit(main())"]


def emulator_errors(err: str) -> list[str]:
    """The emulator's stderr lines that say something went wrong (its last line, the block
    counts with "0 failed blocks", does not)."""
    bad = ("error", "connecting to", "lacks ports", "Traceback", "cffi callback")
    return [x for x in err.splitlines() if any(b in x for b in bad)]


class EmulatorProcess:
    """``rtctl emulate audio SCENE --set ...`` in its own process group; stdout read by lines,
    stderr collected on a thread (a full pipe would stall the emulator)."""

    def __init__(self, server: JackServer, scene: str, overrides=(), extra=()):
        cmd = [*CLI, "emulate", "audio", scene, *extra]
        for o in overrides:
            cmd += ["--set", o]
        self.proc = subprocess.Popen(cmd, env=server.env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, start_new_session=True)
        self.out = Lines(self.proc.stdout)
        self._err: list[str] = []
        self._err_pump = threading.Thread(target=lambda: self._err.extend(self.proc.stderr), daemon=True)
        self._err_pump.start()

    def wait_for(self, word: str, timeout: float) -> bool:
        return self.out.wait_for(word, timeout)

    def stop(self, wait: float = 60.0) -> tuple[int, str]:
        """SIGTERM (the emulator's normal end), SIGKILL only after ``wait`` seconds: a busy
        machine may take seconds to run its JACK client's deactivation and the interpreter's
        exit. Returns the exit status (negative: a signal ended it) and everything on stderr."""
        _killpg(self.proc, wait=wait)
        self._err_pump.join(10)
        return self.proc.returncode, "".join(self._err)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


_FAKE_RUN = """
import random, sys, threading, time, jack
server, cycles, n_out, n_in, wired = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
for k in range(cycles):
    # A new name each time ("rtctl-01", as PortAudio names a run's client while another "rtctl"
    # is there): with jackd2 1.9.21, a client opened by the process that closed one of the same
    # name a moment before fails now and then (server_error; jackd: "Cannot connect to client
    # name = rtctl" or "NotifyAddClient new_client fails"), 2 in 2 runs of 60 cycles on a busy
    # machine. Real runs are one process each; the emulator's handling of a same-named next
    # run is tests/test_emulate_audio.py's.
    c = jack.Client(f"rtctl-{k + 1:02d}", no_start_server=True, servername=server)
    first = threading.Event()
    c.set_port_connect_callback(lambda a, b, connect: connect and first.set())
    ports = ([c.outports.register(f"out_{i}") for i in range(n_out)]
             + [c.inports.register(f"in_{i}") for i in range(n_in)])
    c.activate()
    mode = ("at the first connection", "after the wiring, back to back", "after the wiring, reversed")[k % 3]
    if mode == "at the first connection":
        first.wait(60)
    else:
        end = time.monotonic() + 60
        while sum(len(p.connections) for p in ports) < wired:
            if time.monotonic() > end:
                print("the emulator never wired cycle", k, flush=True)
                sys.exit(1)
            time.sleep(0.005)
    for p in (ports[::-1] if mode.endswith("reversed") else ports):
        p.unregister()
        if mode.endswith("reversed"):
            time.sleep(random.random() * 0.0003)
    c.deactivate()
    c.close()
    print(k, mode, flush=True)
print("done", flush=True)
"""


class FakeRun:
    """A child JACK client named like an rtctl run (``rtctl-NN``, ports ``out_N``/``in_N``) that
    comes and goes ``cycles`` times, its ports going one by one as PortAudio's do when a stream
    closes: at the moment the emulator makes its first connection to it, or once the emulator
    has made ``wired`` connections (back to back, as PortAudio does; reversed, 0-0.3 ms apart),
    in turn. Prints a line per cycle and ``done``."""

    def __init__(self, server: JackServer, cycles: int, n_out: int, n_in: int, wired: int):
        self.proc = subprocess.Popen([sys.executable, "-c", _FAKE_RUN, server.name, str(cycles), str(n_out),
                                      str(n_in), str(wired)], env=server.env, text=True, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, start_new_session=True)
        self.out = Lines(self.proc.stdout)

    def wait_done(self, timeout: float) -> bool:
        return self.out.wait_for("done", timeout)

    def stop(self) -> tuple[int, str]:
        _killpg(self.proc)
        return self.proc.returncode, self.proc.stderr.read()
