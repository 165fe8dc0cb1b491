"""Design sweeps: a scene's keys varied over a grid of points, each point a model build, a reach
computation, a self-sensing accuracy run or a whole run, computed on Dask (``rtctl sweep``,
docs/sweep.md).

:mod:`~rtctl.sweep.spec` parses ``--vary`` and makes the product, :mod:`~rtctl.sweep.points`
computes one point, :mod:`~rtctl.sweep.engine` runs the tasks (Dask or this process),
:mod:`~rtctl.sweep.results` keeps the sweep's directory and table, :mod:`~rtctl.sweep.plots` draws
it, :mod:`~rtctl.sweep.job` ties them together and :mod:`~rtctl.sweep.cli` is the command.
Importing this package imports none of them (and no Dask).
"""
