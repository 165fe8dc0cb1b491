"""Run any discrete LTI system through the plant package's streaming kernel.

:class:`~rtctl.plant.bimorph.SimGroup` is the rig's bimorph kernel, discretized for a DAC
staircase (zoh) at the loop rate. The work-precision report also needs the *same recursion* on
other discretizations (first-order hold, tone-augmented plants, higher rates), so this wrapper
takes any discrete single-input system, puts it in the form ``SimGroup`` would use
(:func:`~rtctl.plant.lti.to_modal`, unit input gains) and calls
:func:`rtctl.plant._kernels.lti_group_process` -- no ADC, no noise.
"""

from __future__ import annotations

import numpy as np

from rtctl.errors import ModelError
from rtctl.plant import _kernels
from rtctl.plant.lti import StateSpace, to_modal

__all__ = ["LtiRunner"]


class LtiRunner:
    """``n_channels`` copies of a discrete single-input system, advanced by the numba kernel.

    Parameters
    ----------
    sysd : StateSpace
        Discrete system (``dt`` set), one input.
    n_channels : int
    chunk, max_block : int
        Scratch sizes as in ``SimGroup`` (performance only; results do not depend on them).
    form : {"auto", "modal", "dense"}
        Passed to :func:`~rtctl.plant.lti.to_modal`.
    blocks : sequence of sequence of int, optional
        Cascade partition passed to ``to_modal`` (e.g. ``BimorphPlant.cascade``).
    input_free : bool
        The input is always zero (e.g. a plant driven by its own oscillator states,
        :func:`~rtctl.plant.lti.augment_tones`). Modes the input does not reach are then
        allowed in modal form; otherwise such a system runs dense, because unit input scaling
        would make the state transform singular and an initial state could not be set.

    Attributes
    ----------
    modal : ModalForm
        The realization that runs; ``modal.T`` maps its states to ``sysd``'s.
    n_states, n_outputs, n_channels : int

    Examples
    --------
    >>> import numpy as np
    >>> from rtctl.plant.lti import StateSpace, c2d
    >>> from rtctl.numerics.runner import LtiRunner
    >>> run = LtiRunner(c2d(StateSpace([[-100.0]], [[100.0]], [[1.0]], [[0.0]]), 1e-3))
    >>> y = np.empty((1, 1, 3))
    >>> run.process(np.ones((1, 3)), y)
    0
    >>> np.round(y[0, 0], 4)
    array([0.    , 0.0952, 0.1813])
    """

    def __init__(self, sysd: StateSpace, n_channels: int = 1, chunk: int = 8,
                 max_block: int = 64, form: str = "auto", blocks=None,
                 input_free: bool = False):
        if not sysd.is_discrete or sysd.n_inputs != 1:
            raise ModelError("LtiRunner needs a discrete single-input system; discretize with "
                             "c2d() and select one input")
        if int(n_channels) < 1 or int(chunk) < 1 or int(max_block) < 1:
            raise ModelError("n_channels, chunk and max_block must be >= 1")
        mf = to_modal(sysd, form=form, blocks=blocks)
        if mf.form == "modal":
            b = mf.sys.B[:, 0]
            pair_gain = np.hypot(b[0:2 * mf.n_pairs:2], b[1:2 * mf.n_pairs:2])
            unreached = np.any(pair_gain == 0.0) or np.any(b[2 * mf.n_pairs:] == 0.0)
            if not unreached:
                mf = mf.unit_input()
            elif not input_free:
                if form == "modal":
                    raise ModelError("a mode is not reached by the input, so unit input scaling "
                                     "is singular; use form='auto' (dense) or input_free=True")
                mf = to_modal(sysd, form="dense")
        self.modal = mf
        self.input_free = bool(input_free)
        s = mf.sys
        self.n_states, self.n_outputs, self.n_channels = s.n_states, s.n_outputs, int(n_channels)
        if mf.form == "modal":
            a, reals = mf.blocks()
            self._form = _kernels.FORM_MODAL
        else:
            a, reals = np.ascontiguousarray(s.A), np.zeros(0)
            self._form = _kernels.FORM_DENSE
        plan, coef = _kernels.output_plan(s.C)
        nc, ch, mb = self.n_channels, int(chunk), int(max_block)
        self.args = (self._form, np.ascontiguousarray(a), np.ascontiguousarray(reals),
                     np.ascontiguousarray(s.B[:, 0]), np.ascontiguousarray(s.D[:, 0]), plan, coef,
                     # Exact shapes: lti_group_process takes its chunk and block lengths
                     # from them (aligned_zeros would pad them).
                     np.zeros((self.n_states, (ch + 1) * nc)), np.zeros(mb * nc),
                     np.zeros((self.n_outputs, ch * nc)))
        self._x0 = np.zeros((self.n_states, nc))

    @property
    def state(self) -> np.ndarray:
        """Current state in the realization's coordinates, shape (n_states, n_channels) (a view)."""
        return self.args[7][:, :self.n_channels]

    def set_state(self, x0) -> None:
        """Set (and remember for :meth:`reset`) the state in ``sysd``'s coordinates.

        Parameters
        ----------
        x0 : array_like, shape (n_states,) or (n_states, n_channels)
        """
        x0 = np.asarray(x0, dtype=np.float64)
        x0 = np.broadcast_to(x0.reshape(self.n_states, -1), (self.n_states, self.n_channels))
        z0 = np.linalg.solve(self.modal.T, x0)
        if not np.all(np.isfinite(z0)):
            raise ModelError("the initial state cannot be expressed in this realization "
                             "(singular transform); build the runner with form='dense'")
        self._x0 = z0
        self.reset()

    def reset(self) -> None:
        """Back to the state given to :meth:`set_state` (zero if never called)."""
        self.args[7][:] = 0.0
        self.state[:] = self._x0

    def process(self, u, y) -> int:
        """Advance every channel over ``u``.

        Parameters
        ----------
        u : ndarray, shape (n_channels, n), float64, C-contiguous
            Input samples (all zero when ``input_free``).
        y : ndarray, shape (n_channels, n_outputs, n)
            Written: outputs ``C x[k] + D u[k]`` (state before sample ``k``).

        Returns
        -------
        int
            2 if a state became NaN/Inf, else 0.
        """
        n = u.shape[-1]
        if u.shape != (self.n_channels, n) or u.dtype != np.float64 or not u.flags.c_contiguous:
            raise ModelError(f"u must be C-contiguous float64 of shape ({self.n_channels}, n)")
        if y.shape != (self.n_channels, self.n_outputs, n) or y.dtype != np.float64 \
                or not y.flags.c_contiguous:
            raise ModelError(f"y must be C-contiguous float64 of shape "
                             f"({self.n_channels}, {self.n_outputs}, {n})")
        if self.input_free and np.any(u):
            raise ModelError("this runner was built input_free (modes the input cannot reach); "
                             "drive it with zeros or build it with input_free=False")
        return _kernels.lti_group_process(*self.args, u, y)
