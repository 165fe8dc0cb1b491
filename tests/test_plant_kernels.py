"""Kernels of rtctl.plant._kernels against their naive twins, chunk invariance, status bits."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import naive_plant
from rtctl._numba import TINY
from rtctl.plant import _kernels as K

N_TRUTH, N_SEG = 4, 2


def random_system(rng, n_pairs=3, n_real=2, n_out=N_TRUTH + N_SEG):
    r = rng.uniform(0.5, 0.999, n_pairs)
    th = rng.uniform(0.01, 3.0, n_pairs)
    pairs = np.column_stack([r * np.cos(th), r * np.sin(th)])
    reals = rng.uniform(-0.9, 0.999, n_real)
    ns = 2 * n_pairs + n_real
    return pairs, reals, rng.normal(size=ns), rng.normal(size=(n_out, ns)), rng.normal(size=n_out)


def scratch(ns, n_out, nc, chunk, max_block):
    """Kernel scratch: state trajectory X, inputs ut, outputs ys."""
    X = np.zeros((ns, (chunk + 1) * nc))
    return X, np.zeros(max_block * nc), np.zeros((n_out, max_block * nc))


@pytest.mark.parametrize("form", [K.FORM_MODAL, K.FORM_DENSE], ids=["modal", "dense"])
def test_lti_group_matches_naive(form):
    rng = np.random.default_rng(1)
    pairs, reals, b, c, d = random_system(rng)
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
    st_ = K.lti_group_process(form, a, reals if form == K.FORM_MODAL else np.zeros(0), b, c, d,
                              X, ut, ys, u, y)
    x = x0.copy()
    y_ref, st_ref = naive_plant.lti_process(A, b, c, d, x, u)
    assert st_ == st_ref == 0
    np.testing.assert_allclose(y, y_ref, rtol=1e-11, atol=1e-12 * np.abs(y_ref).max())
    np.testing.assert_allclose(X[:, :nc], x, rtol=1e-11, atol=1e-12 * np.abs(x).max())


def group_args(rng, nc, chunk=4, max_block=16, gain=100.0, fs_v=2.5, bits=16, noise_v=1e-3):
    pairs, reals, b, c, d = random_system(rng)
    ns, n_out = b.size, c.shape[0]
    X, ut, ys = scratch(ns, n_out, nc, chunk, max_block)
    S = nc * N_SEG
    t1 = rng.standard_normal(1009).astype(np.float32)  # small primes: wraps happen in tests
    t2 = rng.standard_normal(1013).astype(np.float32)
    lsb = 2 * fs_v / 2**bits
    lo, hi = -2.0 ** (bits - 1), 2.0 ** (bits - 1) - 1
    adc = np.array([gain, 1 / lsb, lsb / gain, hi, lo, noise_v / np.sqrt(2)])
    args = (np.array([K.FORM_MODAL, N_TRUTH, N_SEG]), pairs, reals, b, c, d, X, ut, ys, adc,
            np.concatenate([t1, t1[:S]]), np.concatenate([t2, t2[:S]]), np.array([1000, 3]))
    naive = dict(A=naive_plant.modal_matrix(pairs, reals), b=b, c=c, d=d, n_truth=N_TRUTH,
                 n_seg=N_SEG, gain=gain, lsb_v=lsb, lo=lo, hi=hi, scale=noise_v / np.sqrt(2),
                 table1=t1, table2=t2, ipos=args[12].copy())
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


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(min_value=1, max_value=40), min_size=1, max_size=8))
def test_chunk_invariance(splits):
    """Any split into blocks gives bitwise the same samples as one call (scipy's zi contract)."""
    nc = 5
    n = sum(splits)
    drive = np.random.default_rng(3).normal(size=(nc, n)) * 1e-3
    args_one, _ = group_args(np.random.default_rng(4), nc)
    s_one, t_one, _ = run(args_one, drive)
    args, _ = group_args(np.random.default_rng(4), nc)
    pieces_s, pieces_t, start = [], [], 0
    for k in splits:
        s, t, _ = run(args, np.ascontiguousarray(drive[:, start:start + k]))
        pieces_s.append(s)
        pieces_t.append(t)
        start += k
    assert np.array_equal(np.concatenate(pieces_t, axis=-1), t_one)
    assert np.array_equal(np.concatenate(pieces_s, axis=-1), s_one)
    assert np.array_equal(args[6][:, :nc], args_one[6][:, :nc])
    assert np.array_equal(args[12], args_one[12])


def test_subnormal_flush_after_silence():
    rng = np.random.default_rng(5)
    nc = 4
    args, _ = group_args(rng, nc)
    pairs, reals = args[1], args[2]
    rad = np.hypot(pairs[:, 0], pairs[:, 1])
    pairs *= (0.9 / rad)[:, None]  # every mode decays by 0.9 per sample
    reals[:] = 0.5
    run(args, rng.normal(size=(nc, 50)))
    X = args[6]
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
    args[6][:] = 0.0
    assert run(args, np.zeros((nc, 8)))[2] == 0
    drive[1, 17] = np.inf
    assert run(args, drive)[2] & K.STATUS_NONFINITE
