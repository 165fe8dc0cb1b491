"""Linear time-invariant plants: continuous state space, exact discretization, modal form.

The simulated rig runs every linear plant as a discrete recursion at the loop rate. This module
turns a continuous model ``x' = A x + B u, y = C x + D u`` into that recursion without any
integrator error: the matrix exponential of a Van Loan block matrix gives the exact solution for
a stated model of the input between samples (:func:`c2d`). What remains is the *input model*
(docs/physics.md, Sec. 4.2): a DAC holds each sample, so ``"zoh"`` is exact for the rig; a
continuous sine is better served by ``"foh"`` or, exactly, by :func:`augment_tones`.

:func:`to_modal` then rewrites the discrete recursion in real block-diagonal form (1x1 blocks for
real eigenvalues, 2x2 rotation-scaling blocks for complex pairs), which costs ~4x fewer flops per
sample than the dense form, but only when the eigenvector basis is well conditioned; otherwise it
keeps the dense form and says so. Given the plant's subsystems in signal order (``blocks``), it
diagonalizes each subsystem on its own, so that every output keeps exact zeros on the states it
cannot depend on; :meth:`ModalForm.unit_input` then scales each mode to unit input gain.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from dataclasses import replace as dataclasses_replace

import numpy as np
import scipy.linalg as sla

from rtctl.errors import ModelError

__all__ = ["StateSpace", "c2d", "augment_tones", "tone_state", "to_modal", "ModalForm"]


def _as_matrix(name, a, shape):
    a = np.array(a, dtype=np.float64, copy=True)
    if a.ndim != 2 or a.shape != shape:
        raise ModelError(f"{name} must have shape {shape}, got {a.shape}; check the state, input "
                         "and output counts of the model")
    if not np.all(np.isfinite(a)):
        raise ModelError(f"{name} contains non-finite entries; the model parameters are invalid")
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class StateSpace:
    """Linear time-invariant system ``x' = A x + B u, y = C x + D u`` (or ``x[k+1] = ...``).

    Parameters
    ----------
    A : array_like, shape (n_states, n_states)
    B : array_like, shape (n_states, n_inputs)
    C : array_like, shape (n_outputs, n_states)
    D : array_like, shape (n_outputs, n_inputs)
    dt : float or None
        Sample time in s for a discrete system; ``None`` (default) for continuous time.
    state_names, input_names, output_names : tuple of str, optional
        Labels carried along (units belong in the names, e.g. ``"tip_m"``).

    Notes
    -----
    The arrays are copied and made read-only. ``rhs(t, x, u)`` and ``outputs(x, u)`` are the names
    every plant model in :mod:`rtctl.plant` uses, so that ``scipy.integrate.solve_ivp`` can run any
    of them as a reference: ``solve_ivp(lambda t, x: sys.rhs(t, x, u(t)), ...)``.

    Examples
    --------
    >>> import numpy as np
    >>> from rtctl.plant.lti import StateSpace
    >>> lowpass = StateSpace([[-10.0]], [[10.0]], [[1.0]], [[0.0]])
    >>> lowpass.rhs(0.0, np.array([0.5]), np.array([1.0]))
    array([5.])
    >>> float(abs(lowpass.frequency_response([0.0])[0, 0, 0]))
    1.0
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    dt: float | None = None
    state_names: tuple = field(default=(), compare=False)
    input_names: tuple = field(default=(), compare=False)
    output_names: tuple = field(default=(), compare=False)

    def __post_init__(self):
        A = np.asarray(self.A, dtype=np.float64)
        if A.ndim != 2 or A.shape[0] != A.shape[1]:
            raise ModelError(f"A must be square, got shape {A.shape}")
        n = A.shape[0]
        B = np.asarray(self.B, dtype=np.float64)
        C = np.asarray(self.C, dtype=np.float64)
        if B.ndim != 2 or C.ndim != 2:
            raise ModelError(f"B and C must be 2-D, got shapes {B.shape} and {C.shape}")
        m, p = B.shape[1], C.shape[0]
        set_ = object.__setattr__
        set_(self, "A", _as_matrix("A", A, (n, n)))
        set_(self, "B", _as_matrix("B", B, (n, m)))
        set_(self, "C", _as_matrix("C", C, (p, n)))
        set_(self, "D", _as_matrix("D", self.D, (p, m)))
        if self.dt is not None:
            dt = float(self.dt)
            if not (dt > 0.0 and np.isfinite(dt)):
                raise ModelError(f"dt must be a positive time step in s or None, got {self.dt!r}")
            set_(self, "dt", dt)
        for attr, count in (("state_names", n), ("input_names", m), ("output_names", p)):
            names = tuple(getattr(self, attr))
            if names and len(names) != count:
                raise ModelError(f"{attr} has {len(names)} labels for {count} entries")
            set_(self, attr, names)

    @property
    def n_states(self) -> int:
        return self.A.shape[0]

    @property
    def n_inputs(self) -> int:
        return self.B.shape[1]

    @property
    def n_outputs(self) -> int:
        return self.C.shape[0]

    @property
    def is_discrete(self) -> bool:
        return self.dt is not None

    def rhs(self, t, x, u):
        """State derivative (continuous) or next state (discrete): ``A x + B u``.

        Parameters
        ----------
        t : float
            Time in s (unused: the system is time invariant).
        x : ndarray, shape (n_states,)
        u : ndarray, shape (n_inputs,)
        """
        return self.A @ np.asarray(x, dtype=np.float64) + self.B @ np.atleast_1d(u)

    def outputs(self, x, u):
        """Outputs ``C x + D u``, shape (n_outputs,)."""
        return self.C @ np.asarray(x, dtype=np.float64) + self.D @ np.atleast_1d(u)

    def frequency_response(self, freqs_hz):
        """Complex transfer matrix at the given frequencies.

        Parameters
        ----------
        freqs_hz : array_like, shape (n_freqs,)
            Frequencies in Hz; evaluated at ``s = j 2 pi f`` (continuous) or
            ``z = exp(j 2 pi f dt)`` (discrete).

        Returns
        -------
        ndarray, shape (n_freqs, n_outputs, n_inputs), complex
        """
        f = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
        w = 2.0 * np.pi * f
        s = np.exp(1j * w * self.dt) if self.is_discrete else 1j * w
        n = self.n_states
        out = np.empty((f.size, self.n_outputs, self.n_inputs), dtype=np.complex128)
        eye = np.eye(n)
        for i, si in enumerate(s):
            out[i] = self.C @ np.linalg.solve(si * eye - self.A, self.B) + self.D
        return out

    def simulate(self, u, x0=None):
        """Run a discrete system over an input sequence (a plain reference loop, not real-time).

        Parameters
        ----------
        u : ndarray, shape (n_samples, n_inputs)
        x0 : ndarray, shape (n_states,), optional

        Returns
        -------
        y : ndarray, shape (n_samples, n_outputs)
        x : ndarray, shape (n_samples + 1, n_states)
            States before each sample and after the last one.
        """
        if not self.is_discrete:
            raise ModelError("simulate() needs a discrete system; discretize with c2d() first")
        u = np.asarray(u, dtype=np.float64).reshape(-1, self.n_inputs)
        x = np.zeros((u.shape[0] + 1, self.n_states))
        if x0 is not None:
            x[0] = x0
        for k in range(u.shape[0]):
            x[k + 1] = self.A @ x[k] + self.B @ u[k]
        y = x[:-1] @ self.C.T + u @ self.D.T
        return y, x

    def _replace(self, A=None, B=None, C=None, D=None, dt=None, state_names=None):
        return StateSpace(self.A if A is None else A, self.B if B is None else B,
                          self.C if C is None else C, self.D if D is None else D,
                          self.dt if dt is None else dt,
                          self.state_names if state_names is None else state_names,
                          self.input_names, self.output_names)


def _expm_structured(M):
    """``expm(M)`` with exact zeros wherever ``M``'s coupling graph has no path.

    ``exp(M)[i, j]`` is exactly zero when no chain ``M[i, k1] M[k1, k2] ... M[kr, j]`` of
    nonzero entries links ``j`` to ``i`` (every power of ``M`` is zero there). Whether the
    computed exponential keeps those zeros is a detail of its implementation and its LAPACK:
    SciPy 1.15-1.17 keep them for the bimorph plant (not for every model), 1.18 leaves round-off
    there, ~1e-14 of the norm, enough for ``to_modal(..., blocks=...)`` to refuse the cascade.
    They are set from the graph here: a cascade stays exactly a cascade (no upstream state sees
    a downstream one) whatever the SciPy version, and every such entry is exact.
    """
    E = sla.expm(M)
    n = M.shape[0]
    reach = (M != 0.0) | np.eye(n, dtype=bool)
    while True:   # transitive closure by repeated squaring: <= log2(n) products
        r = reach.astype(np.float64)
        nxt = (r @ r) > 0.0
        if np.array_equal(nxt, reach):
            break
        reach = nxt
    E[~reach] = 0.0
    return E


def c2d(sys: StateSpace, dt: float, method: str = "zoh") -> StateSpace:
    """Discretize exactly by the matrix exponential (Van Loan's block-matrix method).

    Parameters
    ----------
    sys : StateSpace
        Continuous-time system.
    dt : float
        Sample time in s (``1 / fs``).
    method : {"zoh", "foh"}
        Model of the input between samples; the result is exact for that model (no integrator
        error, stable for any stable plant and any ``dt``):

        ``"zoh"``: each input sample is held for one sample period. This is what a DAC outputs
        (a staircase), so it is the exact model of the simulated rig and the default. For a
        sampled *continuous* sine it adds a half-sample delay (docs/physics.md, Sec. 4.2: 2.7e-2 off at
        250 Hz, 48 kHz).

        ``"foh"``: first-order (triangle) hold, the input is the straight line through the
        samples (non-causal). Good for smooth inputs (~1e-4 at 250 Hz, 48 kHz). The discrete
        state is then ``x[k] - Gamma2 u[k]`` rather than ``x[k]`` (outputs are unchanged);
        see Franklin, Powell & Workman, Digital Control of Dynamic Systems, Sec. 6.3.

    Returns
    -------
    StateSpace
        Discrete system with ``dt`` set; ``C`` is unchanged for ``"zoh"``. Entries that no
        path of the continuous model's couplings reaches are exactly zero (e.g. the upstream
        blocks of a cascade), whatever the SciPy version.

    Examples
    --------
    >>> from rtctl.plant.lti import StateSpace, c2d
    >>> sysd = c2d(StateSpace([[-1.0]], [[1.0]], [[1.0]], [[0.0]]), 0.1)
    >>> round(float(sysd.A[0, 0]), 6), round(float(sysd.B[0, 0]), 6)
    (0.904837, 0.095163)
    """
    if sys.is_discrete:
        raise ModelError("c2d() needs a continuous system (dt=None)")
    dt = float(dt)
    if not (dt > 0.0 and np.isfinite(dt)):
        raise ModelError(f"dt must be a positive time step in s, got {dt!r}")
    n, m = sys.n_states, sys.n_inputs
    if method == "zoh":
        # expm([[A, B], [0, 0]] dt) = [[Phi, Gamma], [0, I]], Gamma = int_0^dt e^{A s} ds B.
        em = np.zeros((n + m, n + m))
        em[:n, :n] = sys.A * dt
        em[:n, n:] = sys.B * dt
        ms = _expm_structured(em)
        return sys._replace(A=ms[:n, :n], B=ms[:n, n:], dt=dt)
    if method == "foh":
        # expm([[A, B, 0], [0, 0, I/dt], [0, 0, 0]] dt) gives Phi, Gamma1 and Gamma2 (the ramp
        # response), from which the triangle-hold recursion follows.
        em = np.zeros((n + 2 * m, n + 2 * m))
        em[:n, :n] = sys.A * dt
        em[:n, n:n + m] = sys.B * dt
        em[n:n + m, n + m:] = np.eye(m)
        ms = _expm_structured(em)
        phi, g1, g2 = ms[:n, :n], ms[:n, n:n + m], ms[:n, n + m:]
        return sys._replace(A=phi, B=g1 - g2 + phi @ g2, D=sys.D + sys.C @ g2, dt=dt)
    raise ModelError(f"unknown discretization method {method!r}; use 'zoh' or 'foh'")


def augment_tones(sys: StateSpace, freqs_hz, input_index: int = 0) -> StateSpace:
    """Append free oscillators whose sine components add to one input (exact sine inputs).

    The returned system has ``n_states + 2 len(freqs_hz)`` states and the same inputs. Tone
    ``i`` owns the appended states ``(c_i, s_i)`` with ``c' = -w s, s' = w c``
    (``w = 2 pi f_i``); ``s_i`` is added to input ``input_index``. Started from
    :func:`tone_state`, ``s_i(t) = a_i sin(w t + phi_i)``. Because the oscillators are part of the
    state, any exact discretization (``c2d(..., "zoh")``) integrates the sine exactly, to
    round-off, whatever the sample rate.

    Parameters
    ----------
    sys : StateSpace
        Continuous-time system.
    freqs_hz : array_like, shape (n_tones,)
        Tone frequencies in Hz.
    input_index : int
        Which input the tones drive.

    Returns
    -------
    StateSpace

    Examples
    --------
    >>> from rtctl.plant.lti import StateSpace, augment_tones
    >>> aug = augment_tones(StateSpace([[-1.0]], [[1.0]], [[1.0]], [[0.0]]), [250.0])
    >>> aug.n_states
    3
    """
    if sys.is_discrete:
        raise ModelError("augment_tones() needs a continuous system")
    f = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
    if not 0 <= input_index < sys.n_inputs:
        raise ModelError(f"input_index {input_index} out of range for {sys.n_inputs} inputs")
    n, k = sys.n_states, f.size
    A = np.zeros((n + 2 * k, n + 2 * k))
    A[:n, :n] = sys.A
    for i, fi in enumerate(f):
        w = 2.0 * np.pi * fi
        c, s = n + 2 * i, n + 2 * i + 1
        A[c, s] = -w
        A[s, c] = w
        A[:n, s] = sys.B[:, input_index]
    B = np.vstack([sys.B, np.zeros((2 * k, sys.n_inputs))])
    C = np.hstack([sys.C, np.zeros((sys.n_outputs, 2 * k))])
    D = sys.D.copy()
    for i in range(k):
        C[:, n + 2 * i + 1] += sys.D[:, input_index]
    names = sys.state_names + tuple(x for i in range(k) for x in (f"tone{i}_cos", f"tone{i}_sin")) \
        if sys.state_names else ()
    return StateSpace(A, B, C, D, None, names, sys.input_names, sys.output_names)


def tone_state(amplitudes, phases_rad=None):
    """Initial oscillator states for :func:`augment_tones`: tone i is ``a_i sin(w t + phi_i)``.

    Parameters
    ----------
    amplitudes : array_like, shape (n_tones,)
        Peak amplitudes in the unit of the driven input.
    phases_rad : array_like, shape (n_tones,), optional
        Phases at t = 0 in rad (default 0).

    Returns
    -------
    ndarray, shape (2 n_tones,)
        To be written after the plant's own states.
    """
    a = np.atleast_1d(np.asarray(amplitudes, dtype=np.float64))
    p = np.zeros_like(a) if phases_rad is None else np.broadcast_to(phases_rad, a.shape)
    out = np.empty(2 * a.size)
    out[0::2] = a * np.cos(p)
    out[1::2] = a * np.sin(p)
    return out


@dataclass(frozen=True)
class ModalForm:
    """A discrete system in real block-diagonal (modal) or dense form, with the evidence.

    Attributes
    ----------
    sys : StateSpace
        The transformed discrete system, states ``z`` with ``x = T z``. In modal form the first
        ``2 n_pairs`` states are the complex pairs, each ``[[sigma, omega], [-omega, sigma]]``
        (eigenvalues ``sigma +- j omega``), followed by ``n_real`` real eigenvalues on the
        diagonal.
    form : {"modal", "dense"}
    T : ndarray, shape (n_states, n_states)
        State transform ``x = T z`` (diagonal scaling for the dense form).
    cond : float
        2-norm condition number of the (balanced, column-normalized) eigenvector basis.
    eig_cond : float
        Largest eigenvalue condition number ``|y| |x| / |y^H x|`` (left/right eigenvectors).
    n_pairs, n_real : int
    reason : str
        Why the form was chosen.
    state_block : ndarray of int, shape (n_states,)
        For a cascade realization (``to_modal(..., blocks=...)``): the index of the subsystem
        (entry of ``blocks``) each modal state belongs to; ``-1`` everywhere otherwise. Output
        ``o`` of a cascade realization has exact zeros in ``sys.C[o]`` on the states of every
        subsystem it does not depend on.
    """

    sys: StateSpace
    form: str
    T: np.ndarray
    cond: float
    eig_cond: float
    n_pairs: int
    n_real: int
    reason: str
    state_block: np.ndarray = None

    def __post_init__(self):
        if self.state_block is None:
            object.__setattr__(self, "state_block", np.full(self.sys.n_states, -1, dtype=np.int64))

    def unit_input(self) -> ModalForm:
        """The same realization with each mode scaled so that the input enters with gain 1.

        A pair's basis can be multiplied by any complex number without changing its block
        (rotation-scalings commute): with ``S_p = [[b1, -b2], [b2, b1]]`` (``x = S_p x'``) its
        input vector becomes ``(1, 0)`` and a real mode's becomes 1. The recursion then needs no
        input multiplies (``x1' = sigma x1 + omega x2 + u``). ``C`` and ``T`` absorb the scaling
        (exact zeros stay exact). A mode the input does not reach (``b = 0``) cannot affect the
        outputs from a zero state: it keeps input 1 with zero columns in ``C`` and ``T``.

        Returns
        -------
        ModalForm
            With ``sys.B`` exactly ``(1, 0)`` per pair and 1 per real mode (single input only).
        """
        if self.form != "modal" or self.sys.n_inputs != 1:
            raise ModelError("unit_input() needs a single-input system in modal form")
        n, n_pairs = self.sys.n_states, self.n_pairs
        b = self.sys.B[:, 0]
        S = np.zeros((n, n))
        for p in range(n_pairs):
            i = 2 * p
            b1, b2 = b[i], b[i + 1]
            S[i:i + 2, i:i + 2] = [[b1, -b2], [b2, b1]]
        r = np.arange(2 * n_pairs, n)
        S[r, r] = b[r]
        B1 = np.zeros((n, 1))
        B1[0:2 * n_pairs:2, 0] = 1.0
        B1[2 * n_pairs:, 0] = 1.0
        s = self.sys._replace(B=B1, C=self.sys.C @ S)
        return dataclasses_replace(self, sys=s, T=self.T @ S,
                                   reason=self.reason + "; unit input per mode")

    @property
    def is_cascade(self) -> bool:
        """True if the realization was built per subsystem (exact structural zeros in ``C``)."""
        return bool(np.any(self.state_block >= 0))

    def blocks(self):
        """Block coefficients for the modal kernel.

        Returns
        -------
        pairs : ndarray, shape (n_pairs, 2)
            ``[sigma, omega]`` of each 2x2 block.
        reals : ndarray, shape (n_real,)
        """
        if self.form != "modal":
            raise ModelError("blocks() exists only for the modal form; this system is dense")
        A = self.sys.A
        idx = 2 * np.arange(self.n_pairs)
        pairs = np.column_stack([A[idx, idx], A[idx, idx + 1]]) if self.n_pairs else \
            np.zeros((0, 2))
        r = np.arange(2 * self.n_pairs, self.sys.n_states)
        return np.ascontiguousarray(pairs), A[r, r].copy()


def _markov_error(a, b, c, a2, b2, c2, n_steps):
    """Largest relative difference of the Markov parameters C A^k B of two realizations."""
    xa, xb = b.copy(), b2.copy()
    worst, scale = 0.0, 0.0
    for _ in range(n_steps):
        h1, h2 = c @ xa, c2 @ xb
        worst = max(worst, float(np.max(np.abs(h1 - h2))))
        scale = max(scale, float(np.max(np.abs(h1))))
        xa, xb = a @ xa, a2 @ xb
    return worst / scale if scale > 0 else worst


def _real_basis(M):
    """Real modal basis of a square matrix: ``(lam_pairs, lam_reals, V)`` or None.

    ``V`` has one column pair ``[Re v, Im v]`` per complex pair (``Im lambda > 0``, sorted by
    frequency), then one column per real eigenvalue (sorted descending); columns unit norm.
    """
    n = M.shape[0]
    lam, vr = sla.eig(M)
    tol = 1e3 * np.finfo(float).eps * max(1.0, float(np.max(np.abs(lam)))) if n else 0.0
    upper = np.flatnonzero(lam.imag > tol)
    upper = upper[np.argsort(np.abs(np.angle(lam[upper])), kind="stable")]
    reals = np.flatnonzero(np.abs(lam.imag) <= tol)
    reals = reals[np.argsort(-lam[reals].real, kind="stable")]
    if 2 * upper.size + reals.size != n:
        return None
    V = np.empty((n, n))
    for k, j in enumerate(upper):
        v = vr[:, j]
        v = v / np.linalg.norm(v)
        # Rotate the complex vector so Re v and Im v are orthogonal: the best-conditioned real
        # basis of the 2-D invariant subspace.
        a2 = np.dot(v, v)
        v = v * np.exp(-0.5j * np.angle(a2))
        V[:, 2 * k], V[:, 2 * k + 1] = v.real, v.imag
    base = 2 * upper.size
    for k, j in enumerate(reals):
        v = vr[:, j].real
        V[:, base + k] = v / np.linalg.norm(v)
    return lam[upper], lam[reals].real, V


def _block_matrix(lam_pairs, lam_reals):
    n_pairs = lam_pairs.size
    n = 2 * n_pairs + lam_reals.size
    Am = np.zeros((n, n))
    for k, lam in enumerate(lam_pairs):
        i = 2 * k
        Am[i, i] = Am[i + 1, i + 1] = lam.real
        Am[i, i + 1] = lam.imag
        Am[i + 1, i] = -lam.imag
    for k, lam in enumerate(lam_reals):
        Am[2 * n_pairs + k, 2 * n_pairs + k] = lam
    return Am


def _check_blocks(blocks, n):
    try:
        blocks = [np.asarray(b, dtype=np.int64).ravel() for b in blocks]
    except (TypeError, ValueError):
        raise ModelError("blocks must be a sequence of state index lists") from None
    allidx = np.concatenate(blocks) if blocks else np.zeros(0, dtype=np.int64)
    if any(b.size == 0 for b in blocks) or allidx.size != n or \
            not np.array_equal(np.sort(allidx), np.arange(n)):
        raise ModelError(f"blocks must partition the {n} states (each index exactly once, no "
                         "empty block)")
    return blocks


def _cascade_basis(Ab, blocks, zero_tol):
    """Block-diagonalize a block lower-triangular matrix, then diagonalize each block.

    ``Ab`` must not let block ``i`` depend on a later block ``j > i`` (``|Ab[b_i, b_j]| <=
    zero_tol``). Returns ``(V, lam_pairs, lam_reals, state_block, feeds)`` or a reason string.
    ``V = S blockdiag(V_k)`` with ``S`` block unit lower-triangular: ``S^-1 Ab S`` is block
    diagonal. ``S[b_j, b_i]`` solves the Sylvester equation ``A_jj P - P A_ii = -(A_ji +
    sum_{i<k<j} A_jk S_ki)``; where the right-hand side is exactly zero (no path from ``i`` to
    ``j``, e.g. two decoupled identical filters), ``P = 0`` exactly and no equation is solved.
    """
    n = Ab.shape[0]
    K = len(blocks)
    for i in range(K):
        for j in range(i + 1, K):
            if np.max(np.abs(Ab[np.ix_(blocks[i], blocks[j])])) > zero_tol:
                return (f"state block {i} depends on the later block {j}: blocks must be "
                        "ordered upstream first")
    feeds = np.zeros((K, K), dtype=bool)  # feeds[j, i]: block i drives block j directly
    A = Ab.copy()
    for i in range(K):
        for j in range(i + 1, K):
            blk = A[np.ix_(blocks[j], blocks[i])]
            blk[np.abs(blk) <= zero_tol] = 0.0
            A[np.ix_(blocks[j], blocks[i])] = blk
            A[np.ix_(blocks[i], blocks[j])] = 0.0
            feeds[j, i] = bool(np.any(blk))
    S = np.eye(n)
    for i in range(K):
        bi = blocks[i]
        for j in range(i + 1, K):
            bj = blocks[j]
            rhs = -A[np.ix_(bj, bi)]
            for k in range(i + 1, j):
                rhs = rhs - A[np.ix_(bj, blocks[k])] @ S[np.ix_(blocks[k], bi)]
            if not np.any(rhs):
                continue
            try:
                P = sla.solve_sylvester(A[np.ix_(bj, bj)], -A[np.ix_(bi, bi)], rhs)
            except (np.linalg.LinAlgError, ValueError):
                P = np.full(rhs.shape, np.nan)
            if not np.all(np.isfinite(P)):
                return f"blocks {i} and {j} share eigenvalues (singular Sylvester equation)"
            S[np.ix_(bj, bi)] = P
    pairs_cols, real_cols, lam_pairs, lam_reals, pair_blk, real_blk = [], [], [], [], [], []
    for k, bk in enumerate(blocks):
        basis = _real_basis(A[np.ix_(bk, bk)])
        if basis is None:
            return f"eigenvalues of block {k} do not split into real values and conjugate pairs"
        lp, lr, Vk = basis
        cols = np.zeros((n, bk.size))
        cols[bk] = Vk
        cols = S @ cols
        pairs_cols.append(cols[:, :2 * lp.size])
        real_cols.append(cols[:, 2 * lp.size:])
        lam_pairs.append(lp)
        lam_reals.append(lr)
        pair_blk += [k] * (2 * lp.size)
        real_blk += [k] * lr.size
    V = np.hstack(pairs_cols + real_cols)
    state_block = np.array(pair_blk + real_blk, dtype=np.int64)
    return V, np.concatenate(lam_pairs), np.concatenate(lam_reals), state_block, feeds


def _downstream(feeds):
    """reach[i, j]: block j is block i or lies downstream of it (transitive closure)."""
    K = feeds.shape[0]
    reach = np.eye(K, dtype=bool)
    for i in reversed(range(K)):
        for j in range(i + 1, K):
            if feeds[j, i]:
                reach[i] |= reach[j]
    return reach


def to_modal(sysd: StateSpace, max_cond: float = 1e8, form: str = "auto",
             markov_steps: int = 256, markov_tol: float = 1e-9, blocks=None) -> ModalForm:
    """Real block-diagonal (modal) form of a discrete system, or the dense form if unsafe.

    Steps: balance the state scaling (``scipy.linalg.matrix_balance``: the plant's states mix
    metres ~1e-6, amperes ~1e-6 and volts ~100), compute eigenvalues and right/left
    eigenvectors of the balanced matrix, build real 2x2 blocks from conjugate pairs, normalize
    the columns, and then check:

    * ``cond`` of the eigenvector basis <= ``max_cond`` (a defective or nearly defective
      matrix, e.g. a Jordan block or two nearly equal damped modes that couple, has nearly
      parallel eigenvectors and fails this);
    * the similarity residual ``|A T - T A_m| / (|A| |T|)`` and the first ``markov_steps``
      Markov parameters ``C A^k B`` of both forms agree to ``markov_tol`` (relative).

    Exactly repeated but non-defective eigenvalues (identical, decoupled filters) pass: only the
    eigenvector basis matters, not the eigenvalue spacing.

    **Cascades** (``blocks``): a plant built from subsystems that only feed downstream (amplifier
    -> mechanics -> anti-alias filters) has a block lower-triangular ``A``. Diagonalizing it as a
    whole mixes the subsystems numerically, so every output picks up round-off-sized
    coefficients on states it cannot depend on. With ``blocks`` the matrix is first
    block-diagonalized (one Sylvester equation per coupled pair of subsystems), then each
    subsystem is diagonalized on its own: the basis vectors of a subsystem are zero upstream of
    it, and ``C`` has exact zeros on the states of every subsystem an output does not depend on
    (set explicitly from the coupling graph, and verified by the Markov check), which a kernel
    can skip. The same checks apply to the combined basis; if they fail, the plain
    eigendecomposition is tried before falling back to dense.

    Parameters
    ----------
    sysd : StateSpace
        Discrete system.
    max_cond : float
        Largest acceptable condition number of the eigenvector basis.
    form : {"auto", "modal", "dense"}
        ``"auto"`` falls back to dense when a check fails; ``"modal"`` raises ``ModelError``
        instead; ``"dense"`` skips the decomposition.
    blocks : sequence of array_like of int, optional
        A partition of the states into subsystems, upstream first: no block may depend on a
        later one (``A[b_i, b_j] = 0`` for ``i < j``, to ``1e-14 |A|``).

    Returns
    -------
    ModalForm

    Examples
    --------
    >>> from rtctl.plant.lti import StateSpace, c2d, to_modal
    >>> osc = StateSpace([[0.0, 1.0], [-1e6, -20.0]], [[0.0], [1.0]], [[1.0, 0.0]], [[0.0]])
    >>> mf = to_modal(c2d(osc, 1 / 48000))
    >>> mf.form, mf.n_pairs, mf.n_real
    ('modal', 1, 0)
    """
    if not sysd.is_discrete:
        raise ModelError("to_modal() expects a discrete system; discretize with c2d() first")
    if form not in ("auto", "modal", "dense"):
        raise ModelError(f"form must be 'auto', 'modal' or 'dense', got {form!r}")
    n = sysd.n_states
    if blocks is not None:
        blocks = _check_blocks(blocks, n)
    A, B, C = sysd.A, sysd.B, sysd.C
    # Without permutation every entry LAPACK returns is a scale factor; scipy still casts them
    # all to int for a permutation it then discards, and a factor beyond 2**63 (a stiff model:
    # 3.8e22 for a 1 m beam at 1.5 kHz) warns on that unused cast.
    with np.errstate(invalid="ignore"):
        _, (scale, _perm) = sla.matrix_balance(A, permute=False, separate=True)
    Ab = A / scale[:, None] * scale[None, :]

    def dense(reason, cond=np.inf, eig_cond=np.inf):
        T = np.diag(scale)
        s = sysd._replace(A=Ab, B=B / scale[:, None], C=C * scale[None, :], state_names=())
        return ModalForm(s, "dense", T, float(cond), float(eig_cond), 0, n, reason)

    if form == "dense" or n == 0:
        return dense("dense form requested")

    lam, vl, vr = sla.eig(Ab, left=True, right=True)
    dots = np.abs(np.einsum("ij,ij->j", vl.conj(), vr))
    norms = np.linalg.norm(vl, axis=0) * np.linalg.norm(vr, axis=0)
    eig_cond = float(np.max(norms / np.maximum(dots, np.finfo(float).tiny)))

    def checked(V, lam_pairs, lam_reals, state_block=None, zero=None):
        """ModalForm for the basis V, or a failure reason."""
        n_pairs, n_real = lam_pairs.size, lam_reals.size
        # Columns are not rescaled one by one: a and b of a pair must share one scale for the
        # block to stay [[sigma, omega], [-omega, sigma]].
        cond = float(np.linalg.cond(V)) if np.all(np.isfinite(V)) else np.inf
        if not (cond <= max_cond):
            return (f"eigenvector basis condition {cond:.3g} > max_cond {max_cond:.3g} "
                    "(near-defective eigenvalues)", cond)
        Am = _block_matrix(lam_pairs, lam_reals)
        Vinv = np.linalg.inv(V)
        Bm = Vinv @ (B / scale[:, None])
        Cm = (C * scale[None, :]) @ V
        if zero is not None:
            Cm[zero] = 0.0
        resid = np.linalg.norm(Ab @ V - V @ Am) / (np.linalg.norm(Ab) * np.linalg.norm(V))
        if not resid <= markov_tol:
            return f"similarity residual {resid:.3g} > {markov_tol:.3g}", cond
        merr = _markov_error(A, B, C, Am, Bm, Cm, markov_steps)
        if not merr <= markov_tol:
            return (f"impulse response differs by {merr:.3g} (relative) over {markov_steps} "
                    "samples", cond)
        s = sysd._replace(A=Am, B=Bm, C=Cm, state_names=())
        T = scale[:, None] * V
        return ModalForm(s, "modal", T, cond, eig_cond, n_pairs, n_real,
                         f"eigenvector basis condition {cond:.3g} <= {max_cond:.3g}", state_block)

    notes = ""
    if blocks is not None:
        zero_tol = 1e-14 * float(np.linalg.norm(Ab))
        got = _cascade_basis(Ab, blocks, zero_tol)
        if isinstance(got, str):
            notes = f"cascade realization failed ({got}); "
        else:
            V, lam_pairs, lam_reals, state_block, feeds = got
            # Output o depends on block k iff C reads a block at or downstream of k.
            reach = _downstream(feeds)
            reads = np.array([[np.any(C[o, bk] != 0.0) for bk in blocks]
                              for o in range(C.shape[0])], dtype=bool).reshape(-1, len(blocks))
            depends = (reads.astype(int) @ reach.T.astype(int)) > 0   # (n_outputs, n_blocks)
            zero = ~depends[:, state_block]
            mf = checked(V, lam_pairs, lam_reals, state_block, zero)
            if isinstance(mf, ModalForm):
                return dataclasses_replace(mf, reason=mf.reason + f"; cascade of {len(blocks)} "
                                           "subsystems")
            notes = f"cascade realization failed ({mf[0]}); "

    basis = _real_basis(Ab)
    if basis is None:
        return _fail(form, dense, notes + "eigenvalues do not split into real values and "
                     "conjugate pairs", eig_cond=eig_cond)
    lam_pairs, lam_reals, V = basis
    mf = checked(V, lam_pairs, lam_reals)
    if isinstance(mf, ModalForm):
        return dataclasses_replace(mf, reason=notes + mf.reason) if notes else mf
    return _fail(form, dense, notes + mf[0], mf[1], eig_cond)


def _fail(form, dense, reason, cond=np.inf, eig_cond=np.inf):
    if form == "modal":
        raise ModelError(f"modal form is unsafe: {reason}; use form='auto' to fall back to the "
                         "dense form, or separate the offending eigenvalues")
    return dense("fell back to dense: " + reason, cond, eig_cond)
