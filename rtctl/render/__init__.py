"""Rendering: images to per-pin stimulus parameters. Imports cv2 lazily.

Public API (import the submodules; this package imports nothing heavy):

- :func:`rtctl.render.factory.make_renderer` (``roi``, ``canny``, ``frequency``, ``beat``) ->
  a :class:`~rtctl.render.hia.Renderer`: ``prepare(image)`` once, ``update(x, y, out)`` per
  render tick, ``render_path(x, y)``; ``out`` columns :data:`~rtctl.render.hia.FIELDS`.
- :func:`rtctl.render.image.load_image` / ``check_image``: one-line :class:`ImageError`.
- :mod:`rtctl.render.path`: ``raster``, ``through``, ``from_csv`` and ``PathPlayer`` (render
  updates handed to the block loop).
- :mod:`rtctl.render.braille` and :mod:`rtctl.render.shapes`: boolean pin frames.
- ``rtctl.render.cli.main(argv)`` and ``rtctl.render.bench.main_bench(argv)``.
"""
