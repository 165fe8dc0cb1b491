"""``rtctl emulate audio``'s connection logic against a fake JACK client whose port table changes
between any two of its calls: the ports of a run go away (JACK removes a closing client's ports
one by one) at every point of the emulator's main loop, in several orders. The run's end must be
the emulator's normal end - never an exception out of ``Emulator.serve`` (the ``rtctl`` command
turns one into "internal error", exit 3), never an error line - and the emulator must connect
to the next run. No JACK server: every interleaving is tried, none is left to timing.
"""

from __future__ import annotations

import errno
import re
from types import SimpleNamespace

import pytest
from optional import require

require("jack")  # JACK-Client's exceptions (the emulator catches jack.JackError)

import jack  # noqa: E402

from rtctl.emulate import audio as ea  # noqa: E402

RUN = "rtctl"
RUN_PORTS = [f"{RUN}:out_{i}" for i in range(3)] + [f"{RUN}:in_{i}" for i in range(3)]
WATCH = f"{RUN}:out_0"  # the first drive source: the port the emulator watches for the run's end
SYSTEM = ["system:capture_1", "system:capture_2", "system:playback_1"]


class Port:
    def __init__(self, name, is_output):
        self.name, self.is_output = name, is_output


class Register:
    def __init__(self, server, is_output):
        self.server, self.is_output = server, is_output

    def register(self, short):
        return self.server.add(f"{self.server.name}:{short}", self.is_output)


class FakeClient:
    """The emulator's JACK client on a server whose ports change between any two calls.

    Each call is a step; ``schedule(step)`` may change the port table before the step runs.
    Lookups behave as JACK-Client's: ``get_ports`` and ``get_all_connections`` list names, then
    look each one up with ``get_port_by_name`` (``JackError('Port ... not available')`` for one
    gone meanwhile); ``connect``/``disconnect`` take names (a port given is used by its name).
    """

    name = "rtctl-emulator"
    blocksize = 64

    def __init__(self, schedule=None, uuids=True):
        self.has_uuids = uuids  # False: a server that cannot tell client UUIDs (it errs)
        self.ports: dict[str, Port] = {}
        self.links: set[tuple[str, str]] = set()
        self.steps = 0
        self.schedule = schedule or (lambda client, step: None)
        self.on_port = None
        self.emu = None
        self.refuse: set[tuple[str, str]] = set()  # connections the server refuses (a real error)
        self.run_uuid, self.uuids = None, 0
        self.inports, self.outports = Register(self, False), Register(self, True)
        for s in SYSTEM:
            self.add(s, "capture" in s)

    # --- the server side, for the test -----------------------------------------------------------
    def add(self, name, is_output):
        self.ports[name] = Port(name, is_output)
        if self.on_port:
            self.on_port(self.ports[name], True)
        return self.ports[name]

    def remove(self, name):
        if self.ports.pop(name, None) is not None:
            self.links = {lk for lk in self.links if name not in lk}
            if self.on_port:
                self.on_port(None, False)

    def start_run(self):
        """A run's PortAudio client: a new UUID, its ports, its inputs auto-connected to system
        capture. The client is there as long as one of its ports is (JACK removes a closing
        client's ports, then the client)."""
        self.uuids += 1
        self.run_uuid = str(self.uuids)
        for n in RUN_PORTS:
            self.add(n, ":out_" in n)
        self.links |= {("system:capture_1", f"{RUN}:in_0"), ("system:capture_2", f"{RUN}:in_1")}

    def _step(self):
        self.steps += 1
        self.schedule(self, self.steps)
        if self.steps > 5000:  # a loop that never ends is a failure too
            self.emu.stop.set()
            raise AssertionError("the emulator's loop did not settle")

    # --- JACK-Client's API, as the emulator uses it ----------------------------------------------
    def set_process_callback(self, cb):
        pass

    def set_xrun_callback(self, cb):
        pass

    def set_shutdown_callback(self, cb):
        pass

    def set_port_registration_callback(self, cb=None, only_available=True):
        self.on_port = cb

    def get_port_by_name(self, name):
        self._step()
        if name not in self.ports:
            raise jack.JackError(f"Port {name!r} not available")
        return self.ports[name]

    def get_uuid_for_client_name(self, name):
        self._step()
        if name != RUN or not any(n in self.ports for n in RUN_PORTS) or not self.has_uuids:
            raise jack.JackError(f"Unable to get session ID for {name!r}")
        return self.run_uuid

    def get_ports(self, name_pattern="", is_audio=False, is_midi=False, is_input=False, is_output=False, **_):
        self._step()
        names = [n for n, p in self.ports.items() if re.search(name_pattern, n)
                 and (not is_output or p.is_output) and (not is_input or not p.is_output)]
        return [self.get_port_by_name(n) for n in names]

    def get_all_connections(self, port):
        self._step()
        port = self.get_port_by_name(port) if isinstance(port, str) else port
        if port is None or port.name not in self.ports:
            return []
        names = [a if b == port.name else b for a, b in sorted(self.links) if port.name in (a, b)]
        return [self.get_port_by_name(n) for n in names]

    def connect(self, source, destination):
        self._step()
        s, d = getattr(source, "name", source), getattr(destination, "name", destination)
        if s not in self.ports or d not in self.ports or (s, d) in self.refuse:
            raise jack.JackErrorCode(f"Error connecting {s!r} -> {d!r}", -1)
        if (s, d) in self.links:
            raise jack.JackErrorCode(f"Connection {s!r} -> {d!r} already exists", errno.EEXIST)
        self.links.add((s, d))

    def disconnect(self, source, destination):
        self._step()
        s, d = getattr(source, "name", source), getattr(destination, "name", destination)
        if (s, d) not in self.links:
            raise jack.JackErrorCode(f"Couldn't disconnect {s!r} -> {d!r}", -1)
        self.links.discard((s, d))


class Now:
    """An event that is always set: the loop never sleeps (every iteration is client steps)."""

    def wait(self, timeout=None):
        return True

    def set(self):
        pass

    def clear(self):
        pass

    def is_set(self):
        return True


PLANT = SimpleNamespace(in_names=["a.0", "a.1"], out_names=["a.0.i", "a.1.i"], outputs=[0, 1], inputs=[0, 1],
                        reset=lambda: None)
WIRED = {(f"{RUN}:out_0", "rtctl-emulator:a.0"), (f"{RUN}:out_1", "rtctl-emulator:a.1"),
         ("rtctl-emulator:a.0.i", f"{RUN}:in_0"), ("rtctl-emulator:a.1.i", f"{RUN}:in_1")}


def emulator(client, monkeypatch):
    monkeypatch.setenv("RTCTL_AUDIO_CFUNC", "0")  # the Python process callback: no libjack needed
    monkeypatch.setattr(ea, "_clock", lambda: client.steps * 0.01)  # each call takes 10 ms
    emu = ea.Emulator(client, PLANT, "rtctl(-[0-9]+)?")
    emu.wake = Now()
    client.emu = emu
    return emu


def serve(client, emu, capsys):
    code = emu.serve()
    out, err = capsys.readouterr()
    return code, out.split(), err


def test_the_fake_server_connects_undisturbed(monkeypatch, capsys):
    """The baseline: a run appears, the emulator wires it (and unwires system capture) once."""
    ready_at = []

    def schedule(c, step):
        if step == 1:
            c.start_run()
        if c.links >= WIRED and not ready_at:
            ready_at.append(step)
        if ready_at and step > ready_at[0] + 20:
            c.emu.stop.set()

    client = FakeClient(schedule)
    emu = emulator(client, monkeypatch)
    code, out, err = serve(client, emu, capsys)
    assert code == 0 and out == ["waiting", "ready"] and err == ""
    assert {lk for lk in client.links if RUN in lk[0] or RUN in lk[1]} == WIRED
    assert 10 < ready_at[0] < 60


ORDERS = {
    "forward": RUN_PORTS,
    "reverse": RUN_PORTS[::-1],
    "watched last": [n for n in RUN_PORTS if n != WATCH] + [WATCH],
    "inputs first": RUN_PORTS[3:] + RUN_PORTS[:3],
}


def vanish_schedule(start, order, per_step, comeback):
    """The run starts at step 1; from step ``start`` on its ports go, ``per_step`` per step in
    ``order`` (all at once for 0); with ``comeback`` a new run of the same name starts 3 steps
    after the last one went. The loop stops 60 steps after the last change."""
    state = {"gone": None, "back": None, "done": None}

    def schedule(c, step):
        if step == 1:
            c.start_run()
        if step >= start and state["gone"] is None:
            left = [n for n in order if n in c.ports]
            for n in left[: per_step or len(left)]:
                c.remove(n)
            if not any(n in c.ports for n in RUN_PORTS):
                state["gone"] = step
        if comeback and state["gone"] is not None and state["back"] is None and step >= state["gone"] + 3:
            c.start_run()
            state["back"] = step
        last = state["back"] if comeback else state["gone"]
        if last is not None and step > last + 60:
            c.emu.stop.set()

    return schedule


@pytest.mark.parametrize("uuids", [True, False], ids=["client UUIDs", "no UUIDs"])
@pytest.mark.parametrize("comeback", [False, True], ids=["run ends", "next run"])
@pytest.mark.parametrize("per_step", [1, 0], ids=["one port per call", "all at once"])
@pytest.mark.parametrize("order", list(ORDERS))
def test_a_run_ending_at_any_call_is_the_emulators_normal_end(order, per_step, comeback, uuids, monkeypatch, capsys):
    """Ports vanish from before each of the emulator's calls on (its discovery, the connection,
    the watch of the connected run): serve never raises, says nothing on stderr, connects to
    the next run, and exits 0. Without client UUIDs (a server that does not tell them) the
    emulator knows runs by their ports alone: a new run of the same name that comes while the
    emulator wires the last one may then stay part-wired, and only the old run's end counts."""
    failures = []
    for start in range(1, 70):
        client = FakeClient(vanish_schedule(start, ORDERS[order], per_step, comeback), uuids=uuids)
        emu = emulator(client, monkeypatch)
        try:
            code, out, err = serve(client, emu, capsys)
        except Exception as e:  # noqa: BLE001 - collected: the first few failing interleavings are shown
            failures.append(f"start {start}: {type(e).__name__}: {e}")
            capsys.readouterr()
            continue
        if code != 0 or err or out[:1] != ["waiting"] or set(out[1:]) - {"ready"}:
            failures.append(f"start {start}: exit {code}, stdout {out}, stderr {err!r}")
        elif comeback and uuids and (out[-1] != "ready" or not client.links >= WIRED
                           or ("system:capture_1", f"{RUN}:in_0") in client.links):
            failures.append(f"start {start}: the next run was not wired: stdout {out}, links {sorted(client.links)}")
    assert not failures, f"{len(failures)} of 69 interleavings failed:\n" + "\n".join(failures[:5])


@pytest.mark.parametrize("refused_steps, lines", [(100, 0), (600, 1)], ids=["a moment", "over 2 s"])
def test_a_refused_connection_is_retried_and_reported_once_if_it_lasts(refused_steps, lines, monkeypatch, capsys):
    """The server refuses a connection while every port is there (as JACK does while their
    client is not active yet): retried, and once it lasts over 2 s one line on stderr (not one
    per retry), never an exception; once the server accepts it, the emulator connects."""
    def schedule(c, step):
        if step == 1:
            c.start_run()
            c.refuse.add((f"{RUN}:out_1", "rtctl-emulator:a.1"))
        if step == refused_steps:
            c.refuse.clear()
        if step == refused_steps + 200:
            c.emu.stop.set()

    client = FakeClient(schedule)
    emu = emulator(client, monkeypatch)
    code, out, err = serve(client, emu, capsys)
    assert code == 0 and out == ["waiting", "ready"], (out, err)
    said = err.splitlines()
    assert len(said) == lines and all("connecting to rtctl failed (Error connecting" in x for x in said), err
    assert client.links >= WIRED


# --- --truth: the ring the process callback fills and the main thread drains -------------------

def truth_plant(n_ch=2, period=64):
    """A Plant with buffers only (no simulated group): the ring's behaviour is all that is tested."""
    import numpy as np

    p = ea.Plant.__new__(ea.Plant)
    p.in_names, p.out_names, p.outputs, p.inputs = [f"a.{c}" for c in range(n_ch)], [], [], []
    p.groups, p.rec, p.meta = [], None, {"scene": "fake"}
    p.drive, p.sensed, p.truth = np.zeros((n_ch, period)), np.zeros((0, period)), np.zeros((n_ch, 4, period))
    return p


def periods(emu, plant, ks):
    """The process callback's side for periods ``ks``: drive k V, tip k um, then the count."""
    for k in ks:
        plant.drive[:] = k
        plant.truth[:, 0, :] = k * 1e-6
        plant.keep(int(emu.ctl[ea.E_RECORDED]))
        emu.ctl[ea.E_RECORDED] += 1


def test_the_truth_trace_holds_every_period_once_and_shows_a_lap_as_a_gap(tmp_path, monkeypatch):
    """Every period from the plant's reset on reaches the trace once, in order, whatever the
    drain's rhythm; periods the ring lapped before a drain are counted and leave a gap in the
    records' ``block`` (a reader can tell), the rest are intact."""
    import numpy as np

    from rtctl.trace import TraceReader

    client = FakeClient()
    client.samplerate = 64 * 50  # a ring of RECORD_S = 1 s: 50 periods
    plant = truth_plant()
    monkeypatch.setenv("RTCTL_AUDIO_CFUNC", "0")  # the Python process callback: no libjack needed
    emu = ea.Emulator(client, plant, "rtctl(-[0-9]+)?", truth=tmp_path)
    assert plant.rec.shape == (50, 2, 2, 64)
    periods(emu, plant, range(7))  # before the run: not in its trace
    emu._reset_plant()  # the Python callback resets at its next period
    emu._truth_open("rtctl")
    emu._truth_drain()  # nothing yet: the reset has not happened
    emu.rec_from = int(emu.ctl[ea.E_RECORDED])  # what the process callback does when it resets
    periods(emu, plant, range(0, 30))
    emu._truth_drain()
    periods(emu, plant, range(30, 45))
    emu._truth_drain()
    emu._truth_drain()  # nothing new: nothing written twice
    periods(emu, plant, range(45, 45 + 80))  # 80 periods on a ring of 50 without a drain
    emu._truth_close()
    assert emu.rec_lost == 31 and emu.runs == 1  # the ring holds 49 whole periods
    tr = TraceReader(tmp_path / "run-1")
    blocks = np.asarray(tr.records["block"])
    want = np.r_[np.arange(45), np.arange(76, 125)]
    np.testing.assert_array_equal(blocks, want)
    np.testing.assert_array_equal(tr.signal("drive")[:, ::64], np.tile(want, (2, 1)))
    np.testing.assert_allclose(tr.signal("tip_um")[:, ::64], np.tile(want, (2, 1)), rtol=1e-6)
    assert tr.layout["meta"]["client"] == "rtctl" and tr.layout["meta"]["scene"] == "fake"


#: line-bimorph-5-closed with its finger events (press, lift, return) early in a short run
EVENTS = ["timing.block=64", "timing.duration=0.3", "events.0.at=0.08", "events.1.at=0.15", "events.2.at=0.22"]


def test_the_plant_plays_the_scene_events_where_sim_does(tmp_path):
    """The emulator's plant (the Python process callback's path) fed a sim run's drive, period
    by period, after periods of silence: its true tip is the sim device's, before and after each
    finger event (press harder, lift off, come back), because its clock starts at the first
    driven period (the run's block 0: open loop, a tone from 0 s) and each event switches the load
    at the period of its block. Without the events the tips part at the press."""
    import numpy as np

    from rtctl import scene
    from rtctl.engine.run import run
    from rtctl.trace import TraceReader

    sc = scene.load("line-bimorph-5-closed", EVENTS + ["control.mode=open"])
    res = run(sc, out_dir=tmp_path / "sim", plot=False)
    tr = TraceReader(res.out_dir / "trace")
    drive, tip = tr.signal("drive").astype(np.float64), tr.signal("tip_um")
    assert np.any(drive[:, :64] != 0)  # the run drives its block 0 (the clock starts there)

    def replay(plant, silent):
        out = []
        for k in range(silent + drive.shape[1] // 64):
            plant.drive[:] = 0.0 if k < silent else drive[:, (k - silent) * 64:(k - silent + 1) * 64]
            plant.step()
            if k >= silent:
                out.append(plant.truth[:, 0, :] * 1e6)
        return np.concatenate(out, axis=1)

    plant = ea.Plant(sc, 48000.0, 64)
    assert [(at, float(v)) for at, _, _, _, v in plant.event_writes] == [(60, 1.0), (112, 2.0), (165, 1.0)]
    got = replay(plant, silent=9)
    # the trace's drive is float32: a few ulp, far below a load's difference
    np.testing.assert_allclose(got, tip, rtol=1e-4, atol=1e-4 * np.abs(tip).max())
    plant.reset()  # back to the scene's first load and a stopped clock: the same again
    np.testing.assert_array_equal(replay(plant, silent=3), got)
    plant.event_writes = []  # events not played: the tips part from the press on
    plant.reset()
    lost = np.abs(replay(plant, silent=0) - tip).max(axis=0) > 0.05 * np.abs(tip).max()
    assert not lost[:60 * 64].any() and lost[60 * 64:112 * 64].any()


def test_an_emulator_connected_late_plays_the_events_late_by_as_much():
    """The clock counts from the first period the emulator hears driven: connected k blocks into
    a run, every event lands k periods after the run's block for it (the run's block count is
    not on the wire). The load index the group runs is the scene's first until then."""

    from rtctl import scene

    plant = ea.Plant(scene.load("line-bimorph-5-closed", EVENTS), 48000.0, 64)
    load = plant.groups[0].load
    seen = []
    for k in range(200):
        plant.drive[:] = 0.0 if k < 5 else 1e-3  # 5 silent periods, then the run k0 blocks in
        plant.step()
        seen.append(float(load[0, 0]))
    # periods since the first driven one (period 5): the press at 60, lift-off 112, return 165
    changes = [k - 5 for k in range(1, 200) if seen[k] != seen[k - 1]]
    assert changes == [60, 112, 165] and seen[0] == 0.0
    plant.reset()
    assert load[0, 0] == 0.0 and plant.clock[0] == -1


def test_a_scene_without_finger_events_writes_nothing(capsys):
    """Nothing to play: no writes, no clock code (the process callback is the one without events)."""
    from rtctl import scene

    plant = ea.Plant(scene.load("line-bimorph-5", ["timing.block=64"]), 48000.0, 64)
    assert plant.event_writes == [] and capsys.readouterr().err == ""
