"""How long a run goes on after a requested stop's fade: until the model's tips have settled.

The criterion is the model's, never the simulated device's truth (which a real display does not
have): after the fade reaches 0 V the loop runs on, driving 0 V and tracing, for ``ln(1000)``
times the slowest decaying oscillation's time constant ``1 / sigma`` of each group's model
under its finger (the envelope of a free oscillation has fallen by 60 dB), at most
``timing.settle_max``.

* bimorph: the loaded beam's modes (:meth:`rtctl.models.Models.ring_time`);
* pvdf: the plate's modes with the finger, the same rule on its state matrix;
* em, solenoid, dot, sma: 0. Their pins rest on an end stop (critically damped), on a latch,
  or hold their place (SMA taxels are bistable): nothing rings once the drive is 0 V.
"""

from __future__ import annotations

import math

import numpy as np

#: Decay of a free oscillation's envelope that counts as settled: 60 dB.
SETTLED = 1e-3


def slowest_ring(A: np.ndarray) -> float:
    """The longest time constant ``1 / sigma`` of the decaying oscillations of ``x' = A x``, s
    (0 with none)."""
    ev = np.linalg.eigvals(A)
    osc = ev[(np.abs(ev.imag) > 1e-6 * np.abs(ev)) & (ev.real < 0)]
    return float(np.max(-1.0 / osc.real)) if osc.size else 0.0


def settle_time(models, scene) -> float:
    """Seconds the loop runs on after a requested stop's fade (see the module)."""
    ring = 0.0
    for g in scene.actuator:
        if g.type == "bimorph":
            ring = max(ring, models.ring_time(g))
        elif g.type == "pvdf":
            ring = max(ring, slowest_ring(np.asarray(models.pvdf(g).sys.A)))
    return min(math.log(1.0 / SETTLED) * ring, float(scene.timing.settle_max))
