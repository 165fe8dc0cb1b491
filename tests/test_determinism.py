"""Deterministic runs: for every bundled scene two runs give bitwise the same trace (timing
fields aside), and a run checkpointed at a block and resumed from the checkpoint, in the same rig
or in a freshly built one, gives bitwise the blocks a run straight through gives. The compared
blocks are the rig's float64 buffers (drive, readings, true plant states, estimates, targets,
temperatures, probes) and status bits, not the float32 trace: a stricter check."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib import cbook

from rtctl import scene
from rtctl.engine.rig import build
from rtctl.engine.run import run
from rtctl.trace import TraceReader

#: Run length, s; the closed-loop scene's finger events moved inside it (press, lift, return),
#: so a checkpoint falls between them and the resumed run goes through a load switch.
DURATION = 0.3
EARLY_EVENTS = {"line-bimorph-5-closed": ["events.0.at=0.08", "events.1.at=0.15", "events.2.at=0.22"]}
#: Timing fields: how long a block took, when its thread woke; the only fields allowed to differ.
TIMING = ("compute_us", "wake_late_us")

PHOTO = cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)
#: Rendered stimuli keep a position outside the arrays (frame shown, path update): one of each.
RENDERED = {
    "image-beat": ("line-bimorph-5", ["stimulus.kind=image", "stimulus.method=beat", f"stimulus.image={PHOTO}",
                                      "stimulus.voltage=100.0"]),
    "image-frequency": ("solenoid-3x3", ["stimulus.kind=image", "stimulus.method=frequency",
                                         f"stimulus.image={PHOTO}"]),
    "braille-frames": ("sma-8x8", ["stimulus.kind=braille", "stimulus.text=hi", "stimulus.frame_s=0.1"]),
}


def overrides(name):
    return [*EARLY_EVENTS.get(name, []), f"timing.duration={DURATION}"]


def blocks(rig):
    """Everything a block leaves in the rig's buffers, copied."""
    r = [rig.out, rig.sensed, rig.estimated, rig.estimated_amp, rig.targets_um, rig.limiter.temperature]
    if rig.truth is not None:
        r.append(rig.truth)
    r += [dev.probe[row, :rig.block] for _, _, dev, row in rig.probes]
    return [np.array(x) for x in r]


def run_blocks(rig, k0, k1):
    out = []
    for k in range(k0, k1):
        rig.apply_schedule(k)
        status = rig.advance()
        out.append((status, blocks(rig)))
    return out


def assert_same(got, want, k0):
    for i, ((sa, a), (sb, b)) in enumerate(zip(got, want)):
        assert sa == sb, f"block {k0 + i}: status {sa} != {sb}"
        for j, (x, y) in enumerate(zip(a, b)):
            assert np.array_equal(x, y, equal_nan=True), f"block {k0 + i}, buffer {j} differs"
    assert len(got) == len(want)


@pytest.mark.parametrize("name", scene.bundled())
def test_two_runs_give_bitwise_the_same_trace(name, tmp_path):
    sc = scene.load(name, overrides(name))
    for d in ("a", "b"):
        run(sc, tmp_path / d, plot=False)
    a, b = TraceReader(tmp_path / "a" / "trace"), TraceReader(tmp_path / "b" / "trace")
    ra, rb = a.records, b.records
    assert len(ra) == len(rb) >= int(DURATION * sc.timing.fs / sc.timing.block)
    compared = [f for f in ra.dtype.names if f not in TIMING]
    assert "drive" in compared and "sensed" in compared
    for f in compared:
        assert ra[f].tobytes() == rb[f].tobytes(), f"{name}: trace field {f} differs between two runs"


def checkpoint_case(name, over):
    sc = scene.load(name, over)
    a, b = build(sc), build(sc)
    n = int(DURATION * a.fs / a.block)
    k = n // 3 + 7  # not on a render, frame or event boundary by construction
    head = run_blocks(a, 0, k)
    cp = a.checkpoint()
    assert cp.block == k == a.blocks and head
    straight = run_blocks(a, k, n)
    b.restore(cp)  # a rig that never ran, built apart
    assert_same(run_blocks(b, k, n), straight, k)
    a.restore(cp)  # the same rig, rewound after running on
    assert_same(run_blocks(a, k, n), straight, k)


@pytest.mark.parametrize("name", scene.bundled())
def test_a_run_resumed_from_a_checkpoint_is_the_run_straight_through(name):
    checkpoint_case(name, overrides(name))


@pytest.mark.parametrize("case", sorted(RENDERED))
def test_a_rendered_stimulus_resumes_at_its_frame_and_path_position(case):
    name, over = RENDERED[case]
    checkpoint_case(name, [*over, f"timing.duration={DURATION}"])


def test_a_checkpoint_into_an_earlier_one_reuses_its_arrays():
    rig = build(scene.load("line-bimorph-5-closed", overrides("line-bimorph-5-closed")))
    run_blocks(rig, 0, 40)
    cp = rig.checkpoint()
    kept = [id(a) for a in cp.arrays]
    want = run_blocks(rig, 40, 80)
    again = rig.checkpoint(into=cp)
    assert again is cp and [id(a) for a in cp.arrays] == kept and cp.block == 80
    after = run_blocks(rig, 80, 90)
    rig.restore(cp)
    assert_same(run_blocks(rig, 80, 90), after, 80)
    # without the checkpoint, a rig resumed at block 80 from rest plays other blocks
    fresh = build(scene.load("line-bimorph-5-closed", overrides("line-bimorph-5-closed")))
    with pytest.raises(AssertionError):
        assert_same(run_blocks(fresh, 80, 90), after, 80)
    assert want


def test_a_checkpoint_refuses_a_rig_of_another_scene():
    """Another display, and the same display with another tone frequency (the same arrays, so only
    the scene's digest tells them apart): refused, in one line."""
    cp = build(scene.load("line-bimorph-5")).checkpoint()
    for other in (build(scene.load("solenoid-3x3")),
                  build(scene.load("line-bimorph-5", ["stimulus.tones.4.freq=240.0"]))):
        with pytest.raises(ValueError, match="another scene"):
            other.restore(cp)
        with pytest.raises(ValueError, match="another scene"):
            other.checkpoint(into=cp)


def test_a_checkpoint_saved_to_a_file_resumes_a_rig_built_apart(tmp_path):
    over = overrides("line-bimorph-5-closed")
    a = build(scene.load("line-bimorph-5-closed", over))
    run_blocks(a, 0, 130)  # past the press at 0.08 s
    path = a.checkpoint().save(tmp_path / "state.npz")
    want = run_blocks(a, 130, 200)
    b = build(scene.load("line-bimorph-5-closed", over))
    b.restore(type(a.checkpoint()).load(path))
    assert b.blocks == 130
    assert_same(run_blocks(b, 130, 200), want, 130)


def test_a_file_that_is_no_checkpoint_is_refused_in_one_line(tmp_path):
    from rtctl.engine.state import Checkpoint

    bad = tmp_path / "x.npz"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="x.npz: not an rtctl checkpoint") as e:
        Checkpoint.load(bad)
    assert "\n" not in str(e.value)


def test_the_state_covers_what_the_blocks_change():
    """Every array that differs between the rest state and a running rig is in the checkpoint:
    restoring the rest checkpoint after a run puts every stage and device array back."""
    rig = build(scene.load("line-bimorph-5-closed", overrides("line-bimorph-5-closed")))
    rest = rig.checkpoint()
    want = run_blocks(rig, 0, 200)
    rig.restore(rest)
    assert rig.blocks == 0
    assert_same(run_blocks(rig, 0, 200), want, 0)
