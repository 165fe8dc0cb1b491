"""The engine's pieces: the composed block function against its stages called one by one, the
parameter queue against plain array writes (batches atomic, one writer, a producer thread racing
the consumer), and the stage list a scene gets."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from rtctl import scene
from rtctl.dsp import OscillatorBank, PulseTrain, osc_bank_process, pulse_process
from rtctl.engine.compose import compose
from rtctl.engine.kernels import clear
from rtctl.engine.queue import ParamQueue, QueueFull, drain
from rtctl.engine.rig import build
from rtctl.engine.stage import Stage
from rtctl.safety import Limiter, limit_block

FS, BLOCK = 48000.0, 32


def synth_stages(seed, out):
    """Oscillators, pulses and the limiter on ``out``: a block function's core, random parameters."""
    rng = np.random.default_rng(seed)
    n = out.shape[0]
    bank = OscillatorBank(n, rng.integers(0, n, 6), FS, rng.uniform(20, 2000, 6), rng.uniform(0, 80, 6),
                          rng.uniform(0, 6, 6), ramp=BLOCK)
    pulses = PulseTrain(n, FS, rng.uniform(1, 300, n), 0.3, 50.0, -20.0)
    lim = Limiter(FS, max_voltage=[100.0] * n, slew=rng.uniform(1e4, 1e6, n), current=[1.0] * n,
                  capacitance=[1e-8] * n, temperature=[80.0] * n, ambient=[25.0] * n, loss_tangent=[0.02] * n,
                  thermal_resistance=[1.0] * n, thermal_tau=[10.0] * n)
    q = ParamQueue([bank.pending, pulses.pending])
    stages = [Stage("params", drain, dict(zip(("ring", "heads", "targets"), q.args))),
              Stage("clear", clear, {"out": out}, status=None),
              Stage("osc", osc_bank_process, dict(zip(("s", "p", "c"), bank.args), out=out), status=None),
              Stage("pulses", pulse_process, dict(zip(("s", "p"), pulses.args), out=out), status=None),
              Stage("limiter", limit_block, dict(x=out, s=lim.state, p=lim.params, f=lim.fade, c=lim.counts))]
    return stages, bank, pulses, lim, q


@pytest.mark.parametrize("seed", range(3))
def test_composed_function_is_its_stages_called_in_order(seed):
    out_a, out_b = np.zeros((4, BLOCK)), np.zeros((4, BLOCK))
    sa, bank_a, pul_a, lim_a, qa = synth_stages(seed, out_a)
    sb, bank_b, pul_b, lim_b, qb = synth_stages(seed, out_b)
    bf = compose(sb)
    assert "k0(" in bf.source and bf.source.count("st |=") == 2  # drain and limiter report status
    rng = np.random.default_rng(seed + 10)
    for k in range(200):
        if k % 17 == 0:  # the same schedule change through each queue
            f, a = rng.uniform(20, 2000), rng.uniform(0, 200)  # some beyond the limiter's 100 V
            for bank, q in ((bank_a, qa), (bank_b, qb)):
                bank.route(lambda r, c, v, q=q: q.post(0, r, c, v))
                bank.set(k % 6, freq=f, amp=a)
                q.publish()
        st_a = sum(s.call() for s in sa)  # (bits never collide here: at most one stage reports)
        st_b = bf()
        np.testing.assert_array_equal(out_a, out_b)
        assert st_a == st_b
    np.testing.assert_array_equal(lim_a.state, lim_b.state)
    assert np.any(lim_a.counts)  # the limiter had work to do


def test_compose_refuses_what_the_generated_code_cannot_reach():
    out = np.zeros((2, 8))
    with pytest.raises(TypeError, match="C-contiguous"):
        compose([Stage("clear", clear, {"out": out[:, ::2]}, status=None)])
    with pytest.raises(TypeError, match="module-level numba kernel"):
        compose([Stage("lambda", lambda x: 0, {"out": out})])


def test_queue_applies_batches_whole_and_in_order():
    a, b = np.zeros((4, 5)), np.zeros((2, 3))
    q = ParamQueue([a, b], capacity=16)
    q.post(0, 1, slice(1, 4), [1.0, 2.0, 3.0])
    q.post(1, 0, 2, 7.0)
    drain(*q.args)  # staged, not published: nothing yet
    assert not a.any() and not b.any() and q.pending() == 0
    q.publish()
    assert q.pending() == 4 and not a.any()  # published, not yet drained: still nothing
    drain(*q.args)
    want_a = np.zeros((4, 5))
    want_a[1, 1:4] = [1, 2, 3]
    np.testing.assert_array_equal(a, want_a)
    assert b[0, 2] == 7.0 and q.pending() == 0
    for k in range(40):  # wraps the ring many times; later writes win
        q.post(0, 3, slice(None), k)
        q.post(0, 3, 0, -k)
        q.publish()
        drain(*q.args)
    np.testing.assert_array_equal(a[3], [-39, 39, 39, 39, 39])
    with pytest.raises(QueueFull, match="holds 16"):
        q.post(0, 0, np.arange(5).repeat(4), 1.0)
    with pytest.raises(ValueError, match="registered"):
        q.target_id(np.zeros((4, 5)))


def test_queue_full_waits_for_the_consumer_then_gives_up():
    a = np.zeros((1, 8))
    q = ParamQueue([a], capacity=8)
    q.post(0, 0, slice(None), 1.0)
    q.publish()
    q.post(0, 0, 0, 2.0)
    with pytest.raises(QueueFull, match="did not drain"):
        q.publish(timeout=0.05)  # nobody drains: no room for the ninth record
    drain(*q.args)
    q.publish()
    drain(*q.args)
    assert a[0, 0] == 2.0


def test_queue_producer_thread_against_a_consumer_thread():
    """One thread posts numbered batches (each writes one value into every column, then a
    counter), the other drains continuously: the consumer must only ever see whole batches
    (every column equal to the counter), and end on the last one."""
    a = np.zeros((2, 64))
    q = ParamQueue([a], capacity=256)
    n_batches = 3000
    torn, stop = [], threading.Event()

    def consume():
        while not stop.is_set():
            drain(*q.args)
            if not np.all(a[0] == a[1, 0]):
                torn.append(a.copy())

    t = threading.Thread(target=consume)
    t.start()
    try:
        for k in range(1, n_batches + 1):
            q.post(0, 0, slice(None), float(k))
            q.post(0, 1, 0, float(k))
            q.publish(timeout=5.0)
    finally:
        stop.set()
        t.join(10)
    drain(*q.args)
    assert not torn, torn[0]
    assert np.all(a[0] == n_batches) and a[1, 0] == n_batches


def test_a_scene_gets_only_the_stages_it_needs():
    names = lambda sc: [s.name for s in build(scene.load(*sc)).stages]  # noqa: E731
    # the simulated device's read first and its plants last (SimDevice.in_block)
    assert names(("line-bimorph-5", ["timing.duration=0.01"])) == [
        "params", "sim read", "clear", "oscillators", "limiter", "sim group 0"]
    assert names(("line-bimorph-5", ["control.observe=true"])) == [
        "params", "sim read", "clear", "oscillators", "limiter", "observer lateral", "sim group 0"]
    assert names(("solenoid-3x3", [])) == ["params", "sim read", "clear", "pulses", "limiter", "sim group 0"]


@pytest.mark.parametrize("name, over", [("line-bimorph-5", ["control.observe=true"]), ("solenoid-3x3", []),
                                        ("line-bimorph-5-closed", ["events.0.at=0.1", "events.1.at=0.15",
                                                                   "events.2.at=0.2"])])
def test_the_simulated_device_inside_the_block_function_changes_nothing(name, over, monkeypatch):
    """SimDevice.in_block runs the plants as stages of the block function instead of from read
    and write: the same blocks, bitwise (events and controllers included)."""
    from rtctl.io.sim import SimDevice

    sc = scene.load(name, [*over, "timing.duration=0.3"])
    monkeypatch.setattr(SimDevice, "in_block", False)
    a = build(sc)
    assert "sim read" not in [s.name for s in a.stages]
    monkeypatch.setattr(SimDevice, "in_block", True)
    b = build(sc)
    assert [s.name for s in b.stages][:2] == ["params", "sim read"] and b.stages[-1].name.startswith("sim group")
    for k in range(int(0.3 * a.fs / a.block)):
        a.apply_schedule(k)
        b.apply_schedule(k)
        assert a.advance() == b.advance()
        np.testing.assert_array_equal(a.out, b.out)
        np.testing.assert_array_equal(a.sensed, b.sensed)
        np.testing.assert_array_equal(a.truth, b.truth)


def test_schedule_changes_reach_pending_only_through_the_block_function():
    rig = build(scene.load("line-bimorph-5"))
    before = rig.bank.pending.copy()
    rig.apply_schedule(0)  # every tone starts at 0 s
    np.testing.assert_array_equal(rig.bank.pending, before)  # posted, not written
    assert rig.queue.pending() > 0
    rig.advance()
    assert rig.queue.pending() == 0
    assert np.all(rig.bank.pending[1] > 0)  # the amplitudes arrived (P_AMP)


def test_end_stop_pins_carry_no_amplitude_target_into_the_trace():
    """Solenoid and Dot pins travel between stops: no perception-margin target in the trace either
    (a bimorph tone at the same frequency keeps its target)."""
    assert np.all(np.isnan(build(scene.load("solenoid-3x3")).targets_um))
    assert np.all(np.isnan(build(scene.load("dot-4x4")).targets_um))
    assert np.isfinite(build(scene.load("line-bimorph-5")).targets_um).sum() == 5


def test_an_observed_group_builds_its_beam_once(monkeypatch):
    """Limiter load, simulated plant and observer share one model per group."""
    import rtctl.plant.beam as beam_mod

    calls = []
    real = beam_mod.build_beam
    monkeypatch.setattr(beam_mod, "build_beam", lambda *a, **k: calls.append(1) or real(*a, **k))
    build(scene.load("line-bimorph-5", ["control.observe=true"]))
    assert len(calls) == 1
