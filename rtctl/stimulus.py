"""Rendered stimuli in the loop: images (along an HIA path), Braille text and shapes become
per-channel parameter changes written between blocks.

The renderer (:mod:`rtctl.render`) produces per-pin parameters at the render rate; this stage maps
them onto the synthesis the display needs, ramped or switched by the dsp kernels in the next block:

| method | drive per pin |
|---|---|
| ``beat`` (PVDF, piezo) | a sine at the pin's ``freq_hz`` (cell pairs at f_c -+ f_b/2), amplitude ``amplitude * voltage``, ramped over a block with phase continuity |
| ``frequency`` (solenoid pins) | a pulse train at ``freq_hz`` between 0 and ``voltage`` (0 Hz: held at 0 V) |
| ``roi``, ``canny``, Braille, shapes (binary pins) | a held level: ``voltage`` when up; when down ``-voltage`` for bipolar pins (Dot, SMA: the current direction commands down), else 0 V |

Only :meth:`RenderStage.apply` runs between blocks; all image-wide work happens at build time.
"""

from __future__ import annotations

import os

import numpy as np

from .errors import SceneError

BIPOLAR = ("dot", "sma")  # pins whose "down" is a command of the opposite polarity


class RenderStage:
    """Per-block parameter updates for ``stimulus.kind`` in image | braille | shape.

    Parameters
    ----------
    scene : Scene
    offsets : dict
        Actuator group name -> its first global channel.
    n_channels : int
    fs, block : float, int

    Attributes
    ----------
    bank : OscillatorBank or None
        Sines of the beat method (one per pin).
    pulses : PulseTrain or None
        Pulse trains and held levels of the other methods.
    channels : slice
        Global channels the rendered group occupies.
    """

    def __init__(self, scene, offsets, n_channels, fs, block):
        st = scene.stimulus
        name = st.actuator or scene.actuator[0].name
        g = scene.group(name)  # a SceneError naming the groups there are
        self.group = g
        R, C = g.grid
        c0 = offsets[g.name]
        self.channels = slice(c0, c0 + R * C)
        self.voltage = st.voltage or g.max_voltage
        self.low = -self.voltage if g.type in BIPOLAR else 0.0
        self.fs, self.block = float(fs), int(block)
        self.kind, self.method = st.kind, st.method
        self.bank = self.pulses = None
        self._frames = None
        if st.kind == "image":
            self._build_image(scene, st, (R, C), n_channels)
        else:
            self._build_frames(scene, st, (R, C), n_channels)

    # --- construction ----------------------------------------------------------------------------

    def _build_image(self, scene, st, grid, n_channels):
        from .render.factory import make_renderer
        from .render.image import load_image
        from .render.path import Path, from_csv, raster

        if st.method not in ("roi", "canny", "frequency", "beat"):
            raise SceneError(f"{scene.source}: stimulus.method = {st.method!r}: an image needs roi | canny | "
                             "frequency | beat")
        if not st.image:
            raise SceneError(f"{scene.source}: stimulus.image is empty: name the image file to render")
        path = st.image  # relative to the scene file when it is there
        if not os.path.isabs(path) and scene.source and not scene.source.startswith("<"):
            cand = os.path.join(os.path.dirname(scene.source), path)
            path = cand if os.path.exists(cand) else path
        image = load_image(path)
        kw = {"grid": grid}
        if st.hia:
            kw["hia"] = st.hia
        if st.method == "frequency":
            kw["f_pmax"] = st.f_pmax
        if st.method == "beat":
            if st.px_size:
                kw["px_size"] = st.px_size
            kw.update(min_blob_area=st.min_blob_area, beat_band=tuple(st.beat_band),
                      carrier_band=tuple(st.carrier_band))
        if st.method == "roi":
            kw["threshold"] = st.threshold
        self.renderer = make_renderer(st.method, **kw).prepare(image)
        h, w = self.renderer.image_shape
        if st.path == "raster":
            self.path = raster(w, h, st.speed, st.rate, step=float(self.renderer.shape[0]))
        elif st.path == "fixed":
            self.path = Path(np.array([0.0]), np.array([float(st.at[0])]), np.array([float(st.at[1])]), st.rate)
        else:
            self.path = from_csv(st.path, st.rate)
        from .render.path import PathPlayer

        self.player = PathPlayer(self.renderer, self.path, self.fs, self.block)
        self.pending = self.renderer.empty()
        n = grid[0] * grid[1]
        if st.method == "beat":
            from .dsp import OscillatorBank

            chans = np.arange(self.channels.start, self.channels.stop)
            self.bank = OscillatorBank(n_channels, chans, self.fs, np.full(n, 100.0), np.zeros(n),
                                       ramp=self.block)
        else:
            from .dsp import PulseTrain

            self.pulses = PulseTrain(n_channels, self.fs, 0.0, 0.5, 0.0, 0.0)

    def _build_frames(self, scene, st, grid, n_channels):
        from .dsp import PulseTrain

        if st.kind == "braille":
            from .render.braille import braille_frames

            if st.dots not in (6, 8):
                raise SceneError(f"{scene.source}: stimulus.dots = {st.dots}: Braille cells have 6 or 8 dots")
            if not st.text:
                raise SceneError(f"{scene.source}: stimulus.text is empty: give the text to show in Braille")
            frames = braille_frames(st.text, grid, st.dots)
        else:
            from .render.shapes import shape

            frames = shape(st.shape, grid)[None]
        self._frames = frames.reshape(frames.shape[0], -1)
        self.pulses = PulseTrain(n_channels, self.fs, 0.0, 0.5, 0.0, 0.0)
        self._frame_blocks = max(1, int(round(st.frame_s * self.fs / self.block)))
        self._shown = -1

    # --- between blocks --------------------------------------------------------------------------

    def apply(self, k: int) -> None:
        """Write the parameter changes due at block ``k``."""
        if self._frames is not None:
            i = (k // self._frame_blocks) % self._frames.shape[0]
            if i != self._shown:
                self._shown = i
                self._levels(self._frames[i])
            return
        if not self.player.step(k, self.pending):
            return
        p = self.pending
        if self.method == "beat":
            f = np.clip(p[:, 1], 1e-3, self.fs / 2 - 1.0)
            self.bank.set_all(freq=f, amp=p[:, 4] * self.voltage)
        elif self.method == "frequency":
            self._pulse(p[:, 1])
        else:
            self._levels(p[:, 0] > 0.5)

    def _levels(self, up) -> None:
        lev = np.where(np.asarray(up, bool), self.voltage, self.low)
        self._set(np.zeros(self._n_pins()), lev, lev)

    def _pulse(self, freq) -> None:
        on = freq > 0.0
        self._set(freq, np.where(on, self.voltage, 0.0), np.zeros(freq.size))

    def _set(self, freq, high, low) -> None:
        self.pulses.set_range(self.channels, freq=freq, high=high, low=low)

    def _n_pins(self) -> int:
        return self.channels.stop - self.channels.start
