"""The DAQ backend without NI's driver (one-line refusals; the backend itself against a stand-in
``nidaqmx`` that loops each AO channel back to an AI channel) and ``rtctl devices``."""

import json
import sys
import types

import numpy as np
import pytest

from rtctl import scene
from rtctl.cli import main
from rtctl.errors import SceneError
from rtctl.io import daq


def test_daq_without_nidaqmx_is_one_line(capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "nidaqmx", None)  # import nidaqmx -> ImportError
    monkeypatch.setitem(sys.modules, "nidaqmx.system", None)
    assert main(["run", "line-bimorph-5", "--set", "io.backend=daq", "--set", "io.device=Dev1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "nidaqmx" in err and "rtctl[daq]" in err


class _Stream:
    def __init__(self, task):
        self.task = task
        self.regen_mode = None


class _Chans:
    def __init__(self, task):
        self.task = task

    def add_ao_voltage_chan(self, name, min_val, max_val):
        self.task.chans.append(name)

    add_ai_voltage_chan = add_ao_voltage_chan


class _Timing:
    def __init__(self, task):
        self.task = task

    def cfg_samp_clk_timing(self, rate, source="", sample_mode=None, samps_per_chan=0):
        self.task.clock = (rate, source)


class _Task:
    """Records what the backend asks of NI-DAQmx; AO data is queued for the AI side."""

    fifo: list = []

    def __init__(self):
        self.chans, self.started, self.closed = [], False, False
        self.ao_channels = self.ai_channels = _Chans(self)
        self.timing = _Timing(self)
        self.out_stream = self.in_stream = _Stream(self)

    def start(self):
        self.started = True

    def stop(self):
        pass

    def write(self, data, auto_start=False):
        pass

    def close(self):
        self.closed = True


class _Writer:
    def __init__(self, stream):
        self.task = stream.task

    def write_many_sample(self, data, timeout=10.0):
        _Task.fifo.append(np.array(data))


class _Reader:
    def __init__(self, stream):
        self.task = stream.task

    def read_many_sample(self, data, number_of_samples_per_channel=-1, timeout=10.0):
        blk = _Task.fifo.pop(0)
        data[...] = blk[:data.shape[0]]  # loopback: ao k -> ai k


@pytest.fixture
def fake_nidaqmx(monkeypatch):
    _Task.fifo = []
    mod = types.ModuleType("nidaqmx")
    mod.Task = _Task
    system = types.ModuleType("nidaqmx.system")
    system.System = types.SimpleNamespace(local=lambda: types.SimpleNamespace(driver_version="fake", devices=[]))
    consts = types.ModuleType("nidaqmx.constants")
    consts.AcquisitionType = types.SimpleNamespace(CONTINUOUS="continuous")
    consts.RegenerationMode = types.SimpleNamespace(DONT_ALLOW_REGENERATION="no-regen")
    readers = types.ModuleType("nidaqmx.stream_readers")
    readers.AnalogMultiChannelReader = _Reader
    writers = types.ModuleType("nidaqmx.stream_writers")
    writers.AnalogMultiChannelWriter = _Writer
    mod.system = system
    for name, m in (("nidaqmx", mod), ("nidaqmx.system", system), ("nidaqmx.constants", consts),
                    ("nidaqmx.stream_readers", readers), ("nidaqmx.stream_writers", writers)):
        monkeypatch.setitem(sys.modules, name, m)
    return mod


def test_daq_backend_scales_maps_and_primes(fake_nidaqmx):
    """Channels named from io.device and the maps, AI clocked by the AO sample clock, no
    regeneration, PRIME zero blocks ahead, volts/amps scaled by the full scales."""
    from rtctl.engine.rig import build

    s = scene.load("line-bimorph-5", ["io.backend=daq", "io.device=Dev1", "io.outputs=[4, 3, 2, 1, 0]",
                                      "io.volts_per_fs=100.0", "io.amps_per_fs=0.02"])
    rig = build(s)
    dev = rig.device
    assert dev.ao.chans == [f"Dev1/ao{c}" for c in (4, 3, 2, 1, 0)]
    assert dev.ai.chans == [f"Dev1/ai{c}" for c in range(10)]
    assert dev.ai.clock == (48000.0, "/Dev1/ao/SampleClock")
    assert dev.ao.out_stream.regen_mode == "no-regen"
    assert len(_Task.fifo) == daq.PRIME and not np.any(_Task.fifo[0])
    rig.out[...] = np.arange(5)[:, None] * 10.0
    assert dev.write() == 0
    np.testing.assert_allclose(_Task.fifo[-1], rig.out * 10.0 / 100.0)  # V -> DAQ volts
    _Task.fifo[:] = [np.full((10, 32), 5.0)]
    assert dev.read() == 0
    np.testing.assert_allclose(rig.sensed, 5.0 * 0.02 / 10.0)  # DAQ volts -> A
    dev.close()
    dev.close()  # idempotent


def test_daq_lost_device_is_a_status_not_an_exception(fake_nidaqmx):
    from rtctl.engine.rig import build
    from rtctl.safety import DEVICE_LOST

    rig = build(scene.load("line-bimorph-5", ["io.backend=daq", "io.device=Dev1"]))

    def gone(*a, **k):
        raise OSError("device removed")

    rig.device.writer.write_many_sample = gone
    assert rig.device.write() == DEVICE_LOST
    assert "device removed" in rig.device.stats()["error"]


def test_daq_channel_map_errors_name_the_key(fake_nidaqmx):
    from rtctl.engine.rig import build

    with pytest.raises(SceneError, match="io.outputs has 2 entries but the scene has 5 drive channels"):
        build(scene.load("line-bimorph-5", ["io.backend=daq", "io.device=Dev1", "io.outputs=[0, 1]"]))
    with pytest.raises(SceneError, match="device channel 3 is given twice"):
        build(scene.load("line-bimorph-5", ["io.backend=daq", "io.device=Dev1", "io.outputs=[0, 1, 2, 3, 3]"]))


def test_devices_lists_every_kind(capsys):
    assert main(["devices", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert set(d) == {"audio", "serial", "daq"}
    for kind, key in (("audio", "devices"), ("serial", "ports"), ("daq", "devices")):
        assert isinstance(d[kind][key], list) and isinstance(d[kind]["note"], str)
        assert d[kind][key] or d[kind]["note"]  # either something found or a reason
    assert main(["devices"]) == 0
    out = capsys.readouterr().out
    assert "audio devices" in out and "serial ports" in out and "DAQ devices" in out


def test_emulate_needs_a_kind(capsys):
    assert main(["emulate"]) == 2
    assert "audio,serial" in capsys.readouterr().err
