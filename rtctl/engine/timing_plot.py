"""plot.png's timing row for a paced run: the block-time histogram beside the wake-up lateness
histogram, both against the period, with the deadline counts (cyclictest's view of a run)."""

from __future__ import annotations

import numpy as np

from .loop import LATE_FIELD


def has_timing(reader) -> bool:
    """The trace is a paced run's (it carries each block's wake-up lateness)."""
    return LATE_FIELD in reader.units


def timing_panels(ax_time, ax_late, summary: dict, reader, n_run_blocks: int) -> None:
    """Log-count histograms of block time and wake-up lateness (us) of the run's blocks, the
    period marked on both."""
    period_us = 1e6 * reader.block / reader.fs
    took = reader.compute_us[:n_run_blocks]
    late = np.asarray(reader.records[LATE_FIELD][:n_run_blocks, 0], dtype=float)
    for ax, x, colour, label in ((ax_time, took, "C0", "block time, us"),
                                 (ax_late, late, "C1", "wake-up lateness, us (a stall's catch-up included)")):
        x = x[np.isfinite(x)]
        top = max(period_us * 1.5, float(x.max()) if x.size else 0.0)
        ax.hist(np.clip(x, 0.0, None), bins=np.linspace(0.0, top, 120), color=colour, log=True)
        ax.axvline(period_us, color="k", lw=0.8, ls="--", label=f"period {period_us:.0f} us")
        ax.set_xlabel(label)
        ax.set_ylabel("blocks")
        ax.legend(fontsize=7, loc="upper right")
    bt, wl = summary.get("block_time_us", {}), summary.get("wake_late_us", {})
    ax_time.set_title(f"block time {_pcts(bt)}; overruns {summary.get('overruns', 0)}", fontsize=9, loc="left")
    ax_late.set_title(f"lateness {_pcts(wl)}; late wake-ups {summary.get('late_wakeups', 0)} in "
                      f"{summary.get('miss_bursts', 0)} stalls", fontsize=9, loc="left")


def _pcts(p: dict) -> str:
    return f"p50 {p.get('p50', 0):.1f}, p99 {p.get('p99', 0):.1f}, max {p.get('max', 0):.0f} us"
