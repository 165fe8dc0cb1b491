"""The ``daq`` backend: hardware-timed analog output and input through NI-DAQmx (``nidaqmx``).

One continuous AO task at ``timing.fs`` drives the channels of ``io.outputs`` on the device named
by ``io.device`` (``Dev1``: channels ``Dev1/ao0`` ...), one AI task clocked by the AO task's
sample clock reads the current-sense channels of ``io.inputs``, so every input sample lines up
with an output sample. Regeneration is off: the device plays only what the loop wrote, and an
output underflow is an error the run reports instead of a repeated old block. The AO buffer is
primed with ``PRIME`` blocks of zeros, which is this backend's output latency.

Scaling: ``io.volts_per_fs`` is the drive at the amplifier's output for the DAQ's +-10 V full
scale; ``io.amps_per_fs`` the segment current at +-10 V on the input.

Without NI's driver (or without the ``nidaqmx`` package), opening says so in one line
(:func:`driver_problem`); that is all that can run on a machine without the hardware.
"""

from __future__ import annotations

import numpy as np

from ..errors import DeviceError, SceneError
from ..safety import DEVICE_LOST
from .base import Backend, channel_map

FULL_SCALE_V = 10.0
PRIME = 2  # blocks of zeros written before the start: the output latency


def driver_problem() -> str:
    """"" when NI-DAQmx can be used, else one line saying what is missing."""
    try:
        import nidaqmx.system
    except ImportError:
        return ("io.backend = 'daq' needs the nidaqmx package and NI's NI-DAQmx driver; nidaqmx is not "
                "installed (pip install 'rtctl[daq]')")
    try:
        # not a useless expression: reading the property queries the driver, which raises when
        # NI-DAQmx is not installed; the version itself is not needed
        _ = nidaqmx.system.System.local().driver_version
    except Exception as e:  # nidaqmx.errors.DaqNotFoundError and friends: no driver
        return f"io.backend = 'daq': the NI-DAQmx driver is not available ({type(e).__name__}: {e})"
    return ""


class DaqBackend(Backend):
    """Polled backend (see :mod:`rtctl.io.base`) over two NI-DAQmx tasks."""

    callback = False
    paced = False  # read() blocks on the hardware clock: the device paces the loop
    clocked = True
    truth = None
    probe_names = ()

    def __init__(self, scene, layout, out, sensed):
        import nidaqmx
        from nidaqmx.constants import AcquisitionType, RegenerationMode
        from nidaqmx.stream_readers import AnalogMultiChannelReader
        from nidaqmx.stream_writers import AnalogMultiChannelWriter

        io = scene.io
        if not io.device:
            raise SceneError("io.backend = 'daq' needs io.device, the NI device name (see `rtctl devices`)")
        self.out, self.sensed, self.block = out, sensed, layout.block
        self.o_map = channel_map(io.outputs, layout.n_channels, None, "io.outputs", "drive channels")
        self.i_map = channel_map(io.inputs, layout.n_sensed, None, "io.inputs", "sensed rows")
        self.o_gain = FULL_SCALE_V / io.volts_per_fs
        self.i_gain = io.amps_per_fs / FULL_SCALE_V
        self._o = np.zeros((layout.n_channels, self.block))
        self._i = np.zeros((layout.n_sensed, self.block))
        self.error = ""
        self.blocks = 0
        buf = 8 * self.block
        try:
            self.ao = nidaqmx.Task()
            self.ai = nidaqmx.Task() if layout.n_sensed else None
            for c in self.o_map:
                self.ao.ao_channels.add_ao_voltage_chan(f"{io.device}/ao{c}",
                                                        min_val=-FULL_SCALE_V, max_val=FULL_SCALE_V)
            self.ao.timing.cfg_samp_clk_timing(layout.fs, sample_mode=AcquisitionType.CONTINUOUS, samps_per_chan=buf)
            self.ao.out_stream.regen_mode = RegenerationMode.DONT_ALLOW_REGENERATION
            self.writer = AnalogMultiChannelWriter(self.ao.out_stream)
            if self.ai is not None:
                for c in self.i_map:
                    self.ai.ai_channels.add_ai_voltage_chan(f"{io.device}/ai{c}",
                                                            min_val=-FULL_SCALE_V, max_val=FULL_SCALE_V)
                self.ai.timing.cfg_samp_clk_timing(layout.fs, source=f"/{io.device}/ao/SampleClock",
                                                   sample_mode=AcquisitionType.CONTINUOUS, samps_per_chan=buf)
                self.reader = AnalogMultiChannelReader(self.ai.in_stream)
            for _ in range(PRIME):
                self.writer.write_many_sample(self._o, timeout=1.0)
            if self.ai is not None:
                self.ai.start()  # armed: it runs on the AO clock
            self.ao.start()
        except Exception as e:
            self.close()
            raise DeviceError(f"io.device = {io.device!r}: NI-DAQmx refused the tasks: {e}") from None
        self.latency_blocks = PRIME

    def read(self) -> int:
        if self.ai is None or self.error:
            return DEVICE_LOST if self.error else 0
        try:
            self.reader.read_many_sample(self._i, number_of_samples_per_channel=self.block,
                                         timeout=10 * self.block / 1000.0 + 1.0)
        except Exception as e:
            self.error = f"input read failed: {e}"
            return DEVICE_LOST
        np.multiply(self._i, self.i_gain, out=self.sensed)
        return 0

    def write(self) -> int:
        if self.error:
            return DEVICE_LOST
        np.multiply(self.out, self.o_gain, out=self._o)
        try:
            self.writer.write_many_sample(self._o, timeout=1.0)
        except Exception as e:
            self.error = f"output write failed (underflow or device gone): {e}"
            return DEVICE_LOST
        self.blocks += 1
        return 0

    def compile(self) -> None:
        pass

    def reset(self) -> None:
        self.sensed[...] = 0.0

    def close(self) -> None:
        for name in ("ao", "ai"):
            t = getattr(self, name, None)
            if t is None:
                continue
            try:
                if name == "ao" and not self.error:  # leave the outputs at 0 V
                    t.stop()
                    t.write(np.zeros((len(self.o_map), 1)) if len(self.o_map) > 1 else 0.0, auto_start=True)
                t.close()
            except Exception:
                pass
            setattr(self, name, None)

    def stats(self) -> dict:
        return {"backend": "daq", "blocks": self.blocks, "latency_blocks": PRIME, "error": self.error}


def open_backend(scene, layout, out, sensed) -> DaqBackend:
    problem = driver_problem()
    if problem:
        raise DeviceError(problem)
    return DaqBackend(scene, layout, out, sensed)
