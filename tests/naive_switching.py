"""Plain numpy twin of ``rtctl.plant.switching.switched_group_process``: the per-load discrete
plants in their own (plant) coordinates, the state map applied at a load change, one sample at a
time, no modal form, no chunks, no ADC (truth rows and anti-aliased currents only)."""

import numpy as np


def switched_run(sysds, maps, load_of_block, drive, block):
    """Outputs of every channel, shape (n_channels, n_outputs, n_samples).

    ``sysds[s]``: load ``s``'s discrete plant (``x[k+1] = A x + B u``, ``y = C x + D u``);
    ``maps[(i, j)] = (M, g)``: ``x_j = M x_i + g u`` with ``u`` the first drive sample of the
    block that switches; ``load_of_block[k]``: the load block ``k`` runs on (block 0's is the
    initial one, no map).
    """
    nc, n = drive.shape
    out = np.zeros((nc, sysds[0].C.shape[0], n))
    for ch in range(nc):
        cur = load_of_block[0]
        x = np.zeros(sysds[cur].A.shape[0])
        for k in range(n // block):
            s = load_of_block[k]
            if s != cur:
                M, g = maps[(cur, s)]
                x = M @ x + g * drive[ch, k * block]
                cur = s
            A, B, C, D = sysds[s].A, sysds[s].B[:, 0], sysds[s].C, sysds[s].D[:, 0]
            for t in range(k * block, (k + 1) * block):
                u = drive[ch, t]
                out[ch, :, t] = C @ x + D * u
                x = A @ x + B * u
    return out
