"""The observer's block step against its reference twin (``twin_observer``: the kernels as they
were before the rewrite for speed): bitwise the same estimates, rebuilt waveform, drive outputs
and lock-in state, block after block, for shared and per-channel windows, hops under the block,
least-squares rows, beat pairs, unused slots and poisoned readings."""

import numpy as np
import pytest
import twin_observer as twin

from rtctl.dsp import _kernels as dk
from rtctl.dsp.lockin import LockIn
from rtctl.plant.materials import BUILTIN
from rtctl.selfsense.rt import Observer, short_windows
from rtctl.selfsense.stage import ObserverStage, observe_stage
from rtctl.selfsense.tmm import TMMBeam, laminate_of

PZT = BUILTIN["PZT-5A"]
FS, BLOCK = 48000.0, 32
# every accumulator row but the currents' amplitude and phase, which the observer no longer reads
ACC_KEPT = [r for r in range(dk.N_ACC) if r not in (dk.EST_A, dk.EST_P)]


def beam(n_seg):
    lam = laminate_of(1.5e-3, [(PZT, 0.3e-3), (PZT, 0.3e-3)], "parallel")
    return TMMBeam(lam, 15e-3, (1.0 / n_seg,) * n_seg, 0.01)


def observers(freqs, n_seg=2, rng=None, **kw):
    """Two observers on the same design, the second's state a copy of the first's, ``H`` random;
    without the drive step's correction, which the twin predates (tests/test_observer_steps.py)."""
    kw = {"steps": False, **kw}
    obs = Observer(beam(n_seg), freqs, FS, BLOCK, **kw)
    obs.H[:] = rng.standard_normal(obs.H.shape)
    obs.H[obs.freqs <= 0] = 0.0
    ref = Observer(beam(n_seg), freqs, FS, BLOCK, **kw)
    ref.H[:] = obs.H
    i_out = np.zeros((obs.n_channels * obs.n_seg, obs.n_tones, 2))
    return obs, ref, i_out


def twin_args(ref, i_out):
    return (*ref.lock_u.args, *ref.lock_i.args, ref.u_out, i_out, ref.H, ref.scale, ref.est, ref.wave)


def inputs(freqs, n_seg, n_blocks, rng, poison_at=None):
    n_total = n_blocks * BLOCK
    n = np.arange(n_total)
    drive = np.stack([sum((np.cos(2 * np.pi * f * n / FS + 0.7 * k) for k, f in enumerate(row) if f > 0),
                          np.zeros(n_total)) for row in freqs]) + 0.1 * rng.standard_normal((len(freqs), n_total))
    sensed = 1e-6 * rng.standard_normal((len(freqs) * n_seg, n_total))
    if poison_at is not None:
        sensed[1, poison_at * BLOCK + 3] = np.nan
    return drive, sensed


def assert_same(obs, ref):
    for name in ("est", "wave", "u_out"):
        assert np.array_equal(getattr(obs, name), getattr(ref, name), equal_nan=True), name
    for a, b in zip(obs.lock_u.args, ref.lock_u.args):
        assert np.array_equal(a, b, equal_nan=True)
    assert np.array_equal(obs.lock_i.ref, ref.lock_i.ref)
    assert np.array_equal(obs.lock_i.ring, ref.lock_i.ring, equal_nan=True)
    assert np.array_equal(obs.lock_i.acc[ACC_KEPT], ref.lock_i.acc[ACC_KEPT], equal_nan=True)


CASES = {
    "one window, beat pair and unused slot": dict(freqs=[[245.0, 255.0], [1000.0, 0.0], [120.0, 40.0]]),
    "one window, one tone, 4 segments": dict(freqs=[[250.0], [80.0], [750.0]], n_seg=4),
    "short windows (closed loop)": dict(freqs=[[80.0, 0.0], [235.0, 265.0], [120.0, 0.0], [455.5, 0.0]],
                                        short=True),
}


@pytest.mark.parametrize("case", list(CASES))
def test_observer_process_is_bitwise_the_old_kernel(case):
    kw = dict(CASES[case])
    freqs = np.array(kw.pop("freqs"))
    n_seg = kw.pop("n_seg", 2)
    rng = np.random.default_rng(11)
    if kw.pop("short", False):
        w, lsq, hop = short_windows(freqs, FS, BLOCK)
        assert hop < BLOCK and lsq.any()           # the case covers both
        kw.update(window=w, lstsq=lsq, hop=hop)
    obs, ref, i_out = observers(freqs, n_seg, rng, **kw)
    n_blocks = 700                                 # past ring wraps and several re-anchors
    drive, sensed = inputs(freqs, n_seg, n_blocks, rng, poison_at=n_blocks - 3)
    args, targs = obs.args, twin_args(ref, i_out)
    for b in range(n_blocks):
        sl = slice(b * BLOCK, (b + 1) * BLOCK)
        d, s = np.ascontiguousarray(drive[:, sl]), np.ascontiguousarray(sensed[:, sl])
        got = observer_process(args, d, s)
        want = twin.observer_process(*targs, d, s)
        assert got == want
        assert_same(obs, ref)
    assert got == twin.STATUS_NONFINITE            # the poisoned reading is flagged by both
    assert np.any(obs.wave != 0.0)


def observer_process(args, d, s):
    from rtctl.selfsense.rt import observer_process as k

    return k(*args, d, s)


def test_observe_stage_is_bitwise_the_old_kernel():
    rng = np.random.default_rng(12)
    freqs = np.array([[250.0], [97.0], [611.0], [40.0]])
    obs, ref, i_out = observers(freqs, 2, rng)
    n_ch, n_blocks = len(freqs), 300
    outs, sensed = inputs(freqs, 2, n_blocks, rng)
    st_new = ObserverStage(obs, 2, np.zeros((n_ch, BLOCK)), np.zeros((2 * n_ch, BLOCK)), np.zeros(n_ch))
    st_old = ObserverStage(ref, 2, np.zeros((n_ch, BLOCK)), np.zeros((2 * n_ch, BLOCK)), np.zeros(n_ch))
    # the old kernel's slot there held the currents' outputs; it reads one image load, unfiltered
    picking = ("Hc", "pick", "resid", "contact", "lag", "pf", "pf_z", "pf_x", "pf_g", "d_acc", "d_edge",
               "invJ", "Kc")
    old_args = dict({k: v for k, v in st_old.args.items() if k not in picking}, back=i_out)
    for b in range(n_blocks):
        sl = slice(b * BLOCK, (b + 1) * BLOCK)
        for st in (st_new, st_old):
            st.args["out"][...] = outs[:, sl]
            st.args["sensed"][...] = sensed[:, sl]
        assert observe_stage(*st_new.args.values()) == twin.observe_stage(*old_args.values())
        assert np.array_equal(st_new.amp, st_old.amp) and np.array_equal(st_new.delay, st_old.delay)
        assert_same(obs, ref)


def test_lockin_sums_are_lockin_process_without_amplitude():
    """``lockin_sums`` keeps every accumulator row of ``lockin_process`` but amplitude and phase."""
    rng = np.random.default_rng(13)
    f = np.array([[235.0, 265.0], [80.0, 0.0], [301.0, 0.0]])
    a = LockIn(3, f, FS, [1600, 600, 960], hop=8, lstsq=[True, False, False])
    b = LockIn(3, f, FS, [1600, 600, 960], hop=8, lstsq=[True, False, False])
    out = np.zeros((3, 2, 2))
    for _ in range(200):
        x = rng.standard_normal((3, BLOCK))
        dk.lockin_process(*a.args, x, out)
        closed = dk.lockin_sums(*b.args, x)
        assert closed
        assert np.array_equal(a.ref, b.ref) and np.array_equal(a.ring, b.ring)
        assert np.array_equal(a.acc[ACC_KEPT], b.acc[ACC_KEPT], equal_nan=True)
