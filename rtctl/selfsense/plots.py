"""Admittance plots in the manner of seed 000, Fig. 8: model lines, observer-estimated markers."""

from __future__ import annotations

import numpy as np

__all__ = ["admittance_figure"]


def admittance_figure(freqs, model, estimated, path):
    """Tip velocity per volt (magnitude and phase) and electrical admittance, per finger load.

    Parameters
    ----------
    freqs : ndarray, shape (n,)
        Model frequencies, Hz.
    model : dict
        ``load name -> TMMBeam.response(...)`` dict (``velocity``, ``admittance``).
    estimated : dict
        ``load name -> (freqs_hz, velocity per volt from the observer on the simulated plant,
        true velocity per volt)``.
    path : str or Path
        PNG written here.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(3, 1, figsize=(7, 9), sharex=True)
    for i, (name, r) in enumerate(model.items()):
        c = f"C{i}"
        ax[0].loglog(freqs, np.abs(r["velocity"]), c, label=f"model, {name}")
        ax[1].semilogx(freqs, np.degrees(np.angle(r["velocity"])), c)
        ax[2].loglog(freqs, np.abs(r["admittance"]), c, label=f"I/U, {name}")
        if name in estimated:
            fe_, est, true = estimated[name]
            ax[0].loglog(fe_, np.abs(est), "o", color=c, mfc="none", label=f"observer, {name}")
            ax[0].loglog(fe_, np.abs(true), "x", color=c)
            ax[1].semilogx(fe_, np.degrees(np.angle(est)), "o", color=c, mfc="none")
            ax[1].semilogx(fe_, np.degrees(np.angle(true)), "x", color=c)
    ax[0].set_ylabel("|v_tip / U|, m/s/V")
    ax[1].set_ylabel("phase, deg")
    ax[2].set_ylabel("|I / U|, A/V")
    ax[2].set_xlabel("frequency, Hz")
    ax[0].legend(fontsize=7, ncol=2)
    ax[0].set_title("tip velocity per volt: TMM model (lines), observer on FE plant (o), FE truth (x)",
                    fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
