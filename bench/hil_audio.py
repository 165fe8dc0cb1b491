"""Hardware-in-the-loop audio benchmark through a private JACK dummy server.

Measures, at 48 kHz:

* **round-trip latency** in blocks: an impulse on drive channel 0 and the block in which it comes
  back on sensed row 0, (a) through a plain JACK wire ``rtctl:out_0 -> rtctl:in_0`` and (b)
  through the plant emulator (``rtctl emulate audio``: amplifier, piezo, current sense);
* **xruns** over ``--seconds`` (default 60) of ``rtctl run line-bimorph-5`` against the emulator at
  block 64 and 32: PortAudio's under/overflow flags, the server's xruns seen by an idle counter
  client, the same counter over an idle stretch first (what the machine does without rtctl),
  late blocks (callback work longer than a block) and the longest pause between callbacks;
* **callback cost** without a server: the rig's block step alone, the Python callback (copies,
  step, snapshot), sounddevice's cffi->Python wrapper around it, and the C callback (numba
  ``cfunc``), per block;
* **GIL contention**: in-process runs whose engine thread spends ``--busy`` (default 0.5 and 1.0)
  of every block period in pure Python (a heavy trace/GUI thread holding the GIL), Python callback
  vs C callback: xruns, late blocks and the longest pause between callbacks.

    python bench/hil_audio.py [--seconds 60] [--blocks 64 32] [--busy 0.5 1.0] [--no-long] [--json]

Prints one JSON object (``--json``: only that), then a table. Needs jackd (Debian jackd2).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from hil_jack import JACKD, EmulatorProcess, JackServer, XrunCounter, xrun_causes  # noqa: E402

SCENE = "line-bimorph-5"
FS = 48000
CLI = [sys.executable, "-c", "import sys; from rtctl.cli import main; sys.exit(main())"]
AUDIO = ["io.backend=audio", "io.device=system", "io.host_api=JACK Audio Connection Kit"]


def sets(items):
    return [a for o in items for a in ("--set", o)]


# --- latency -------------------------------------------------------------------------------------

class ImpulseRig:
    """A rig stand-in whose block step plays one sample of ``volts`` on channel 0 at block ``k0``."""

    def __init__(self, n_ch, n_sensed, block, k0, volts=75.0):
        from rtctl.safety import Limiter

        self.block, self.k0, self.volts, self.k = block, k0, volts, 0
        self.out = np.zeros((n_ch, block))
        self.sensed = np.zeros((n_sensed, block))
        one = [1.0] * n_ch
        self.limiter = Limiter(FS, max_voltage=[150.0] * n_ch, slew=[1e15] * n_ch, current=[1e9] * n_ch,
                               capacitance=[1e-9] * n_ch, temperature=[1e9] * n_ch, ambient=[25.0] * n_ch,
                               loss_tangent=[0.0] * n_ch, thermal_resistance=one, thermal_tau=one)

    def step(self):
        self.out[:] = 0.0
        if self.k == self.k0:
            self.out[0, 0] = self.volts
        self.k += 1
        return self.limiter.process(self.out)

    def snapshot(self, snaps, slot):
        snaps.out[slot] = self.out
        snaps.sensed[slot] = self.sensed


def impulse_latency(srv, scene, wire: bool, k0=300):
    """Blocks (and samples) from the impulse's block to the first sensed block showing it."""
    from rtctl.io.audio import open_backend

    lay = _layout(scene)
    rig = ImpulseRig(lay.n_channels, lay.n_sensed, lay.block, k0)
    be = open_backend(scene, lay, rig.out, rig.sensed)
    be.compile()
    rows = []

    def on_block(k, slot):
        if wire and k == 20:  # the stream's ports exist now: wire out_0 -> in_0 (JACK's own tools)
            for tool, a, b in (("jack_disconnect", "system:capture_1", "rtctl:in_0"),
                               ("jack_connect", "rtctl:out_0", "rtctl:in_0")):
                subprocess.run([tool, "-s", srv.name, a, b], env=srv.env, capture_output=True)
        rows.append(be.snaps.sensed[slot][0].copy())
        return False

    try:
        be.run(rig, k0 + 200, on_block)
    finally:
        be.close()
    x = np.concatenate(rows)
    noise = np.max(np.abs(x[(k0 - 100) * lay.block:k0 * lay.block]))
    hit = np.nonzero(np.abs(x[k0 * lay.block:]) > max(10 * noise, 1e-12))[0]
    if hit.size == 0:
        return None
    return {"blocks": int(hit[0] // lay.block), "samples": int(hit[0]), "noise": float(noise)}


def _layout(scene):
    from rtctl.io.base import Layout
    from rtctl.models import sensed_layout

    rows, owner = sensed_layout(scene)
    names = [f"{g.name}.{i}" for g in scene.actuator for i in range(g.grid[0] * g.grid[1])]
    groups = [g.name for g in scene.actuator for _ in range(g.grid[0] * g.grid[1])]
    types = [g.type for g in scene.actuator for _ in range(g.grid[0] * g.grid[1])]
    return Layout(float(scene.timing.fs), int(scene.timing.block), tuple(names), tuple(groups), tuple(types),
                  tuple(rows), tuple(owner))


# --- xruns over a long run -----------------------------------------------------------------------

def long_run(srv, block, seconds, baseline_s):
    timing = [f"timing.block={block}", f"timing.duration={seconds}"]
    emu = EmulatorProcess(srv, SCENE, timing)
    try:
        if not emu.wait_for("waiting", 300):
            raise RuntimeError(f"emulator did not start: {emu.stop()[1]}")
        counter = XrunCounter(srv)
        time.sleep(0.5)
        counter.take()
        time.sleep(baseline_s)
        baseline = counter.take()
        mark = len(srv.log_text())
        with tempfile.TemporaryDirectory() as tmp:
            # the burst guard off: every xrun of the whole run is counted, and what the default
            # guard (io.xrun_limit in io.xrun_window) would have done is replayed on the flags
            r = subprocess.run(CLI + ["run", SCENE, "--json", "--no-plot", "--out", tmp,
                                      *sets(timing + AUDIO + ["io.xrun_limit=0"])],
                               env=srv.env, capture_output=True, text=True, timeout=seconds + 300)
            bursts = xrun_bursts(tmp, block) if r.returncode == 0 else {}
        server = counter.take()
        causes = xrun_causes(srv.log_text()[mark:])
        counter.close()
    finally:
        code, err = emu.stop()
    if r.returncode != 0:
        raise RuntimeError(f"rtctl run failed ({r.returncode}): {r.stderr[-1000:]}")
    s = json.loads(r.stdout)
    io = s["io"]
    return {"block": block, "seconds": s["duration_s"], "xruns": io["xruns"],
            "first_xrun_block": io["first_xrun_block"],
            "server_xruns_during_run": server, "server_xruns_idle": baseline, "idle_seconds": baseline_s,
            "late_blocks": io["late_blocks"], "max_callback_gap_us": io["max_callback_gap_us"],
            "callback_us": s["block_time_us"], "cfunc": io["cfunc"],
            "emulator": err.strip().splitlines()[-1] if err.strip() else "", "jackd_xrun_causes": causes,
            **bursts}


def xrun_bursts(out_dir, block):
    """The most xrun-flagged blocks in any window of the default io.xrun_window, and the block at
    which the default burst guard (the device thread's leaky bucket) would have ended the run."""
    import numpy as np

    from rtctl.safety import IO_XRUN
    from rtctl.schema import SCENE as SPEC
    from rtctl.trace import TraceReader

    io = SPEC.keys["io"].keys
    limit, window = io["xrun_limit"].default, io["xrun_window"].default
    flags = (TraceReader(os.path.join(out_dir, "trace")).status & IO_XRUN) != 0
    w = max(1, round(window * 48000 / block))
    most = int(np.convolve(flags, np.ones(w, dtype=int), mode="valid").max()) if flags.size >= w else int(flags.sum())
    level, fired = 0, None
    for k, f in enumerate(flags):
        level = level - min(level, limit) + (w if f else 0)
        if level > limit * w and fired is None:
            fired = k
    return {"most_xruns_in_window": most, "window_s": window, "default_guard_would_stop_at_block": fired}


# --- callback cost without a server ----------------------------------------------------------------

def _no_stream_sd():
    """Just enough of sounddevice for an AudioBackend that is never started."""
    import sounddevice as sd

    class NoStream:
        PortAudioError, CallbackAbort, CallbackFlags = sd.PortAudioError, sd.CallbackAbort, sd.CallbackFlags

        def check_input_settings(self, **kw):
            pass

        check_output_settings = check_input_settings

    return NoStream()


def callback_costs(block, n_calls=20000):
    import sounddevice as sd

    from rtctl import scene as scenes
    from rtctl.engine.rig import build
    from rtctl.io import _audio_kernels as K
    from rtctl.io.audio import AudioBackend, channel_map

    sc = scenes.load(SCENE, [f"timing.block={block}"])
    out = {}
    for kind in ("python", "cfunc"):
        os.environ["RTCTL_AUDIO_CFUNC"] = "1" if kind == "cfunc" else "0"
        rig = build(sc)  # sim backend: it has the sensed rows; its device is not used here
        n, m = rig.n_channels, rig.sensed.shape[0]
        lay = _layout(sc)
        dev = {"name": "none", "max_input_channels": 64, "max_output_channels": 64}
        be = AudioBackend(_no_stream_sd(), 0, dev, "-", lay, rig.out, rig.sensed, channel_map((), n, 64, "", ""),
                          channel_map((), m, 64, "", ""), 150.0, 0.01)
        be.compile()
        rig.apply_schedule(0)
        be.bind(rig)
        ibuf, obuf = sd._ffi.new("float[]", block * m), sd._ffi.new("float[]", block * n)
        if kind == "cfunc":
            fn = sd._ffi.cast("PaStreamCallback *", be._cfunc.address)
            user = sd._ffi.cast("void *", int(be._cfunc_keep[0].ctypes.data))
            out["cfunc_note"] = be.stats()["cfunc_note"]
        else:
            def wrapper(iptr, optr, frames, t, status, _, m=m, n=n, be=be):  # what sounddevice does per callback
                idata = sd._array(sd._buffer(iptr, frames, m, 4), m, "float32")
                odata = sd._array(sd._buffer(optr, frames, n, 4), n, "float32")
                return sd._wrap_callback(be._callback, idata, odata, frames, t, status)

            fn = sd._ffi.callback("PaStreamCallback", error=sd._lib.paAbort)(wrapper)
            user = sd._ffi.NULL
            ind = sd._array(sd._buffer(ibuf, block, m, 4), m, "float32")
            outd = sd._array(sd._buffer(obuf, block, n, 4), n, "float32")
            flags = sd.CallbackFlags(0)
            t = time.perf_counter()
            for _ in range(n_calls):
                be._callback(ind, outd, block, None, flags)
            out["python_callback_us"] = (time.perf_counter() - t) / n_calls * 1e6
            t = time.perf_counter()
            for _ in range(n_calls):
                rig.step()
            out["step_us"] = (time.perf_counter() - t) / n_calls * 1e6
        be.ctl[K.DONE] = 0
        t = time.perf_counter()
        for _ in range(n_calls):
            fn(ibuf, obuf, block, sd._ffi.NULL, 0, user)
        out[f"{kind}_via_portaudio_entry_us"] = (time.perf_counter() - t) / n_calls * 1e6
    noop = sd._ffi.callback("PaStreamCallback")(lambda *a: 0)
    t = time.perf_counter()
    for _ in range(n_calls):
        noop(sd._ffi.NULL, sd._ffi.NULL, block, sd._ffi.NULL, 0, sd._ffi.NULL)
    out["cffi_python_roundtrip_us"] = (time.perf_counter() - t) / n_calls * 1e6
    os.environ.pop("RTCTL_AUDIO_CFUNC", None)
    return out


# --- GIL contention ----------------------------------------------------------------------------------

def busy_engine(srv, block, seconds, busy):
    from rtctl import scene as scenes
    from rtctl.engine.rig import build

    res = {}
    for kind in ("python", "cfunc"):
        os.environ["RTCTL_AUDIO_CFUNC"] = "1" if kind == "cfunc" else "0"
        # the burst guard off: these runs count xruns, a burst must not end them
        sc = scenes.load(SCENE, [f"timing.block={block}", *AUDIO, "io.xrun_limit=0"])
        rig = build(sc)
        dev = rig.device
        n = int(seconds * FS / block)
        busy_s = busy * block / FS

        def on_block(k, slot, busy_s=busy_s, n=n, rig=rig):
            t = time.perf_counter()
            while time.perf_counter() - t < busy_s:  # pure Python: holds the GIL
                pass
            if k + 1 < n:
                rig.apply_schedule(k + 1)
            return False

        rig.apply_schedule(0)
        try:
            dev.run(rig, n, on_block)
        finally:
            dev.close()
        s = dev.stats()
        res[kind] = {k: s[k] for k in ("xruns", "late_blocks", "max_callback_gap_us", "blocks", "cfunc", "error")}
        res[kind]["xruns_per_1000_blocks"] = 1000 * s["xruns"] / max(s["blocks"], 1)
    os.environ.pop("RTCTL_AUDIO_CFUNC", None)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="length of each xrun run (default 60)")
    ap.add_argument("--blocks", type=int, nargs="+", default=[64, 32], help="JACK periods = scene blocks")
    ap.add_argument("--idle", type=float, default=10.0, help="idle seconds for the server's own xrun baseline")
    ap.add_argument("--busy", type=float, nargs="+", default=[0.5, 1.0],
                    help="shares of each block the engine spends in pure Python (1 = never idle)")
    ap.add_argument("--no-long", action="store_true", help="skip the long runs")
    ap.add_argument("--busy-seconds", type=float, default=10.0)
    ap.add_argument("--json", action="store_true", help="print only the JSON object")
    args = ap.parse_args(argv)
    if JACKD is None:
        print("bench/hil_audio.py: jackd not installed (Debian: apt-get install jackd2)", file=sys.stderr)
        return 2
    from rtctl import scene as scenes

    result = {"fs": FS, "scene": SCENE, "latency": {}, "runs": [], "busy_engine": {},
              "load_avg_start": os.getloadavg()[0]}
    for i, block in enumerate(args.blocks):
        with JackServer(period=block) as srv:
            # before sounddevice is imported: PortAudio joins this server, never another one
            os.environ["JACK_DEFAULT_SERVER"] = srv.name
            if i == 0:
                result["callback_cost"] = callback_costs(64)
            sc = scenes.load(SCENE, [f"timing.block={block}", *AUDIO])
            lat = {"jack_wire": impulse_latency(srv, sc, wire=True)}
            emu = EmulatorProcess(srv, SCENE, [f"timing.block={block}"])
            try:
                emu.wait_for("waiting", 300)
                lat["through_emulator"] = impulse_latency(srv, sc, wire=False)
            finally:
                emu.stop()
            result["latency"][block] = lat
            result["busy_engine"][block] = {b: busy_engine(srv, block, args.busy_seconds, b) for b in args.busy}
            if not args.no_long:
                result["runs"].append(long_run(srv, block, args.seconds, args.idle))
    result["busy"] = args.busy
    result["load_avg_end"] = os.getloadavg()[0]
    print(json.dumps(result, indent=None if args.json else 1))
    if not args.json:
        _table(result)
    return 0


def _table(r):
    c = r["callback_cost"]
    print(f"\ncallback cost per block (block 64, {SCENE}, no server):")
    print(f"  rig.step() from Python            {c['step_us']:8.2f} us")
    print(f"  Python callback (copy+step+snap)  {c['python_callback_us']:8.2f} us")
    print(f"  ... through sounddevice's wrapper {c['python_via_portaudio_entry_us']:8.2f} us  (cffi->Python alone "
          f"{c['cffi_python_roundtrip_us']:.2f} us)")
    print(f"  C callback (cfunc)                {c['cfunc_via_portaudio_entry_us']:8.2f} us  ({c.get('cfunc_note')})")
    print("\nround-trip latency (impulse on drive 0 -> sensed row 0):")
    for b, lat in r["latency"].items():
        for k, v in lat.items():
            print(f"  block {b:>3} {k:<17} " + (f"{v['blocks']} blocks ({v['samples']} samples after the impulse's "
                                                 f"block start)" if v else "not seen"))
    print("\nengine thread in pure Python (share of every block):")
    for b, dd in r["busy_engine"].items():
        for busy, d in dd.items():
            for k, v in d.items():
                print(f"  block {b:>3} busy {busy:4.2f} {k:<7} xruns {v['xruns']:>5} "
                      f"({v['xruns_per_1000_blocks']:5.2f} per 1000 blocks)  late {v['late_blocks']:>4}  "
                      f"longest pause {v['max_callback_gap_us'] / 1e3:6.2f} ms over {v['blocks']} blocks")
    print("\nlong runs against the emulator:")
    print("  block  seconds  xruns  server-xruns  idle-server-xruns  late  longest-pause  callback p50/p99/max us")
    for x in r["runs"]:
        cu = x["callback_us"]
        print(f"  {x['block']:>5}  {x['seconds']:7.1f}  {x['xruns']:>5}  {x['server_xruns_during_run']:>12}  "
              f"{x['server_xruns_idle']:>8} in {x['idle_seconds']:.0f} s  {x['late_blocks']:>4}  "
              f"{x['max_callback_gap_us'] / 1e3:10.2f} ms  {cu['p50']:.1f}/{cu['p99']:.1f}/{cu['max']:.1f}")
        print(f"         jackd's causes: {x['jackd_xrun_causes'] or 'none'}")
    print(f"\nload average {r['load_avg_start']:.2f} at start, {r['load_avg_end']:.2f} at the end")


if __name__ == "__main__":
    sys.exit(main())
