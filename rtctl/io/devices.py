"""``rtctl devices``: the audio devices (with host API and channel counts), serial ports and DAQ
devices this machine has. Each kind is listed independently: a missing library or driver gives a
one-line note for that kind, never an error for the others.
"""

from __future__ import annotations

import contextlib
import os


@contextlib.contextmanager
def quiet_c_stderr():
    """Silence what C libraries print on fd 2 while PortAudio probes its host APIs (ALSA's
    "cannot find card", JACK's "server is not running"): our own errors are Python exceptions."""
    try:
        saved = os.dup(2)
    except OSError:  # no fd 2 at all
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def audio_devices() -> dict:
    """``{"devices": [{name, host_api, inputs, outputs, default_samplerate}], "note": str}``."""
    from ..errors import DeviceError
    from .audio import _sounddevice, rescan

    try:
        with quiet_c_stderr():  # the host APIs' chatter while PortAudio probes them
            sd = _sounddevice()
    except DeviceError as e:
        return {"devices": [], "note": str(e)}
    with quiet_c_stderr():
        rescan(sd)  # PortAudio may be shut down (last stream closed) or a server started since
        apis = sd.query_hostapis()
        devs = sd.query_devices()
    out = [{"name": d["name"], "host_api": apis[d["hostapi"]]["name"], "inputs": d["max_input_channels"],
            "outputs": d["max_output_channels"], "default_samplerate": d["default_samplerate"]} for d in devs]
    return {"devices": out, "note": "" if out else "no audio devices (is the audio server running?)"}


def serial_ports() -> dict:
    """``{"ports": [{port, description, hwid}], "note": str}`` (pseudo-terminals are not listed:
    ``rtctl emulate serial`` prints its own)."""
    try:
        from serial.tools import list_ports
    except ImportError as e:
        return {"ports": [], "note": f"pyserial not installed ({e})"}
    ports = [{"port": p.device, "description": p.description, "hwid": p.hwid} for p in list_ports.comports()]
    return {"ports": ports, "note": "" if ports else "no serial ports"}


def daq_devices() -> dict:
    """``{"devices": [{name, product, ao, ai}], "note": str}`` from NI-DAQmx, if present."""
    from .daq import driver_problem

    problem = driver_problem()
    if problem:
        return {"devices": [], "note": problem}
    import nidaqmx.system

    devs = []
    for d in nidaqmx.system.System.local().devices:
        devs.append({"name": d.name, "product": d.product_type,
                     "ao": len(d.ao_physical_chans), "ai": len(d.ai_physical_chans)})
    return {"devices": devs, "note": "" if devs else "NI-DAQmx found no devices"}


def list_devices() -> dict:
    return {"audio": audio_devices(), "serial": serial_ports(), "daq": daq_devices()}


def format_table(found: dict) -> str:
    lines = ["audio devices (name | host API | in | out | default rate):"]
    a = found["audio"]
    lines += [f"  {d['name']} | {d['host_api']} | {d['inputs']} | {d['outputs']} | {d['default_samplerate']:g} Hz"
              for d in a["devices"]] or [f"  none: {a['note']}"]
    lines.append("serial ports:")
    s = found["serial"]
    lines += [f"  {p['port']} | {p['description']}" for p in s["ports"]] or [f"  none: {s['note']}"]
    lines.append("DAQ devices:")
    q = found["daq"]
    lines += [f"  {d['name']} | {d['product']} | AO {d['ao']} | AI {d['ai']}" for d in q["devices"]] \
        or [f"  none: {q['note']}"]
    return "\n".join(lines)
