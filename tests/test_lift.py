"""The lift-off test (rtctl/selfsense/lift.py): in a closed-loop run through a press, a lift-off
and a landing, it flags the low tones' channels in the first block read after the lift-off and
in no other block, and in the first block read after the landing puts every channel on a finger's
candidate, in no other block; its residuals are the currents' less each candidate's steady
currents and ring, recomputed here from the block's own drive by least squares (not from the
lock-in's phasors); and a scene that needs no such test compiles none."""

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

#: blocks run past the landing's first read
AFTER = 60


@pytest.fixture(scope="module")
def run():
    """The sweep's tones on the nominal device (the model exact), through its three events: per
    block the channels flagged (lift-offs, landings) and each channel's candidate, and at the
    lift-off's and the landing's first read the block's currents and the test's state."""
    s = scene.load(sweep.SCENE, sweep.overrides({}, calibrated=False))
    rig = build(s)
    (st, ctl, lift), = rig.lifts
    fs, block = s.timing.fs, s.timing.block
    events = [block_of(at, fs, block) for at, _ in sweep.EVENTS]
    first, land = (events[i] + rig.latency for i in (1, 2))  # the lift-off's and landing's first reads
    flags, lands, picks, drives, seen = {}, {}, [], [], {}
    for k in range(land + AFTER):
        rig.apply_schedule(k)
        rig.advance()
        drives.append(rig.out.copy())
        picks.append(st.observer.pick.copy())
        for d, sign in ((flags, 1.0), (lands, -1.0)):
            on = np.flatnonzero(lift.state[:, S_FLAG] == sign)
            if on.size:
                d[k] = on.tolist()
        if k in (first, land):
            seen[k] = (rig.sensed.copy(), lift.state.copy(), ctl.state[NREL].copy())
    return rig, lift, ctl, events, first, land, flags, lands, np.array(picks), np.array(drives), seen


def test_a_lift_off_is_flagged_from_its_first_block_read_and_nothing_else_is(run):
    """The low tones' channels are flagged in the first block read after the lift-off; nothing
    before it (the press, event 1, and every steady block under the finger), and what is flagged
    after it is while the finger is off (a later block's ring, read right: the drive already on
    the lifted beam's, so no second release)."""
    rig, lift, ctl, events, first, land, flags, _, _, _, seen = run
    released = seen[first][2]
    assert events[0] < first and first + AFTER < events[2]
    assert min(flags) == first and max(flags) < events[2]
    low = [n for n, (f, b, _) in enumerate(sweep.TONES) if f <= 120]  # 10-120 Hz, the 40/10 Hz pair
    assert set(low) <= set(flags[first])
    # the tones the release rule watches on the flagged channels were released in that block
    watched = [j for j in range(ctl.state.shape[1])
               if ctl.index[OBS_CH, j] in flags[first] and ctl.state[JNOISE, j] >= 0.0]
    assert watched and all(released[j] == 1.0 for j in watched)
    # every controlled channel is tested for a landing, and for a lift-off those with a watched
    # tone (elsewhere the flag would be read by no one)
    assert set(np.flatnonzero(lift.free >= 0)) == set(ctl.index[OBS_CH].tolist())
    has_rule = {int(ctl.index[OBS_CH, j]) for j in range(ctl.state.shape[1]) if ctl.state[JNOISE, j] >= 0.0}
    assert has_rule and set(np.flatnonzero(lift.watch)) == has_rule
    assert set().union(*flags.values()) <= has_rule
    assert np.all(ctl.state[NREL] <= 1)  # none released twice (the beat pairs by their estimates since)


def test_a_landing_puts_the_channels_on_a_finger_from_its_first_block_read(run):
    """In the first block read after the finger lands, every channel that read through the free
    tip's candidate reads through a finger's (its matrices those of the finger whose residual is
    least, by 1.3 times in rms), where the observer's own votes took up to half a window; no
    landing anywhere else (not while the finger is off, ringing after the drop, nor under it);
    and the votes do not take it back over the blocks after."""
    rig, lift, ctl, events, first, land, _, lands, picks, _, seen = run
    obs = lift.observer
    free = [q for q, x in enumerate(obs.image_loads) if x is None][0]
    before = picks[land - 1]
    was_free = set(np.flatnonzero(before == free))
    assert was_free  # (where the images tell the loads apart, the votes had put the channel on the free tip)
    assert list(lands) == [land] and set(lands[land]) == was_free
    state = seen[land][1]
    n_seg = obs.n_seg
    for c in was_free:
        e = state[c, S_LAST + n_seg:]
        fingers = [q for q in range(e.size) if q != free]
        best = min(fingers, key=lambda q: e[q])
        assert picks[land, c] == best and e[best] * 1.3**2 < e[free]
        assert np.array_equal(obs.H[c], obs.Hc[c, :, picks[-1][c]])
        assert np.all(picks[land:, c] != free)


def test_the_residuals_are_the_currents_less_each_candidate_s_steady_currents_and_ring(run):
    """Recomputed in numpy for every channel flagged at the lift-off and the landing
    (bench/ring_test.py) from the block's drive fitted by least squares at the tones over the 16
    blocks it was held: within 1e-6 of the kernel's, whose drive is the lock-in's window phasors
    (a held drive's phasors)."""
    rig, lift, _, _, first, land, flags, lands, _, drives, seen = run
    n_seg, blocks = lift.observer.n_seg, ring.DRIVE_BLOCKS
    for k, channels in ((first, flags[first]), (land, lands[land])):
        sensed, state, _ = seen[k]
        kb = k - rig.latency  # the block the currents answer
        for c in channels:
            held = drives[kb - blocks + 1:kb + 1, c]
            expect = ring.residuals(lift, sensed[c * n_seg:(c + 1) * n_seg], held, c, kb)
            np.testing.assert_allclose(state[c, S_LAST + n_seg:], expect, rtol=1e-6)


def test_a_scene_that_needs_no_test_compiles_none():
    """Open loop: no lift-off stage. Closed loop on tones the release rule does not watch
    (windows under 8 ms): the stage, for a landing only."""
    open_loop = build(scene.load(sweep.SCENE, [*sweep.overrides({}, calibrated=False), "control.mode=open"]))
    assert not open_loop.lifts and not any(s.name.startswith("contact") for s in open_loop.stages)
    high = ((1000, 0, 4.4), (500, 0, 10.5))
    rig = build(scene.load(sweep.SCENE, sweep.overrides({}, high, calibrated=False)))
    (_, ctl, lift), = rig.lifts
    assert np.all(ctl.state[JNOISE] < 0.0) and set(np.flatnonzero(lift.free >= 0)) == {0, 1}
    assert not lift.watch.any()  # (no lift-off looked for: no tone has the release rule)


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


def _synthetic(n_q=2, free=1, block=16):
    """One channel, one tone (a cosine of 1/16 turn per sample, 1 V), one segment, the finger's
    candidate 0 and the free tip's 1 with their own segment readings per volt (1 and 2 uA/V) and
    one ring column each (the finger's a sine of 3/16 turn per sample, the free tip's a level):
    the stage's arguments, and a function giving the currents of a device that reads ``y`` per
    volt and rings the finger's column by ``ring`` A."""
    from rtctl.dsp import _kernels as dk

    th = 2 * np.pi / 16
    u_ref = np.zeros((4, 1))
    u_ref[[dk.ZR, dk.WR, dk.WI], 0] = 1.0, np.cos(th), np.sin(th)
    u_acc = np.zeros((dk.N_ACC, 1))
    u_acc[dk.X_R, 0] = 1.0
    ly = np.zeros((1, 1, n_q, 1, 2))
    ly[0, 0, :, 0, 0] = [1e-6, 2e-6]  # A per V: the finger's candidate, the free tip's
    m = np.arange(block)
    lq = np.zeros((n_q, block, 1))
    lq[0, :, 0] = np.sin(3 * th * m) / np.sqrt(block / 2)
    lq[1, :, 0] = 1.0 / np.sqrt(block)
    H = np.zeros((1, 1, 2, 2, 2))
    Hc = np.stack([np.full((1, 1, 2, 2, 2), q + 1.0) for q in range(n_q)], axis=2)  # (c, k, q, e, j, 2)
    drive = np.cos(th * m)[None]
    args = dict(u_ref=u_ref, u_acc=u_acc, pf_g=np.array([[[1.0, 0.0]]]), scale=np.ones(1),
                pick=np.array([free]), H=H, Hc=Hc, resid=np.zeros((1, 3, n_q)), free=np.array([free]),
                watch=np.ones(1, dtype=np.int64), ly=ly, lq=lq, lz=np.zeros((1, block, 2)), lr=np.zeros(block),
                state=np.zeros((1, S_LAST + 1 + n_q)), delay=drive[None], head=np.zeros(1, dtype=np.int64),
                c_index=np.zeros((5, 1), dtype=np.int64), c_state=np.zeros((90, 1)), lifted_row=0, c0=0)
    return args, lambda y, ring=0.0: y * drive + ring * lq[0, :, 0]


def test_a_landing_is_a_change_the_free_tip_no_longer_explains_not_a_steady_misfit():
    """Where the free tip is in use, a steady block that a finger's candidate explains better
    (the calibrated free tip off the device by more than the noise) is no landing however long it
    lasts; a block the free tip explains many times worse than the one before, and a finger well,
    is one: the channel reads through the finger's candidate from there. A block whose drive is
    not the window's is not tested for a landing."""
    from rtctl.selfsense.lift import LAND_JUMP, LIFT_RATIO, lift_stage

    args, device = _synthetic()
    # a lifted device that reads 1.4 uA/V: the finger's candidate (1) fits it better than the
    # free tip's (2), by more than the verdict's ratio
    assert (2.0 - 1.4) ** 2 > LIFT_RATIO**2 * (1.4 - 1.0) ** 2
    for _ in range(5):
        lift_stage(**args, sensed=device(1.4e-6))
        assert args["state"][0, S_FLAG] == 0.0 and args["pick"][0] == 1
    # a block whose drive is 0.5 % off the window's phasors (a correction ramped in) is not
    # tested, whatever its currents; nor is the block after it (no level yet to jump from)
    held = args["delay"].copy()
    args["delay"][:] = 1.005 * held
    lift_stage(**args, sensed=device(1.0e-6, 20e-6))
    args["delay"][:] = held
    lift_stage(**args, sensed=device(1.4e-6))
    assert args["state"][0, S_FLAG] == 0.0 and args["pick"][0] == 1
    # the finger lands: the device reads 1 uA/V and rings the finger's mode
    lift_stage(**args, sensed=device(1.0e-6, 20e-6))
    assert args["state"][0, S_LAST + 1 + 1] > LAND_JUMP * 0.6e-6**2 * 8  # (the free tip's residual jumped)
    assert args["state"][0, S_FLAG] == -1.0 and args["pick"][0] == 0
    assert np.array_equal(args["H"][0], args["Hc"][0, :, 0])
    assert args["resid"][0, 0].tolist() == [0.0, 1.0]  # (the votes must go against it to take it back)
    assert args["c_state"][0, 0] == 0.0  # (no lift-off for the release rule)
