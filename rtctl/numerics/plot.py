"""Work-precision diagram: error against wall time, log-log, one panel per problem."""

from __future__ import annotations

__all__ = ["plot_work_precision"]


def plot_work_precision(entries, path, target: float = 1e-6) -> None:
    """Write the diagram (as SciML's work-precision plots) to ``path`` (PNG).

    Parameters
    ----------
    entries : sequence of Entry
    path : str or Path
    target : float
        Drawn as a dashed line: the "equal error" of the report.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plants = list(dict.fromkeys(e.plant for e in entries))
    fig, axes = plt.subplots(1, len(plants), figsize=(6.5 * len(plants), 5), squeeze=False)
    for ax, plant in zip(axes[0], plants):
        es = [e for e in entries if e.plant == plant and e.error is not None]
        for method in dict.fromkeys(e.method for e in es):
            pts = sorted((e.wall_s, max(e.error, 1e-17)) for e in es if e.method == method)
            ours = any(e.ours for e in es if e.method == method)
            ax.loglog([p[0] for p in pts], [p[1] for p in pts], "o-" if ours else "s--",
                      lw=2 if ours else 1, ms=5, label=method)
        ax.axhline(target, color="k", ls=":", lw=1)
        ax.set_xlabel("wall time per run, s")
        ax.set_ylabel("max relative error on the output grid")
        ax.set_title(plant)
        ax.grid(True, which="both", alpha=0.3)
        if es:
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
