"""Serial pin-controller link through a real pty and the device emulator: frames per second
acknowledged, round trip per frame, resends under injected faults, time to notice a kill -9.

Each case starts `python -m rtctl.emulate.serial SCENE [faults]`, opens the backend as a run
would (HELLO included) and calls ``read(); write()``:

- ``saturated``: back to back, a pin command changing on every call: the link's ceiling (one
  frame in flight, so frames/s = 1 / round trip);
- ``paced``: once per block period (48 kHz, 32 samples: 0.67 ms) as the engine calls it, a
  command change every block;
- ``faults``: saturated, with ``--drop-byte-every 97 --garbage-every 5 --corrupt-every 11``;
- ``kill``: the emulator is killed (SIGKILL) while paced; time until ``DEVICE_LOST``;
- ``dot_switch``: all 16 Dot pins commanded up, then down: time until every reported state agrees.

Also the time one ``read(); write()`` pair takes (the engine's share of a block).

Baseline in the same process: a bare pty ping-pong (a thread echoing 11-byte frames on the
master), the floor any protocol over this pty pays. Prints one JSON object, then a table.

    python bench/serial.py [--seconds 2] [--kills 3]
"""

import argparse
import json
import os
import pty
import select
import signal
import subprocess
import sys
import threading
import time
import tty

# Run as `python bench/serial.py`, this file's folder comes first on sys.path and `import serial`
# would find this file instead of pyserial.
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != os.path.dirname(os.path.abspath(__file__))]

import numpy as np  # noqa: E402

from rtctl import scene  # noqa: E402
from rtctl.io.base import Layout  # noqa: E402
from rtctl.io.serial import DEVICE_LOST, open_backend  # noqa: E402

BLOCK_S = 32 / 48000.0


def start_emulator(name, *args):
    p = subprocess.Popen([sys.executable, "-m", "rtctl.emulate.serial", name, *args],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if not select.select([p.stdout], [], [], 120)[0]:
        p.kill()
        raise SystemExit("emulator did not start")
    return p, p.stdout.readline().strip()


def stop(p):
    if p.poll() is None:
        p.terminate()
    p.communicate(timeout=10)


def open_link(name, port, keepalive=0.05):
    sc = scene.load(name, [f"io.port={port}", "io.backend=serial", "io.timeout=0.02", "io.retries=3",
                           f"io.keepalive={keepalive}"])
    g = sc.actuator[0]
    n = g.grid[0] * g.grid[1]
    lay = Layout(48000.0, 32, tuple(f"p.{i}" for i in range(n)), ("p",) * n, (g.type,) * n, (), ())
    out = np.zeros((n, 32))
    return open_backend(sc, lay, out, np.zeros((0, 32))), out, float(g.max_voltage)


def drive(be, out, v, seconds, paced):
    """Toggle pin 0 between up and down on every call; returns (statuses OR, call times s)."""
    t0 = time.perf_counter()
    k, status, calls = 0, 0, []
    while (now := time.perf_counter()) - t0 < seconds:
        out[0, -1] = v if k % 2 else -v
        status |= be.read() | be.write()
        calls.append(time.perf_counter() - now)
        k += 1
        if paced:
            time.sleep(max(0.0, t0 + k * BLOCK_S - time.perf_counter()))
    return status, np.array(calls)


def case(name, scene_name, seconds, paced, faults=()):
    p, port = start_emulator(scene_name, *faults)
    try:
        be, out, vmax = open_link(scene_name, port)
        be.reset()
        status, calls = drive(be, out, vmax, seconds, paced)
        us = calls * 1e6
        s = be.stats()
        be.close()
    finally:
        stop(p)
    return {"case": name, "display": scene_name, "paced": paced, "faults": " ".join(faults),
            "calls": len(calls), "call_us": {"p50": float(np.median(us)), "p99": float(np.percentile(us, 99)),
                                             "max": float(us.max())},
            "frames_per_s": s["frame_rate_hz"],
            "rtt_median_ms": s["rtt_ms"]["median"], "rtt_p99_ms": s["rtt_ms"]["p99"],
            "rtt_max_ms": s["rtt_ms"]["max"], "frames_sent": s["frames_sent"],
            "frames_acked": s["frames_acked"], "resends": s["resends"], "timeouts": s["timeouts"],
            "nacks": s["nacks"], "bad_frames": s["bad_frames"], "garbage_bytes": s["garbage_bytes"],
            "device_lost": bool(status & DEVICE_LOST), "error": s["error"]}


def switch_times(n):
    """All 16 Dot pins commanded up, then down, ``n`` times: ms until every ACKed state agrees."""
    p, port = start_emulator("dot-4x4")
    try:
        be, out, vmax = open_link("dot-4x4", port, keepalive=0.002)
        res = {"up": [], "down": []}
        for i in range(2 * n):
            v, want, key = (vmax, 1, "up") if i % 2 == 0 else (-vmax, 2, "down")
            out[:, -1] = v
            t0 = time.perf_counter()
            k = 0
            while not (be.states == want).all() and time.perf_counter() - t0 < 1.0:
                be.read()
                be.write()
                k += 1
                time.sleep(max(0.0, t0 + k * BLOCK_S - time.perf_counter()))
            res[key].append((time.perf_counter() - t0) * 1e3)
            time.sleep(0.06)  # the plant settles (the watchdog may trip: harmless, pins latch)
        be.close()
    finally:
        stop(p)
    return {k: {"median": float(np.median(v)), "max": float(np.max(v))} for k, v in res.items()}


def kill_latency(n):
    out_ms = []
    for _ in range(n):
        p, port = start_emulator("dot-4x4")
        be, out, vmax = open_link("dot-4x4", port)
        drive(be, out, vmax, 0.2, True)
        os.kill(p.pid, signal.SIGKILL)
        t0 = time.perf_counter()
        k = 0
        while not (be.read() | be.write()) & DEVICE_LOST and time.perf_counter() - t0 < 2.0:
            k += 1
            time.sleep(max(0.0, t0 + k * BLOCK_S - time.perf_counter()))
        out_ms.append((time.perf_counter() - t0) * 1e3)
        be.close()
        p.communicate(timeout=10)
    return out_ms


def pty_baseline(seconds):
    """Round trip of a bare 11-byte ping-pong through a pty (echo thread on the master)."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    stop_flag = []

    def echo():
        while not stop_flag:
            if select.select([master], [], [], 0.01)[0]:
                os.write(master, os.read(master, 4096))

    th = threading.Thread(target=echo, daemon=True)
    th.start()
    msg, rtt = b"\x00" + bytes(range(1, 10)) + b"\x00", []
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        t = time.perf_counter()
        os.write(slave, msg)
        got = b""
        while len(got) < len(msg):
            select.select([slave], [], [], 1.0)
            got += os.read(slave, 4096)
        rtt.append(time.perf_counter() - t)
    stop_flag.append(1)
    th.join(1.0)
    os.close(master)
    os.close(slave)
    r = np.array(rtt) * 1e3
    return {"round_trips_per_s": len(r) / seconds, "rtt_median_ms": float(np.median(r)),
            "rtt_p99_ms": float(np.percentile(r, 99))}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--kills", type=int, default=3)
    a = ap.parse_args(argv)
    faults = ("--drop-byte-every", "97", "--garbage-every", "5", "--corrupt-every", "11")
    cases = [case("saturated", "dot-4x4", a.seconds, False),
             case("paced", "dot-4x4", a.seconds, True),
             case("saturated", "sma-8x8", a.seconds, False),
             case("paced", "sma-8x8", a.seconds, True),
             case("faults", "dot-4x4", a.seconds, False, faults)]
    kills = kill_latency(a.kills)
    sw = switch_times(5)
    res = {"baseline_pty": pty_baseline(a.seconds), "cases": cases, "dot_switch_ms": sw,
           "kill_to_device_lost_ms": {"each": kills, "max": max(kills)}}
    print(json.dumps(res, indent=1))
    b = res["baseline_pty"]
    print(f"\nbare pty ping-pong: {b['round_trips_per_s']:.0f} round trips/s, median "
          f"{b['rtt_median_ms']:.3f} ms, p99 {b['rtt_p99_ms']:.3f} ms")
    print(f"{'case':<10} {'display':<8} {'frames/s':>9} {'rtt p50 ms':>10} {'rtt p99 ms':>10} "
          f"{'resends':>8} {'timeouts':>8} {'nacks':>6} {'bad':>5} {'lost':>5} {'call p50/p99 us':>16}")
    for c in cases:
        print(f"{c['case']:<10} {c['display']:<8} {c['frames_per_s']:>9.0f} {c['rtt_median_ms']:>10.3f} "
              f"{c['rtt_p99_ms']:>10.3f} {c['resends']:>8} {c['timeouts']:>8} {c['nacks']:>6} "
              f"{c['bad_frames']:>5} {str(c['device_lost']):>5} "
              f"{c['call_us']['p50']:>7.1f}/{c['call_us']['p99']:<7.1f}")
    print(f"kill -9 -> DEVICE_LOST: {', '.join(f'{k:.2f}' for k in kills)} ms")
    print(f"16 Dot pins, command -> every ACKed state agrees: up median {sw['up']['median']:.2f} ms "
          f"(max {sw['up']['max']:.2f}), down median {sw['down']['median']:.2f} ms (max {sw['down']['max']:.2f})")


if __name__ == "__main__":
    main()
