"""Scene events: validation and schedule, the bimorph load switch against scipy and a naive twin,
continuity across a switch, no drift over many switches, the device's event API through the
parameter queue, and the other actuator types."""

import naive_switching
import numpy as np
import pytest
from scipy import signal

from rtctl import scene
from rtctl.engine.queue import ParamQueue, drain
from rtctl.errors import SceneError
from rtctl.events import block_of, schedule
from rtctl.io.sim import SimDevice, build_group
from rtctl.models import Models
from rtctl.plant import (
    BUILTIN,
    TRUTH_NAMES,
    Amplifier,
    BeamSpec,
    BimorphPlant,
    CurrentSense,
    Layer,
    MaxwellLoad,
    SimGroup,
    build_fe,
)
from rtctl.plant.bimorph import realization
from rtctl.plant.switching import SwitchedSimGroup, load_map

FS, BLOCK = 48000.0, 32
# Two Maxwell sets of one finger, test data: as rested (the three branches of docs/references.md) and
# pressing harder (stiffer, heavier, two branches).
A = MaxwellLoad(1e-4, 300.0, ((300.0, 0.004), (150.0, 0.07), (80.0, 1.4)))
B = MaxwellLoad(2e-4, 700.0, ((500.0, 0.003), (200.0, 0.05)))
AMP = Amplifier(20e3)
# No noise and a 32-bit ADC: the sensed currents are the anti-aliased currents to 4.7e-12 A.
SENSE = CurrentSense(100.0, 20e3, aa_order=2, bits=32, full_scale_v=1.0, noise_rms_v=0.0)
LSB_A = SENSE.lsb_v / SENSE.shunt_ohm

SCENE = """
[scene]
name = "events"
[timing]
duration = 0.2
[finger]
preload = 0.49
subject = "S"
[[finger.subjects]]
name = "S"
direction = "lateral"
preload = 0.49
mass = 1e-4
k0 = 300.0
branches = [{k = 300.0, tau = 0.004}, {k = 150.0, tau = 0.07}, {k = 80.0, tau = 1.4}]
[[finger.subjects]]
name = "S"
direction = "lateral"
preload = 1.96
mass = 2e-4
k0 = 700.0
branches = [{k = 500.0, tau = 0.003}, {k = 200.0, tau = 0.05}]
[[actuator]]
name = "lat"
type = "bimorph"
grid = [1, 2]
max_voltage = 150.0
[actuator.beam]
length = 15.0e-3
width = 1.5e-3
layers = [{material = "PZT-5A", thickness = 0.3e-3}, {material = "PZT-5A", thickness = 0.3e-3}]
segments = [0.5, 0.5]
[stimulus]
tones = [{channel = 0, freq = 250.0, voltage = 50.0}, {channel = 1, freq = 40.0, voltage = 50.0}]
"""

EVENTS = """
[[events]]
at = 0.02
set = { "finger.preload" = 1.96 }
[[events]]
at = 0.04
set = { finger.contact = false, stimulus.tones.1.target_um = 12 }
[[events]]
at = 0.06
set.finger.contact = true
[[events]]
at = 0.08
set = { "finger.preload" = 0.49 }
"""


def events_scene(text=EVENTS, overrides=()):
    return scene.loads(SCENE + text, list(overrides))


# ---------------------------------------------------------------------------- scene and schedule

def test_schedule_blocks_values_and_scenes_after():
    evs = schedule(events_scene())
    assert [e.block for e in evs] == [30, 60, 90, 120]           # at * 48000 / 32
    assert [e.index for e in evs] == [0, 1, 2, 3]
    # quoted and nested keys read the same; values are the validated ones (2 -> 2.0 stays float)
    assert evs[1].sets == {"finger.contact": False, "stimulus.tones.1.target_um": 12.0}
    assert evs[2].sets == {"finger.contact": True}
    # each scene carries every earlier event, and no events of its own
    after = [(e.scene_after.finger.preload, e.scene_after.finger.contact,
              e.scene_after.stimulus.tones[1].target_um) for e in evs]
    assert after == [(1.96, True, 0.0), (1.96, False, 12.0), (1.96, True, 12.0), (0.49, True, 12.0)]
    assert all(e.scene_after.events == () for e in evs)
    assert schedule(scene.loads(SCENE)) == []


def test_block_quantization():
    # the block that holds the time: at most one block late, never early
    assert block_of(0.0, FS, BLOCK) == 0
    assert block_of(1.0, FS, BLOCK) == 1500
    assert block_of(0.7, FS, BLOCK) == 1050                      # 0.7 * 48000 rounds to 33599.999...
    assert block_of((1500 * 32 - 0.5) / FS, FS, BLOCK) == 1499   # half a sample early: previous block
    assert block_of((1500 * 32 + 31.9) / FS, FS, BLOCK) == 1500


BAD = [
    ('set = { "finger.k0" = 1 }',
     ("events.0.set: 'finger.k0' cannot change during a run (allowed: finger.preload, finger.contact, "
      "finger.subject, stimulus.tones.N.target_um, actuator.NAME.em.preload, actuator.NAME.dot.preload, "
      "actuator.NAME.solenoid.preload)")),
    ('set = { "finger.prelaod" = 1 }', "did you mean 'finger.preload'?"),
    ('set = { "finger.preload" = 25 }', "events.0: finger.preload = 25.0: must be in [0, 20] N"),
    ('set = { "finger.contact" = 1 }', "events.0: finger.contact = 1: must be true or false"),
    ('set = { "stimulus.tones.7.target_um" = 1 }',
     "events.0.set: 'stimulus.tones.7.target_um': stimulus.tones.7: index 7 out of range (have 2 items)"),
    ('set = { "stimulus.tones.1.target_um" = -1 }',
     "events.0: stimulus.tones.1.target_um = -1.0: must be in [0, 100000] um"),
    ('set = { "actuator.lat.em.preload" = 0.1 }',
     "events.0: actuator.lat.em = {'preload': 0.1}: applies to actuator type em, not 'bimorph'"),
    ('set = {}', "events.0.set = {}: an event sets at least one key"),
    ('set = 3', "events.0.set = 3: must be a table"),
    ('set = { "finger.subject" = "T" }', "events.0: finger.subject = 'T' has no lateral set in finger.subjects"),
    # (both spellings pass TOML; one value was dropped, whichever came last held)
    ('set = { "finger.preload" = 1.0, finger = { preload = 2.0 } }',
     "events.0.set.finger.preload = 2.0: set twice in one event (also 1.0)"),
]


@pytest.mark.parametrize("body, message", BAD, ids=[b for b, _ in BAD])
def test_bad_event_refused_in_one_line(body, message):
    with pytest.raises(SceneError) as e:
        schedule(events_scene(f"[[events]]\nat = 0.1\n{body}\n"))
    assert message in str(e.value) and "\n" not in str(e.value)
    assert str(e.value).startswith("<scene>: ")


def test_event_values_checked_as_set_checks_them():
    for key, value in (("finger.preload", "25"), ("finger.contact", "1"), ("stimulus.tones.1.target_um", "-1")):
        with pytest.raises(SceneError) as s:
            scene.loads(SCENE, [f"{key}={value}"])
        with pytest.raises(SceneError) as e:
            events_scene(f"[[events]]\nat = 0.1\nset = {{ \"{key}\" = {value} }}\n")
        # the same message, with the event named between the file and the key
        assert str(e.value) == str(s.value).replace("<scene>: ", "<scene>: events.0: ")


def test_events_in_time_order_and_inside_the_run():
    with pytest.raises(SceneError, match=r"events.1.at = 0.05: events must be in time order "
                                         r"\(events.0 is at 0.1 s\)"):
        events_scene('[[events]]\nat = 0.1\nset.finger.contact = false\n'
                     '[[events]]\nat = 0.05\nset.finger.contact = true\n')
    with pytest.raises(SceneError, match=r"events.0.at = 0.2: after the end of the run \(0.2 s\)"):
        events_scene('[[events]]\nat = 0.2\nset.finger.contact = false\n')
    with pytest.raises(SceneError, match=r"events.0.at = -1.0: must be in \[0, 86400\] s"):
        events_scene('[[events]]\nat = -1.0\nset.finger.contact = false\n')
    # equal times: both, in order, in the same block
    evs = schedule(events_scene('[[events]]\nat = 0.1\nset.finger.contact = false\n'
                                '[[events]]\nat = 0.1\nset.finger.contact = true\n'))
    assert [e.block for e in evs] == [150, 150] and evs[1].scene_after.finger.contact


# ---------------------------------------------------------------------------- the switched plant

@pytest.fixture(scope="module")
def plants():
    pzt = BUILTIN["PZT-5A"]
    fe = build_fe(BeamSpec(15e-3, 1.5e-3, (Layer(pzt, 0.3e-3), Layer(pzt, 0.3e-3)), "parallel",
                           (0.5, 0.5), 0.01))
    return [BimorphPlant(fe, AMP, SENSE, f) for f in (A, None, B)]


@pytest.fixture(scope="module")
def group(plants):
    return SwitchedSimGroup(plants, FS, 2, max_block=BLOCK)


N_BLOCKS = 300
SWITCHES = {60: 1, 120: 2, 180: 0, 240: 1}   # lift, come back harder, back to A, lift


def drive(n_blocks=N_BLOCKS, seed=1):
    """Two channels: 250 Hz + 31 Hz, and 600 Hz plus a white staircase (every DAC step counts)."""
    t = np.arange(n_blocks * BLOCK) / FS
    rng = np.random.default_rng(seed)
    return np.vstack([50 * np.sin(2 * np.pi * 250 * t) + 20 * np.sin(2 * np.pi * 31 * t),
                      30 * np.sin(2 * np.pi * 600 * t) + rng.normal(0.0, 3.0, t.size)])


def run(grp, D, switches):
    """Run ``grp`` block by block; at block k first write ``group.load`` as the parameter queue's
    drain would. Returns truth (channels, 4, samples) and sensed (channels * 2, samples)."""
    grp.reset()
    n = D.shape[1] // BLOCK
    tr = np.zeros((grp.n_channels, 4, n * BLOCK))
    se = np.zeros((grp.n_channels * 2, n * BLOCK))
    truth, sensed = np.zeros((grp.n_channels, 4, BLOCK)), np.zeros((grp.n_channels * 2, BLOCK))
    for k in range(n):
        if k in switches:
            grp.load[0, 0] = switches[k]
        assert grp.process(np.ascontiguousarray(D[:, k * BLOCK:(k + 1) * BLOCK]), sensed, truth) == 0
        tr[:, :, k * BLOCK:(k + 1) * BLOCK] = truth
        se[:, k * BLOCK:(k + 1) * BLOCK] = sensed
    return tr, se


ROWS = list(range(4)) + [4 + 2 + j for j in range(2)]   # truth rows, anti-aliased currents


def lsim_reference(plants, D, switches):
    """scipy's exact zero-order-hold solution, load segment by load segment, the state carried
    across each switch by the plant-coordinate map."""
    out = np.zeros((D.shape[0], len(ROWS), D.shape[1]))
    bounds = [0, *sorted(switches), D.shape[1] // BLOCK]
    loads = [0] + [switches[k] for k in sorted(switches)]
    for ch in range(D.shape[0]):
        cur, x = 0, np.zeros(plants[0].sys.n_states)
        for k0, k1, s in zip(bounds[:-1], bounds[1:], loads):
            if s != cur:
                M, g = load_map(plants[cur], plants[s])
                x, cur = M @ x + g * D[ch, k0 * BLOCK], s
            p = plants[s].sys
            u = D[ch, k0 * BLOCK:k1 * BLOCK]
            t = np.arange(u.size + 1) / FS
            _, y, xs = signal.lsim(signal.StateSpace(p.A, p.B, p.C[ROWS], p.D[ROWS]), np.append(u, u[-1]),
                                   t, X0=x, interp=False)
            out[ch, :, k0 * BLOCK:k1 * BLOCK] = y[:-1].T
            x = xs[-1]
    return out


def rel_err(a, ref):
    """Largest difference relative to the reference's peak (an all-zero reference must be met
    exactly: the force without a finger)."""
    peak = np.max(np.abs(ref))
    return float(np.max(np.abs(a - ref)) / peak) if peak > 0 else (0.0 if not np.any(a) else np.inf)


def test_switch_matches_scipy_zoh_reference(plants, group):
    D = drive()
    tr, se = run(group, D, SWITCHES)
    ref = lsim_reference(plants, D, SWITCHES)
    # The budget: what each load's own realization (a SimGroup, no switching) already differs
    # from scipy by on this drive; the maps may not add to it (measured: switched 7.5e-11, the
    # worst load alone 7.5e-11, the finger set B's modal basis at condition 511).
    own = 0.0
    for p in plants:
        t_own, _ = run(SimGroup(p, FS, 2, max_block=BLOCK), D, {})
        r_own = lsim_reference([p], D, {})
        own = max(own, *(rel_err(t_own[:, r], r_own[:, r]) for r in range(3)))
    assert own < 1e-9
    for r in range(4):
        assert rel_err(tr[:, r], ref[:, r]) <= 3.0 * own, TRUTH_NAMES[r]
    # sensed currents: the reference's anti-aliased currents through an ideal 32-bit ADC
    for ch in range(2):
        for j in range(2):
            err = np.max(np.abs(se[ch * 2 + j] - ref[ch, 4 + j]))
            assert err <= 0.5 * LSB_A + 3.0 * own * np.max(np.abs(ref[:, 4 + j]))


def test_switch_matches_naive_twin(plants, group):
    D = drive(120)
    switches = {30: 1, 60: 2, 90: 0}
    tr, _ = run(group, D, switches)
    per_block = [0] * 120
    for k, s in sorted(switches.items()):
        per_block[k:] = [s] * (120 - k)
    sysds = [realization(p, FS)[0] for p in plants]
    twin = naive_switching.switched_run(sysds, group.maps, per_block, D, BLOCK)
    for r in range(4):
        assert rel_err(tr[:, r], twin[:, r]) < 1e-9, TRUTH_NAMES[r]


def test_until_the_first_switch_bitwise_a_simgroup(plants, group):
    D = drive(100)
    plain, _ = run(SimGroup(plants[0], FS, 2, max_block=BLOCK), D, {})
    tr, _ = run(group, D, {50: 2})
    assert np.array_equal(tr[:, :, :50 * BLOCK], plain[:, :, :50 * BLOCK])
    never, _ = run(group, D, {})
    assert np.array_equal(never, plain)
    # a load index that is not one is ignored (NaN, out of range)
    odd, _ = run(group, D, {10: np.nan, 20: 7.0, 30: -1.0})
    assert np.array_equal(odd, plain)


def test_tip_continuous_force_switches(plants, group):
    D = drive()
    tr, _ = run(group, D, SWITCHES)
    keys = sorted(SWITCHES)
    for i, k in enumerate(keys):
        # the same run without this switch (and the later ones) continues the old load
        cont, _ = run(group, D, {kk: SWITCHES[kk] for kk in keys[:i]})
        j = k * BLOCK
        assert np.array_equal(tr[:, :, :j], cont[:, :, :j])
        for r in (0, 1):   # displacement, velocity at the switch sample: continuous to rounding
            scale = np.max(np.abs(cont[:, r]))
            assert np.max(np.abs(tr[:, r, j] - cont[:, r, j])) < 1e-13 * scale, TRUTH_NAMES[r]
            # (a sample-to-sample step is ~1e-2 of the peak here: continuity is not vacuous)
            assert np.min(np.abs(cont[:, r, j] - cont[:, r, j - 1])) > 1e-5 * scale
    # lifted (blocks 60-119 and from 240): no force on the finger from the first sample on
    assert np.all(tr[:, 2, 60 * BLOCK:120 * BLOCK] == 0.0) and np.all(tr[:, 2, 240 * BLOCK:] == 0.0)
    assert np.all(tr[:, 2, 60 * BLOCK - 1] != 0.0)
    # back (block 120, set B): the branches come back relaxed, only k0 x acts
    j = 120 * BLOCK
    np.testing.assert_allclose(tr[:, 2, j], B.k0 * tr[:, 0, j], rtol=1e-11)


def test_load_map_is_its_definition(plants):
    pa, pn, pb = plants
    nr = pa.n_modes
    M, g = load_map(pa, pa)
    np.testing.assert_allclose(M, np.eye(M.shape[0]), atol=1e-12)
    assert not np.any(g)
    rng = np.random.default_rng(2)
    for src, dst in ((pa, pn), (pn, pb), (pa, pb), (pb, pa)):
        M, g = load_map(src, dst)
        x = rng.normal(size=src.sys.n_states)
        u = rng.normal()
        V = x[src.sys.state_names.index("voltage_v")]
        y = src.mode_shapes @ x[:nr] + (src.static_correction - dst.static_correction) * V
        # closed form: the M_dst-weighted least-squares fit with the tip DOF held, from its KKT system
        phi, Md, tip = dst.mode_shapes, dst.mass_matrix, dst.tip
        kkt = np.zeros((nr + 1, nr + 1))
        kkt[:nr, :nr] = phi.T @ Md @ phi
        kkt[:nr, nr] = kkt[nr, :nr] = phi[tip]
        eta = np.linalg.solve(kkt, np.append(phi.T @ Md @ y, y[tip]))[:nr]
        xd = M @ x + g * u
        np.testing.assert_allclose(xd[:nr], eta, rtol=1e-9, atol=1e-12 * np.max(np.abs(eta)))
        # the outputs the trace shows: tip displacement and velocity the same in both loads
        for r in (0, 1):
            before = src.sys.C[r] @ x + src.sys.D[r, 0] * u
            after = dst.sys.C[r] @ xd + dst.sys.D[r, 0] * u
            assert abs(after - before) < 1e-12 * max(abs(before), 1e-30)
        # branches: carried by index while the finger stays, else 0; voltage and filters as they were
        i_f, j_f = 2 * nr, 2 * nr
        carried = min(src.n_branches, dst.n_branches) if (src.finger and dst.finger) else 0
        np.testing.assert_array_equal(xd[j_f:j_f + carried], x[i_f:i_f + carried])
        assert not np.any(xd[j_f + carried:j_f + dst.n_branches])
        np.testing.assert_array_equal(xd[j_f + dst.n_branches:], x[i_f + src.n_branches:])


def test_many_switches_do_not_drift(plants, group):
    """200-odd switches among the three loads at random block boundaries, ending on A; then the
    run must converge to one that never switched: the tone phasors (fitted with an offset and a
    drift, which the 1.4 s branch's leftover force makes) agree ever closer, and the remaining
    difference (that branch's slow decay) shrinks window after window."""
    rng = np.random.default_rng(5)
    at = 20 + np.cumsum(rng.integers(3, 14, 201))
    switches = {int(k): [1, 2, 0][i % 3] for i, k in enumerate(at)}
    last = int(at[-1])
    assert switches[last] == 0
    n = last + 1500
    t = np.arange(n * BLOCK) / FS
    D = np.vstack([50 * np.sin(2 * np.pi * 250 * t), 50 * np.sin(2 * np.pi * 40 * t)])
    sw, _ = run(group, D, switches)
    never, _ = run(group, D, {})
    assert np.all(np.isfinite(sw))

    def phasor(y, f, sl):
        tt = t[sl]
        X = np.column_stack([np.sin(2 * np.pi * f * tt), np.cos(2 * np.pi * f * tt), np.ones_like(tt), tt - tt[0]])
        c = np.linalg.lstsq(X, y[sl], rcond=None)[0]
        return c[0] + 1j * c[1]

    t0 = last * BLOCK
    windows = [slice(t0 + int(a * FS), t0 + int((a + 0.1) * FS)) for a in (0.1, 0.3, 0.5, 0.75)]
    for ch, f in ((0, 250.0), (1, 40.0)):
        d = [abs(phasor(sw[ch, 0], f, w) - phasor(never[ch, 0], f, w)) / abs(phasor(never[ch, 0], f, w))
             for w in windows]
        peak = [np.max(np.abs(sw[ch, 0, w] - never[ch, 0, w])) for w in windows]
        # measured: 250 Hz 1.7e-5 .. 7.9e-9, 40 Hz 8.4e-5 .. 5.3e-7; peak difference 5 % .. 2 % of the tip
        assert all(b < a for a, b in zip(d, d[1:])) and d[-1] < 1e-5, d
        assert all(b < a for a, b in zip(peak, peak[1:])), peak


# ---------------------------------------------------------------------------- the device's event API

def device_of(s):
    models = Models(s)
    groups, ch0, row0 = [], 0, 0
    for gi, g in enumerate(s.actuator):
        sim = build_group(models, g, gi, s.timing.fs, s.timing.block)
        n = g.grid[0] * g.grid[1]
        groups.append((sim, slice(ch0, ch0 + n), slice(row0, row0 + n * sim.n_sensed)))
        ch0, row0 = ch0 + n, row0 + n * sim.n_sensed
    out = np.zeros((ch0, s.timing.block))
    return SimDevice(groups, out, np.zeros((row0, s.timing.block)), len(TRUTH_NAMES)), out


def device_run(dev, out, D, evs, queue=None):
    """Blocks through the device; each event's posts written at its block, either directly or
    through a parameter queue and its drain (what the engine's block function runs first)."""
    dev.reset()
    if queue is not None:
        queue.reset()
    n = D.shape[1] // BLOCK
    tip = np.zeros((out.shape[0], n * BLOCK))
    for k in range(n):
        for e in evs:
            if e.block == k:
                for arr, r, c, v in dev.event_posts(e):
                    if queue is None:
                        arr[r, c] = v
                    else:
                        queue.post(queue.target_id(arr), r, c, v)
        if queue is not None:
            queue.publish()
            drain(*queue.args)
        out[...] = D[:, k * BLOCK:(k + 1) * BLOCK]
        assert dev.write() == 0
        tip[:, k * BLOCK:(k + 1) * BLOCK] = dev.truth[:, 0]
    return tip


def test_device_event_api_through_the_parameter_queue():
    s = events_scene()
    evs = schedule(s)
    dev, out = device_of(s)
    grp = dev.groups[0][0]
    assert isinstance(grp, SwitchedSimGroup)
    assert grp.loads == (A, B, None)          # in the order the scene visits them
    targets = dev.event_targets()
    assert len(targets) == 1 and targets[0] is grp.load and targets[0].shape == (1, 1)
    # what each event posts: the index of the group's load after it
    assert [[(a is grp.load, r, c, v) for a, r, c, v in dev.event_posts(e)] for e in evs] == \
        [[(True, 0, 0, 1.0)], [(True, 0, 0, 2.0)], [(True, 0, 0, 1.0)], [(True, 0, 0, 0.0)]]
    D = drive(160)
    direct = device_run(dev, out, D, evs)
    queued = device_run(dev, out, D, evs, ParamQueue(targets))
    np.testing.assert_array_equal(queued, direct)
    assert grp.load[0, 0] == 0.0 and grp.active[0] == 0      # the last event went back to A
    dev.reset()
    assert grp.load[0, 0] == 0.0 and not np.any(grp.state)
    # against the group driven by hand with the same loads at the same blocks
    hand, _ = run(grp, D, {30: 1, 60: 2, 90: 1, 120: 0})
    np.testing.assert_array_equal(direct, hand[:, 0])


def test_events_that_change_no_load_keep_the_plain_group():
    # no subjects: one finger table for every preload, so a preload change is nothing for a bimorph
    plain = SCENE.replace('subject = "S"', 'subject = ""')
    s = scene.loads(plain + '[[events]]\nat = 0.1\nset = { "finger.preload" = 1.96, '
                    '"stimulus.tones.0.target_um" = 3.0 }\n')
    dev, _ = device_of(s)
    assert type(dev.groups[0][0]) is SimGroup and dev.groups[0][0].events is None
    assert dev.event_targets() == [] and dev.event_posts(schedule(s)[0]) == []
    dev, _ = device_of(scene.loads(SCENE))
    assert type(dev.groups[0][0]) is SimGroup


def test_pins_and_plates():
    def with_events(name, body, over=()):
        text = (scene.resolve(name)).read_text() + f"\n[[events]]\nat = 0.01\nset = {body}\n"
        return scene.loads(text, list(over))

    # a load change on a plant that cannot switch: refused in one line, naming group, type and event
    with pytest.raises(SceneError, match=r"actuator.pins: events.0 \(finger.contact\) changes the finger "
                                         r"load on this 'solenoid' group, whose simulated plant cannot "
                                         r"switch loads during a run .*actuator.pins.solenoid.preload"):
        device_of(with_events("solenoid-3x3", '{ "finger.contact" = false }'))
    with pytest.raises(SceneError, match=r"actuator.cells: events.0 \(finger.contact\) .* 'pvdf' group"):
        device_of(with_events("pvdf-6x8", '{ "finger.contact" = false }', ["finger.contact=true"]))

    # PVDF: the finger's static force is an offset of the finger cell's force, from the event's block on
    over = ["finger.contact=true", "timing.duration=0.05"]
    s = with_events("pvdf-6x8", '{ "finger.preload" = 1.0 }', over)
    dev, out = device_of(s)
    evs = schedule(s)
    (arr, r, c, v), = dev.event_posts(evs[0])
    assert arr is dev.event_targets()[0] and (r, c, v) == (0, 1, 1.0)
    D = np.zeros((out.shape[0], 30 * BLOCK))
    D[:, :] = 100.0 * np.sin(2 * np.pi * 100.0 * np.arange(30 * BLOCK) / FS)
    fch = dev.groups[0][0].args[0][1]

    def forces(evs):
        dev.reset()
        f = np.zeros((out.shape[0], 30 * BLOCK))
        for k in range(30):
            for e in evs:
                if e.block == k:
                    for a, rr, cc, vv in dev.event_posts(e):
                        a[rr, cc] = vv
            out[...] = D[:, k * BLOCK:(k + 1) * BLOCK]
            dev.write()
            f[:, k * BLOCK:(k + 1) * BLOCK] = dev.truth[:, 2]
        return f

    f1, f0 = forces(evs), forces([])
    j = evs[0].block * BLOCK
    assert evs[0].block == 15
    np.testing.assert_array_equal(f1[:, :j], f0[:, :j])
    np.testing.assert_allclose(f1[fch, j:] - f0[fch, j:], 1.0 - 0.49, rtol=1e-12)
    np.testing.assert_array_equal(np.delete(f1, fch, axis=0), np.delete(f0, fch, axis=0))


def test_em_pin_preload_settles_where_statics_put_it():
    """A pin preload event on the bimodal display's EM pins: with a pure-spring finger the pin
    settles where the statics of pin, penalty contact and skin put it,
    ``F_c = F_p / (1 + k0 / k + k0 / k_c)``, ``x = -F_c / k``."""
    text = scene.resolve("bimodal-4x4").read_text()
    s = scene.loads(text + '\n[[events]]\nat = 0.01\nset = { "actuator.normal.em.preload" = 0.06 }\n',
                    ["finger.normal.branches=[]", "timing.duration=0.6"])
    models = Models(s)
    g = s.group("normal")
    grp = build_group(models, g, 0, FS, BLOCK)
    ev, = schedule(s)
    posts = [w for w in grp.events.writes[ev.index]]
    assert len(posts) == 16 and all(a is grp.params and c == 0 and v == 0.06 for a, _, c, v in posts)
    plant = models.em(g)
    k, k0, kc = plant.stiffness, plant.finger.k0, plant.skin.k_contact
    n = int(0.6 * FS / BLOCK)
    truth, sensed = np.zeros((16, 4, BLOCK)), np.zeros((16, BLOCK))   # one coil current per pin
    zero = np.zeros((16, BLOCK))
    heights = []
    for blk in range(n):
        if blk == ev.block:
            for a, r, c, v in posts:
                a[r, c] = v
        grp.process(zero, sensed, truth)
        if blk in (ev.block - 1, n - 1):
            heights.append(truth[:, 0, -1].copy())
    for h, fp in zip(heights, (0.03, 0.06)):
        x = -fp / (1.0 + k0 / k + k0 / kc) / k
        np.testing.assert_allclose(h, x, rtol=1e-6)
