"""The spatializer: each channel's gain against the roll-off laws worked by hand, on a 1x5 line
and a 5x5 array, played as levels through the oscillator bank."""

import copy
import math

import numpy as np
import pytest
from test_signals import render

from rtctl import scene
from rtctl.errors import SceneError
from rtctl.spatial import rolloff
from rtctl.stimulus import Stimulus

LEVEL = 'signals = [{name = "one", type = "dc", amp = 1.0}]\nplay = [{signal = "one", spatial = "s"}]\n'


def spatial(**keys):
    body = "\n".join(f"{k} = {v}" for k, v in keys.items())
    return LEVEL + f'[[stimulus.spatial]]\nname = "s"\n{body}\n'


def steady(stim, **kw):
    out, _ = render(stim, duration=0.05, **kw)
    return out[:, -1]  # after the 20 ms fade-in


@pytest.mark.parametrize("law, table, g2, g3", [
    ("linear", "[]", 0.7, 0.3),
    ("smoothstep", "[]", 0.7**2 * (3 - 1.4), 0.3**2 * (3 - 0.6)),  # u^2 (3 - 2u)
    ("log", "[]", (10**-0.9 - 1e-3) / (1 - 1e-3), (10**-2.1 - 1e-3) / (1 - 1e-3)),  # -60 dB * d / r, shifted to 0
    ("table", "[1.0, 0.8, 0.0]", 1 - 0.2 * 0.3 / 0.5, 0.8 * (1 - 0.2 / 0.5)),  # at d / r = 0.3 and 0.7
])
def test_a_source_between_two_channels_of_a_line_shares_them_by_the_law(law, table, g2, g3):
    g = steady(spatial(rolloff=f'"{law}"', table=table, radius=1.0, x="[2.3]", y="[0.0]"))
    np.testing.assert_allclose(g, [0, 0, g2, g3, 0], rtol=0, atol=1e-12)


def test_positions_in_metres_with_the_grid_pitch_give_the_same_gains():
    g = steady(spatial(radius=1.9e-3, x=f"[{2.3 * 1.9e-3}]", y="[0.0]", pitch="[1.9e-3, 1.58e-3]"))
    np.testing.assert_allclose(g, [0, 0, 0.7, 0.3, 0], rtol=0, atol=1e-12)


ARRAY = scene.resolve("array-bimorph-5x5").read_text().split("[stimulus]")[0]


def test_on_a_5x5_array_the_gain_falls_with_distance_in_both_directions():
    s = scene.loads(ARRAY + '[stimulus]\nkind = "tones"\n' + spatial(radius=1.5, x="[1.5]", y="[2.0]"),
                    ["timing.duration=0.05"])
    st = Stimulus(s, {"array": 0}, 25, 48000.0, 32)
    g = np.zeros(25)
    for v, _, _ in st.voices:
        g[v.channel] = v.amp[-1]
    near, diag = 1 - 0.5 / 1.5, 1 - math.hypot(0.5, 1.0) / 1.5
    want = np.zeros((5, 5))
    want[2, 1] = want[2, 2] = near  # d = 0.5
    want[1, 1] = want[1, 2] = want[3, 1] = want[3, 2] = diag  # d = 1.118
    np.testing.assert_allclose(g.reshape(5, 5), want, rtol=0, atol=1e-12)  # d = 1.5 and beyond: 0


def test_a_moving_source_gives_the_law_at_every_update():
    """x from 0 to 4 over 0.1 s along a 1x5 line; gains every 1 / 400 s (120 samples), straight
    lines between: at each update the output is the law at the source's position then."""
    out, _ = render(spatial(radius=1.0, times="[0.0, 0.1]", x="[0.0, 4.0]", y="[0.0, 0.0]", rate=400.0)
                    + "\n", duration=0.12, overrides=["stimulus.ramp=0.0001"])
    for x in range(120, 4800, 120):  # sample m carries the value at x = m + 1
        src = 4.0 * x / 4800
        want = np.clip(1 - np.abs(np.arange(5) - src), 0, None)
        np.testing.assert_allclose(out[:, x - 1], want, rtol=0, atol=1e-9)


def test_the_seed_array_scene_pans_a_phantom_between_neighbours():
    """array-bimorph-5x5: the source is halfway between columns 2 and 3 of the middle row at
    0.1 + 0.8 * 2.5 / 4 = 0.6 s: channels 12 and 13 each play half the burst's 40 V."""
    s = scene.load("array-bimorph-5x5")
    st = Stimulus(s, {"array": 0}, 25, 48000.0, 32)
    x = 0.6 * 48000
    amp = {v.channel: float(np.interp(x, v.x, v.amp)) for v, _, _ in st.voices}
    assert amp[12] == pytest.approx(20.0, abs=1e-9) and amp[13] == pytest.approx(20.0, abs=1e-9)
    assert all(a == 0.0 for c, a in amp.items() if c not in (12, 13))
    assert set(amp) == {10, 11, 12, 13, 14}  # only the middle row ever sounds


def test_rolloff_laws_reach_1_at_the_source_and_0_at_the_radius():
    for law, tab in (("linear", ()), ("smoothstep", ()), ("log", ()), ("table", (1.0, 0.3, 0.0))):
        np.testing.assert_allclose(rolloff(law, [0.0, 2.0, 3.0], 2.0, tab), [1.0, 0.0, 0.0], atol=1e-15)


@pytest.mark.parametrize("keys, words", [
    (dict(times="[0.0, 1.0]", x="[0.0]", y="[0.0]"), "same number"),
    (dict(times="[1.0, 0.0]", x="[0.0, 1.0]", y="[0.0, 0.0]"), "time order"),
    (dict(rolloff='"table"', table="[1.0]"), "at least 2"),
    (dict(radius=0.0), "radius"),
    (dict(pitch="[1.9e-3, 0.0]"), "both pitches"),
])
def test_bad_spatial_tables_are_refused_in_one_line(keys, words):
    with pytest.raises(SceneError) as e:
        render(spatial(**keys), duration=0.05)
    assert words in str(e.value) and "\n" not in str(e.value)


def test_the_block_functions_played_schedule_writes_what_one_set_per_entry_writes():
    # the rig hands the played signals' schedule to a stage of the block function
    # (osc_schedule): block by block from block 0, it must leave the bank's pending parameters
    # as OscillatorBank.set of every entry in order does
    from rtctl.dsp._kernels import osc_schedule

    s = scene.load("array-bimorph-5x5")
    st = Stimulus(s, {"array": 0}, 25, 48000.0, 32)
    twin = copy.deepcopy(st.bank)
    pending = st.bank.pending
    last = max(st._sig_schedule)
    repeated = 0
    for k in range(last + 3):
        assert osc_schedule(*st.played.args, pending) == 0
        items = st._sig_schedule.get(k, ())
        repeated += len(items) - len({i for i, *_ in items})
        for i, f, amp, r in items:
            twin.set(i, freq=f, amp=amp, ramp=r)
        np.testing.assert_array_equal(pending, twin.pending)
    assert list(st.played.pos) == [last + 3, len(st._sig_schedule)]
    assert len(st._sig_schedule) > 100 and repeated > 0  # some blocks set a tone twice: the last wins
    st.reset()
    assert list(st.played.pos) == [0, 0]


def test_a_rig_with_played_signals_needs_python_at_none_of_their_blocks():
    from rtctl.engine.rig import build

    rig = build(scene.load("array-bimorph-5x5"))
    assert rig.stimulus.played_in_block and rig.next_busy(0) > 1 << 40
    assert [s.name for s in rig.stages][:2] == ["played signals", "params"]
