"""Naive twin of rtctl.control._kernels.amplitude_control: the same rules, written plainly."""

import math

from rtctl.control._kernels import (
    AGREE,
    AMAX,
    BANK,
    BIG,
    CHANNEL,
    CMD,
    ENABLE,
    EST,
    FF,
    FROZEN,
    GAIN,
    GHAT,
    LIMSEEN,
    MAX_STEP,
    OBS_CH,
    OBS_SLOT,
    ON,
    PATIENCE,
    PREV,
    RING,
    SAT,
    TARGET,
    TPREV,
    TRIES,
    WAIT,
    WARM,
)
from rtctl.dsp._kernels import P_AMP, P_FLAG, P_RAMP
from rtctl.safety import CONTROL_FROZEN, CONTROL_SATURATED


def amplitude_control(est, index, target, state, pending, lim_counts, ramp):
    status = 0
    for i in range(state.shape[1]):
        b = index[BANK, i]
        col = state[:, i]
        if target[ENABLE, i] == 0:
            if col[ON]:
                col[ON] = col[CMD] = 0.0
                pending[P_AMP, b], pending[P_RAMP, b], pending[P_FLAG, b] = 0.0, ramp, 1.0
            continue
        r = target[TARGET, i]
        lim = float(lim_counts[:, index[CHANNEL, i]].sum())
        limited, col[LIMSEEN] = lim != col[LIMSEEN], lim
        a = col[CMD]
        starting = not col[ON]
        if starting or r != col[TPREV]:
            a = r / col[GHAT] if col[GHAT] > 0 else r * col[FF]
            col[ON], col[TPREV], col[WAIT], col[PREV], col[TRIES] = 1.0, r, col[WARM] + col[RING], 0.0, 0.0
        elif col[WAIT] > 0:
            col[WAIT] -= 1
            continue
        else:
            e = est[index[OBS_CH, i], index[OBS_SLOT, i], 0]
            y = math.hypot(e[0], e[1])
            col[EST] = y
            if not (0 < y < math.inf and r > 0):
                col[FROZEN] = 1.0
                status |= CONTROL_FROZEN
                continue
            col[FROZEN] = 0.0
            col[GHAT] = y / a
            prev, col[PREV] = col[PREV], y
            settled = (prev > 0 and abs(y / prev - 1) <= AGREE) or abs(r / y - 1) > BIG
            if not settled and col[TRIES] < PATIENCE:
                col[TRIES] += 1
                col[WAIT] = col[WARM]
                continue
            g = col[GAIN] if settled else 0.5 * col[GAIN]
            col[PREV] = col[TRIES] = 0.0
            step = min(max((r / y) ** g, 1 / MAX_STEP), MAX_STEP)
            if limited and step > 1:
                step = 1.0
            a *= step
            col[WAIT] = col[WARM]
        if a >= col[AMAX]:
            a = col[AMAX]
            col[SAT] = 1.0 if (col[EST] < r or col[WAIT] > 0) else 0.0
        else:
            col[SAT] = 0.0
        if col[SAT]:
            status |= CONTROL_SATURATED
        col[CMD] = a
        pending[P_AMP, b], pending[P_RAMP, b], pending[P_FLAG, b] = a, ramp, 1.0
    return status
