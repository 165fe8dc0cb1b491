"""PulseTrain: exact twin, chunk invariance, edges, phase continuity, level mode."""

import naive_dsp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rtctl.dsp import PulseTrain, pulse_process

FS = 48000.0


def run(train, n, splits=(), schedule=None):
    schedule = schedule or {}
    cuts = sorted({0, n, *splits, *schedule})
    blocks = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        for c, kw in schedule.get(a, ()):
            train.set(c, **kw)
        out = np.zeros((train.n_channels, b - a))
        train.process(out)
        blocks.append(out)
    return np.concatenate(blocks, axis=1)


def rising_edges(y, high):
    on = y == high
    return np.flatnonzero(on[1:] & ~on[:-1]) + 1


def test_matches_naive_twin_exactly():
    """The DDS position is exact integer arithmetic in float64, so the twin's rational
    arithmetic on the same frequency grid must agree sample for sample (no tolerance)."""
    rng = np.random.default_rng(4)
    n = 4000
    freqs = rng.uniform(0, 3000, 3)
    duty = rng.uniform(0, 1, 3)
    phase = rng.uniform(0, 1, 3)
    sched = {700: [(1, dict(freq=1234.5, duty=0.1))],
             2100: [(0, dict(freq=0.0)), (2, dict(high=3.0, low=-1.0))],
             3000: [(0, dict(freq=77.7))]}
    train = PulseTrain(3, FS, freqs, duty, 1.0, 0.0, phase)
    got = run(train, n, splits=range(0, n, 251), schedule=sched)
    for c in range(3):
        per_ch = {j: dict(kw) for j, changes in sched.items() for cc, kw in changes if cc == c}
        want = naive_dsp.pulse_train(FS, freqs[c], duty[c], 1.0, 0.0, phase[c], n, per_ch)
        assert np.array_equal(got[c], want), f"channel {c}"


@given(splits=st.lists(st.integers(1, 2999), max_size=20),
       changes=st.lists(st.tuples(st.integers(0, 2999), st.floats(0, FS / 2), st.floats(0, 1)), max_size=5))
@settings(max_examples=40, deadline=None)
def test_chunk_invariance(splits, changes):
    sched = {}
    for j, f, d in changes:
        sched.setdefault(j, []).append((0, dict(freq=f, duty=d)))
    one = run(PulseTrain(2, FS, [500.0, 3.0], [0.3, 0.9]), 3000, schedule=sched)
    many = run(PulseTrain(2, FS, [500.0, 3.0], [0.3, 0.9]), 3000, splits=splits, schedule=sched)
    assert np.array_equal(one, many)


@pytest.mark.parametrize("freq, duty", [(250.0, 0.5), (333.0, 0.2), (17.0, 0.75), (4000.0, 0.5)],
                         ids=["250Hz-50%", "333Hz-20%", "17Hz-75%", "4kHz-50%"])
def test_frequency_and_duty_from_edges(freq, duty):
    train = PulseTrain(1, FS, freq, duty, high=5.0, low=0.0)
    y = run(train, int(FS))[0]
    rises = rising_edges(y, 5.0)
    period = np.mean(np.diff(rises))  # samples; individual periods differ by at most one
    assert FS / period == pytest.approx(freq, rel=1e-3)
    assert np.ptp(np.diff(rises)) <= 1
    cycles = y[rises[0] : rises[-1]]
    assert np.mean(cycles == 5.0) == pytest.approx(duty, abs=1.5 / period)


def test_frequency_change_keeps_position_in_cycle():
    """Change 100 Hz -> 300 Hz a third into a cycle (sample 160 of 480): the position 1/3 is
    kept, so the high part ends (1/2 - 1/3) and the cycle (1 - 1/3) of a 160-sample period later;
    a restart at phase 0 would put the next fall at 160 + 80."""
    train = PulseTrain(1, FS, 100.0, 0.5)  # 480 samples per cycle, high first
    y = run(train, 2000, schedule={160: [(0, dict(freq=300.0))]})[0]
    assert train.freq[0] == pytest.approx(300.0, abs=FS / 2**41)  # the documented DDS grid
    falls = np.flatnonzero((y[1:] == 0.0) & (y[:-1] == 1.0)) + 1
    assert falls[0] == 160 + np.ceil((0.5 - 1 / 3) * 160)
    rises = rising_edges(y, 1.0)
    assert rises[0] == 160 + np.ceil((1 - 1 / 3) * 160)
    assert np.all(np.diff(rises) == 160)


def test_zero_hz_holds_and_resumes():
    train = PulseTrain(1, FS, 100.0, 0.5)
    y = run(train, 1000, schedule={100: [(0, dict(freq=0.0))], 600: [(0, dict(freq=100.0))]})[0]
    assert np.all(y[100:600] == 1.0)  # position 100/480 < duty: held high
    # resumes where it stopped: the cycle continues from sample 100's position
    ref = run(PulseTrain(1, FS, 100.0, 0.5), 500)[0]
    assert np.array_equal(y[600:1000], ref[100:500])


def test_level_mode_and_levels():
    train = PulseTrain(2, FS, 1000.0, 0.5, high=2.0, low=-2.0)
    train.set_level(0, True)
    train.set_level(1, False)
    y = run(train, 100)
    assert np.all(y[0] == 2.0) and np.all(y[1] == -2.0)
    train.set_all(freq=0.0, duty=1.0, high=7.0)
    y = run(train, 10)
    assert np.all(y == 7.0)


def test_adds_into_out_and_kernel_args():
    train = PulseTrain(1, FS, 0.0, 1.0, high=1.0)
    out = np.full((1, 4), 0.5)
    pulse_process(*train.args, out)
    assert np.all(out == 1.5)


@pytest.mark.parametrize(
    "kwargs, match",
    [(dict(freq=-1.0), r"freq = -1.0 Hz"), (dict(duty=1.5), r"duty = 1.5 is out of range"), (dict(high=np.nan), "high"),
     (dict(phase=1.0), "phase")],
    ids=["negative-freq", "duty-above-1", "nan-level", "phase-1"],
)
def test_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PulseTrain(1, FS, **kwargs)
