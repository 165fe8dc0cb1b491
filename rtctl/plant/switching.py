"""A bimorph group whose finger load changes at block boundaries: the finger presses harder (another
measured Maxwell set), lifts off, comes back, while the loop runs.

Every load state a run visits (a :class:`~rtctl.plant.finger.MaxwellLoad`, or ``None`` without
contact) has its own :class:`~rtctl.plant.bimorph.BimorphPlant`: its modes are those of the beam
*under that load*, so no realization serves two loads. :class:`SwitchedSimGroup` discretizes each
of them once, exactly as :class:`~rtctl.plant.bimorph.SimGroup` does, and precomputes the state map
of every ordered pair of loads. Its kernel reads the requested load from a ``(1, 1)`` float64 array
(``group.load``, written only by the engine's parameter queue) and, when it differs from the
active one, maps every channel's state and switches matrices before the block's first sample:
nothing is allocated and nothing but a matrix-vector product per channel runs at a switch.

The state map (:func:`load_map`), in the plants' own coordinates ``(eta, eta', f, V, aa)``:

* **Beam: position and velocity continuous.** The finite-element deflection
  ``q = Phi_i eta + r_i V`` and velocity ``q' = Phi_i eta' + r_i V'`` of the old load are projected
  onto the new load's modes in the new load's mass metric (``Phi_j`` is ``M_j``-orthonormal: the
  projection ``Phi_j^T M_j`` is the least kinetic-energy-norm fit), constrained to reproduce the
  tip DOF exactly: the tip displacement and velocity the trace shows are continuous to rounding,
  whatever the truncation does elsewhere. ``V' = w_a (u - V)`` is taken with the block's first
  drive sample ``u`` (the held input the tip velocity output uses at that sample), so the map has
  a term in ``u``.
* **Velocity, not momentum.** When the finger comes back, its skin mass takes the tip's velocity
  (the finger is put down moving with the tip; a plastic impact would instead keep the momentum
  and slow the first mode to ``m_eff / (m_eff + m_skin)``, a fifth for the bundled beam's 26 mg
  against 100 mg of skin). When it lifts, the beam keeps its velocity and the skin keeps its own.
* **Branch forces** ``f_k`` carry over, branch by branch (by index), while the finger stays (a
  change of Maxwell set: a branch the new set does not have is dropped, a new one starts at 0);
  they are 0 when the finger lifts, and 0 when it comes back (the tissue returns relaxed).
* **The finger's rest position** is the tip's undriven, undeflected position (``x = 0``), the
  same as when the run started: the linear bonded model has one rest position, and the finger
  comes back to the same spot of the display. Coming back onto a deflected tip therefore loads it
  at once with ``k0 x`` (the branches, relaxed, only see what moves after). This keeps every load
  state's steady state the one its own scene gives: a run that switched converges to a run that
  never did.
* **Amplifier and anti-alias states** are the electronics': unchanged.
"""

from __future__ import annotations

import numpy as np

from rtctl._numba import kernel
from rtctl.errors import ModelError
from rtctl.plant import _kernels
from rtctl.plant.bimorph import BimorphPlant, SimGroup, realization, sim_group_process

__all__ = ["SwitchedSimGroup", "load_map", "switched_group_process"]


def load_map(src: BimorphPlant, dst: BimorphPlant):
    """The state map from ``src``'s load to ``dst``'s (see the module docstring).

    Both plants must share the beam, amplifier, current sense and the number of modes: only the
    finger may differ.

    Returns
    -------
    M : ndarray, shape (dst.sys.n_states, src.sys.n_states)
    g : ndarray, shape (dst.sys.n_states,)
        ``x_dst = M x_src + g u`` with ``u`` the commanded voltage held over the first sample
        after the switch.
    """
    if (dst.fe is not src.fe or dst.amplifier != src.amplifier or not dst.sense.same_analog(src.sense)
            or dst.n_modes != src.n_modes):
        raise ModelError("a load switch needs two plants of the same beam, amplifier, current sense "
                         "and number of modes; only the finger may differ")
    nr, ni, nj = src.n_modes, src.sys.n_states, dst.sys.n_states
    bi, bj = src.n_branches, dst.n_branches
    tip = dst.tip
    phi_j, M_j = dst.mode_shapes, dst.mass_matrix
    c = phi_j[tip]                                       # tip row of the new modes
    P = phi_j.T @ M_j                                    # M_j-orthogonal projection onto Phi_j
    # Constrained fit: eta = P y + c (y_tip - c.P y) / |c|^2 puts the tip exactly at y_tip.
    Pc = P - np.outer(c, c @ P) / (c @ c)
    Pc[:, tip] += c / (c @ c)
    dr = src.static_correction - dst.static_correction
    wa = src.amplifier.omega
    M = np.zeros((nj, ni))
    g = np.zeros(nj)
    e, v = slice(0, nr), slice(nr, 2 * nr)
    Vi, Vj = 2 * nr + bi, 2 * nr + bj
    M[e, e] = Pc @ src.mode_shapes
    M[e, Vi] = Pc @ dr
    M[v, v] = Pc @ src.mode_shapes
    M[v, Vi] = -wa * (Pc @ dr)
    g[v] = wa * (Pc @ dr)
    if src.finger is not None and dst.finger is not None:
        for k in range(min(bi, bj)):
            M[2 * nr + k, 2 * nr + k] = 1.0
    M[Vj, Vi] = 1.0
    M[Vj + 1:, Vi + 1:] = np.eye(nj - Vj - 1)            # anti-alias states
    return M, g


def _solve_equilibrated(T, Y):
    """``T^-1 Y`` with ``T``'s rows and columns scaled to unit size first: a realization's
    transform mixes metres, volts and amperes (condition ~1e13 from units alone)."""
    r = 1.0 / np.max(np.abs(T), axis=1)
    col = np.max(np.abs(T * r[:, None]), axis=0)
    col[col == 0.0] = 1.0
    Ts = T * r[:, None] / col[None, :]
    return np.linalg.solve(Ts, Y * r[:, None] if Y.ndim == 2 else Y * r) / (
        col[:, None] if Y.ndim == 2 else col)


@kernel
def _switch_state(m, g, X, drive, nc):
    """Every channel's persistent state (slot 0 of ``X``) <- ``m x + g u`` (``u`` the first drive
    sample), through slot 1 as scratch; rows past the new load's states come out 0."""
    n = X.shape[0]
    for i in range(n):
        row = m[i]
        gi = g[i]
        out = X[i, nc:2 * nc]
        for ch in range(nc):
            out[ch] = gi * drive[ch, 0]
        for q in range(n):
            mq = row[q]
            if mq != 0.0:
                src = X[q, 0:nc]
                for ch in range(nc):
                    out[ch] += mq * src[ch]
    for i in range(n):
        dst = X[i, 0:nc]
        src = X[i, nc:2 * nc]
        for ch in range(nc):
            dst[ch] = src[ch]


@kernel
def switched_group_process(load, active, dims, sizes, a_all, reals_all, b_all, d_all, plan_all,
                           coef_all, smap, gmap, X, ut, ys, adc, table1, table2, ipos,
                           drive, sensed, truth):
    """:func:`~rtctl.plant.bimorph.sim_group_process` with the load chosen by ``load[0, 0]``.

    ``load[0, 0]`` is the requested load's index (a float: the parameter queue writes float64);
    ``active[0]`` the one running. When they differ, every channel's state is mapped by
    ``smap[active, load]``/``gmap[active, load]`` with this block's first drive sample, then the
    block runs on the new load's realization (a value that is not a load index is ignored).
    Per load ``s``: ``dims[s] = (a rows, a columns, real modes, states, output tiles)``, its
    coefficients the leading parts of the rows of ``a_all`` (flattened), ``reals_all``, ``b_all``,
    ``d_all``, ``plan_all`` and ``coef_all``; ``sizes[s]`` as ``sim_group_process``'s ``sizes``.
    """
    nl = dims.shape[0]
    s = active[0]
    want = load[0, 0]
    if want >= 0.0 and want < nl:                        # False for NaN
        w = int(want)
        if w != s:
            _switch_state(smap[s, w], gmap[s, w], X, drive, drive.shape[0])
            active[0] = w
            s = w
    na = dims[s, 0]
    ncol = dims[s, 1]
    a = a_all[s, :na * ncol].reshape((na, ncol))
    return sim_group_process(sizes[s], a, reals_all[s, :dims[s, 2]], b_all[s, :dims[s, 3]], d_all[s],
                             plan_all[s, :dims[s, 4]], coef_all[s, :dims[s, 4]], X, ut, ys, adc,
                             table1, table2, ipos, drive, sensed, truth)


class SwitchedSimGroup(SimGroup):
    """A :class:`~rtctl.plant.bimorph.SimGroup` whose finger load switches among ``plants``.

    Parameters
    ----------
    plants : sequence of BimorphPlant
        One per load state (same beam, amplifier, sense and number of modes; the finger differs).
    fs, n_channels, sense, seed, max_block, chunk, form, max_cond
        As :class:`~rtctl.plant.bimorph.SimGroup`; every load gets its own realization, built the
        way ``SimGroup`` builds its one (so until the first switch the group runs bitwise as a
        ``SimGroup`` of ``plants[initial]``).
    initial : int
        The load after :meth:`reset`.

    Attributes
    ----------
    load : ndarray, shape (1, 1), float64
        The requested load index. Between runs :meth:`reset` writes it; during a run only the
        block function may (the engine's parameter queue): the kernel switches when it differs
        from the active load, at the start of the block.
    loads : tuple
        Each load state's finger (``MaxwellLoad`` or None), in index order.
    plants, realizations
        Per load: the plant and its :class:`~rtctl.plant.lti.ModalForm`.
    maps : dict
        ``(i, j) -> (M, g)`` in plant coordinates (:func:`load_map`).
    """

    def __init__(self, plants, fs: float, n_channels: int, initial: int = 0, sense=None, seed=None,
                 max_block: int = 64, chunk: int = 8, form: str = "auto", max_cond: float = 1e8):
        plants = list(plants)
        if not plants or not all(isinstance(p, BimorphPlant) for p in plants):
            raise ModelError("SwitchedSimGroup needs a list of BimorphPlant, one per load state")
        if not 0 <= int(initial) < len(plants):
            raise ModelError(f"initial load {initial!r} is not an index of the {len(plants)} plants")
        initial = int(initial)
        super().__init__(plants[initial], fs, n_channels, sense, seed, max_block, chunk, form, max_cond)
        self.initial, self.plants = initial, tuple(plants)
        self.loads = tuple(p.finger for p in plants)
        self.maps = {(i, j): load_map(plants[i], plants[j])
                     for i in range(len(plants)) for j in range(len(plants)) if i != j}
        base = self.args
        L = len(plants)
        reals_, coefs = [], []
        for i, p in enumerate(plants):
            if i == initial:
                r = (self.sysd, self.modal, int(base[0][0]), base[1], base[2])
                pc = (base[5], base[6])
            else:
                r = realization(p, self.fs, form, max_cond)
                pc = _kernels.output_plan(r[1].sys.C)
            reals_.append(r)
            coefs.append(pc)
        self.realizations = tuple(r[1] for r in reals_)
        ns = [m.sys.n_states for m in self.realizations]
        N = max(ns)
        n_out = self.realizations[0].sys.n_outputs
        dims = np.zeros((L, 5), dtype=np.int64)
        sizes = np.tile(base[0], (L, 1))
        a_all = np.zeros((L, max(r[3].size for r in reals_)))
        reals_all = np.zeros((L, max(1, max(r[4].size for r in reals_))))
        b_all = np.zeros((L, N))
        d_all = np.zeros((L, n_out))
        nt = max(pc[0].shape[0] for pc in coefs)
        plan_all = np.zeros((L, nt, _kernels.PLAN_COLUMNS), dtype=np.int64)
        coef_all = np.zeros((L, nt, 3, 8))
        for i, ((_, m, code, a, reals), (plan, coef)) in enumerate(zip(reals_, coefs)):
            dims[i] = (a.shape[0], a.shape[1], reals.size, ns[i], plan.shape[0])
            sizes[i, 0] = code
            a_all[i, :a.size] = a.ravel()
            reals_all[i, :reals.size] = reals
            b_all[i, :ns[i]] = m.sys.B[:, 0]
            d_all[i] = m.sys.D[:, 0]
            plan_all[i, :plan.shape[0]] = plan
            coef_all[i, :plan.shape[0]] = coef
        # The maps in each realization's coordinates: z_j = T_j^-1 (M T_i z_i + g u).
        smap = np.zeros((L, L, N, N))
        gmap = np.zeros((L, L, N))
        for (i, j), (M, g) in self.maps.items():
            Ti, Tj = self.realizations[i].T, self.realizations[j].T
            if not np.all(np.any(Tj != 0.0, axis=0)):
                raise ModelError(f"load state {j}: its realization has a mode the drive cannot "
                                 "reach, which a switched state could excite; use form='dense'")
            smap[i, j, :ns[j], :ns[i]] = _solve_equilibrated(Tj, M @ Ti)
            gmap[i, j, :ns[j]] = _solve_equilibrated(Tj, g)
        for i in range(L):
            smap[i, i] = np.eye(N)
        ch = int(base[0][3])
        self.n_states = N
        self.load = np.full((1, 1), float(initial))
        self.active = np.array([initial], dtype=np.int64)
        self.kernel = switched_group_process
        self.args = (self.load, self.active, dims, sizes, a_all, reals_all, b_all, d_all, plan_all,
                     coef_all, smap, gmap,
                     _kernels.aligned_zeros((N, (ch + 1) * self.n_channels)),   # X
                     base[8], base[9], base[10], base[11], base[12], base[13])
        self._x = 12

    @property
    def state(self) -> np.ndarray:
        """Current state in the active load's realization, shape (n_states of that load,
        n_channels) (a view)."""
        n = self.realizations[int(self.active[0])].sys.n_states
        return self.args[self._x][:n, :self.n_channels]

    def physical_state(self) -> np.ndarray:
        """Current state in the active load's plant coordinates, a copy."""
        return self.realizations[int(self.active[0])].T @ self.state

    def reset(self) -> None:
        """Zero all states, back to the initial load, restart the noise sequence."""
        self.args[self._x][:] = 0.0
        self.args[-1][:] = self._ipos0
        self.load[0, 0] = float(self.initial)
        self.active[0] = self.initial
