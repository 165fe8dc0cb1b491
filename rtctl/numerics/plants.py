"""Work-precision problems of the display plants (beyond the bimorph and the skin contact):
each plant's group kernel at several substeps against Radau on the same drive staircase."""

from __future__ import annotations

import numpy as np

from rtctl.numerics.base import group_problem, register


@register("sma")
def sma_problem(quick: bool = False):
    """SMA taxel (forced air): heat the raise spring, let it cool, heat the lower one. The slow
    physics is thermal (0.45 s) with a snap-through of the pin, so the loop rate here is 4.8 kHz
    and the knob is samples per mechanical solve. Compared: the pin height (the pin is massless,
    its velocity is a secant between solves in the kernel)."""
    from rtctl.plant.sma import SmaGroup, SmaTaxel

    plant = SmaTaxel(cooling="forced")
    v = plant.voltage_for(110.0)
    fs = 4800.0
    return group_problem(
        "sma", lambda fs_, k: SmaGroup(plant, fs_, 1, max_block=4096, substeps=k),
        plant.rhs, plant.y0, plant.outputs, fs=fs, levels=[v, 0.0, -v, 0.0],
        hold_s=0.25 if quick else 1.0, substeps=(16, 4) if quick else (48, 16, 4, 1),
        truth_lag="group", ref_rtol=1e-9, rows=(0,),
        description=f"SMA taxel, +-{v:.2f} V held {0.25 if quick else 1.0} s each at {fs:g} Hz")


@register("pvdf")
def pvdf_problem(quick: bool = False):
    """PVDF plate (6x8 cells, one driven): exact zoh, so the error is round-off at any rate;
    what it shows is the cost of reaching it against the integrators."""
    from rtctl.plant.pvdf import PvdfGroup, PvdfPlate

    plant = PvdfPlate()
    return group_problem(
        "pvdf", lambda fs_, k: _Single(PvdfGroup(plant, fs_, max_block=4096), plant.ref_channel),
        plant.rhs, plant.y0, plant.outputs, fs=48000.0, levels=[250.0, -250.0, 0.0],
        hold_s=2e-3 if quick else 5e-3, substeps=(1,), ref_rtol=1e-10,
        description="PVDF plate, one cell driven by a +-250 V staircase, 48 kHz")


class _Single:
    """One driven channel of a MIMO group (the others held at 0 V), as a one-channel group."""

    def __init__(self, group, channel):
        self.g, self.c = group, channel
        self.n_channels = 1
        self.n_sensed = 0

    def reset(self):
        self.g.reset()

    def process(self, drive, sensed, truth):
        n = drive.shape[1]  # (sensed is not passed on: this view reports truth only)
        d = np.zeros((self.g.n_channels, n))
        d[self.c] = drive[0]
        s = np.zeros((self.g.n_channels * self.g.n_sensed, n))
        t = np.zeros((self.g.n_channels, 4, n))
        status = self.g.process(d, s, t)
        truth[0] = t[self.c]
        return status


def _pin_problem(name, plant, make, levels, hold_s, quick, description):
    return group_problem(name, make, plant.rhs, plant.y0, plant.outputs, fs=48000.0, levels=levels,
                         hold_s=hold_s, substeps=(1, 4) if quick else (1, 2, 4, 8), ref_rtol=1e-10,
                         description=description)


@register("solenoid")
def solenoid_problem(quick: bool = False):
    """Solenoid pin (seed 003): 5 V pulses throw it against the stiff top stop (1e8 N/m) and the
    spring returns it to the bottom one, under the finger (switched-linear engine)."""
    from rtctl.plant.solenoid import SolenoidGroup, SolenoidPin

    plant = SolenoidPin()
    return _pin_problem("solenoid", plant, lambda fs, k: SolenoidGroup(plant, fs, 1, max_block=4096, substeps=k),
                        [5.0, 0.0, 5.0, 0.0], 2e-3 if quick else 4e-3, quick,
                        "solenoid pin, 5 V pulses onto stiff end stops, finger on top, 48 kHz")


@register("em")
def em_problem(quick: bool = False):
    """EM perpendicular actuator (bimodal display) with the unilateral finger: a voltage staircase
    that lifts the pin into the skin and pulls it away faster than the skin follows."""
    from rtctl.plant.em import EMGroup, EMPlant

    plant = EMPlant()
    return _pin_problem("em", plant, lambda fs, k: EMGroup(plant, fs, 1, max_block=4096, substeps=k),
                        [3.0, -3.0, 0.0], 3e-3 if quick else 6e-3, quick,
                        "EM actuator, +-3 V staircase, unilateral finger contact, 48 kHz")


@register("dot")
def dot_problem(quick: bool = False):
    """Latching Dot pin: an up pulse, hold (latched, unpowered), a down pulse."""
    from rtctl.plant.dot import DotGroup, DotPin

    plant = DotPin()
    return _pin_problem("dot", plant, lambda fs, k: DotGroup(plant, fs, 1, max_block=4096, substeps=k),
                        [5.0, 0.0, -5.0, 0.0], 3e-3 if quick else 5e-3, quick,
                        "Dot pin, up pulse, latched hold, down pulse, 48 kHz")
