"""Reference twin of the closed loop's control: one AmplitudeController per channel, each a stage
of its own reading its channel's rows of the group's observer (an ObserverChannels view), stepped
right after the observer in channel order -- the arrangement the rig had before one controller
served a whole group. Only the tests build it: whatever the group controller does must come out
bitwise as this does."""

from __future__ import annotations

import numpy as np

from rtctl.control import AmplitudeController, amplitude_control
from rtctl.control._kernels import JNOISE
from rtctl.control.amplitude import RELEASE_WINDOW, RELEASE_Z
from rtctl.engine.report import fit_window
from rtctl.engine.rig import Rig
from rtctl.engine.stage import Stage


class PerChannelRig(Rig):
    """A :class:`~rtctl.engine.rig.Rig` whose closed loop has a controller per channel."""

    def _build_control(self, scene):
        self.controlled = {}  # bank tone index -> (controller, its column)
        per_channel = {}
        for tone, bank in zip(self.tones, self.stimulus.bank_index):
            per_channel[tone.channel] = per_channel.get(tone.channel, 0) + len(bank)
        views = [(f"{name}.{c}", st.channels(c, c + 1), g, ch0 + c)
                 for name, st, g, ch0 in self.observer_stages for c in range(st.observer.n_channels)]
        for name, st, g, c0 in views:
            obs = st.observer
            finger = self.models.finger(g)
            cols = []
            for tone, bank in zip(self.tones, self.stimulus.bank_index):
                c = tone.channel - c0
                if not bank or not (0 <= c < obs.n_channels) or not np.isfinite(tone.target_m):
                    continue
                for f, b in zip(tone.freqs, bank):
                    slot = int(np.nonzero(obs.freqs[c] == f)[0][0])
                    cols.append((c, slot, b, tone.channel, f, tone.target_m / len(bank),
                                 g.max_voltage * (1.0 - 1e-9) / per_channel[tone.channel],
                                 fit_window(tone.freqs) * self.fs))
            if not cols:
                continue
            c_, slot, bank, chan, f, target, amax, wamp = (np.array(x) for x in zip(*cols))
            amp = np.abs(1.0 + 1j * f / g.amplifier.bandwidth)
            tip = np.abs(obs.beam.response(f, finger)["tip"]) / amp
            loads = self.models.spread_loads(g)
            gains = np.array([np.abs(obs.beam.response(f, load)["tip"]) for load in loads]) / amp
            top = gains.max(axis=0)
            free = gains[[load is None for load in loads]].max(axis=0)
            ring = int(np.ceil(self.models.ring_time(g) * self.fs / self.block))
            rise = int(round(scene.control.rise_s * self.fs / self.block))
            beat, tau = self.models.nearest_modes(g, f)
            self._noise_floor(g, obs, c_, slot, bank, chan, f, target)
            release = [RELEASE_Z * self.control_noise[int(b)]
                       if fr >= tp * (1 - 1e-9) and obs.windows[c] >= RELEASE_WINDOW * self.fs else -1.0
                       for c, b, fr, tp in zip(c_, bank, free, top)]
            ctl = AmplitudeController(c_, slot, bank, chan, tip, amax, target, self.latency,
                                      -(-(obs.window + int(obs.prefilter_memory.max())) // self.block), self.block,
                                      ring, rise,
                                      (beat * self.block / self.fs, tau * self.fs / self.block), np.maximum(top, tip),
                                      release, f * self.block / self.fs, [self.control_noise[int(b)] for b in bank],
                                      np.full(len(bank), obs.window), wamp)
            self.controllers.append((name, st, ctl))
            for j, b in enumerate(bank):
                self.controlled[int(b)] = (ctl, j)

    def _stages(self) -> list:
        """The rig's stages with a control stage per channel right after its group's observer (the
        rig's own list matches controllers to whole-group stages only, so it has none), and before
        the observer a lift-off test per controller, each testing its channel (its own state) and
        flagging its channel's tones."""
        from rtctl.selfsense.lift import LiftTest, lift_stage

        stages = super()._stages()
        for name, st, _, _ in self.observer_stages:
            at = [s.name for s in stages].index(f"observer {name}")
            lifts = []
            for cname, seen, ctl in self.controllers:
                if seen.stage is not st:
                    continue
                first = seen.observer.first
                lift = LiftTest(st.observer, [first], [first] if np.any(ctl.state[JNOISE] >= 0.0) else [])
                if lift.active:
                    args = lift.stage_args(st.args, ctl, first)
                    lifts.append(Stage(f"contact {cname}", lift_stage, args, status=None, reset=lift.reset))
            stages[at:at] = lifts
            at = [s.name for s in stages].index(f"observer {name}") + 1
            mine = [Stage(f"control {cname}", amplitude_control,
                          dict(est=seen.observer.est, drive_est=seen.observer.u_out, **ctl.args,
                               pending=self.bank.pending, lim_counts=self.limiter.counts, ramp=float(self.block)),
                          reset=ctl.reset)
                    for cname, seen, ctl in self.controllers if seen.stage is st]
            stages[at:at] = mine
        return stages
