"""Switched-linear ("piecewise linear") plants: end stops, unilateral contacts, latches.

A continuous model here is one physical state vector ``x`` (n), inputs ``u`` (m) and ``s``
*switches*, each on while a linear function of state and input is positive::

    bit_i = [ S_i . (x, u, 1) > 0 ]              mode = sum_i bit_i 2^i     (2^s modes)
    x' = A_mode x + B_mode u + e_mode            y = C_mode x + D_mode u + y0_mode

Every mode is linear, so every mode is discretized *exactly* by the matrix exponential
(:func:`rtctl.plant.lti.c2d`'s Van Loan method, zero-order hold) at the substep
``h = 1 / (fs * substeps)``: a 1e9 N/m end stop or a 1e-8 s relaxation time is stable and exact
inside its mode, never integrated explicitly. Per substep the kernel applies
``x <- Phi_mode x + Gamma_mode (u, 1)`` and re-evaluates the switches.

**Switching times.** Without localization (``levels=0``) a switch takes effect at the next
substep boundary: the switching time is resolved only to ``h`` (first order). For a stiff
penalty that is an O(1) energy error: engaging late starts the spring pre-compressed (it *adds*
``k d^2 / 2``; a 0.3 m/s pin 0.8 um into a 1e8 N/m stop gains 7x its kinetic energy), letting
go late lets it pull (energy lost); a 1 g mass bouncing at 0.3 m/s on a 1e8 N/m stop at 4
substeps of 48 kHz rebounds 14 % slow.
With ``levels=K`` the kernel also holds the exact steps ``Phi(h 2^-k)``, ``k = 0..K``, and
localizes each switch by bisection: it tries the largest power-of-two piece of the remaining
substep, halves it while the mode at its end differs, and crosses the surface with a piece of
``h 2^-K``. The switching time is then resolved to ``h 2^-K`` at a cost of ~2K extra small steps
per switch and nothing between switches. ``max_events`` bounds the localized switches per
substep (a state resting on a surface could chatter); beyond it the rest of the substep is taken
first order, so the cost of a substep is bounded.

**Penalty elements** (:func:`unilateral`) keep the state continuous across every switch: the
element's force is zero on its switching surface (a spring ``k d`` switches on at ``d = 0``;
with a damper, ``k d + c d'`` must also be positive, so the element never pulls, and the force
is continuous where it lets go). The state is continuous, the mode is a function of the state
and the input, so the kernel keeps no mode memory: any split of a signal into blocks gives the
same samples.

The builder (:class:`HybridBuilder`) assembles a model from linear forms (:class:`Lin`);
contacts (:mod:`rtctl.plant.contact`), the solenoid pin (:mod:`rtctl.plant.solenoid`) and other
switched actuators build on it, and :class:`HybridGroup` runs any such model under the
simulated-group contract (``kernel(*args, drive, sensed, truth) -> status``).
"""

from __future__ import annotations

import inspect
import math

import numpy as np
import scipy.linalg as sla

from rtctl._numba import TINY, kernel
from rtctl.errors import ModelError

__all__ = ["Lin", "HybridBuilder", "HybridModel", "HybridGroup", "unilateral",
           "hybrid_process", "MAX_SWITCHES", "TRUTH_NAMES"]

#: Truth rows of the simulated-group contract, in order.
TRUTH_NAMES = ("height_m", "velocity_m_s", "force_n", "voltage_v")
#: Upper bound on switches: 2^s modes are discretized and stored, (K + 1) steps each.
MAX_SWITCHES = 10
_ONE = ("1", 0)


class Lin:
    """A linear form ``sum_i a_i x_i + sum_j b_j u_j + c`` of the state, the inputs and 1.

    Forms add, subtract and scale by numbers; a builder turns them into matrix rows. States and
    inputs are named by their index in the builder.

    Examples
    --------
    >>> from rtctl.plant.hybrid import Lin
    >>> gap = Lin.x(0) - Lin.x(1) - 1e-6      # pin height - skin height - 1 um
    >>> (2.0 * gap).row(n=2, m=1)             # coefficients on (x0, x1, u0, 1)
    array([ 2.e+00, -2.e+00,  0.e+00, -2.e-06])
    """

    __slots__ = ("terms",)

    def __init__(self, terms=None):
        self.terms = {k: float(v) for k, v in (terms or {}).items()}

    @classmethod
    def x(cls, i: int, coef: float = 1.0) -> Lin:
        """``coef * x_i``."""
        return cls({("x", int(i)): coef})

    @classmethod
    def u(cls, j: int, coef: float = 1.0) -> Lin:
        """``coef * u_j``."""
        return cls({("u", int(j)): coef})

    @classmethod
    def const(cls, c: float) -> Lin:
        return cls({_ONE: c})

    def __add__(self, other):
        other = other if isinstance(other, Lin) else Lin.const(other)
        out = dict(self.terms)
        for k, v in other.terms.items():
            out[k] = out.get(k, 0.0) + v
        return Lin(out)

    __radd__ = __add__

    def __neg__(self):
        return Lin({k: -v for k, v in self.terms.items()})

    def __sub__(self, other):
        return self + (-(other if isinstance(other, Lin) else Lin.const(other)))

    def __rsub__(self, other):
        return (-self) + other

    def __mul__(self, a):
        a = float(a)
        return Lin({k: a * v for k, v in self.terms.items()})

    __rmul__ = __mul__

    def row(self, n: int, m: int) -> np.ndarray:
        """Coefficients on ``z = (x, u, 1)``, shape ``(n + m + 1,)``."""
        r = np.zeros(n + m + 1)
        for (kind, i), v in self.terms.items():
            if kind == "x":
                if not 0 <= i < n:
                    raise ModelError(f"linear form uses state {i}, but the model has {n} states")
                r[i] += v
            elif kind == "u":
                if not 0 <= i < m:
                    raise ModelError(f"linear form uses input {i}, but the model has {m} inputs")
                r[n + i] += v
            else:
                r[n + m] += v
        return r


class HybridBuilder:
    """Assemble a switched-linear model term by term.

    Parameters
    ----------
    input_names : sequence of str
        Inputs in order, with units in the names; input 0 is the drive of a simulated group,
        the others are per-channel parameters held between blocks (e.g. ``"preload_n"``).

    Examples
    --------
    A mass on a spring that hits a stop at 1 mm (a unilateral spring, no damper):

    >>> from rtctl.plant.hybrid import HybridBuilder, Lin, unilateral
    >>> b = HybridBuilder(["force_n"])
    >>> x, v = b.add_state("x_m"), b.add_state("v_m_s")
    >>> b.derivative(x, Lin.x(v))
    >>> b.derivative(v, Lin.u(0, 1e3) - Lin.x(x, 1e4))            # m = 1 g, k = 10 N/m
    >>> when, force = unilateral(b, "stop", Lin.x(x) - 1e-3, Lin.x(v), 1e6, 0.0, [(v, -1e3)])
    >>> b.output("x_m", Lin.x(x))
    0
    >>> model = b.build()
    >>> model.n_modes, model.mode([2e-3, 0.0], [0.0])
    (2, 1)
    """

    def __init__(self, input_names):
        self.input_names = tuple(str(s) for s in input_names)
        if not self.input_names:
            raise ModelError("a hybrid model needs at least one input (the drive)")
        self.state_names: list[str] = []
        self.output_names: list[str] = []
        self.switch_names: list[str] = []
        self._switches: list[Lin] = []
        self._dyn: list[tuple[int, Lin, tuple]] = []
        self._out: list[tuple[int, Lin, tuple]] = []

    def add_state(self, name: str) -> int:
        """Append a state; returns its index."""
        self.state_names.append(str(name))
        return len(self.state_names) - 1

    def add_switch(self, name: str, form: Lin) -> int:
        """Append a switch that is on while ``form > 0``; returns its bit number."""
        if len(self._switches) >= MAX_SWITCHES:
            raise ModelError(f"at most {MAX_SWITCHES} switches ({2 ** MAX_SWITCHES} modes); "
                             "merge elements that can never act together")
        self.switch_names.append(str(name))
        self._switches.append(form)
        return len(self._switches) - 1

    def derivative(self, i: int, form: Lin, when=()) -> None:
        """Add ``form`` to ``x_i'`` in every mode where all switches ``when`` are on."""
        self._dyn.append((int(i), form, tuple(int(w) for w in when)))

    def output(self, name: str, form: Lin, when=()) -> int:
        """Append an output ``form`` (in modes where all ``when`` are on); returns its row."""
        self.output_names.append(str(name))
        row = len(self.output_names) - 1
        self._out.append((row, form, tuple(int(w) for w in when)))
        return row

    def add_to_output(self, row: int, form: Lin, when=()) -> None:
        """Add ``form`` to output ``row`` in modes where all switches ``when`` are on."""
        if not 0 <= row < len(self.output_names):
            raise ModelError(f"output row {row} does not exist; add it with output() first")
        self._out.append((int(row), form, tuple(int(w) for w in when)))

    def build(self) -> HybridModel:
        n, m, s = len(self.state_names), len(self.input_names), len(self._switches)
        if n == 0:
            raise ModelError("a hybrid model needs at least one state")
        nz, p, n_modes = n + m + 1, len(self.output_names), 1 << s
        M = np.zeros((n_modes, n, nz))
        Y = np.zeros((n_modes, p, nz))
        masks = np.arange(n_modes)
        for target, terms in ((M, self._dyn), (Y, self._out)):
            for i, form, when in terms:
                if any(not 0 <= w < s for w in when):
                    raise ModelError(f"term uses switch {when}, but only {s} switches exist")
                need = sum(1 << w for w in when)
                on = (masks & need) == need
                target[on, i] += form.row(n, m)
        S = np.array([f.row(n, m) for f in self._switches]).reshape(s, nz)
        return HybridModel(M, Y, S, tuple(self.state_names), self.input_names,
                           tuple(self.output_names), tuple(self.switch_names))


def unilateral(builder: HybridBuilder, name: str, gap: Lin, rate: Lin, k: float, c: float,
               acts_on, output_row: int | None = None):
    """Add a penalty spring-damper that pushes but never pulls.

    Force ``F = k d + c d'`` with ``d = gap`` (penetration, m) and ``d' = rate`` (m/s, which must
    be the time derivative of ``gap``): on while ``d > 0`` and, if ``c > 0``, also ``F > 0``
    (so the damper cannot pull a separating body back; the force is zero on both switching
    surfaces except at impact, where ``c d'`` starts the force, as in a Kelvin-Voigt contact).

    Parameters
    ----------
    builder : HybridBuilder
    name : str
        Switch names ``name + "_gap"`` and ``name + "_push"``.
    gap, rate : Lin
    k : float
        Penalty stiffness, N/m (> 0).
    c : float
        Penalty damping, N s/m (>= 0).
    acts_on : sequence of (int, float)
        ``(state row, gain)``: ``gain * F`` is added to that state's derivative (e.g.
        ``(v_pin, -1 / m_pin)``, ``(v_skin, +1 / m_skin)``).
    output_row : int, optional
        Add ``F`` to this output row while on.

    Returns
    -------
    when : tuple of int
        The switch bits that must all be on for the element to act.
    force : Lin
        ``k gap + c rate`` (valid only while on).
    """
    k, c = float(k), float(c)
    if not (k > 0.0 and math.isfinite(k)) or not (c >= 0.0 and math.isfinite(c)):
        raise ModelError(f"{name}: penalty stiffness must be > 0 and damping >= 0, got k={k!r}, "
                         f"c={c!r}")
    force = gap * k + rate * c
    when = (builder.add_switch(name + "_gap", gap),)
    if c > 0.0:
        when += (builder.add_switch(name + "_push", force),)
    for row, gain in acts_on:
        builder.derivative(row, force * float(gain), when)
    if output_row is not None:
        builder.add_to_output(output_row, force, when)
    return when, force


class HybridModel:
    """A switched-linear continuous model: mode tables and switch functions.

    Parameters
    ----------
    M : ndarray, shape (n_modes, n, n + m + 1)
        ``[A | B | e]`` per mode: ``x' = M[mode] @ (x, u, 1)``.
    Y : ndarray, shape (n_modes, p, n + m + 1)
        ``[C | D | y0]`` per mode.
    S : ndarray, shape (s, n + m + 1)
        Switch ``i`` is on while ``S[i] @ (x, u, 1) > 0``; ``n_modes = 2**s``.
    state_names, input_names, output_names, switch_names : tuple of str

    Notes
    -----
    Build with :class:`HybridBuilder`. ``rhs``/``outputs`` follow the ``(t, x, u)`` convention so
    ``scipy.integrate.solve_ivp`` can run the model as a reference.
    """

    def __init__(self, M, Y, S, state_names, input_names, output_names, switch_names):
        self.M, self.Y, self.S = (np.ascontiguousarray(a, dtype=np.float64) for a in (M, Y, S))
        for nm, a in (("dynamics", self.M), ("outputs", self.Y), ("switches", self.S)):
            if not np.all(np.isfinite(a)):
                raise ModelError(f"the {nm} of the hybrid model contain non-finite entries; "
                                 "check its parameters")
        self.state_names, self.input_names = state_names, input_names
        self.output_names, self.switch_names = output_names, switch_names
        self.n_states, self.n_inputs = len(state_names), len(input_names)
        self.n_outputs, self.n_switches = len(output_names), len(switch_names)
        self.n_modes = 1 << self.n_switches
        # Modes with identical dynamics and outputs (a damper's push switch flips while its gap
        # switch is off) form one class; only a change of class is a switching event.
        # Classes are numbered 0.. in order of their first mode (``class_rep``).
        cls = np.full(self.n_modes, -1, dtype=np.int64)
        reps = []
        for a in range(self.n_modes):
            for c, b in enumerate(reps):
                if np.array_equal(self.M[a], self.M[b]) and np.array_equal(self.Y[a], self.Y[b]):
                    cls[a] = c
                    break
            else:
                cls[a] = len(reps)
                reps.append(a)
        self.mode_class = cls
        self.class_rep = np.array(reps, dtype=np.int64)
        self.n_classes = len(reps)

    def _z(self, x, u):
        u = np.atleast_1d(np.asarray(u, dtype=np.float64))
        if u.size != self.n_inputs:
            raise ModelError(f"u must have {self.n_inputs} entries {self.input_names}, got {u.size}")
        return np.concatenate([np.asarray(x, dtype=np.float64).ravel(), u, [1.0]])

    def mode(self, x, u) -> int:
        """Mode number (bit i = switch i on) at state ``x`` and input ``u``."""
        on = self.S @ self._z(x, u) > 0.0
        return int(sum(1 << i for i in np.flatnonzero(on)))

    def rhs(self, t, x, u):
        """State derivative in the mode the state is in, shape (n,)."""
        z = self._z(x, u)
        return self.M[self.mode(x, u)] @ z

    def outputs(self, x, u):
        """Outputs in the mode the state is in, shape (p,)."""
        z = self._z(x, u)
        return self.Y[self.mode(x, u)] @ z

    def matrices(self, mode: int):
        """``(A, B, e)`` of one mode: shapes (n, n), (n, m), (n,)."""
        n, m = self.n_states, self.n_inputs
        Mm = self.M[int(mode)]
        return Mm[:, :n], Mm[:, n:n + m], Mm[:, n + m]

    def equilibrium(self, u, prefer=None, fixed=None):
        """A state at rest (``x' = 0``) consistent with its own mode, for a constant input.

        Solves ``A_m x = -(B_m u + e_m)`` for every mode (``prefer`` first) and returns the first
        solution whose switches put it in that mode. ``fixed`` (``{state index: value}``)
        replaces those states' equations by ``x_i = value``: pure integrators (a kinematic
        pin's height) are at rest anywhere.

        Returns
        -------
        x : ndarray, shape (n,)
        mode : int
        """
        order = list(range(self.n_modes))
        if prefer is not None:
            order.remove(int(prefer))
            order.insert(0, int(prefer))
        z_u = self._z(np.zeros(self.n_states), u)[self.n_states:]
        for mode in order:
            A = self.M[mode, :, :self.n_states].copy()
            rhs = -(self.M[mode, :, self.n_states:] @ z_u)
            for i, value in (fixed or {}).items():
                A[i] = 0.0
                A[i, i] = 1.0
                rhs[i] = value
            # Balanced first: states in m, A and N put ~1e12 between the entries of A.
            _, (sc, _) = sla.matrix_balance(A, permute=False, separate=True)
            Ab = A / sc[:, None] * sc[None, :]
            try:
                if np.linalg.cond(Ab) > 1e12:
                    continue
                x = sc * np.linalg.solve(Ab, rhs / sc)
            except np.linalg.LinAlgError:
                continue
            if self.mode(x, u) == mode:
                return x, mode
        raise ModelError("the hybrid model has no equilibrium at this input (every mode is "
                         "singular or inconsistent); a body may be free to drift, e.g. a skin "
                         "with k0 = 0 out of contact")

    def discretize(self, h: float, levels: int = 0, tol: float = 1e-8):
        """Exact zero-order-hold steps of every mode at ``h 2^-k``, ``k = 0..levels``.

        Each step is ``expm([[A, B, e], [0, 0, 0]] dt)`` of the mode, computed in balanced
        coordinates (``scipy.linalg.matrix_balance``: states mix metres, amperes and newtons).

        Parameters
        ----------
        h : float
            Substep, s.
        levels : int
            Number of halvings kept for switch localization (0..30).
        tol : float
            Largest accepted relative disagreement between a step and the square of the half
            step (a direct test of the matrix exponential's accuracy on this model).

        Returns
        -------
        ndarray, shape (n_classes, levels + 1, n, n + m + 1)
            ``[Phi | Gamma_u | Gamma_1]``: ``x <- PG[mode_class[mode], k] @ (x, u, 1)`` over
            ``h 2^-k``.

        Raises
        ------
        ModelError
            Non-finite steps, a mode that grows more than 2x per substep (an unstable or
            mis-signed model), or an inaccurate matrix exponential (badly scaled model).
        """
        h = float(h)
        levels = int(levels)
        if not (h > 0.0 and math.isfinite(h)) or not 0 <= levels <= 30:
            raise ModelError(f"substep must be > 0 and levels in 0..30, got h={h!r}, "
                             f"levels={levels!r}")
        n, nz = self.n_states, self.n_states + self.n_inputs + 1
        PG = np.empty((self.n_classes, levels + 1, n, nz))
        aug = np.zeros((nz, nz))
        for c, mode in enumerate(self.class_rep):
            aug[:n] = self.M[mode]
            _, (scale, _) = sla.matrix_balance(aug, permute=False, separate=True)
            ab = aug / scale[:, None] * scale[None, :]
            steps = [sla.expm(ab * (h * 0.5 ** k)) for k in range(levels + 2)]
            for k in range(levels + 1):
                eb, half = steps[k], steps[k + 1]
                if not np.all(np.isfinite(eb)):
                    raise ModelError(f"mode {mode} ({self.describe(mode)}): the matrix "
                                     "exponential is not finite; the model is too stiff or "
                                     "unstable at this substep")
                err = np.linalg.norm(eb - half @ half, 1) / max(np.linalg.norm(eb, 1), 1.0)
                if not err <= tol:
                    raise ModelError(f"mode {mode} ({self.describe(mode)}): matrix exponential "
                                     f"inaccurate (step vs squared half step differ by "
                                     f"{err:.2g} > {tol:.2g}); the model is badly conditioned, "
                                     "rescale its states or soften its stiffest element")
                full = eb * scale[:, None] / scale[None, :]      # T eb T^-1
                PG[c, k] = full[:n]
            rho = float(np.max(np.abs(np.linalg.eigvals(PG[c, 0, :, :n]))))
            if rho > 2.0:
                raise ModelError(f"mode {mode} ({self.describe(mode)}) grows {rho:.3g}x per "
                                 "substep: the model is unstable on the substep scale; check "
                                 "the signs of its stiffnesses or raise substeps")
        return PG

    def piece_levels(self, h: float, levels: int, theta: float = 1.0) -> np.ndarray:
        """Smallest allowed piece level per mode class, shape (n_classes,), int64.

        Switches are checked at the end of each piece, so a mode that swings through a switching
        surface and back within one piece would go unnoticed (an underdamped stop mode whose
        whole bounce fits in a substep). In a mode whose fastest oscillation has damped angular
        frequency ``w``, pieces are at most ``h 2^-k`` with ``w h 2^-k <= theta`` (rad), never
        finer than ``levels``. Non-oscillatory (critically damped or slower) modes keep whole
        substeps.
        """
        n = self.n_states
        out = np.zeros(self.n_classes, dtype=np.int64)
        if levels <= 0:
            return out
        for c, mode in enumerate(self.class_rep):
            A = self.M[mode, :, :n]
            _, (sc, _) = sla.matrix_balance(A, permute=False, separate=True)
            lam = np.linalg.eigvals(A / sc[:, None] * sc[None, :])
            w = float(np.max(np.abs(lam.imag))) if lam.size else 0.0
            # Ignore round-off imaginary parts of (nearly) repeated real eigenvalues.
            if w <= 1e-6 * float(np.max(np.abs(lam))):
                w = 0.0
            k = math.ceil(math.log2(w * float(h) / theta)) if w * float(h) > theta else 0
            out[c] = min(int(levels), k)
        return out

    def switch_slopes(self, h: float) -> np.ndarray:
        """``h dS/dt`` per class: ``h S[:, :n] M[rep]``, shape (n_classes, n_switches, nz)."""
        n = self.n_states
        return np.ascontiguousarray(float(h) * np.einsum("sj,cjk->csk", self.S[:, :n],
                                                         self.M[self.class_rep]))

    def relevant_switches(self) -> np.ndarray:
        """Per mode a bit mask of the switches whose flip changes the mode class, int64."""
        out = np.zeros(self.n_modes, dtype=np.int64)
        for mode in range(self.n_modes):
            for i in range(self.n_switches):
                if self.mode_class[mode ^ (1 << i)] != self.mode_class[mode]:
                    out[mode] |= 1 << i
        return out

    def mask(self, *names) -> int:
        """Bit mask of the named switches (e.g. for a probe: all of them on)."""
        try:
            return sum(1 << self.switch_names.index(nm) for nm in names)
        except ValueError:
            raise ModelError(f"unknown switch in {names}; the model has "
                             f"{self.switch_names}") from None

    def describe(self, mode: int) -> str:
        """Names of the switches that are on in ``mode``, e.g. ``"stop_gap+stop_push"``."""
        on = [nm for i, nm in enumerate(self.switch_names) if int(mode) >> i & 1]
        return "+".join(on) if on else "all off"


# --------------------------------------------------------------------------- real-time kernels

@kernel
def _mode_at(S, x, z, n):
    """Mode (bit i = switch i on) at state ``x[:n]`` with the inputs in ``z[n:]``."""
    mask = 0
    nz = z.shape[0]
    for i in range(S.shape[0]):
        acc = 0.0
        for j in range(n):
            acc += S[i, j] * x[j]
        for j in range(n, nz):
            acc += S[i, j] * z[j]
        if acc > 0.0:
            mask |= 1 << i
    return mask


@kernel
def _step(PG, c, k, z, out, n):
    """``out = PG[c, k] @ z`` for the ``n`` state rows, subnormals flushed to zero.

    (Row dot products measured faster than column-wise accumulation at these sizes, n ~ 8.)
    """
    nz = z.shape[0]
    for i in range(n):
        acc = 0.0
        for j in range(nz):
            acc += PG[c, k, i, j] * z[j]
        if abs(acc) < TINY:
            acc = 0.0
        out[i] = acc


@kernel
def _excursion(S, SD, rel, c, z, xt, n, frac):
    """True if a switch may have left its side and come back within a piece that ends on it.

    Only the end points' modes are known; a forced stiff mode can swing through a switching
    surface and back within one piece (a pin pressed onto a stop bounces off and returns).
    For each switch that matters in this mode (bit set in ``rel``) and that heads toward its
    surface at the start, the switch value is interpolated by the cubic Hermite through its
    end values and end slopes (``SD[c] = S A_c`` times the piece length ``frac h``, pre-scaled
    by ``h``) at 1/4, 1/2 and 3/4 of the piece; a sign change there asks for a smaller piece.
    """
    nz = z.shape[0]
    for i in range(S.shape[0]):
        if not (rel >> i) & 1:
            continue
        s0 = 0.0
        d0 = 0.0
        su = 0.0
        du = 0.0
        for j in range(n):
            s0 += S[i, j] * z[j]
            d0 += SD[c, i, j] * z[j]
        for j in range(n, nz):
            su += S[i, j] * z[j]
            du += SD[c, i, j] * z[j]
        s0 += su
        d0 += du
        on = s0 > 0.0
        if (on and d0 >= 0.0) or (not on and d0 <= 0.0):
            continue                                  # heading away from the surface
        s1 = su
        d1 = du
        for j in range(n):
            s1 += S[i, j] * xt[j]
            d1 += SD[c, i, j] * xt[j]
        if (s1 > 0.0) != on:
            continue                                  # an end-point crossing, seen elsewhere
        d0 *= frac
        d1 *= frac
        for q in range(1, 4):
            t = 0.25 * q
            t2 = t * t
            t3 = t2 * t
            p = ((2.0 * t3 - 3.0 * t2 + 1.0) * s0 + (t3 - 2.0 * t2 + t) * d0
                 + (3.0 * t2 - 2.0 * t3) * s1 + (t3 - t2) * d1)
            if (p > 0.0) != on:
                return True
    return False


@kernel
def _substep(PG, S, SD, cls, rel, kmin, z, xt, n, levels, max_events, m_known):
    """Advance ``z[:n]`` by one substep, localizing switches by bisection (see module doc).

    ``PG`` is indexed by mode class (``cls[mode]``): only a change of class is an event.
    Pieces in class ``c`` are at most ``h 2^-kmin[c]`` (:meth:`HybridModel.piece_levels`); a
    piece whose end mode is unchanged is still halved if a switch may have crossed and come
    back inside it (:func:`_excursion`). ``m_known`` is the mode at the current state if known
    (else -1); returns the mode at the new state if it was computed on the way (else -1), so
    that a quiet substep evaluates the switches once.
    """
    full = 1 << levels
    remaining = full
    events = 0
    m0 = m_known
    while remaining > 0:
        if m0 < 0:
            m0 = _mode_at(S, z, z, n)
        c0 = cls[m0]
        k = kmin[c0]
        while (full >> k) > remaining:
            k += 1
        m1 = -1
        while True:
            _step(PG, c0, k, z, xt, n)
            if events >= max_events:
                m1 = -1
                break
            m1 = _mode_at(S, xt, z, n)
            if cls[m1] == c0:
                if k == levels or not _excursion(S, SD, rel[m0], c0, z, xt, n,
                                                 1.0 / (1 << k)):
                    break
            elif k == levels:
                events += 1          # crossed a switching surface within h 2^-levels
                break
            k += 1
        for i in range(n):
            z[i] = xt[i]
        remaining -= full >> k
        m0 = m1
    return m0


@kernel
def hybrid_process(sizes, PG, CD, S, SD, cls, rel, kmin, params, Z, z, xt, adc, pmask, probe,
                   drive, sensed, truth):
    """Advance ``n_channels`` copies of a hybrid model by one block (simulated-group contract).

    Parameters
    ----------
    sizes : int64 array
        ``(n_states, n_inputs, substeps, levels, max_events, n_sensed)``.
    PG : (n_classes, levels + 1, n, nz)
        Exact steps (:meth:`HybridModel.discretize`), ``nz = n + n_inputs + 1``, indexed by
        mode class.
    CD : (n_modes, 4 + n_sensed, nz)
        Output rows: the 4 truth rows, then the sensed rows.
    S : (n_switches, nz)
    SD : (n_classes, n_switches, nz)
        Switch slopes per class times the substep: ``h S[:, :n] M[c]``.
    cls : (n_modes,) int64
        Mode class (:attr:`HybridModel.mode_class`).
    rel : (n_modes,) int64
        Bit i set if flipping switch i changes the class of the mode.
    kmin : (n_classes,) int64
        Smallest piece level per class (:meth:`HybridModel.piece_levels`).
    params : (n_channels, n_inputs - 1)
        Inputs 1.. per channel, held over the block (written by Python between blocks).
    Z : (n_channels, n)
        Per channel the state.
    z, xt : (nz,), (n,)
        Scratch: ``z = (x, u, 1)`` of the channel being advanced.
    adc : (n_sensed, 2)
        Per sensed row ``(lsb, full_scale)``: clipped to +-full_scale (status bit 1), rounded
        to a multiple of ``lsb`` (none if 0).
    pmask : (n_probe,) int64
        Probe row r: fraction of channels whose mode has all bits of ``pmask[r]`` on.
    probe : (n_probe, max_block)
        Written for the first ``max_block`` samples.
    drive : (n_channels, B)
        Input 0 per sample (zero-order hold).
    sensed : (n_channels * n_sensed, B)
    truth : (n_channels, 4, B)

    Returns
    -------
    int
        Bit value 1: a sensed row clipped; bit value 2: a state is NaN/Inf (it stays so until
        the state is reset). Outputs are those of the state *before* each sample's update.
    """
    n, m, substeps, levels, max_events, n_sensed = (sizes[0], sizes[1], sizes[2], sizes[3],
                                                     sizes[4], sizes[5])
    nc, nb = drive.shape
    n_truth = truth.shape[1]
    n_probe, pw = probe.shape
    nz = n + m + 1
    status = 0
    for r in range(n_probe):
        for k in range(min(nb, pw)):
            probe[r, k] = 0.0
    inv = 1.0 / nc
    for ch in range(nc):
        for i in range(n):
            z[i] = Z[ch, i]
        for j in range(1, m):
            z[n + j] = params[ch, j - 1]
        z[nz - 1] = 1.0
        for k in range(nb):
            z[n] = drive[ch, k]
            mode = _mode_at(S, z, z, n)
            for r in range(n_truth):
                acc = 0.0
                for j in range(nz):
                    acc += CD[mode, r, j] * z[j]
                truth[ch, r, k] = acc
            for r in range(n_sensed):
                acc = 0.0
                for j in range(nz):
                    acc += CD[mode, n_truth + r, j] * z[j]
                lsb, fsc = adc[r, 0], adc[r, 1]
                if acc > fsc:
                    acc = fsc
                    status |= 1
                elif acc < -fsc:
                    acc = -fsc
                    status |= 1
                if lsb > 0.0:
                    acc = lsb * math.floor(acc / lsb + 0.5)
                sensed[ch * n_sensed + r, k] = acc
            if k < pw:
                for r in range(n_probe):
                    if (mode & pmask[r]) == pmask[r]:
                        probe[r, k] += inv
            mk = mode
            for _ in range(substeps):
                mk = _substep(PG, S, SD, cls, rel, kmin, z, xt, n, levels, max_events, mk)
        for i in range(n):
            Z[ch, i] = z[i]
            if not math.isfinite(z[i]):
                status |= 2
    return status


# --------------------------------------------------------------------- kernels per switch pattern
#
# A switch reads 1-4 of the ~11 entries of (x, u, 1), and the switch values are most of a
# substep's arithmetic: at every piece's end all switches (the mode), for the excursion test the
# relevant ones at both ends. :func:`specialized` writes ``_mode_at`` with the nonzero entries of
# ``S`` unrolled (values still read from ``S``), and compiles it with copies of ``_step``,
# ``_excursion``, ``_substep`` and ``hybrid_process``. Each sum runs over the nonzero entries in
# ascending column order: the generic loops without their exact no-ops (``acc + 0 * x`` is
# ``acc`` for finite ``x``), so the samples are bitwise those of :func:`hybrid_process`
# (``tests/test_plant_hybrid.py``). Kernel CPU per block: dot-4x4 1.40x, solenoid-3x3 1.37x,
# bimodal-4x4's EM pins 1.15x less. Not kept: the excursion test and output rows unrolled the
# same way (0.7-1.1x), index lists of every sparse row (0.88x: short loops of varying length cost
# more than the zeros they skip). A module depends on the pattern only: a model with other
# parameter values reuses its compiled code.

_GEN_HEADER = """# generated by rtctl.plant.hybrid.specialized; package stamp {stamp}
import math

from rtctl._numba import TINY, kernel
"""


def _switch_source(pattern, n: int, nz: int) -> str:
    """``_mode_at`` for the nonzero ``pattern`` of ``S`` (per switch, its columns).

    Each sum starts from a zero the compiler cannot see (``1 * 0`` is not folded without
    ``nnan``), as the generic loop's does: from a literal 0 it may fuse the first product into
    the second add instead (another rounding)."""
    src = ["@kernel", "def _mode_at(S, x, z, n):", f"    zero = z[{nz - 1}] * 0.0", "    mask = 0"]
    for i, cols in enumerate(pattern):
        src.append("    acc = zero")
        src += [f"    acc += S[{i}, {j}] * {'x' if j < n else 'z'}[{j}]" for j in cols]
        src += ["    if acc > 0.0:", f"        mask |= {1 << i}"]
    return "\n".join(src + ["    return mask", ""])


_SPECIALIZED: dict = {}
# Read when the module is imported: later the file on disk may be another version of it.
_SOURCES = [inspect.getsource(getattr(f, "py_func", f)) for f in (_step, _excursion, _substep, hybrid_process)]


def specialized(S, n: int):
    """:func:`hybrid_process` for models whose switch rows ``S`` (n_switches, nz) have this
    pattern of nonzero entries (and ``n`` states): same arguments, bitwise the same samples."""
    from rtctl._codegen import load_generated
    from rtctl._numba import package_stamp

    S = np.asarray(S)
    pattern = tuple(tuple(int(j) for j in np.flatnonzero(row)) for row in S)
    key = (pattern, int(n), int(S.shape[1]))
    if key not in _SPECIALIZED:
        parts = [_GEN_HEADER.format(stamp=package_stamp().hex()[:16]), "", _switch_source(*key)]
        _SPECIALIZED[key] = load_generated("\n\n".join(parts + _SOURCES), "rtctl_hybrid").hybrid_process
    return _SPECIALIZED[key]


_Z = 9  # position of the per-channel state in HybridGroup.args


class HybridGroup:
    """``n_channels`` identical channels of a hybrid model, advanced block by block.

    Parameters
    ----------
    model : HybridModel
        Input 0 is the drive (V); inputs 1.. are per-channel parameters (``params``). Outputs 0-3
        are the truth rows (:data:`TRUTH_NAMES`), the rows named in ``sensed`` follow.
    fs : float
        Sample rate, Hz.
    n_channels : int
    x0 : array_like, shape (n_states,)
        State after :meth:`reset` (e.g. ``model.equilibrium(...)``), the same for every channel.
    params : array_like, shape (n_inputs - 1,), optional
        Initial per-channel parameters (default zeros); ``group.params`` may be written between
        blocks, shape (n_channels, n_inputs - 1).
    sensed : sequence of (str, int, float, float)
        ``(label, output row, lsb, full_scale)`` per sensed row of a channel.
    probes : sequence of (str, str, int)
        ``(name, unit, mask)``: fraction of channels whose mode has all bits of ``mask`` on.
    substeps : int
        Exact steps per sample (``h = 1 / (fs substeps)``).
    levels : int
        Switch localization to ``h 2^-levels`` (0: first order at the substep).
    max_events : int
        Localized switches per substep before the rest is taken first order.
    max_block : int
        Columns of ``probe``; longer calls to :meth:`process` are split.
    capacitance : float
        F per channel as seen by the drive (0 for coils).

    Attributes
    ----------
    kernel : callable
        :func:`hybrid_process` as :func:`specialized` for the model's switches, called as
        ``kernel(*args, drive, sensed, truth) -> int``.
    args : tuple of ndarray
    n_sensed, sensed_labels, probe_names, probe, params, capacitance, n_channels, fs
    adc : ndarray, shape (n_sensed, 2)
        ``(lsb, full_scale)`` per sensed row.
    PG : ndarray
        The exact steps (:meth:`HybridModel.discretize`).
    dt : float
        The substep, s.
    kmin : ndarray of int64, shape (n_classes,)
        Smallest piece level per mode class (:meth:`HybridModel.piece_levels`).

    Examples
    --------
    >>> import numpy as np
    >>> from rtctl.plant.hybrid import HybridBuilder, HybridGroup, Lin, unilateral
    >>> b = HybridBuilder(["force_n"])
    >>> x, v = b.add_state("x_m"), b.add_state("v_m_s")
    >>> b.derivative(x, Lin.x(v))
    >>> b.derivative(v, Lin.u(0, 1e3) - Lin.x(x, 1e4) - Lin.x(v, 1.0))
    >>> when, force = unilateral(b, "stop", Lin.x(x) - 1e-3, Lin.x(v), 1e7, 10.0, [(v, -1e3)])
    >>> for name, form in [("x", Lin.x(x)), ("v", Lin.x(v)), ("f", Lin()), ("u", Lin.u(0))]:
    ...     _ = b.output(name, form)
    >>> group = HybridGroup(b.build(), fs=48000.0, n_channels=2, x0=[0.0, 0.0],
    ...                     probes=[("on_stop", "", 1)])
    >>> drive = np.full((2, 4800), 1.0); truth = np.empty((2, 4, 4800))
    >>> group.process(drive, np.empty((0, 4800)), truth)
    0
    >>> round(float(truth[0, 0, -1]) * 1e3, 4)   # mm: 1 N on 10 N/m wants 100 mm; the stop holds
    1.0001
    >>> float(group.probe[0, -1])                # share of channels on the stop
    1.0
    """

    def __init__(self, model: HybridModel, fs: float, n_channels: int, x0, params=None,
                 sensed=(), probes=(), substeps: int = 1, levels: int = 16,
                 max_events: int = 8, max_block: int = 64, capacitance: float = 0.0):
        fs = float(fs)
        if not (fs > 0.0 and math.isfinite(fs)):
            raise ModelError(f"fs must be a positive sample rate in Hz, got {fs!r}")
        nc = int(n_channels)
        if nc < 1 or nc != n_channels:
            raise ModelError(f"n_channels must be a positive integer, got {n_channels!r}")
        for nm, v, lo in (("substeps", substeps, 1), ("levels", levels, 0),
                          ("max_events", max_events, 0), ("max_block", max_block, 1)):
            if int(v) != v or int(v) < lo:
                raise ModelError(f"{nm} must be an integer >= {lo}, got {v!r}")
        if model.n_outputs < len(TRUTH_NAMES):
            raise ModelError(f"the model needs the {len(TRUTH_NAMES)} truth outputs "
                             f"{TRUTH_NAMES} first, it has {model.n_outputs} outputs")
        n, m = model.n_states, model.n_inputs
        x0 = np.asarray(x0, dtype=np.float64).ravel()
        if x0.size != n or not np.all(np.isfinite(x0)):
            raise ModelError(f"x0 must be {n} finite numbers {model.state_names}")
        p0 = np.zeros(m - 1) if params is None else np.asarray(params, np.float64).ravel()
        if p0.size != m - 1 or not np.all(np.isfinite(p0)):
            raise ModelError(f"params must be {m - 1} finite numbers {model.input_names[1:]}")
        self.model, self.fs, self.n_channels = model, fs, nc
        self.substeps, self.levels, self.max_events = int(substeps), int(levels), int(max_events)
        self.dt = 1.0 / (fs * self.substeps)
        self.PG = model.discretize(self.dt, self.levels)
        rows = list(range(len(TRUTH_NAMES)))
        adc = []
        for label, row, lsb, fsc in sensed:
            if not 0 <= int(row) < model.n_outputs or not (lsb >= 0.0 and fsc > 0.0):
                raise ModelError(f"sensed row {label!r}: output {row!r} must exist, lsb >= 0, "
                                 "full_scale > 0")
            rows.append(int(row))
            adc.append((float(lsb), float(fsc)))
        self.sensed_labels = tuple(str(s[0]) for s in sensed)
        self.n_sensed = len(self.sensed_labels)
        self.probe_names = tuple((str(p[0]), str(p[1])) for p in probes)
        self.capacitance = float(capacitance)
        self.max_block = int(max_block)
        self._x0 = x0.copy()
        self._p0 = p0.copy()
        self.params = np.tile(p0, (nc, 1)).reshape(nc, m - 1)
        self.probe = np.zeros((len(self.probe_names), self.max_block))
        Z = np.zeros((nc, n))
        self.adc = np.array(adc, dtype=np.float64).reshape(self.n_sensed, 2)
        self.kmin = model.piece_levels(self.dt, self.levels)
        self.kernel = specialized(model.S.reshape(model.n_switches, n + m + 1), n)
        self.args = (
            np.array([n, m, self.substeps, self.levels, self.max_events, self.n_sensed],
                     dtype=np.int64),
            np.ascontiguousarray(self.PG),
            np.ascontiguousarray(model.Y[:, rows]),
            np.ascontiguousarray(model.S).reshape(model.n_switches, n + m + 1),
            model.switch_slopes(self.dt),
            model.mode_class.astype(np.int64),
            model.relevant_switches(),
            self.kmin,
            self.params,
            Z,
            np.zeros(n + m + 1),
            np.zeros(n),
            self.adc,
            np.array([int(p[2]) for p in probes], dtype=np.int64),
            self.probe,
        )
        self.reset()

    @property
    def state(self) -> np.ndarray:
        """Current states, shape (n_channels, n_states) (a view)."""
        return self.args[_Z]

    def reset(self) -> None:
        """Every channel back to ``x0``, parameters back to their initial values."""
        self.args[_Z][:] = self._x0
        self.params[:] = self._p0

    def process(self, drive, sensed, truth) -> int:
        """Advance every channel by ``drive.shape[1]`` samples (any length).

        Parameters
        ----------
        drive : ndarray, shape (n_channels, B), float64, C-contiguous
            Input 0 (V), held for each sample.
        sensed : ndarray, shape (n_channels * n_sensed, B)
            Written: row ``ch * n_sensed + j`` is sensed row ``j`` of channel ``ch``.
        truth : ndarray, shape (n_channels, 4, B)
            Written: the :data:`TRUTH_NAMES` rows.

        Returns
        -------
        int
            Status bits (see :func:`hybrid_process`). ``probe`` holds the last piece of at
            most ``max_block`` samples.
        """
        nb = drive.shape[-1] if drive.ndim == 2 else -1
        for name, arr, shape in (("drive", drive, (self.n_channels, nb)),
                                 ("sensed", sensed, (self.n_channels * self.n_sensed, nb)),
                                 ("truth", truth, (self.n_channels, len(TRUTH_NAMES), nb))):
            if arr.shape != shape or arr.dtype != np.float64 or not arr.flags.c_contiguous:
                raise ModelError(f"{name} must be C-contiguous float64 of shape {shape}, got "
                                 f"{arr.dtype} {arr.shape}")
        status = 0
        for a in range(0, nb, self.max_block):
            b = min(nb, a + self.max_block)
            if a == 0 and b == nb:
                return self.kernel(*self.args, drive, sensed, truth)
            status |= self.kernel(*self.args, np.ascontiguousarray(drive[:, a:b]),
                                  sv := np.empty((sensed.shape[0], b - a)),
                                  tv := np.empty((self.n_channels, len(TRUTH_NAMES), b - a)))
            sensed[:, a:b] = sv
            truth[:, :, a:b] = tv
        return status
