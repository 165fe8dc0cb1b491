"""Where a dsp bank's parameter changes go: into its ``pending`` array, or to an engine's queue."""


class Routed:
    """Mixin of the banks with a ``pending`` parameter array (:class:`OscillatorBank`,
    :class:`PulseTrain`): their setters write through :meth:`_write`."""

    _post = None

    def route(self, post) -> None:
        """Hand parameter changes to ``post(row, cols, values)`` instead of writing ``pending``
        (``None``: write it again). An engine whose block function drains a queue into
        ``pending`` routes them there, so that the block function stays its only writer."""
        self._post = post

    def _write(self, row, cols, values) -> None:
        if self._post is None:
            self.pending[row, cols] = values
        else:
            self._post(row, cols, values)
