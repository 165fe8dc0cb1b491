"""One simulated bimorph channel (reduced FE beam + finger + amplifier + current sense), and a
group of identical channels advanced in real time.

Continuous model of one channel (input: commanded voltage ``u``, V)::

    eta''  = -Omega^2 eta - C_r eta' + Phi^T theta V - Phi_tip sum_i f_i     retained modes
    f_i'   = k_i x' - f_i / tau_i                                            finger branches
    V'     = w_a (u - V)                                                     amplifier
    z_j'   = A_f z_j + B_f I_j                                               AA filter per segment
    x      = Phi_tip eta + r_tip V            (tip displacement, static correction r)
    I_j    = Theta_j^T Phi eta' + (Cp_j + Theta_j^T r) V'                    segment current

* All electrode segments are driven together by the one amplifier (seed 000, Eq. 2: one voltage
  ``U``), so the beam sees ``theta = Theta 1``. Currents are per segment.
* Modes: of the *loaded* structure, ``M + mass e e^T`` and ``K + k0 e e^T`` (skin mass and
  long-term finger stiffness at the tip DOF ``e``), mass-normalized, ``Omega`` their angular
  frequencies; ``C_r = Phi^T C Phi`` projects the beam's modal damping ``C`` (not diagonal once
  the finger loads it). The finger's Maxwell branches act through their states.
* Static (residual-flexibility) correction: ``r = K_L^-1 theta - Phi Omega^-2 Phi^T theta`` is
  the quasi-static deflection per volt of the truncated modes. ``q = Phi eta + r V`` makes the
  DC deflection per volt and the static capacitance exact whatever the number of modes kept.
  It enters through the amplifier-voltage *state*, so ``x`` and ``I`` are explicit functions of
  the state and the input: no algebraic loop (``V'`` comes from the amplifier's state equation).
  Only the voltage input is corrected: at DC the branch forces vanish, and the truncated modes'
  share of the tip compliance under finger force is ~1e-3 (tested to 1 % against the full FE).
* Output ``tip_force_n`` is the tissue force ``k0 x + sum f_i`` (what the tip pushes the finger
  with); the skin inertia ``mass x''`` is not in it (it would need the derivative of ``u``).

Outputs, in order (``OUTPUT_NAMES``): tip displacement (m), tip velocity (m/s), tip force (N),
actuator voltage (V), true segment currents (A, ``n_seg``), anti-aliased currents before the ADC
(A, ``n_seg``).
"""

from __future__ import annotations

import math

import numpy as np

from rtctl.errors import ModelError
from rtctl.plant import _kernels
from rtctl.plant.finger import MaxwellLoad
from rtctl.plant.frontend import Amplifier, CurrentSense
from rtctl.plant.lti import StateSpace, c2d, to_modal

__all__ = ["BimorphPlant", "SimGroup", "TRUTH_NAMES", "sim_group_process", "realization"]

TRUTH_NAMES = ("tip_m", "tip_velocity_m_s", "tip_force_n", "voltage_v")

#: The real-time kernel of :class:`SimGroup`: ``sim_group_process(*group.args, drive, sensed,
#: truth) -> int`` (callable from other numba functions).
sim_group_process = _kernels.sim_group_process
_X, _IPOS = 7, 13  # positions of the state trajectory and the noise positions in SimGroup.args


class BimorphPlant:
    """Continuous-time model of one bimorph channel, reduced to a few modes.

    Parameters
    ----------
    fe : BeamFE
        Finite-element beam (``M, K, Theta, Cp, tip``, ``with_tip``, ``modes``,
        ``damping_matrix``, ``static_solve``), without the finger.
    amplifier : Amplifier
    sense : CurrentSense
        Its shunt and AA filter are part of this plant; its ADC settings are used by
        :class:`SimGroup`.
    finger : MaxwellLoad, optional
        Finger at the tip DOF (skin mass added to the tip).
    n_modes : int or None
        Keep at most this many modes (default 4).
    max_mode_hz : float or None
        Keep only modes at or below this frequency, Hz.
    zeta : float or array_like, optional
        Modal damping ratio of the beam (default ``fe.spec.damping``).

    Attributes
    ----------
    sys : StateSpace
        Continuous model; input ``command_v``; outputs ``OUTPUT_NAMES``.
    cascade : tuple of tuple of int
        State indices of the subsystems in signal order (amplifier; beam modes and finger
        branches; one anti-alias filter per segment). Nothing feeds back upstream, so ``A`` is
        block lower-triangular in this order (``to_modal(..., blocks=cascade)``).
    modes_hz : ndarray
        Undamped frequencies of the retained modes of the loaded structure, Hz.
    n_seg : int

    Examples
    --------
    >>> from rtctl.plant import (BeamSpec, Layer, build_fe, BUILTIN, Amplifier, CurrentSense,
    ...                          MaxwellLoad, BimorphPlant)
    >>> pzt = BUILTIN["PZT-5A"]
    >>> fe = build_fe(BeamSpec(15e-3, 1.5e-3, (Layer(pzt, 0.3e-3), Layer(pzt, 0.3e-3)),
    ...                        "parallel", (0.5, 0.5), 0.01))
    >>> finger = MaxwellLoad(1e-4, 300.0, ((300.0, 0.004), (150.0, 0.07), (80.0, 1.4)))
    >>> plant = BimorphPlant(fe, Amplifier(20e3), CurrentSense(100.0, 15e3), finger)
    >>> plant.sys.n_states, plant.OUTPUT_NAMES[:2]
    (16, ('tip_m', 'tip_velocity_m_s'))
    """

    def __init__(self, fe, amplifier: Amplifier, sense: CurrentSense,
                 finger: MaxwellLoad | None = None, n_modes: int | None = 4,
                 max_mode_hz: float | None = None, zeta=None):
        if not isinstance(amplifier, Amplifier) or not isinstance(sense, CurrentSense):
            raise ModelError("BimorphPlant needs an Amplifier and a CurrentSense")
        if finger is not None and not isinstance(finger, MaxwellLoad):
            raise ModelError("finger must be a MaxwellLoad or None")
        self.fe, self.amplifier, self.sense, self.finger = fe, amplifier, sense, finger
        n_seg = int(fe.Cp.size)
        tip = int(fe.tip)
        mass = finger.mass if finger else 0.0
        k0 = finger.k0 if finger else 0.0
        loaded = fe.with_tip(mass=mass, k=k0) if (mass or k0) else fe
        f_all, phi_all = loaded.modes()
        keep = np.ones(f_all.size, dtype=bool)
        if n_modes is not None:
            if int(n_modes) < 1:
                raise ModelError(f"n_modes must be >= 1, got {n_modes!r}")
            keep[int(n_modes):] = False
        if max_mode_hz is not None:
            keep &= f_all <= float(max_mode_hz)
        if not keep.any():
            raise ModelError(f"no mode kept: the first mode is at {f_all[0]:.4g} Hz; raise "
                             f"max_mode_hz ({max_mode_hz!r}) or n_modes")
        phi = phi_all[:, keep]
        om = 2.0 * math.pi * f_all[keep]
        nr = om.size
        C_r = phi.T @ fe.damping_matrix(zeta) @ phi
        theta = fe.Theta.sum(axis=1)
        r = loaded.static_solve(theta) - phi @ ((phi.T @ theta) / om**2)
        ph_tip, r_tip = phi[tip], float(r[tip])
        th_phi = fe.Theta.T @ phi                      # (n_seg, nr)
        cap = fe.Cp + fe.Theta.T @ r                   # capacitive coefficient of V', F
        kb = finger.k if finger else np.zeros(0)
        taub = finger.tau if finger else np.zeros(0)
        nb = kb.size
        wa = amplifier.omega
        aa = sense.aa_filter()
        na = aa.n_states

        # State layout: eta (nr), eta' (nr), branch forces (nb), V (1), AA states (na per seg).
        i_v, i_f, i_V, i_z = nr, 2 * nr, 2 * nr + nb, 2 * nr + nb + 1
        n = i_z + na * n_seg
        A = np.zeros((n, n))
        B = np.zeros((n, 1))
        A[:nr, i_v:i_f] = np.eye(nr)
        A[i_v:i_f, :nr] = -np.diag(om**2)
        A[i_v:i_f, i_v:i_f] = -C_r
        A[i_v:i_f, i_V] = phi.T @ theta
        A[i_v:i_f, i_f:i_V] = -np.outer(ph_tip, np.ones(nb))
        # Tip velocity x' = Phi_tip eta' + r_tip V', V' = w_a (u - V).
        vel_x = np.zeros(n)
        vel_x[i_v:i_f] = ph_tip
        vel_x[i_V] = -r_tip * wa
        vel_u = r_tip * wa
        for i in range(nb):
            A[i_f + i] = kb[i] * vel_x
            A[i_f + i, i_f + i] -= 1.0 / taub[i]
            B[i_f + i, 0] = kb[i] * vel_u
        A[i_V, i_V] = -wa
        B[i_V, 0] = wa
        # Segment currents I_j = cur_x[j] . x + cur_u[j] u.
        cur_x = np.zeros((n_seg, n))
        cur_x[:, i_v:i_f] = th_phi
        cur_x[:, i_V] = -cap * wa
        cur_u = cap * wa
        for j in range(n_seg):
            sl = slice(i_z + na * j, i_z + na * (j + 1))
            A[sl, sl] = aa.A
            A[sl] += aa.B @ cur_x[j:j + 1]
            B[sl, 0] += aa.B[:, 0] * cur_u[j]

        p = 4 + 2 * n_seg
        C = np.zeros((p, n))
        D = np.zeros((p, 1))
        C[0, :nr] = ph_tip
        C[0, i_V] = r_tip
        C[1] = vel_x
        D[1, 0] = vel_u
        C[2] = k0 * C[0]
        C[2, i_f:i_V] = 1.0
        C[3, i_V] = 1.0
        C[4:4 + n_seg] = cur_x
        D[4:4 + n_seg, 0] = cur_u
        for j in range(n_seg):
            C[4 + n_seg + j, i_z + na * j:i_z + na * (j + 1)] = aa.C[0]

        names = (tuple(f"eta{i}" for i in range(nr)) + tuple(f"eta{i}_dot" for i in range(nr))
                 + tuple(f"branch{i}_force_n" for i in range(nb)) + ("voltage_v",)
                 + tuple(f"aa{j}_{k}" for j in range(n_seg) for k in range(na)))
        self.OUTPUT_NAMES = (TRUTH_NAMES + tuple(f"current{j}_a" for j in range(n_seg))
                             + tuple(f"sensed{j}_a" for j in range(n_seg)))
        self.sys = StateSpace(A, B, C, D, None, names, ("command_v",), self.OUTPUT_NAMES)
        self.n_seg = n_seg
        self.modes_hz = f_all[keep].copy()
        self.residual_tip_per_volt = r_tip
        # What a load switch needs to carry the beam's state into another load's modes
        # (rtctl.plant.switching): the full finite-element shapes and static correction, and the
        # loaded mass matrix they are orthonormal in.
        self.mode_shapes, self.static_correction, self.mass_matrix = phi, r, loaded.M
        self.n_modes, self.n_branches, self.tip = nr, nb, tip
        self.capacitance_feedthrough = cap.copy()  # Cp + Theta^T r: current per dV/dt, F
        # Subsystems in signal order; nothing feeds back upstream (block lower-triangular A).
        self.cascade = ((i_V,), tuple(range(i_V)),
                        *(tuple(range(i_z + na * j, i_z + na * (j + 1))) for j in range(n_seg)))

    def frequency_response(self, freqs_hz):
        """Continuous-model response per commanded volt at each frequency.

        Parameters
        ----------
        freqs_hz : array_like, shape (n_freqs,)

        Returns
        -------
        ndarray, shape (n_freqs, n_outputs), complex
            Columns in ``OUTPUT_NAMES`` order (m/V, m/s/V, N/V, V/V, A/V, A/V).
        """
        return self.sys.frequency_response(freqs_hz)[:, :, 0]


def realization(plant: BimorphPlant, fs: float, form: str = "auto", max_cond: float = 1e8):
    """The discrete recursion a :class:`SimGroup` runs for ``plant`` at ``fs``.

    The truth rows and the anti-aliased currents, discretized exactly for a DAC staircase, in
    modal form per subsystem of ``plant.cascade`` with unit input gains where that is safe, else
    dense.

    Returns
    -------
    sysd : StateSpace
        The discrete plant (plant coordinates, selected outputs).
    modal : ModalForm
        The realization that runs, ``x = modal.T z``.
    code : int
        ``FORM_MODAL`` or ``FORM_DENSE`` (the kernel's switch).
    a, reals : ndarray
        The kernel's state coefficients: ``(n_pairs, 2)`` blocks and the real modes, or the dense
        ``(n_states, n_states)`` matrix and an empty ``reals``.
    """
    n_seg = plant.n_seg
    rows = list(range(len(TRUTH_NAMES))) + [4 + n_seg + j for j in range(n_seg)]
    s = plant.sys
    sel = StateSpace(s.A, s.B, s.C[rows], s.D[rows])
    sysd = c2d(sel, 1.0 / fs, "zoh")
    modal = to_modal(sysd, max_cond=max_cond, form=form, blocks=plant.cascade)
    if modal.form == "modal":
        modal = modal.unit_input()
    ms = modal.sys
    if modal.form == "modal":
        a, reals = modal.blocks()
        code = _kernels.FORM_MODAL
    else:
        a, reals = np.ascontiguousarray(ms.A), np.zeros(0)
        code = _kernels.FORM_DENSE
    return sysd, modal, code, a, reals


#: Largest ``R_s Cp fs`` a simulated group accepts: the model neglects the shunt's drop on the
#: piezo (a pole at ``1 / (2 pi R_s Cp)``), which holds while that pole is far above ``fs``.
SHUNT_RC_FS = 0.01


class SimGroup:
    """``n_channels`` identical simulated bimorph channels advanced block by block.

    The plant is discretized exactly for a DAC staircase (``c2d(..., "zoh")`` at
    ``dt = 1 / fs``), put in modal form where that is safe (:func:`~rtctl.plant.lti.to_modal`,
    per subsystem of ``plant.cascade`` so that the outputs skip the states they cannot depend
    on; else dense) and run by :func:`sim_group_process`. Sensed currents then go through the
    ADC (seeded table noise, quantization, clipping).

    Parameters
    ----------
    plant : BimorphPlant
    fs : float
        Sample rate, Hz.
    n_channels : int
    sense : CurrentSense, optional
        ADC settings (bits, full scale, noise, seed); default ``plant.sense``. Its shunt and AA
        filter must equal the plant's (they are part of the discretized plant).
    seed : int, optional
        Overrides the noise seed (start positions and tables), e.g. per group.
    max_block : int
        Samples per internal block (scratch size); longer calls are split, results unchanged.
    chunk : int
        Samples per recursion chunk (performance only; the state trajectory of a chunk is
        kept, ``(chunk + 1) * n_channels * n_states`` floats).
    form : {"auto", "modal", "dense"}
    max_cond : float
        Passed to ``to_modal``.

    Attributes
    ----------
    args : tuple of ndarray
        Kernel arguments in order: ``sim_group_process(*args, drive, sensed, truth)``.
    modal : ModalForm
        The discrete realization that runs (``modal.form``, ``modal.cond``). In modal form it is
        built per subsystem of ``plant.cascade`` (``modal.is_cascade``; exact zeros in ``C``)
        and scaled to unit input gains (:meth:`~rtctl.plant.lti.ModalForm.unit_input`).
    n_states, n_seg, n_channels, fs

    Examples
    --------
    >>> import numpy as np
    >>> from rtctl.plant import (BeamSpec, Layer, build_fe, BUILTIN, Amplifier, CurrentSense,
    ...                          BimorphPlant, SimGroup, TRUTH_NAMES)
    >>> pzt = BUILTIN["PZT-5A"]
    >>> fe = build_fe(BeamSpec(15e-3, 1.5e-3, (Layer(pzt, 0.3e-3), Layer(pzt, 0.3e-3)),
    ...                        "parallel", (0.5, 0.5), 0.01))
    >>> plant = BimorphPlant(fe, Amplifier(20e3), CurrentSense(100.0, 15e3))
    >>> group = SimGroup(plant, fs=48000.0, n_channels=4)
    >>> drive = np.full((4, 32), 10.0)
    >>> sensed = np.empty((4 * plant.n_seg, 32)); truth = np.empty((4, len(TRUTH_NAMES), 32))
    >>> group.process(drive, sensed, truth)
    0
    """

    def __init__(self, plant: BimorphPlant, fs: float, n_channels: int,
                 sense: CurrentSense | None = None, seed: int | None = None,
                 max_block: int = 64, chunk: int = 8, form: str = "auto",
                 max_cond: float = 1e8):
        fs = float(fs)
        if not (fs > 0.0 and math.isfinite(fs)):
            raise ModelError(f"fs must be a positive sample rate in Hz, got {fs!r}")
        nc = int(n_channels)
        if nc < 1 or nc != n_channels:
            raise ModelError(f"n_channels must be a positive integer, got {n_channels!r}")
        if int(max_block) < 1 or int(chunk) < 1:
            raise ModelError("max_block and chunk must be >= 1")
        sense = plant.sense if sense is None else sense
        if not sense.same_analog(plant.sense):
            raise ModelError("SimGroup sense must have the plant's shunt and AA filter (they are "
                             "part of the discretized plant); build the plant with it instead")
        rc = sense.shunt_ohm * float(np.max(plant.fe.Cp))
        if rc * fs > SHUNT_RC_FS:
            raise ModelError(f"shunt time constant R_s Cp = {rc:.3g} s is not << 1/fs "
                             f"({1 / fs:.3g} s): the shunt drop on the piezo would matter; use "
                             f"a shunt below {SHUNT_RC_FS / (fs * float(np.max(plant.fe.Cp))):.3g} ohm")
        self.plant, self.fs, self.n_channels, self.sense = plant, fs, nc, sense
        n_seg = plant.n_seg
        self.n_seg = n_seg
        # the simulated-group contract shared by every plant (see rtctl.io.sim)
        self.kernel = sim_group_process
        self.n_sensed = n_seg
        self.sensed_labels = tuple(f"seg{j}" for j in range(n_seg))
        self.probe_names = ()
        self.probe = np.zeros((0, int(max_block)))
        self.capacitance = float(plant.fe.capacitance())
        self.sysd, self.modal, code, a, reals = realization(plant, fs, form, max_cond)
        ms = self.modal.sys
        self.n_states = ms.n_states
        n_out = ms.n_outputs
        plan, coef = _kernels.output_plan(ms.C)
        mb, ch = int(max_block), int(chunk)
        lo, hi = sense.code_range
        S = n_seg * nc
        t1, t2 = sense.noise_tables() if seed is None else \
            CurrentSense(sense.shunt_ohm, sense.aa_cutoff_hz, sense.aa_order, sense.bits,
                         sense.full_scale_v, sense.noise_rms_v, seed).noise_tables()
        if S >= min(t1.size, t2.size):
            raise ModelError(f"{S} sensed streams exceed the noise table length {t2.size}")
        self._ipos0 = sense.noise_start(seed)
        self.args = (
            np.array([code, len(TRUTH_NAMES), n_seg, ch, mb], dtype=np.int64),
            np.ascontiguousarray(a, dtype=np.float64),
            np.ascontiguousarray(reals, dtype=np.float64),
            np.ascontiguousarray(ms.B[:, 0]),
            np.ascontiguousarray(ms.D[:, 0]),
            plan,                                                # output tiles (C)
            coef,
            _kernels.aligned_zeros((self.n_states, (ch + 1) * nc)),  # X: state trajectory
            _kernels.aligned_zeros((mb * nc,)),                      # ut: inputs of a block
            _kernels.aligned_zeros((n_out, ch * nc)),                # ys: outputs of a chunk
            np.array([sense.shunt_ohm, 1.0 / sense.lsb_v, sense.lsb_v / sense.shunt_ohm, hi,
                      lo, sense.noise_rms_v / math.sqrt(2.0)]),
            np.concatenate([t1, t1[:S]]),
            np.concatenate([t2, t2[:S]]),
            self._ipos0.copy(),
        )

    @property
    def state(self) -> np.ndarray:
        """Current state in the realization's coordinates, shape (n_states, n_channels) (a view)."""
        return self.args[_X][:, :self.n_channels]

    def physical_state(self) -> np.ndarray:
        """Current state in the plant's coordinates (``plant.sys.state_names``), a copy."""
        return self.modal.T @ self.state

    def reset(self) -> None:
        """Zero all states and restart the noise sequence (as just built)."""
        self.args[_X][:] = 0.0
        self.args[_IPOS][:] = self._ipos0

    def process(self, drive, sensed, truth) -> int:
        """Advance every channel by one block.

        Parameters
        ----------
        drive : ndarray, shape (n_channels, n), float64, C-contiguous
            Commanded voltage, V.
        sensed : ndarray, shape (n_channels * n_seg, n)
            Written: ADC readings in A, row ``ch * n_seg + seg``.
        truth : ndarray, shape (n_channels, len(TRUTH_NAMES), n)
            Written: tip displacement (m), tip velocity (m/s), tip force (N), actuator
            voltage (V).

        Returns
        -------
        int
            Bit value 1: an ADC clipped; bit value 2: a state is NaN/Inf (stays until
            :meth:`reset`).
        """
        n = drive.shape[-1]
        for name, arr, shape in (("drive", drive, (self.n_channels, n)),
                                 ("sensed", sensed, (self.n_channels * self.n_seg, n)),
                                 ("truth", truth, (self.n_channels, len(TRUTH_NAMES), n))):
            if arr.shape != shape or arr.dtype != np.float64 or not arr.flags.c_contiguous:
                raise ModelError(f"{name} must be C-contiguous float64 of shape {shape}, got "
                                 f"{arr.dtype} {arr.shape}")
        return self.kernel(*self.args, drive, sensed, truth)
