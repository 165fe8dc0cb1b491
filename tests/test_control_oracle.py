"""bench/control_oracle.py, the referee of what no loop can do after a finger event: its open-loop
drive, set from the simulated device's own frequency response under each segment's finger, must
put the device's true tip on every reachable target once the segment has settled (else its
settle times and overshoots would measure the oracle, not the beam)."""

import pytest
from bench_module import load

from rtctl.engine.report import fit_amplitudes

sweep = load("control_sweep")
oracle = load("control_oracle")


@pytest.mark.parametrize("device", [{}, sweep.LOW], ids=["nominal", "low"])
def test_the_oracles_drive_holds_every_reachable_target(device):
    run = oracle.oracle(device, [0] * len(sweep.TONES))
    t, tip = run["t"], run["tip"]
    ends = run["events"] + [sweep.DURATION]
    starts = [0.0] + run["events"]
    gains = sweep.gains(device)
    from rtctl import scene

    vmax = scene.load(sweep.SCENE).actuator[0].max_voltage
    checked = 0
    for seg, (t0, t1) in enumerate(zip(starts, ends)):
        m = (t >= t1 - 0.2) & (t < t1)  # the segment's last 200 ms: settled (a 10 Hz tone: two periods)
        assert t1 - t0 >= 0.5
        for n, (f, b, target) in enumerate(sweep.TONES):
            if target > sweep.reach(gains[seg][n], vmax):
                continue
            freqs = [f] if not b else [f - b / 2, f + b / 2]
            amp = fit_amplitudes(tip[n][m], t[m], freqs).sum()  # a beat pair's envelope peak
            assert amp == pytest.approx(target, rel=0.01), (seg, f, b)
            checked += 1
    assert checked >= 40


def test_a_lift_off_overshoots_at_the_held_drive_and_not_with_the_oracle_at_the_event():
    """The 40 Hz tone as the finger lifts: with the drive moved only WARM blocks later (51 ms)
    the amplitude first grows as the event alone makes it (about x2 on the nominal device, the
    unloaded beam's reach over the loaded one's); switched in the event's block it stays within 5 %."""
    from rtctl.engine.report import against_target

    n = [k for k, (f, b, _) in enumerate(sweep.TONES) if (f, b) == (40, 0)][0]
    warm, _ = oracle._loop_blocks({})
    at_event = oracle.oracle({}, [0] * len(sweep.TONES))
    late = oracle.oracle({}, warm)
    t0, t1 = at_event["events"][1], at_event["events"][2]
    target = sweep.TONES[n][2]
    g = sweep.gains({})
    step = g[2][n].sum() / g[1][n].sum() - 1.0  # lifted over 200 g, at the same drive
    a = against_target(at_event["tip"][n], at_event["t"], [40.0], t0, t1, target)
    b = against_target(late["tip"][n], late["t"], [40.0], t0, t1, target)
    assert a["overshoot_pct"] < 5.0
    assert b["overshoot_pct"] == pytest.approx(100.0 * step, abs=3.0)


def test_acts_by_is_the_last_delay_of_an_unbroken_run_of_meets():
    """The latency class is sorted by how soon the oracle must act: the last delay of ``LADDER``
    up to which every delay meets the clause (a later delay that meets again does not count)."""
    ok = {"settle_ms": 20.0, "overshoot_pct": 1.0}
    ovs = {"settle_ms": 20.0, "overshoot_pct": 40.0}
    slow = {"settle_ms": 80.0, "overshoot_pct": 1.0}
    ladder = oracle.LADDER
    assert ladder[:3] == (0, 1, 2)

    def row(figs):
        return {"required_ms": 50.0, "ladder": dict(zip(ladder, figs))}

    rest = [ovs] * (len(ladder) - 3)
    assert oracle._acts_by(row([ok, ok, ok, *rest]), "overshoot") == 2
    assert oracle._acts_by(row([ok, ok, ok, *rest]), "settle") == ladder[-1]
    assert oracle._acts_by(row([ok, ovs, ok, *[ok] * len(rest)]), "overshoot") == 0
    assert oracle._acts_by(row([slow, ok, ok, *rest]), "settle") is None


def test_the_currents_tell_of_an_event_first_when_the_devices_latency_says():
    """d' counts only what a loop has read before it sets each delay's drive: nothing of the
    event before the device's I/O latency and the controller's block have passed (the sim
    delivers a block's currents one block later), then the lift-off at once."""
    _, first = oracle._loop_blocks({})
    assert first == 2  # the sim's one block of I/O latency, then the controller's block
    told = oracle.information({})
    lifted = sweep.SEGMENTS.index("lifted") - 1
    for per_tone in told:
        for d in per_tone:
            assert all(d[k] == 0.0 for k in oracle.LADDER if k < first)
    assert min(d[first] for d in told[lifted]) > 100.0  # the lift-off is plain in the first block read
    for per_tone in told:
        for d in per_tone:
            later = [d[k] for k in oracle.LADDER if k >= first]
            assert all(b >= a for a, b in zip(later, later[1:]))  # more blocks read tell no less


def test_the_noise_d_prime_is_measured_in_is_the_sensed_currents_own():
    """d' divides the noise-free difference by the noise the device adds to every sensed sample:
    the spread of a noisy run about the same run without noise."""
    import numpy as np

    from rtctl import scene

    clean = oracle._held_sensed({}, (), 0, 300, 16)
    noisy = oracle._held_sensed({}, (), 0, 300, 16, noisy=True)
    assert np.std(noisy - clean) == pytest.approx(oracle.noise_rms(scene.load(sweep.SCENE)), rel=0.03)


def test_a_miss_is_the_first_of_beam_block_latency_whose_oracle_misses_it_too():
    """The classes nest: the oracle at the event, then at the first read, then after WARM; a
    miss goes to the first of them that misses it too, and to the loop if none does."""
    ok = {"settle_ms": 20.0, "overshoot_pct": 1.0}
    ovs = {"settle_ms": 20.0, "overshoot_pct": 40.0}

    def row(at_event, first_read, after_warm):
        return {"required_ms": 50.0, "closed": ovs, "at_event": at_event, "first_read": first_read,
                "after_warm": after_warm}

    assert oracle.classify(row(ovs, ovs, ovs)) == {"overshoot": "beam"}
    assert oracle.classify(row(ok, ovs, ovs)) == {"overshoot": "block"}
    assert oracle.classify(row(ok, ok, ovs)) == {"overshoot": "latency"}
    assert oracle.classify(row(ok, ok, ok)) == {"overshoot": "loop"}
    assert oracle.classify({**row(ovs, ovs, ovs), "closed": ok}) == {}


def test_a_sweep_of_another_beam_is_refused(tmp_path, capsys):
    """``--against`` a sweep run with other ``--set`` overrides would sort one device's misses by
    another's oracle: refused before any run, naming both."""
    import json

    swept = tmp_path / "sweep.json"
    swept.write_text(json.dumps({"set": ["actuator.lateral.beam.length=12e-3"], "cases": []}))
    assert oracle.main(["--quick", "--against", str(swept)]) == 2
    err = capsys.readouterr().err
    assert "beam.length=12e-3" in err and "another device" in err
