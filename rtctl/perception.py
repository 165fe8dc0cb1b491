"""Perception thresholds of the four mechanoreceptor channels.

Seed 000 (section 1) gives, per receptor, the band it responds to and the smallest displacement
amplitude it needs: Meissner 1-300 Hz >= 6 um, Merkel 0-30 Hz >= 30 um, Ruffini 0-15 Hz >= 300 um,
Pacinian 5-1000 Hz >= 0.08 um. These are the thresholds rtctl uses. Seed 000 (Fig. 3) also shows
that thresholds depend on direction and preload; the paper gives those only as plots, so they are
not modelled here and a run reports against the constants above.

>>> threshold_m(250.0, "pacinian")
8e-08
>>> auto_receptor(2.0)
'ruffini'
"""

from __future__ import annotations

import math

# name: (f_lo Hz, f_hi Hz, threshold m)
RECEPTORS = {
    "pacinian": (5.0, 1000.0, 0.08e-6),
    "meissner": (1.0, 300.0, 6.0e-6),
    "merkel": (0.0, 30.0, 30.0e-6),
    "ruffini": (0.0, 15.0, 300.0e-6),
}


def in_band(freq: float, receptor: str) -> bool:
    lo, hi, _ = RECEPTORS[receptor]
    return lo <= freq <= hi


def threshold_m(freq: float, receptor: str) -> float:
    """Displacement threshold (peak, m) of ``receptor`` at ``freq``; NaN outside its band."""
    lo, hi, th = RECEPTORS[receptor]
    return th if lo <= freq <= hi else math.nan


def auto_receptor(freq: float) -> str | None:
    """The receptor a tone at ``freq`` is meant for when a scene does not say.

    The rule: the receptor with the *highest* threshold whose band holds ``freq``, i.e. the one
    that needs the largest stroke, so that a tone chosen for a slow receptor is judged against its
    own threshold rather than silently against the Pacinian one. With seed 000's bands that is
    Ruffini up to 15 Hz, Merkel to 30 Hz, Meissner to 300 Hz and Pacinian only from 300 to
    1000 Hz: a scene that means the Pacinian channel at 250 Hz, or Meissner at 20 Hz, names the
    receptor. None outside every band.
    """
    cands = [(th, name) for name, (lo, hi, th) in RECEPTORS.items() if lo <= freq <= hi]
    return max(cands)[1] if cands else None


def target_m(freq: float, receptor: str, margin_db: float) -> float:
    """Control target: threshold raised by ``margin_db`` (target = threshold * 10^(margin_db/20))."""
    return threshold_m(freq, receptor) * 10.0 ** (margin_db / 20.0)
