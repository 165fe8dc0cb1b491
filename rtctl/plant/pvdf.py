"""PVDF film cells on a thin plate (seed 004): a MIMO plant and its real-time group.

Seed 004 patterns ITO electrodes on both faces of an 80 um stretched PVDF film into a 6 x 8 cell
array, 1.5 mm apart, and attaches it to the rear of a 153 x 93 x 0.8 mm touch panel; each cell
is driven with 500-1000 Vpp through a high-voltage amplifier, and an accelerometer between two
adjacent cells shows that 500 Vpp at 100 Hz plus 500 Vpp at 110 Hz on two neighbours beats (10
Hz envelope, 105 Hz carrier) with the peaks of 1000 Vpp on one cell. All cells share the plate's
modes, so the group is one coupled MIMO system. ``docs/plants/pvdf.md`` has the derivation.

Continuous model (inputs ``u``: commanded cell voltages, V; modes mass-normalized)::

    v_j'  = w_a (u_j - v_j)                                    amplifier, one per cell
    M_L eta'' = -K_L eta - C eta' - phi_f sum_i f_i + Theta v  plate modes (Kirchhoff, SS edges)
    f_i'  = k_i phi_f . eta' - f_i / tau_i                     finger branches (optional)

* Plate modes ``W_mn = sin(m pi x / a) sin(n pi y / b) / sqrt(rho h a b / 4)``,
  ``w_mn = pi^2 (m^2/a^2 + n^2/b^2) sqrt(D / (rho h))``, ``D = E h^3 / (12 (1 - nu^2))``
  (Navier's solution of a simply supported Kirchhoff plate), modal damping ``zeta``.
* A cell is a blocked film (its in-plane stiffness ``E_f t_f`` is ~300x below the plate's), so
  it applies the uniform moments ``m_x = e_x v (h + t_f)/2``, ``m_y = e_y v (h + t_f)/2`` over
  its electrode with ``e_x = E_f (d31 + nu_f d32) / (1 - nu_f^2)`` (Dimitriadis, Fuller &
  Rogers 1991). Its modal force is ``Theta_kj = int (m_x W_k,xx + m_y W_k,yy) dA`` per volt,
  in closed form for a rectangle; the charge is ``q_j = Theta_j . eta + C_f v_j`` (reciprocity).
* Finger (optional, LTI): generalized Maxwell load at one cell centre; its skin mass and ``k0``
  load the modes (``M_L = I + m phi_f phi_f^T``, ``K_L = Omega^2 + k0 phi_f phi_f^T``).

Truth rows per cell: plate displacement at the cell centre (m, positive towards the finger, on
the film's far side), its velocity, the tissue force ``preload + k0 w + sum f_i`` on the finger's
cell (0 elsewhere), the cell voltage. Probes at the measurement point (midway between two
cells): displacement, velocity, acceleration.
"""

from __future__ import annotations

import math

import numpy as np

from rtctl.errors import ModelError
from rtctl.plant import _pvdf_kernels as _k
from rtctl.plant._checks import positive
from rtctl.plant._kernels import PLAN_COLUMNS, aligned_zeros, output_plan
from rtctl.plant.finger import MaxwellLoad
from rtctl.plant.lti import StateSpace, c2d, to_modal
from rtctl.plant.materials import EPS0

__all__ = ["PvdfPlate", "PvdfGroup", "pvdf_group_process", "TRUTH_NAMES", "PROBE_NAMES"]

TRUTH_NAMES = ("displacement_m", "velocity_m_s", "finger_force_n", "voltage_v")
PROBE_NAMES = (("probe_displacement", "m"), ("probe_velocity", "m/s"),
               ("probe_acceleration", "m/s^2"))

#: The real-time kernel of :class:`PvdfGroup`: ``pvdf_group_process(*group.args, drive, sensed,
#: truth) -> int``.
pvdf_group_process = _k.pvdf_group_process

_Z, _G, _V = 7, 8, 9  # positions of the states in PvdfGroup.args
_CELLS = (16, 17, 18)  # the plans' cells of each tile source (-1: always read)
_QUIET = 19  # which cells' sources are all zero (not stepped, their tiles left out)


def _pos(name, value):
    return positive("PvdfPlate", name, value)


class PvdfPlate:
    """Continuous-time model of a grid of PVDF film cells bonded to a simply supported plate.

    Defaults are seed 004's numbers where it gives them (grid, gap, film thickness, panel
    size) and stated assumptions otherwise (plate material, damping, amplifier bandwidth).

    Parameters
    ----------
    rows, cols : int
        Cell grid; channel ``r * cols + c`` is the cell in row ``r`` (along y), column ``c``.
    plate_length, plate_width, plate_thickness : float
        Plate ``a`` (along x, the columns), ``b`` (along y) and ``h``, m. Seed: touch panel
        153 x 93 x 0.8 mm.
    plate_E, plate_nu, plate_rho : float
        Plate Young's modulus (Pa), Poisson ratio, density (kg/m^3). The seed does not name the
        panel's material: default cover glass (70 GPa, 0.22, 2500). Its acrylic mount (3.2 GPa,
        0.35, 1190) puts the first mode at ~95 Hz, on top of the 100-110 Hz drive.
    gap : float
        Gap between neighbouring electrodes, m (seed: 1.5 mm).
    pitch_x, pitch_y : float or None
        Cell pitch, m; ``None`` tiles the plate (``a / cols``, ``b / rows``: the seed's array
        "fits into the touch panel"). The array is centred on the plate.
    film_thickness : float
        PVDF thickness ``t_f``, m (seed: 80 um).
    film_E, film_nu, film_rho : float
        Film modulus (Pa), Poisson ratio (assumed 0.34), density (kg/m^3); MEAS values.
    d31, d32 : float
        Film charge constants, m/V: 23 and 3 pC/N for uniaxially stretched film (MEAS).
    eps33T : float
        Relative permittivity of the film (12).
    zeta : float or array_like
        Modal damping ratio of the plate modes (assumed 0.02; mounted panel).
    max_mode_hz : float
        Keep the plate modes at or below this frequency, Hz (at least one mode is kept).
    n_modes : int or None
        Keep at most this many modes (lowest first).
    amplifier_bandwidth_hz : float
        First-order bandwidth of each cell's unity-gain amplifier, Hz (assumed 20 kHz).
    finger : MaxwellLoad or None
        Finger resting on ``finger_cell``'s centre (skin mass and ``k0`` load the modes).
    finger_cell : (int, int)
        ``(row, col)`` of the cell the finger touches.
    preload : float
        Static finger force added to the force row, N (the displacement is about the static
        equilibrium under it).
    probe_cells : ((int, int), (int, int))
        Two adjacent cells; the probe sits midway between their centres (the seed's
        accelerometer). The default pair is symmetric about ``x = a / 2``.
    residual : bool
        Add the static (quasi-static) response of the truncated modes to the displacement and
        velocity rows, the probe's displacement and velocity, and the cell capacitances
        (mode-acceleration method). Without it the cell-centre displacement of the default
        plate is ~20 % low at 4 kHz truncation: a cell is a short-wavelength load.
    residual_halfwaves : float
        The static series runs to this many half-waves per cell pitch in each direction.

    Attributes
    ----------
    sys : StateSpace
        Full continuous model: states ``[v, y, y' (n_cells each), eta (K), eta' (K), f
        (n_branches)]`` (``y``: residual mode per cell, V), inputs ``u`` (n_cells), outputs
        ``OUTPUT_NAMES``: the four truth rows of every cell (row-major), the three probes,
        the cell currents.
    modes_hz : ndarray, shape (K,)
        Undamped frequencies of the bare plate modes kept, Hz (Navier).
    mode_indices : ndarray of int, shape (K, 2)
        ``(m, n)`` half-wave numbers along x and y.
    theta : ndarray, shape (K, n_cells)
        Modal force per cell volt (mass-normalized modes), sqrt(kg) m / s^2 / V.
    residual_disp : ndarray, shape (n_cells + 1, n_cells)
        Static displacement of the truncated modes at the cell centres and the probe, m/V
        (zeros when ``residual=False``).
    residual_capacitance : ndarray, shape (n_cells, n_cells)
        The truncated modes' share of the cell capacitances, F.
    capacitance_matrix : ndarray, shape (n_cells, n_cells)
        Static cell capacitances: ``capacitance`` on the diagonal plus the truncated modes'
        share, F (the retained modes add ``theta^T Omega^-2 theta`` at DC).
    residual_omega, residual_zeta : float
        The lumped residual mode (rad/s; damping ratio = mean ``zeta``).
    capacitance : float
        Film capacitance of one cell ``eps0 eps33T A / t_f``, F.
    cell_centres : ndarray, shape (n_cells, 2)
    probe_xy, finger_xy : ndarray, shape (2,)

    Examples
    --------
    >>> from rtctl.plant.pvdf import PvdfPlate
    >>> plate = PvdfPlate()
    >>> plate.n_cells, round(float(plate.modes_hz[0]), 1)
    (48, 301.0)
    >>> round(plate.capacitance * 1e12, 1)     # pF per cell
    327.7
    """

    def __init__(self, rows: int = 6, cols: int = 8, plate_length: float = 0.153,
                 plate_width: float = 0.093, plate_thickness: float = 0.8e-3,
                 plate_E: float = 70e9, plate_nu: float = 0.22, plate_rho: float = 2500.0,
                 gap: float = 1.5e-3, pitch_x: float | None = None, pitch_y: float | None = None,
                 film_thickness: float = 80e-6, film_E: float = 2.5e9, film_nu: float = 0.34,
                 film_rho: float = 1780.0, d31: float = 23e-12, d32: float = 3e-12,
                 eps33T: float = 12.0, zeta=0.02, max_mode_hz: float = 4000.0,
                 n_modes: int | None = None, amplifier_bandwidth_hz: float = 20e3,
                 finger: MaxwellLoad | None = None, finger_cell=(2, 3), preload: float = 0.0,
                 probe_cells=((2, 3), (2, 4)), residual: bool = True,
                 residual_halfwaves: float = 25.0):
        rows, cols = int(rows), int(cols)
        if rows < 1 or cols < 1:
            raise ModelError(f"PvdfPlate grid must be at least 1 x 1, got {rows} x {cols}")
        a = _pos("plate_length", plate_length)
        b = _pos("plate_width", plate_width)
        h = _pos("plate_thickness", plate_thickness)
        E = _pos("plate_E", plate_E)
        rho = _pos("plate_rho", plate_rho)
        tf = _pos("film_thickness", film_thickness)
        Ef = _pos("film_E", film_E)
        wa = 2.0 * math.pi * _pos("amplifier_bandwidth_hz", amplifier_bandwidth_hz)
        for name, nu in (("plate_nu", plate_nu), ("film_nu", film_nu)):
            if not (-1.0 < float(nu) < 0.5):
                raise ModelError(f"PvdfPlate {name} must lie in (-1, 0.5), got {nu!r}")
        px = a / cols if pitch_x is None else _pos("pitch_x", pitch_x)
        py = b / rows if pitch_y is None else _pos("pitch_y", pitch_y)
        gap = float(gap)
        if not (0.0 <= gap < min(px, py)):
            raise ModelError(f"PvdfPlate gap {gap!r} m must be >= 0 and below the cell pitch "
                             f"({min(px, py):.4g} m); reduce the gap or the grid")
        if cols * px > a * (1 + 1e-12) or rows * py > b * (1 + 1e-12):
            raise ModelError(f"a {rows} x {cols} grid at pitch {px:.4g} x {py:.4g} m does not fit "
                             f"the {a:.4g} x {b:.4g} m plate; reduce the pitch or the grid")
        # The film covers the plate: its mass is smeared over it; its bending stiffness about
        # the plate's mid-plane, E_f t_f (h/2)^2 ~ 1 % of D for the defaults, is neglected.
        D = E * h**3 / (12.0 * (1.0 - float(plate_nu) ** 2))
        rho_h = rho * h + _pos("film_rho", film_rho) * tf
        c_plate = math.sqrt(D / rho_h)
        f_max = _pos("max_mode_hz", max_mode_hz)
        mn, om = [], []
        m = 1
        while math.pi**2 * (m / a) ** 2 * c_plate / (2 * math.pi) <= f_max or m == 1:
            n = 1
            while True:
                w = math.pi**2 * ((m / a) ** 2 + (n / b) ** 2) * c_plate
                if w / (2 * math.pi) > f_max and not (m == 1 and n == 1):
                    break
                mn.append((m, n))
                om.append(w)
                n += 1
            m += 1
        order = np.argsort(om, kind="stable")
        if n_modes is not None:
            if int(n_modes) < 1:
                raise ModelError(f"n_modes must be >= 1, got {n_modes!r}")
            order = order[:int(n_modes)]
        mn = np.array(mn, dtype=np.int64)[order]
        om = np.array(om)[order]
        K = om.size
        zeta = np.broadcast_to(np.asarray(zeta, dtype=np.float64), (K,)).copy()
        if not np.all((zeta >= 0.0) & np.isfinite(zeta)):
            raise ModelError(f"zeta must be finite and >= 0, got {zeta!r}")
        alpha_x = mn[:, 0] * math.pi / a
        beta_y = mn[:, 1] * math.pi / b
        norm = 1.0 / math.sqrt(rho_h * a * b / 4.0)  # mass-normalized modes

        def shape(x, y):
            """Mode shapes at points, shape (K, n_points)."""
            x, y = np.atleast_1d(x), np.atleast_1d(y)
            return norm * np.sin(np.outer(alpha_x, x)) * np.sin(np.outer(beta_y, y))

        n_cells = rows * cols
        col_idx = np.tile(np.arange(cols), rows)
        row_idx = np.repeat(np.arange(rows), cols)
        xc = a / 2 + (col_idx - (cols - 1) / 2) * px
        yc = b / 2 + (row_idx - (rows - 1) / 2) * py
        ex, ey = (px - gap) / 2, (py - gap) / 2
        nuf = float(film_nu)
        e_x = Ef * (float(d31) + nuf * float(d32)) / (1 - nuf**2)
        e_y = Ef * (float(d32) + nuf * float(d31)) / (1 - nuf**2)
        arm = (h + tf) / 2
        # int over the electrode of W_xx and W_yy: -alpha^2 Ix Iy and -beta^2 Ix Iy.
        Ix = (np.cos(np.outer(alpha_x, xc - ex)) - np.cos(np.outer(alpha_x, xc + ex))) \
            / alpha_x[:, None]
        Iy = (np.cos(np.outer(beta_y, yc - ey)) - np.cos(np.outer(beta_y, yc + ey))) \
            / beta_y[:, None]
        theta = -arm * norm * (e_x * alpha_x[:, None] ** 2 + e_y * beta_y[:, None] ** 2) * Ix * Iy

        def cell(rc, what):
            r, c = (int(v) for v in rc)
            if not (0 <= r < rows and 0 <= c < cols):
                raise ModelError(f"{what} {tuple(rc)!r} is outside the {rows} x {cols} grid")
            return r * cols + c

        pa, pb = (cell(rc, "probe cell") for rc in probe_cells)
        ra, ca = divmod(pa, cols)
        rb, cb = divmod(pb, cols)
        if abs(ra - rb) + abs(ca - cb) != 1:
            raise ModelError(f"probe_cells {tuple(probe_cells)!r} must be two adjacent cells")
        probe_xy = np.array([(xc[pa] + xc[pb]) / 2, (yc[pa] + yc[pb]) / 2])
        fch = cell(finger_cell, "finger_cell")
        finger_xy = np.array([xc[fch], yc[fch]])

        W_cells = shape(xc, yc)                       # (K, n_cells)
        w_probe = shape(*probe_xy)[:, 0]
        phi_f = shape(*finger_xy)[:, 0]
        if finger is not None and not isinstance(finger, MaxwellLoad):
            raise ModelError("finger must be a MaxwellLoad or None")
        mass = finger.mass if finger else 0.0
        k0 = finger.k0 if finger else 0.0
        kb = finger.k if finger else np.zeros(0)
        taub = finger.tau if finger else np.zeros(0)
        nb = kb.size

        # Structural subsystem x_s = [eta, eta', f], input v (cell voltages).
        M_L = np.eye(K) + mass * np.outer(phi_f, phi_f)
        K_L = np.diag(om**2) + k0 * np.outer(phi_f, phi_f)
        C_d = np.diag(2.0 * zeta * om)
        Minv = np.linalg.inv(M_L)
        ns = 2 * K + nb
        A_s = np.zeros((ns, ns))
        A_s[:K, K:2 * K] = np.eye(K)
        A_s[K:2 * K, :K] = -Minv @ K_L
        A_s[K:2 * K, K:2 * K] = -Minv @ C_d
        A_s[K:2 * K, 2 * K:] = -Minv @ np.outer(phi_f, np.ones(nb))
        for i in range(nb):
            A_s[2 * K + i, K:2 * K] = kb[i] * phi_f
            A_s[2 * K + i, 2 * K + i] = -1.0 / taub[i]
        B_s = np.zeros((ns, n_cells))
        B_s[K:2 * K] = Minv @ theta
        # Structural outputs (on x_s): disp, vel, plate-motion current, force, probe d/v/a.
        Cs = np.zeros((3 * n_cells + 1 + 3, ns))
        Ds = np.zeros((Cs.shape[0], n_cells))      # feedthrough of v (acceleration only)
        Cs[:n_cells, :K] = W_cells.T
        Cs[n_cells:2 * n_cells, K:2 * K] = W_cells.T
        Cs[2 * n_cells:3 * n_cells, K:2 * K] = theta.T
        Cs[3 * n_cells, :K] = k0 * phi_f
        Cs[3 * n_cells, 2 * K:] = 1.0
        Cs[3 * n_cells + 1, :K] = w_probe
        Cs[3 * n_cells + 2, K:2 * K] = w_probe
        Cs[3 * n_cells + 3] = Cs[3 * n_cells + 2] @ A_s
        Ds[3 * n_cells + 3] = Cs[3 * n_cells + 2] @ B_s

        cap = EPS0 * float(eps33T) * (2 * ex) * (2 * ey) / tf
        Rd = np.zeros((n_cells + 1, n_cells))
        Rq = np.zeros((n_cells, n_cells))
        kept_set = {tuple(v) for v in mn.tolist()}
        r4 = 0.0   # trace of sum W Theta / w^4 over the cells: the residual's w^2 term
        if residual:
            kept = kept_set
            m_max = max(int(math.ceil(float(residual_halfwaves) * a / px)), int(mn[:, 0].max()))
            n_max = max(int(math.ceil(float(residual_halfwaves) * b / py)), int(mn[:, 1].max()))
            pts_x = np.append(xc, probe_xy[0])
            pts_y = np.append(yc, probe_xy[1])
            nn = np.arange(1, n_max + 1)
            be = nn * math.pi / b
            Iy_all = (np.cos(np.outer(be, yc - ey)) - np.cos(np.outer(be, yc + ey))) / be[:, None]
            Sy = np.sin(np.outer(be, pts_y))
            for m in range(1, m_max + 1):
                al = m * math.pi / a
                drop = np.array([(m, int(v)) not in kept for v in nn])
                if not drop.any():
                    continue
                Ix_m = (np.cos(al * (xc - ex)) - np.cos(al * (xc + ex))) / al
                w2 = (al**2 + be[drop] ** 2) ** 2 * c_plate**2
                th = (-arm * norm * (e_x * al**2 + e_y * be[drop] ** 2))[:, None] \
                    * Ix_m[None, :] * Iy_all[drop]                    # (n_drop, n_cells)
                Wm = norm * np.sin(al * pts_x)[None, :] * Sy[drop]     # (n_drop, n_cells + 1)
                thw = th / w2[:, None]
                Rd += Wm.T @ thw
                Rq += th.T @ thw
                r4 += float(np.einsum("ij,ij->", Wm[:, :n_cells], thw / w2[:, None]))
        # One lumped residual mode: quasi-static at low frequency and mass-controlled far above,
        # so a DAC staircase does not kick it. Its frequency matches the w^2 term of the
        # truncated modes' response at the cell centres (sum r_k / w_k^4 = R0 / w_r^2, traces);
        # it is never below the lowest truncated mode.
        f_low = min(math.pi * ((i / a) ** 2 + (j / b) ** 2) * c_plate / 2
                     for i in range(1, int(mn[:, 0].max()) + 2)
                     for j in range(1, int(mn[:, 1].max()) + 2) if (i, j) not in kept_set)
        r0 = float(np.trace(Rd[:n_cells]))
        w_r = math.sqrt(r0 / r4) if (residual and r4 * r0 > 0) else 2 * math.pi * f_low
        self.residual_omega = max(w_r, 2 * math.pi * f_low)
        self.residual_zeta = float(np.mean(zeta))
        self.residual_disp = Rd
        self.residual_capacitance = Rq
        self.capacitance_matrix = cap * np.eye(n_cells) + Rq
        self.rows, self.cols, self.n_cells, self.n_modes = rows, cols, n_cells, K
        self.modes_hz = om / (2 * math.pi)
        self.mode_indices = mn
        self.zeta = zeta
        self.theta = theta
        self.capacitance = cap
        self.cell_centres = np.column_stack([xc, yc])
        self.electrode_size = (2 * ex, 2 * ey)
        self.plate_size = (a, b)
        self.flexural_rigidity = D
        self.mass_per_area = rho_h
        self.probe_xy, self.finger_xy = probe_xy, finger_xy
        self.probe_channels = (pa, pb)
        self.finger_channel = fch if finger is not None else -1
        self.finger, self.preload = finger, float(preload)
        self.amplifier_omega = wa
        self.ref_channel = pa
        self.mode_shape = shape
        self.A_s, self.B_s, self.C_s, self.D_s = A_s, B_s, Cs, Ds

        # Full model: states [v, y, y', x_s], input u; outputs in OUTPUT_NAMES order. The
        # truncated modes act as one residual mode per cell, y'' = w_r^2 (v - y) - c_r y',
        # with the static gains Rd (displacement) and Rq (charge).
        nc = n_cells
        wr2, cr = self.residual_omega**2, 2.0 * self.residual_zeta * self.residual_omega
        iv, iy, iw, ix = 0, nc, 2 * nc, 3 * nc
        n = 3 * nc + ns
        eye = np.eye(nc)
        A = np.zeros((n, n))
        B = np.zeros((n, nc))
        A[iv:iy, iv:iy] = -wa * eye
        B[iv:iy] = wa * eye
        A[iy:iw, iw:ix] = eye
        A[iw:ix, iv:iy] = wr2 * eye
        A[iw:ix, iy:iw] = -wr2 * eye
        A[iw:ix, iw:ix] = -cr * eye
        A[ix:, ix:] = A_s
        A[ix:, iv:iy] = B_s
        C = np.zeros((5 * nc + 3, n))
        D = np.zeros((C.shape[0], nc))
        C[:nc, ix:] = Cs[:nc]
        C[:nc, iy:iw] = Rd[:nc]
        C[nc:2 * nc, ix:] = Cs[nc:2 * nc]
        C[nc:2 * nc, iw:ix] = Rd[:nc]
        if finger is not None:
            C[2 * nc + fch, ix:] = Cs[3 * nc]
        C[3 * nc:4 * nc, iv:iy] = eye
        p0 = 4 * nc
        C[p0:p0 + 3, ix:] = Cs[3 * nc + 1:]
        C[p0 + 2, iv:iy] = Ds[3 * nc + 3]
        C[p0, iy:iw] = Rd[nc]
        C[p0 + 1, iw:ix] = Rd[nc]
        C[p0 + 2] += Rd[nc] @ A[iw:ix]
        # Cell current: C_f v' + Theta_j . eta' + Rq y', v' = w_a (u - v).
        C[p0 + 3:, ix:] = Cs[2 * nc:3 * nc]
        C[p0 + 3:, iv:iy] = -wa * cap * eye
        C[p0 + 3:, iw:ix] = Rq
        D[p0 + 3:] = wa * cap * eye
        self.OUTPUT_NAMES = (tuple(f"{q}{j}" for q in ("displacement_m", "velocity_m_s",
                                                        "finger_force_n", "voltage_v")
                                   for j in range(n_cells))
                             + tuple(p for p, _ in PROBE_NAMES)
                             + tuple(f"current{j}_a" for j in range(n_cells)))
        names = (tuple(f"voltage{j}_v" for j in range(nc)) + tuple(f"resid{j}_v" for j in range(nc))
                 + tuple(f"resid{j}_dot_v_s" for j in range(nc)) + tuple(f"eta{k}" for k in range(K))
                 + tuple(f"eta{k}_dot" for k in range(K))
                 + tuple(f"branch{i}_force_n" for i in range(nb)))
        self.sys = StateSpace(A, B, C, D, None, names, tuple(f"u{j}_v" for j in range(n_cells)),
                              self.OUTPUT_NAMES)
        self.y0 = np.zeros(n)

    # -- continuous reference for one channel (the numerics report's contract) -------------
    def _u(self, u):
        u = np.asarray(u, dtype=np.float64)
        if u.ndim == 0:
            full = np.zeros(self.n_cells)
            full[self.ref_channel] = u
            return full
        return u

    def rhs(self, t, y, u):
        """State derivative of the full model.

        Parameters
        ----------
        t : float
            Time, s (unused: time invariant).
        y : ndarray, shape (n_states,)
        u : float or ndarray, shape (n_cells,)
            Commanded voltages, V; a scalar drives ``ref_channel`` alone (others at 0 V).
        """
        return self.sys.A @ y + self.sys.B @ self._u(u)

    def outputs(self, y, u, channel=None):
        """Truth rows of one cell, shape (4,): displacement, velocity, finger force, voltage.

        ``channel`` defaults to ``ref_channel``; ``u`` as in :meth:`rhs`. The force includes
        ``preload`` when the finger is on that cell.
        """
        ch = self.ref_channel if channel is None else int(channel)
        out = self.sys.C @ y + self.sys.D @ self._u(u)
        nc = self.n_cells
        row = out[[ch, nc + ch, 2 * nc + ch, 3 * nc + ch]]
        if ch == self.finger_channel:
            row[2] += self.preload
        return row

    def frequency_response(self, freqs_hz):
        """Continuous response per commanded volt, shape (n_freqs, n_outputs, n_cells), complex."""
        return self.sys.frequency_response(freqs_hz)


class PvdfGroup:
    """All cells of one plate advanced block by block (the simulated-group contract).

    Discretization: exact for a DAC staircase (zero-order hold) at ``dt = 1 / fs``. The
    structural part is split into decoupled modal blocks: the bare plate modes as they are
    (``(eta_k, eta_k')``), or with a finger the real modal form of the loaded, coupled system
    (:func:`~rtctl.plant.lti.to_modal`). Each block's input ``Btilde_b v`` is factored into
    one or two projections ``q_b . v``; because every cell has the same amplifier, the
    projection of the amplifier states obeys that amplifier's equation driven by ``q_b . u``,
    so amplifier + block is a small SISO/2-input cascade discretized exactly by
    :func:`~rtctl.plant.lti.c2d` (no approximation of the amplifier lag).

    Parameters
    ----------
    plant : PvdfPlate
    fs : float
        Sample rate, Hz.
    n_channels : int or None
        Must equal ``plant.n_cells`` (the plate couples all of them); ``None`` takes it.
    max_block : int
        Samples per internal chunk (scratch size); longer calls are split, same result.
    currents : bool
        Also write the cell currents as sensed rows (``n_sensed = 1``; ~+25 % cost).
    max_cond : float
        Passed to ``to_modal`` (finger case).

    Attributes
    ----------
    kernel, args, n_channels, n_sensed, sensed_labels, probe_names, probe, capacitance
        The simulated-group contract (``rtctl.io.sim``).
    n_blocks, n_projections : int

    Examples
    --------
    >>> import numpy as np
    >>> from rtctl.plant.pvdf import PvdfPlate, PvdfGroup
    >>> group = PvdfGroup(PvdfPlate(), fs=48000.0)
    >>> drive = np.zeros((48, 32)); drive[19] = 250.0
    >>> sensed = np.empty((0, 32)); truth = np.empty((48, 4, 32))
    >>> group.process(drive, sensed, truth)
    0
    >>> bool(truth[19, 3, -1] > 0), group.probe.shape
    (True, (3, 64))
    """

    def __init__(self, plant: PvdfPlate, fs: float, n_channels: int | None = None,
                 max_block: int = 64, currents: bool = False, max_cond: float = 1e8):
        if not isinstance(plant, PvdfPlate):
            raise ModelError("PvdfGroup needs a PvdfPlate")
        fs = float(fs)
        if not (fs > 0.0 and math.isfinite(fs)):
            raise ModelError(f"fs must be a positive sample rate in Hz, got {fs!r}")
        nc = plant.n_cells if n_channels is None else n_channels
        if nc != plant.n_cells:
            raise ModelError(f"a PvdfGroup drives all {plant.n_cells} cells of its plate, got "
                             f"n_channels={n_channels!r}; set the grid to {plant.rows} x "
                             f"{plant.cols}")
        mb = int(max_block)
        if mb < 1:
            raise ModelError(f"max_block must be >= 1, got {max_block!r}")
        if np.max(plant.modes_hz) >= fs / 2:
            raise ModelError(f"plate mode at {np.max(plant.modes_hz):.4g} Hz is not below "
                             f"fs/2 = {fs / 2:.4g} Hz; lower max_mode_hz")
        dt = 1.0 / fs
        self.plant, self.fs, self.n_channels = plant, fs, nc
        A_s, B_s, Cs = plant.A_s, plant.B_s, plant.C_s
        K, ns = plant.n_modes, A_s.shape[0]
        if plant.finger is None:
            # Bare modes are already decoupled: keep physical coordinates, so displacement
            # rows read eta only and velocity rows eta' only (exact zeros, half the work).
            T = np.eye(ns)
            blocks = [(k, K + k) for k in range(K)]
            lam_c = A_s
            self.modal = None
        else:
            sd = c2d(StateSpace(A_s, B_s, Cs, np.zeros((Cs.shape[0], B_s.shape[1]))), dt)
            mf = to_modal(sd, max_cond=max_cond, form="modal")
            T = mf.T
            blocks = [(2 * p, 2 * p + 1) for p in range(mf.n_pairs)] + \
                [(2 * mf.n_pairs + r,) for r in range(mf.n_real)]
            lam_c = np.linalg.solve(T, A_s @ T)
            mask = np.zeros_like(lam_c, dtype=bool)
            for blk in blocks:
                mask[np.ix_(blk, blk)] = True
            off = np.max(np.abs(lam_c[~mask])) if (~mask).any() else 0.0
            if off > 1e-9 * np.max(np.abs(lam_c)):
                raise ModelError(f"loaded plate modes do not decouple (residual {off:.3g}); "
                                 "raise max_cond or drop the finger")
            self.modal = mf
        Bt = np.linalg.solve(T, B_s)
        Ct = Cs @ T
        wa = plant.amplifier_omega
        n_blocks = len(blocks)
        zi = np.empty((n_blocks, 2), dtype=np.int64)
        pi = np.empty((n_blocks, 2), dtype=np.int64)
        L = np.zeros((n_blocks, 2, 2))
        Gg = np.zeros((n_blocks, 2, 2))
        Gp = np.zeros((n_blocks, 2, 2))
        q_rows, vr_cols = [], []   # projections and their directions (columns of Btilde)
        n_z = ns
        alpha = math.exp(-wa * dt)
        for b, blk in enumerate(blocks):
            nz = len(blk)
            U, S, Vt = np.linalg.svd(Bt[list(blk)], full_matrices=False)
            rank = int(np.sum(S > 1e-10 * S[0])) if S.size and S[0] > 0 else 0
            p0 = len(q_rows)
            for r in range(rank):
                q_rows.append(S[r] * Vt[r])
            Vr = U[:, :rank]
            # Amplifier on the projections, then the block: [g (rank), z (nz)], input p.
            Ae = np.zeros((rank + nz, rank + nz))
            Be = np.zeros((rank + nz, max(rank, 1)))
            Ae[:rank, :rank] = -wa * np.eye(rank)
            Ae[rank:, :rank] = Vr
            Ae[rank:, rank:] = lam_c[np.ix_(blk, blk)]
            Be[:rank, :rank] = wa * np.eye(rank)
            ed = c2d(StateSpace(Ae, Be, np.zeros((1, rank + nz)), np.zeros((1, Be.shape[1]))),
                     dt)
            L[b, :nz, :nz] = ed.A[rank:, rank:]
            Gg[b, :nz, :rank] = ed.A[rank:, :rank]
            Gp[b, :nz, :rank] = ed.B[rank:, :rank]
            zi[b] = [blk[0], blk[1] if nz == 2 else n_z]
            vr_cols.append((p0, rank, blk, Vr))
        n_p = len(q_rows)
        for b, (p0, rank, _blk, _Vr) in enumerate(vr_cols):
            pi[b] = [p0 if rank > 0 else n_p, p0 + 1 if rank == 2 else n_p]
        Q = np.array(q_rows).reshape(n_p, nc)
        # Output rows over e = [z, g]; acceleration = d/dt(velocity) = c (Lam z + Vr g).
        n_e = n_z + n_p
        Cout = np.zeros((Cs.shape[0], n_e))
        Cout[:, :n_z] = Ct
        acc = 3 * nc + 3
        cvel = Ct[3 * nc + 2]
        Cout[acc, :n_z] = cvel @ lam_c
        for p0, rank, blk, Vr in vr_cols:
            Cout[acc, n_z + p0:n_z + p0 + rank] = cvel[list(blk)] @ Vr
        # Per cell: amplifier, then the residual mode driven by its voltage (exact ZOH).
        wr = plant.residual_omega
        A3 = np.array([[-wa, 0.0, 0.0], [0.0, 0.0, 1.0],
                       [wr**2, -wr**2, -2 * plant.residual_zeta * wr]])
        cell = c2d(StateSpace(A3, [[wa], [0.0], [0.0]], np.eye(3), np.zeros((3, 1))), dt)
        self.n_blocks, self.n_projections, self.n_states = n_blocks, n_p, n_e + 3 * nc
        self.currents = bool(currents)
        self.n_sensed = 1 if currents else 0
        self.sensed_labels = ("current",) if currents else ()
        self.probe_names = PROBE_NAMES
        self.capacitance = plant.capacitance
        self.kernel = pvdf_group_process
        self.T = T
        self.probe = np.zeros((len(PROBE_NAMES), mb))
        residual = bool(np.any(plant.residual_disp))
        consts = np.concatenate([[alpha, plant.preload, plant.capacitance * wa, wr**2,
                                  2 * plant.residual_zeta * wr], cell.A.ravel(), cell.B[:, 0]])
        #: The model's matrices (what the kernel's tiles are built from): input projections
        #: (per volt), output rows over [z; g], the truncated modes' static displacement at the
        #: cells and the probe (m/V) and share of the cell capacitances (F).
        self.Q, self.C = np.ascontiguousarray(Q), Cout
        self.Rd, self.Rq = plant.residual_disp, plant.residual_capacitance
        #: Every output row (as ``C``'s) over the kernel's sources ``[e; v; y'; u - v; v - y; u]``,
        #: less the truncated modes' ``Rd [y; y']`` on the displacement and velocity rows (cells
        #: and probe), which the kernel adds from one product over ``[y | y']``.
        self.W = self._outputs(n_e, nc, consts, residual, plant.finger_channel)
        n_out, n_src = self.W.shape
        active = [r for r in range(n_out) if np.any(self.W[r] != 0.0)] or [0]
        oplan, ocoef = output_plan(self.W[active])
        oplan[:, 1:4] = np.asarray(active)[oplan[:, 1:4]]
        qplan, qcoef = output_plan(self.Q)
        qplan[:, 5:] += n_e + 4 * nc          # the drive's rows of the sources
        if residual:
            rplan, rcoef = output_plan(self.Rd)
        else:
            rplan, rcoef = np.zeros((0, PLAN_COLUMNS), dtype=np.int64), np.zeros((0, 3, 8))
        self.consts = consts
        self.args = (
            np.array([mb, plant.finger_channel, self.n_sensed, len(PROBE_NAMES), int(residual),
                      n_e], dtype=np.int64),
            zi, pi, L, Gg, Gp, consts,
            np.zeros(n_z + 1),            # Z: modal states (+ dummy)
            np.zeros(n_p + 1),            # G: amplified projections (+ dummy)
            np.zeros((nc, 3)),            # V: per cell voltage and residual mode (v, y, y')
            qplan, qcoef, oplan, ocoef, rplan, rcoef,
            # the cell each tile's sources belong to (-1: e), and which cells' sources are zero
            np.where(qplan[:, 5:] >= n_e, (qplan[:, 5:] - n_e) % nc, -1),
            np.where(oplan[:, 5:] >= n_e, (oplan[:, 5:] - n_e) % nc, -1),
            rplan[:, 5:].copy(),
            np.ones(nc, dtype=np.int64),  # quiet: every cell's rows start as zeros
            np.zeros(max(n_out, n_p + 1, 2 * mb)),
            aligned_zeros((n_p + 1, mb)),  # P: projections of a chunk (last row stays 0)
            aligned_zeros((n_src, mb)),    # X: the sources of a chunk
            aligned_zeros((n_out, mb)),    # ys: the outputs of a chunk
            aligned_zeros((nc, 2 * mb)),   # Y2: per cell [y | y'] of a chunk
            aligned_zeros((nc + 1, 2 * mb)),  # ys2: Rd [y | y']
            self.probe,
        )

    def _outputs(self, n_e, nc, consts, residual, finger):
        """The output matrix over the sources (see :attr:`W`): rows of ``C`` for what is
        written (the currents only when sensed, the force only with a finger), the residual
        terms but ``Rd [y; y']``, and the currents' amplifier term."""
        C, Rd, Rq = self.C, self.Rd, self.Rq
        cf_wa, wr2, cr = consts[2], consts[3], consts[4]
        _, yd, uv, vy = (n_e + k * nc for k in range(4))  # after e: v (the truth's voltage), y', u - v, v - y
        W = np.zeros((C.shape[0], n_e + 5 * nc))
        W[:, :n_e] = C
        cells = np.arange(nc)
        if self.currents:
            W[2 * nc + cells, uv + cells] = cf_wa
        else:
            W[2 * nc:3 * nc] = 0.0
        if finger < 0:
            W[3 * nc] = 0.0
        if residual:  # (Rd [y; y'] on displacement and velocity is the kernel's second product)
            if self.currents:
                W[2 * nc:3 * nc, yd:yd + nc] = Rq
            W[3 * nc + 3, vy:vy + nc] = wr2 * Rd[nc]
            W[3 * nc + 3, yd:yd + nc] = -cr * Rd[nc]
        return W

    def physical_state(self) -> np.ndarray:
        """State in ``plant.sys`` coordinates ``[v, y, y', eta, eta', f]``, a copy."""
        Z, V = self.args[_Z], self.args[_V]
        return np.concatenate([V[:, 0], V[:, 1], V[:, 2], self.T @ Z[:-1]])

    def reset(self) -> None:
        """Zero every state (as just built)."""
        for i in (_Z, _G, _V):
            self.args[i][:] = 0.0
        self.probe[:] = 0.0

    def process(self, drive, sensed, truth) -> int:
        """Advance every cell by one block.

        Parameters
        ----------
        drive : ndarray, shape (n_channels, n), float64, C-contiguous
            Commanded cell voltages, V.
        sensed : ndarray, shape (n_channels * n_sensed, n)
            Written: cell currents (A) when ``currents=True``.
        truth : ndarray, shape (n_channels, 4, n)
            Written: ``TRUTH_NAMES`` rows.

        Returns
        -------
        int
            2 if a state is NaN/Inf (stays until :meth:`reset`), else 0.
        """
        n = drive.shape[-1]
        for name, arr, shape in (("drive", drive, (self.n_channels, n)),
                                 ("sensed", sensed, (self.n_channels * self.n_sensed, n)),
                                 ("truth", truth, (self.n_channels, len(TRUTH_NAMES), n))):
            if arr.shape != shape or arr.dtype != np.float64 or not arr.flags.c_contiguous:
                raise ModelError(f"{name} must be C-contiguous float64 of shape {shape}, got "
                                 f"{arr.dtype} {arr.shape}")
        return pvdf_group_process(*self.args, drive, sensed, truth)
