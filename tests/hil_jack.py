"""Hardware-in-the-loop helpers: a private JACK dummy server, the plant emulator
(``rtctl emulate audio``) and an xrun counter, each a child process.

Every child runs in its own process group and is killed by group on exit, so a failing test
leaves no ``jackd`` or emulator behind. Servers get their own names (``-n rtctl-hil-N``), never
``default``. This process itself opens no JACK client: libjack serves one server per process, and
the test process may hold PortAudio's client of another one.
"""

from __future__ import annotations

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


def _killpg(proc: subprocess.Popen, sig=signal.SIGTERM, wait: float = 3.0) -> None:
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


class JackServer:
    """``jackd -n NAME -d dummy -r FS -p PERIOD`` in its own process group.

    ``env`` is the environment for clients of this server (``JACK_DEFAULT_SERVER`` set).
    """

    def __init__(self, fs: int = 48000, period: int = 64, channels: int = 16, name: str | None = None):
        self.names = [name] if name else [f"rtctl-hil-{i}" for i in range(6)]
        self.args = ["-d", "dummy", "-r", str(fs), "-p", str(period), "-C", str(channels), "-P", str(channels)]
        self.proc = None

    def start(self, timeout: float = 10.0) -> "JackServer":
        """Start on the first free name of a few fixed ones. Fixed, not unique: JACK's registry
        has 8 server slots, and the slot of a server that died without unregistering (SIGKILL,
        as the unplug test does) is reclaimed only by a server of the same name."""
        for name in self.names:
            try:
                return self._start(name, timeout)
            except FileExistsError:
                continue
        raise RuntimeError(f"no free JACK server name among {self.names}")

    def _start(self, name: str, timeout: float) -> "JackServer":
        self.name = name
        self.env = dict(os.environ, JACK_DEFAULT_SERVER=name, JACK_NO_START_SERVER="1")
        self.cmd = [JACKD, "-n", name, *self.args]
        # jackd's chatter (a line per xrun) goes to a file: an unread pipe would fill and stall it.
        # Append mode: jackd shares the file offset with us, and reading must not move its writes.
        self.log = tempfile.TemporaryFile("a+")
        self.proc = subprocess.Popen(self.cmd, env=self.env, stdout=subprocess.DEVNULL, stderr=self.log,
                                     start_new_session=True, text=True)
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                log = self.log_text()
                self.log.close()
                if "already active" in log:  # that name is another live server's
                    raise FileExistsError(name)
                raise RuntimeError(f"jackd exited with {self.proc.returncode}: {log[-500:]}")
            # Probe from a child: libjack keeps per-process state, and this process may hold
            # PortAudio's JACK client of another server (mixing servers in one process crashes).
            probe = subprocess.run(["jack_lsp", "-s", self.name], env=self.env, capture_output=True)
            if probe.returncode == 0:
                return self
            time.sleep(0.05)
        self.stop()
        raise RuntimeError(f"jackd -n {self.name} did not come up in {timeout} s")

    def log_text(self) -> str:
        """Everything jackd wrote so far (stderr)."""
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


class EmulatorProcess:
    """``rtctl emulate audio SCENE --set ...`` in its own process group; stdout read by lines."""

    def __init__(self, server: JackServer, scene: str, overrides=(), extra=()):
        cmd = [*CLI, "emulate", "audio", scene, *extra]
        for o in overrides:
            cmd += ["--set", o]
        self.proc = subprocess.Popen(cmd, env=server.env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, start_new_session=True)
        self.out = Lines(self.proc.stdout)

    def wait_for(self, word: str, timeout: float) -> bool:
        return self.out.wait_for(word, timeout)

    def stop(self) -> tuple[int, str]:
        _killpg(self.proc)
        err = self.proc.stderr.read() if self.proc.stderr else ""
        return self.proc.returncode, err

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
