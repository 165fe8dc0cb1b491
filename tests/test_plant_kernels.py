"""Kernels of rtctl.plant._kernels against their naive twins, chunk invariance, status bits."""

import naive_plant
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rtctl._numba import TINY
from rtctl.plant import _kernels as K

N_TRUTH, N_SEG = 4, 2
X_, IPOS = 7, 13  # positions of the state trajectory and the noise positions in the kernel args


def random_system(rng, n_pairs=3, n_real=2, n_out=N_TRUTH + N_SEG, sparse=False):
    """Modal system with unit input gains; ``sparse``: a cascade-like zero pattern in c, d."""
    r = rng.uniform(0.5, 0.999, n_pairs)
    th = rng.uniform(0.01, 3.0, n_pairs)
    pairs = np.column_stack([r * np.cos(th), r * np.sin(th)])
    reals = rng.uniform(-0.9, 0.999, n_real)
    ns = 2 * n_pairs + n_real
    c, d = rng.normal(size=(n_out, ns)), rng.normal(size=n_out)
    if sparse:
        c[rng.uniform(size=c.shape) < 0.4] = 0.0
        c[0] = 0.0                                 # an output that reads no state at all
        d[rng.uniform(size=n_out) < 0.7] = 0.0
    return pairs, reals, naive_plant.unit_b(n_pairs, n_real), c, d


def scratch(ns, n_out, nc, chunk, max_block):
    """Kernel scratch: state trajectory X, inputs ut, outputs ys (one chunk)."""
    X = np.zeros((ns, (chunk + 1) * nc))
    return X, np.zeros(max_block * nc), np.zeros((n_out, chunk * nc))


@pytest.mark.parametrize("sparse", [False, True], ids=["dense-c", "sparse-c"])
@pytest.mark.parametrize("form", [K.FORM_MODAL, K.FORM_DENSE], ids=["modal", "dense"])
def test_lti_group_matches_naive(form, sparse):
    rng = np.random.default_rng(1)
    pairs, reals, b, c, d = random_system(rng, sparse=sparse)
    A = naive_plant.modal_matrix(pairs, reals)
    if form == K.FORM_DENSE:  # a genuinely dense matrix: rotate the modal one
        Q, _ = np.linalg.qr(rng.normal(size=A.shape))
        A, b, c = Q @ A @ Q.T, Q @ b, c @ Q.T
    nc, n = 5, 101
    X, ut, ys = scratch(A.shape[0], c.shape[0], nc, chunk=3, max_block=7)
    x0 = rng.normal(size=(A.shape[0], nc))
    X[:, :nc] = x0
    u = rng.normal(size=(nc, n))
    y = np.empty((nc, c.shape[0], n))
    a = pairs if form == K.FORM_MODAL else A
    plan, coef = K.output_plan(c)
    st_ = K.lti_group_process(form, a, reals if form == K.FORM_MODAL else np.zeros(0), b, d,
                              plan, coef, X, ut, ys, u, y)
    x = x0.copy()
    y_ref, st_ref = naive_plant.lti_process(A, b, c, d, x, u)
    assert st_ == st_ref == 0
    np.testing.assert_allclose(y, y_ref, rtol=1e-11, atol=1e-12 * np.abs(y_ref).max())
    np.testing.assert_allclose(X[:, :nc], x, rtol=1e-11, atol=1e-12 * np.abs(x).max())


def group_args(rng, nc, chunk=4, max_block=16, gain=100.0, fs_v=2.5, bits=16, noise_v=1e-3,
               sparse=False):
    pairs, reals, b, c, d = random_system(rng, sparse=sparse)
    ns, n_out = b.size, c.shape[0]
    X, ut, ys = scratch(ns, n_out, nc, chunk, max_block)
    S = nc * N_SEG
    t1 = rng.standard_normal(1009).astype(np.float32)  # small primes: wraps happen in tests
    t2 = rng.standard_normal(1013).astype(np.float32)
    lsb = 2 * fs_v / 2**bits
    lo, hi = -2.0 ** (bits - 1), 2.0 ** (bits - 1) - 1
    adc = np.array([gain, 1 / lsb, lsb / gain, hi, lo, noise_v / np.sqrt(2)])
    plan, coef = K.output_plan(c)
    args = (np.array([K.FORM_MODAL, N_TRUTH, N_SEG, chunk, max_block]), pairs, reals, b, d, plan,
            coef, X, ut, ys,
            adc, np.concatenate([t1, t1[:S]]), np.concatenate([t2, t2[:S]]), np.array([1000, 3]))
    naive = dict(A=naive_plant.modal_matrix(pairs, reals), b=b, c=c, d=d, n_truth=N_TRUTH,
                 n_seg=N_SEG, gain=gain, lsb_v=lsb, lo=lo, hi=hi, scale=noise_v / np.sqrt(2),
                 table1=t1, table2=t2, ipos=args[IPOS].copy())
    return args, naive


def run(args, drive):
    nc, n = drive.shape
    sensed, truth = np.empty((nc * N_SEG, n)), np.empty((nc, N_TRUTH, n))
    status = K.sim_group_process(*args, drive, sensed, truth)
    return sensed, truth, status


def test_sim_group_matches_naive():
    rng = np.random.default_rng(2)
    nc, n = 3, 77
    args, nv = group_args(rng, nc)
    drive = rng.normal(size=(nc, n)) * 1e-3
    sensed, truth, status = run(args, drive)
    x = np.zeros((nv["b"].size, nc))
    s_ref, t_ref, st_ref = naive_plant.sim_group(x=x, drive=drive, **nv)
    assert status == st_ref
    np.testing.assert_allclose(truth, t_ref, rtol=1e-11, atol=1e-14)
    # Readings agree to one LSB (x/lsb vs x*(1/lsb) may round differently at a code boundary).
    lsb_a = nv["lsb_v"] / nv["gain"]
    assert np.max(np.abs(sensed - s_ref)) <= lsb_a * 1.000001
    assert np.mean(np.round(sensed / lsb_a) == np.round(s_ref / lsb_a)) > 0.99
    # The noise is really there, at its rms: compare with a noiseless run of the same system.
    args0, nv0 = group_args(np.random.default_rng(2), nc, noise_v=0.0)
    quiet, _, _ = run(args0, drive)
    diff = (sensed - quiet) * nv["gain"]  # V at the ADC input
    assert 0.8e-3 < np.std(diff) < 1.2e-3


@pytest.mark.parametrize("nc, chunk, sparse", [(5, 4, False), (48, 8, True)],
                         ids=["5ch-scalar", "48ch-vector"])
@settings(max_examples=25, deadline=None)
@given(splits=st.lists(st.integers(min_value=1, max_value=40), min_size=1, max_size=8))
def test_chunk_invariance(nc, chunk, sparse, splits):
    """Any split into blocks gives bitwise the same samples as one call (scipy's zi contract).

    With 48 channels the loops run vectorized, and a split moves samples between the vector
    bodies and the scalar remainders of the output and transpose loops.
    """
    n = sum(splits)
    drive = np.random.default_rng(3).normal(size=(nc, n)) * 1e-3
    args_one, _ = group_args(np.random.default_rng(4), nc, chunk=chunk, sparse=sparse)
    s_one, t_one, _ = run(args_one, drive)
    args, _ = group_args(np.random.default_rng(4), nc, chunk=chunk, sparse=sparse)
    pieces_s, pieces_t, start = [], [], 0
    for k in splits:
        s, t, _ = run(args, np.ascontiguousarray(drive[:, start:start + k]))
        pieces_s.append(s)
        pieces_t.append(t)
        start += k
    assert np.array_equal(np.concatenate(pieces_t, axis=-1), t_one)
    assert np.array_equal(np.concatenate(pieces_s, axis=-1), s_one)
    assert np.array_equal(args[X_][:, :nc], args_one[X_][:, :nc])
    assert np.array_equal(args[IPOS], args_one[IPOS])


def test_subnormal_flush_after_silence():
    rng = np.random.default_rng(5)
    nc = 4
    args, _ = group_args(rng, nc)
    pairs, reals = args[1], args[2]
    rad = np.hypot(pairs[:, 0], pairs[:, 1])
    pairs *= (0.9 / rad)[:, None]  # every mode decays by 0.9 per sample
    reals[:] = 0.5
    run(args, rng.normal(size=(nc, 50)))
    X = args[X_]
    assert np.all(np.abs(X[:, :nc]) > 1e-3)
    # 0.9^n passes the subnormal range (< 2.2e-308) near n = 6700; the flush at TINY = 1e-200
    # zeroes states from n ~ 4400 on. Check the states on the way down and at the end.
    for _ in range(10):
        run(args, np.zeros((nc, 1000)))
        x = X[:, :nc]
        assert np.all((x == 0.0) | (np.abs(x) >= TINY))
    assert np.all(X[:, :nc] == 0.0)
    # The naive twin without a flush would hold subnormals here (the reason for the flush).
    assert 0.0 < 0.9 ** 6800 * 1e-3 < 2.2e-308


def test_adc_clipping_sets_status_bit():
    rng = np.random.default_rng(6)
    nc = 2
    args, nv = group_args(rng, nc, noise_v=0.0)
    drive = np.zeros((nc, 40))
    assert run(args, drive)[2] == 0
    big = np.full((nc, 40), 1e3)  # currents far beyond full scale / gain
    sensed, _, status = run(args, big)
    assert status & K.STATUS_SATURATED and not status & K.STATUS_NONFINITE
    fs_a = 2.0 ** (16 - 1) * nv["lsb_v"] / nv["gain"]
    assert np.max(np.abs(sensed)) <= fs_a
    assert np.any(np.isclose(np.abs(sensed), fs_a, rtol=1e-4))


def test_adc_clips_far_out_of_range_currents_to_the_right_side():
    """Codes beyond the int64 range clip by sign (no integer conversion); NaN reads as the
    lowest code and counts as clipped."""
    rng = np.random.default_rng(9)
    nc = 2
    args, nv = group_args(rng, nc, noise_v=0.0)
    adc, t1, t2, ipos = args[10:14]
    ys = np.zeros((N_TRUTH + N_SEG, 4 * nc))
    ys[N_TRUTH, :4] = [1e30, -1e30, np.nan, 1e-9]
    assert K.adc_block(ys, N_TRUTH, N_SEG, nc, 4, adc, t1, t2, ipos)
    lsb_a = nv["lsb_v"] / nv["gain"]
    np.testing.assert_array_equal(ys[N_TRUTH, :3], [nv["hi"] * lsb_a, nv["lo"] * lsb_a,
                                                     nv["lo"] * lsb_a])
    ys[N_TRUTH, :4] = [1e-9, 0.0, -1e-9, 0.0]
    assert not K.adc_block(ys, N_TRUTH, N_SEG, nc, 4, adc, t1, t2, ipos)


def test_nan_input_sets_nonfinite_bit():
    rng = np.random.default_rng(7)
    nc = 3
    args, _ = group_args(rng, nc)
    drive = rng.normal(size=(nc, 32)) * 1e-3
    assert run(args, drive)[2] & K.STATUS_NONFINITE == 0
    drive[1, 17] = np.nan
    assert run(args, drive)[2] & K.STATUS_NONFINITE
    # The state stays poisoned until it is reset.
    assert run(args, np.zeros((nc, 8)))[2] & K.STATUS_NONFINITE
    args[X_][:] = 0.0
    assert run(args, np.zeros((nc, 8)))[2] == 0
    drive[1, 17] = np.inf
    assert run(args, drive)[2] & K.STATUS_NONFINITE


def plan_matrix(plan, coef, shape):
    """The coefficient matrix a plan applies, and how often it touches each entry."""
    c = np.zeros(shape)
    hits = np.zeros(shape, dtype=int)
    for (nr, r0, r1, r2, w, *cols), cf in zip(plan, coef):
        for i, r in enumerate((r0, r1, r2)[:nr]):
            for j in range(w):
                c[r, cols[j]] += cf[i, j]
                hits[r, cols[j]] += cf[i, j] != 0.0
    return c, hits


@pytest.mark.parametrize("seed", range(6))
def test_output_plan_covers_each_nonzero_once(seed):
    rng = np.random.default_rng(seed)
    n_out, ns = rng.integers(1, 8), rng.integers(1, 21)
    c = rng.normal(size=(n_out, ns))
    c[rng.uniform(size=c.shape) < rng.uniform(0, 0.8)] = 0.0
    plan, coef = K.output_plan(c)
    assert plan.shape == (len(coef), K.PLAN_COLUMNS)
    rebuilt, hits = plan_matrix(plan, coef, c.shape)
    assert np.array_equal(rebuilt, c)
    assert np.array_equal(hits, (c != 0).astype(int))
    for nr, *_, w in plan[:, :5]:
        assert (nr, w) in K.TILE_SHAPES
    # A tile's rows are distinct, and every output row belongs to some tile.
    seen = set()
    for nr, r0, r1, r2, *_ in plan:
        rows = (r0, r1, r2)[:nr]
        assert len(set(rows)) == nr
        seen |= set(rows)
    assert seen == set(range(n_out))


def test_output_plan_skips_cascade_zeros():
    """Tip rows never read the filter states, each current only its own filter: the bimorph's
    pattern (3 tip rows, voltage, 2 currents; 12 shared states, 2 filters of 2) costs 69
    multiply-adds per sample (65 nonzeros, 4 zeros shared by the two currents), not 96."""
    c = np.zeros((6, 16))
    up = list(range(4, 16))
    c[0:3, up] = 1.0
    c[3, 12] = 1.0
    c[4, up + [0, 1]] = 1.0
    c[5, up + [2, 3]] = 1.0
    plan, coef = K.output_plan(c)
    assert sum(nr * w for nr, *_, w, _s in plan[:, :6]) == 69
    assert len(plan) == 5


@pytest.mark.parametrize("L", [1, 7, 8, 45, 384])
def test_lti_outputs_matches_naive(L):
    rng = np.random.default_rng(L)
    c = rng.normal(size=(6, 13))
    c[rng.uniform(size=c.shape) < 0.4] = 0.0
    d = np.where(rng.uniform(size=6) < 0.5, rng.normal(size=6), 0.0)
    plan, coef = K.output_plan(c)
    X = rng.normal(size=(13, L + 5))
    ut = rng.normal(size=L + 9)
    ys = np.full((6, L + 3), np.nan)
    K.lti_outputs(plan, coef, d, X, ut, 4, ys, L)
    np.testing.assert_allclose(ys[:, :L], naive_plant.outputs(c, d, X, ut, 4, L), rtol=1e-13,
                               atol=1e-13)
    assert np.all(np.isnan(ys[:, L:]))   # nothing written beyond the chunk


def test_modal_steps_match_naive():
    rng = np.random.default_rng(8)
    for n_pairs, n_real in [(0, 1), (1, 0), (3, 2), (6, 4), (5, 3)]:
        pairs, reals, *_ = random_system(rng, n_pairs, n_real)
        nc, steps = 11, 5
        X = rng.normal(size=(2 * n_pairs + n_real, 9 * nc))
        X[:, 3] = 1e-201                      # channel 3 decays below TINY in its first step
        ut = rng.normal(size=8 * nc)
        ut[nc + 3] = 0.0
        Xn = X.copy()
        K.lti_steps_modal(pairs, reals, X, 0, nc, steps, ut, nc, nc)       # slots 0..4 -> 1..5
        K.lti_steps_modal(pairs, reals, X, 5 * nc, 0, 1, ut, 6 * nc, nc)   # slot 5 -> slot 0
        naive_plant.modal_steps(pairs, reals, Xn, 0, nc, steps, ut, nc, nc)
        naive_plant.modal_steps(pairs, reals, Xn, 5 * nc, 0, 1, ut, 6 * nc, nc)
        # fused multiply-adds vs numpy: round-off of cancelling terms, relative to the states
        np.testing.assert_allclose(X, Xn, rtol=1e-13, atol=1e-15 * np.abs(Xn).max())
        assert np.all(X[:, nc + 3] == 0.0)


@pytest.mark.parametrize("m", [1, 2, 3, 4, 5, 7, 8, 9, 13, 16, 23])
def test_rows_out_matches_naive(m):
    rng = np.random.default_rng(m)
    nc, n_truth, n_seg, n = 9, 4, 2, 40
    ys = rng.normal(size=(n_truth + n_seg, m * nc + 3))
    truth, sensed = np.zeros((nc, n_truth, n)), np.zeros((nc * n_seg, n))
    t_ref, s_ref = truth.copy(), sensed.copy()
    K.rows_out(ys, n_truth, n_seg, truth, sensed, 11, m, nc)
    naive_plant.rows(ys, n_truth, n_seg, t_ref, s_ref, 11, m, nc)
    assert np.array_equal(truth, t_ref) and np.array_equal(sensed, s_ref)


def test_aligned_zeros():
    for shape in [(16, 432), (5,), (6, 405), (3, 7)]:
        a = K.aligned_zeros(shape)
        assert a.ctypes.data % 64 == 0 and a.flags.c_contiguous and a.dtype == np.float64
        assert a.shape[:-1] == shape[:-1] and shape[-1] <= a.shape[-1] < shape[-1] + 8
        assert a.shape[-1] % 8 == 0 and not np.any(a)
