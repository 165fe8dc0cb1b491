"""Plain numpy/loop twins of every numba kernel (stumpy's ``tests/naive.py``), one module per
subpackage so that their authors never edit the same file: import them from here or directly.

- :mod:`naive_dsp`: oscillator bank, beat pairs, pulse trains, ramps, fades, lock-in
- :mod:`naive_plant`: LTI recursion (modal and dense), outputs, ADC, the simulated group
- :mod:`naive_loop`: the final limiter
"""

from naive_dsp import *  # noqa: F401,F403
from naive_loop import *  # noqa: F401,F403
from naive_plant import *  # noqa: F401,F403
