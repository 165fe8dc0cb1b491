"""The lift-off test (rtctl/selfsense/lift.py): in a closed-loop run through a press, a lift-off
and a landing, it flags the low tones' channels in the first block read after the lift-off and
in no other block; its residuals are the currents' less each candidate's steady currents and ring,
recomputed here from the block's own drive by least squares (not from the lock-in's phasors); and
a scene that needs no such test compiles none."""

import numpy as np
import pytest
from bench_module import load

from rtctl import scene
from rtctl.control._kernels import JNOISE, NREL, OBS_CH
from rtctl.engine.rig import build
from rtctl.events import block_of
from rtctl.selfsense.lift import S_FLAG, S_LAST

sweep = load("control_sweep")
load("control_oracle")  # the bench imports it by name
ring = load("ring_test")


@pytest.fixture(scope="module")
def run():
    """The sweep's tones on the nominal device (the model exact), through its three events: per
    block the channels flagged, and at the lift-off's first read the block's currents and drive."""
    s = scene.load(sweep.SCENE, sweep.overrides({}, calibrated=False))
    rig = build(s)
    (st, ctl, lift), = rig.lifts
    fs, block = s.timing.fs, s.timing.block
    events = [block_of(at, fs, block) for at, _ in sweep.EVENTS]
    first = events[1] + rig.latency  # the lift-off's first block read
    flags, drives, seen = {}, [], None
    for k in range(first + 60):
        rig.apply_schedule(k)
        rig.advance()
        drives.append(rig.out.copy())
        on = np.flatnonzero(lift.state[:, S_FLAG])
        if on.size:
            flags[k] = on.tolist()
        if k == first:
            seen = (rig.sensed.copy(), lift.state.copy(), ctl.state[NREL].copy())
    return rig, lift, ctl, events, first, flags, np.array(drives), seen


def test_a_lift_off_is_flagged_from_its_first_block_read_and_nothing_else_is(run):
    """The low tones' channels are flagged in the first block read after the lift-off; nothing
    before it (the press, event 1, and every steady block under the finger), and what is flagged
    after it is while the finger is off (a later block's ring, read right: the drive already on
    the lifted beam's, so no second release)."""
    rig, lift, ctl, events, first, flags, _, (_, _, released) = run
    assert events[0] < first and first + 60 < events[2]
    assert min(flags) == first
    low = [n for n, (f, b, _) in enumerate(sweep.TONES) if f <= 120]  # 10-120 Hz, the 40/10 Hz pair
    assert set(low) <= set(flags[first])
    # the tones the release rule watches on the flagged channels were released in that block
    watched = [j for j in range(ctl.state.shape[1])
               if ctl.index[OBS_CH, j] in flags[first] and ctl.state[JNOISE, j] >= 0.0]
    assert watched and all(released[j] == 1.0 for j in watched)
    # only channels with a watched tone are tested (a flag elsewhere would be read by no one)
    has_rule = {int(ctl.index[OBS_CH, j]) for j in range(ctl.state.shape[1]) if ctl.state[JNOISE, j] >= 0.0}
    assert has_rule and set(np.flatnonzero(lift.free >= 0)) == has_rule
    assert set().union(*flags.values()) <= has_rule
    assert np.all(ctl.state[NREL] <= 1)  # none released twice (the beat pairs by their estimates since)


def test_the_residuals_are_the_currents_less_each_candidate_s_steady_currents_and_ring(run):
    """Recomputed in numpy for every flagged channel (bench/ring_test.py) from the block's drive
    fitted by least squares at the tones over the 16 blocks it was held: within 1e-6 of the
    kernel's, whose drive is the lock-in's window phasors (a held drive's phasors)."""
    rig, lift, _, _, first, flags, drives, (sensed, state, _) = run
    n_seg, blocks = lift.observer.n_seg, ring.DRIVE_BLOCKS
    kb = first - rig.latency  # the block the currents answer
    for c in flags[first]:
        held = drives[kb - blocks + 1:kb + 1, c]
        expect = ring.residuals(lift, sensed[c * n_seg:(c + 1) * n_seg], held, c, kb)
        np.testing.assert_allclose(state[c, S_LAST + n_seg:], expect, rtol=1e-6)


def test_a_scene_that_needs_no_test_compiles_none():
    """Open loop, or closed loop on tones the release rule does not watch (windows under 8 ms):
    no lift-off stage."""
    open_loop = build(scene.load(sweep.SCENE, [*sweep.overrides({}, calibrated=False), "control.mode=open"]))
    assert not open_loop.lifts and not any(s.name.startswith("lift-off") for s in open_loop.stages)
    high = ((1000, 0, 4.4), (500, 0, 10.5))
    rig = build(scene.load(sweep.SCENE, sweep.overrides({}, high, calibrated=False)))
    assert rig.controllers and not rig.lifts


def test_a_candidate_without_modes_leaves_the_test_out_and_says_so(monkeypatch):
    """Where a candidate's loaded modes cannot be found, the run goes on without the stage (the
    release rule's estimates still tell a lift-off) and the summary's warnings name the cause."""
    from rtctl.errors import ModelError
    from rtctl.selfsense.tmm import TMMBeam

    def fails(self, load, n=4):
        raise ModelError("loaded mode near 631 Hz did not converge")

    monkeypatch.setattr(TMMBeam, "loaded_frequencies", fails)
    rig = build(scene.load(sweep.SCENE, sweep.overrides({}, calibrated=False)))
    assert rig.controllers and not rig.lifts
    assert any("no lift-off test" in w and "did not converge" in w for w in rig.warnings)
