"""The device side of hardware-in-the-loop: the simulated plant as a JACK client
(``rtctl emulate audio``) and a Dot/SMA pin controller's firmware behind a pseudo-terminal
(``rtctl emulate serial``). With :mod:`rtctl.io.sim` they are the only readers of ``io.mismatch``,
the simulated device's secret; the backends in :mod:`rtctl.io` talk to them as to real devices.
"""
