"""After a run: per-channel results from the trace, the table, and plot.png.

The true tip amplitude of a channel is a least-squares fit of the simulated tip displacement to
its tone frequencies (plus an offset and a linear drift, which absorb the slow relaxation of the
finger's 1.4 s Maxwell branch) over the analysis window: the last 0.5 s of the run, or two
periods of the channel's lowest tone if that is longer, capped at the second half of the run. For
a beat pair it is the sum of both tones' amplitudes, the peak of the envelope. For a square or
pulse tone (binary pins, SMA taxels) the fundamental says little about the motion: the amplitude
is half the peak-to-peak stroke over the whole periods of the analysis window; so it is for a
channel driven by a rendered stimulus (no tone), over the analysis window.

A pin between end stops (solenoid, Dot) moves its full stroke or not at all: it has no amplitude
target, so its target and error are None, as its settle time is. Nothing is felt without a
finger on the display (``finger.contact = false`` at the run's end, after its events): every
channel's ``felt`` is then False.
"""

from __future__ import annotations

import math

import numpy as np

from ..stimulus import END_STOP_TYPES  # pins with no amplitude target
from .judged import judged_span, played_voices

#: How a played signal's row was judged (rtctl.engine.judged), in the table's words.
JUDGED = {"steady": "the end of its longest steady stretch", "peak": "its strongest window",
          "stroke": "half its peak-to-peak stroke"}
SETTLE_BAND = 0.05  # settled once every later envelope estimate is within 5 % of the final one


def fit_amplitudes(x: np.ndarray, t: np.ndarray, freqs) -> np.ndarray:
    """Amplitudes of ``x(t)`` at ``freqs`` (Hz) by least squares with offset and linear drift."""
    cols = [np.ones_like(t), t - t.mean()]
    for f in freqs:
        w = 2 * np.pi * f * t
        cols += [np.cos(w), np.sin(w)]
    a = np.column_stack(cols)
    coef, *_ = np.linalg.lstsq(a, x, rcond=None)
    c = coef[2:].reshape(-1, 2)
    return np.hypot(c[:, 0], c[:, 1])


def analysis_window(duration: float, freqs) -> float:
    lowest = min(freqs) if freqs else 1.0
    return min(max(0.5, 2.0 / lowest), duration / 2)


def fit_window(freqs) -> float:
    """Seconds of the windows a changing amplitude is fitted over: one period of the lowest tone
    and of the closest two tones' difference (a beat pair's envelope: over less, their columns
    are nearly alike and any transient shows as a huge pair of amplitudes), at least 4 ms."""
    f = np.unique(np.asarray(freqs, dtype=float))
    gap = float(np.min(np.diff(f))) if f.size > 1 else math.inf
    return max(1.0 / f[0], 1.0 / gap, 4e-3)


def settle_time(x, t, freqs, start, final) -> float | None:
    """Seconds from ``start`` until the amplitude stays within SETTLE_BAND of ``final``.

    The amplitude is fitted over windows of :func:`fit_window` at half-window steps; the result
    is the end of the first window from which every later one is within the band, so it is an
    upper bound with a resolution of half a window. None if the amplitude never settles in the
    run.
    """
    if not final > 0:
        return None
    w = fit_window(freqs)
    edges = np.arange(start, t[-1] - w, w / 2)
    if edges.size == 0:
        return None
    # t is sorted: the samples with e <= t < e + w are one slice (a mask per window made the
    # report of a long run cost more than the run)
    lo, hi = np.searchsorted(t, edges, "left"), np.searchsorted(t, edges + w, "left")
    amps = [fit_amplitudes(x[i:j], t[i:j], freqs).sum() for i, j in zip(lo, hi)]
    ok = np.abs(np.asarray(amps) / final - 1.0) <= SETTLE_BAND
    bad = np.flatnonzero(~ok)
    if bad.size == 0:  # settled in the first window: its end is the best bound we can give
        return float(edges[0] + w - start)
    if bad[-1] == ok.size - 1:
        return None
    return float(edges[bad[-1] + 1] + w - start)


def channel_rows(rig, reader, n_run_blocks: int) -> list[dict]:
    """The ``channels`` list of the run summary (what ``rtctl run --json`` prints), one row per channel."""
    fs, block = rig.fs, rig.block
    n = n_run_blocks * block
    t = np.arange(n) / fs
    has_tip = "tip_um" in reader.units
    n_b = n // block if block else 0
    # finger.contact is one switch for the whole display: each group's direction picks the
    # finger.lateral or finger.normal load, but without contact no group touches a finger. The
    # row judges the run's last segment: the contact then, after the events that took effect
    ran = [ev for ev in rig.events if ev.block < n_b]
    contacts = [bool(rig.scene.finger.contact)] + [bool(ev.scene_after.finger.contact) for ev in ran]
    contact = contacts[-1]
    rows = []
    for ch in range(rig.n_channels):
        drive = reader.signal("drive", ch)[:n]
        tip = reader.signal("tip_um", ch)[:n] if has_tip else None
        tones = [tn for tn in rig.tones if tn.channel == ch]
        freqs = [f for tn in tones for f in tn.freqs]
        main = tones[0] if tones else None
        stops = rig.scene.group(rig.channel_groups[ch]).type in END_STOP_TYPES
        # per segment (the start, then each event: an event may step a tone's target) the sum of
        # the channel's tones' targets; the row's is the one in force at the run's end
        targets = segment_targets(rig, ch) if main is not None and not stops else None
        target_m = targets[-1] if targets else None
        row = {
            "name": rig.channel_names[ch],
            "group": rig.channel_groups[ch],
            "receptor": main.receptor if main else None,
            "freq_hz": main.freq if main else None,
            "target_um": _um(target_m),
            "threshold_um": _um(main.threshold_m) if main else None,
            "true_um": None,
            "estimated_um": None,
            "error_pct": None,
            "settle_ms": None,
            "felt": None,
            "contact": contact,
            "v_peak": float(np.max(np.abs(drive))) if n else 0.0,
            "freqs_hz": freqs or None,
            "limited": bool(rig.limiter.counts[:, ch].sum() > 0),
            "limited_by": limited_by(rig.limiter, ch),
        }
        if len(tones) > 1:  # each tone's frequency (a beat pair's carrier): freqs_hz has a pair's two sines
            row["tones_hz"] = [tn.freq for tn in tones]
        voices = played_voices(rig, ch)
        span = judged_span(voices, n) if voices and n else None
        if span is not None:  # a played signal: judged over its own stretch, not the run's end
            g = rig.scene.group(rig.channel_groups[ch])
            tail = 3.0 * rig.models.ring_time(g) if g.type == "bimorph" else 0.0
            w0, w1 = _judge_played(row, span, tip, t, freqs, fs, block, tail)
            if target_m is not None and math.isfinite(target_m):  # the level held (at most) there, m
                target_m = span["level"]
                row["target_um"] = _um(target_m)
                if row["true_um"] is not None:
                    row["error_pct"] = 100.0 * (row["true_um"] * 1e-6 - target_m) / target_m
            # a peak: the observer's highest estimate from the onset (its window lags the truth)
            k0 = int(span["on"]) // block if span["by"] != "steady" else int(w0 * fs) // block
            k1 = n_b if span["by"] != "steady" else -(-int(w1 * fs) // block)
            _estimate(row, reader, ch, n_b, block / fs, freqs, target_m, blocks=(k0, k1),
                      peak=span["by"] != "steady")
            _felt(row, contact)
            rows.append(row)
            continue
        if tip is not None and not freqs and n and np.all(np.isfinite(tip)):
            # a rendered stimulus (image, Braille, shape): no tone to fit, so the stroke over
            # the analysis window (half peak-to-peak) says how far the pin moved
            seg = tip[t >= t[-1] - analysis_window(n / fs, [])]
            row["true_um"] = 0.5 * float(seg.max() - seg.min())
        if tip is not None and freqs:
            win = analysis_window(n / fs, freqs)
            m = t >= t[-1] - win
            if main.shape != "sine":  # stroke: half peak-to-peak over whole periods
                per = max(1, int(round(win * main.freq)))
                m = t >= t[-1] - per / main.freq
                seg = tip[m]
                amp = 0.5 * float(seg.max() - seg.min()) if np.all(np.isfinite(seg)) else math.nan
            else:
                amp = float(fit_amplitudes(tip[m], t[m], freqs).sum()) if np.all(np.isfinite(tip)) else math.nan
            if not math.isfinite(amp):  # a plant fault left NaN in the truth: nothing to report
                _felt(row, contact)
                rows.append(row)
                continue
            row["true_um"] = amp
            if target_m and math.isfinite(target_m):
                row["error_pct"] = 100.0 * (amp * 1e-6 - target_m) / target_m
            if main.shape == "sine" and rig.events:
                # the run is a sequence of segments (start, then each event): the amplitude each
                # settled to and how long that took; the row reports the last amplitude (the
                # error against the target) and the worst settle over all segments
                start = min(tn.start for tn in tones)
                segs = _event_settles(rig, tip, t, freqs, n / fs, start, targets)
                for sg, c_on in zip(segs, contacts):
                    sg["contact"] = c_on
                row["start"], row["events"] = segs[0], segs[1:]
                last = segs[-1]["true_um"]
                if last is not None:
                    row["true_um"] = amp = last
                    if target_m and math.isfinite(target_m):
                        row["error_pct"] = 100.0 * (amp * 1e-6 - target_m) / target_m
                # the worst over the segments long enough to judge (an event at the instant of
                # another, or just before the end, leaves one too short to fit an amplitude in)
                times = [sg["settle_ms"] for sg in segs if sg["judged"]]
                row["settle_ms"] = None if not times or any(x is None for x in times) else max(times)
            elif main.shape == "sine":
                st = settle_time(tip, t, freqs, min(tn.start for tn in tones), amp)
                row["settle_ms"] = None if st is None else 1e3 * st
        # the last segment of the run: from its last event, or from the channel's start
        since = max((ev.block for ev in ran),
                    default=int(min((tn.start for tn in tones), default=0.0) * fs) // block)
        _estimate(row, reader, ch, n_b, block / fs, freqs, target_m, since, lag=rig.estimate_lag(ch))
        _felt(row, contact)
        rows.append(row)
    _control(rig, rows)
    return rows


def _judge_played(row, span, tip, t, freqs, fs, block, tail) -> tuple[float, float]:
    """``row``'s true amplitude (and settle time) over ``span`` (:func:`judged_span`), and
    ``row["judged"]``: the rule, the window the amplitude was taken over (s, returned too) and
    the stretch the signal was active. ``tail``: seconds the plant rings on after the stretch,
    searched too for a peak or a stroke."""
    a, b = span["from"] / fs, span["to"] / fs
    if span["to"] < len(t):  # the bank starts the change that ends it at its block's start
        b = max(a, (span["to"] // block) * block / fs)
    by = span["by"]
    w0, w1 = a, b
    ok = tip is not None and bool(np.all(np.isfinite(tip)))
    if by == "steady":
        w0 = b - min(analysis_window(b - a, freqs), (b - a) / 2)
        m = (t >= w0) & (t < b)
        if ok and m.sum() > 2 * len(freqs) + 2:
            amp = float(fit_amplitudes(tip[m], t[m], freqs).sum())
            row["true_um"] = amp
            seg = t < b
            st = settle_time(tip[seg], t[seg], freqs, span["on"] / fs, amp)  # from the onset
            row["settle_ms"] = None if st is None else 1e3 * st
    else:
        w1 = min(b + tail, float(t[-1]))
        seg = (t >= a) & (t <= w1)
        amps = np.zeros(0)
        if ok and by == "peak":
            tc, amps = amplitude_track(t[seg], tip[seg], freqs, a)
        if ok and np.any(np.isfinite(amps)):
            k = int(np.nanargmax(amps))
            half = fit_window(freqs) / 2
            w0, w1 = float(tc[k] - half), float(tc[k] + half)
            row["true_um"] = float(amps[k])
        elif ok and seg.any():  # a moving frequency (or too short a stretch to fit): the stroke
            by = "stroke"
            row["true_um"] = 0.5 * float(np.ptp(tip[seg]))
    row["judged"] = {"by": by, "from_s": w0, "to_s": w1, "active_s": [span["on"] / fs, span["off"] / fs]}
    return w0, w1


def _control(rig, rows) -> None:
    """Closed loop: per channel under amplitude control, whether its controller ended saturated
    (the target out of reach at the channel's max_voltage) and what amplitude it reached there,
    from the controllers' final state."""
    if not rig.controllers:
        return  # open loop: rtctl.control is neither needed nor imported
    from ..control._kernels import AMAX, BANK, CHANNEL, CMD, EST, LOWN, NREL, OBS_CH, PULSED, SAT

    owner = {b: i for i, bank in enumerate(rig.stimulus.bank_index) for b in bank}  # bank tone -> scene tone
    for _, st, ctl in rig.controllers:
        # a tone's cap is the sum of its sines' (a beat pair's envelope peak); where the channel
        # plays more than one tone it is a share of max_voltage, not the whole
        caps: dict = {}
        for j in range(ctl.n):
            i = owner[int(ctl.index[BANK, j])]
            caps[i] = caps.get(i, 0.0) + float(ctl.state[AMAX, j])
        shared: dict = {}  # channel -> its saturated tones whose cap is a share, tone -> cap (V)
        for j in range(ctl.n):
            row = rows[int(ctl.index[CHANNEL, j])]
            row["controlled"] = True
            # the channel's own window (its observer's row), not the group's longest
            row["observer_window_s"] = int(st.observer.windows[ctl.index[OBS_CH, j]]) / rig.fs
            # how much a relative error of the currents grows into the tip's, over the channel's
            # tones; with the calibration's scale bound and residual, how far its amplitude may be
            # off (None: uncalibrated)
            freqs = st.observer.freqs[ctl.index[OBS_CH, j]]
            gain = max(st.observer.designs[float(f)].gain for f in freqs if f > 0.0)
            row["observer_gain"] = gain
            # the load the observer took the drive's images to see at the end (its tip-moment
            # residual's choice among the finger lifted and the finger's sets)
            load = st.observer.image_loads[int(st.observer.pick[ctl.index[OBS_CH, j]])]
            row["observer_load"] = "lifted" if load is None else f"{load.mass * 1e3:g} g of skin, k0 {load.k0:g} N/m"
            row["uncertainty_pct"] = (rig.calibration.tone_uncertainty_pct(row["group"], gain)
                                      if rig.calibration else None)
            sat = bool(ctl.state[SAT, j])
            row["saturated"] = row.get("saturated", False) or sat
            i = owner[int(ctl.index[BANK, j])]
            if sat and caps[i] < rig.scene.group(row["group"]).max_voltage * (1.0 - 1e-6):
                # to the microvolt: the cap sits a hair below the share (rtctl.engine.rig)
                shared.setdefault(int(ctl.index[CHANNEL, j]), {})[i] = round(caps[i], 6)
            # how long it was held at the least drive any load the model knows allows, the
            # estimate still above the target: the estimate was not following the tip
            # (rtctl.control.amplitude); any time at all is worth a look
            row["floor_s"] = max(row.get("floor_s", 0.0), float(ctl.state[LOWN, j]) * rig.block / rig.fs)
            row["at_floor"] = row["floor_s"] > 0.0
            # how often its drive dropped at once for a finger that let go (the release rule)
            row["releases"] = row.get("releases", 0) + int(ctl.state[NREL, j])
            # and how often it cancelled a ring with a pulse of drive (rtctl.control.amplitude)
            row["pulses"] = row.get("pulses", 0) + int(ctl.state[PULSED, j])
            # the rms its estimate's noise leaves in the amplitude (over its tones' sines)
            n2 = (row.get("noise_um") or 0.0) ** 2 + (1e6 * rig.control_noise.get(int(ctl.index[BANK, j]), 0.0)) ** 2
            row["noise_um"] = math.sqrt(n2)
            row.setdefault("command_v", {})[int(ctl.index[BANK, j])] = float(ctl.state[CMD, j])
            if sat and (row.get("judged") or {}).get("by", "steady") != "steady":
                # a played signal judged at its peak: its row holds its highest estimate since the
                # onset (a transient's ring read 16 um where the tip reached 9.5), and the final
                # state its tones' estimates after they ended (0): neither is what the cap reaches
                row["reachable_um"] = None
            elif sat:  # what the estimate shows at the cap (the run's final window), else the last one used
                est = row.get("estimated_um")
                e = float(ctl.state[EST, j])  # NaN while a non-finite reading is in the window
                # (the last estimate used only where the trace's were not finite; with no window
                # wholly within the last segment there is nothing to say what it reaches)
                if est is None and row.get("estimate_window") is not False and \
                        row.get("reachable_um", 0.0) is not None:
                    est = (row.get("reachable_um") or 0.0) + e * 1e6 if math.isfinite(e) else None
                row["reachable_um"] = est
        for ch, per_tone in shared.items():  # only where there is a share: a tone alone has the whole channel
            rows[ch]["share_v"] = [per_tone[i] for i in sorted(per_tone)]


def segment_targets(rig, ch: int) -> list[float]:
    """Channel ``ch``'s target (m) from the start and after each of the run's events: the sum of
    its tones' targets (a channel's amplitude is the sum of its tones', as a beat pair's envelope
    peak is its two sines'), NaN where a tone has none; an event's ``stimulus.tones.N.target_um``
    replaces tone N's, as the rig resolved it (``Rig.event_targets``)."""
    per = {i: tn.target_m for i, tn in enumerate(rig.tones) if tn.channel == ch}
    out = [math.fsum(per.values())]
    for ev in rig.events:
        for i, target_m in rig.event_targets.get(ev.index, ()):
            if i in per:
                per[i] = target_m
        out.append(math.fsum(per.values()))
    return out


def _event_settles(rig, tip, t, freqs, t_end, start, targets=None) -> list[dict]:
    """Per segment of the run (from ``start``, then from each event): the true amplitude it
    settled to (over the last analysis window before the next event or the run's end), how long
    after the segment's start that took (5 % band), and with ``targets`` (m per segment,
    :func:`segment_targets`) the segment's target and the error against it."""
    out = []
    starts = [start] + [ev.block * rig.block / rig.fs for ev in rig.events]
    for i, t0 in enumerate(starts):
        t1 = starts[i + 1] if i + 1 < len(starts) else t_end
        if t0 >= t_end:
            break
        win = min(analysis_window(t1 - t0, freqs), (t1 - t0) / 2)
        m = (t >= t1 - win) & (t < t1)
        ok = m.sum() > 8 and np.all(np.isfinite(tip[m]))
        final = float(fit_amplitudes(tip[m], t[m], freqs).sum()) if ok else math.nan
        seg = (t >= t0) & (t < t1)
        st = settle_time(tip[seg], t[seg], freqs, t0, final) if math.isfinite(final) else None
        # judged: an amplitude to settle to, and room for one fit window after the start (a
        # settle time of None then means it never settled, not that there was nothing to see)
        judged = bool(math.isfinite(final) and t1 - t0 > fit_window(freqs))
        row = {"t_s": t0, "true_um": final if math.isfinite(final) else None,
               "settle_ms": None if st is None else 1e3 * st, "judged": judged}
        if targets is not None:
            tgt = targets[i]
            row["target_um"] = _um(tgt)
            row["error_pct"] = (100.0 * (final * 1e-6 - tgt) / tgt
                                if math.isfinite(final) and math.isfinite(tgt) and tgt > 0 else None)
        out.append(row)
    return out


def _felt(row, contact: bool) -> None:
    """``row["felt"]``: False for every channel without a finger on the display (a tip moving in
    air is felt by no one, however far it moves); otherwise whether the true amplitude reaches
    the threshold, None without either."""
    if not contact:
        row["felt"] = False
    elif row["true_um"] is not None and row["threshold_um"] is not None:
        row["felt"] = row["true_um"] >= row["threshold_um"]


def _estimate(row, reader, ch, n_blocks, period, freqs, target_m, since: int = 0, blocks=None,
              peak: bool = False, lag: int | None = None) -> None:
    """The observer's amplitude (median of its per-block estimate over the analysis window, or
    over ``blocks`` ``(first, end)``: a played signal's judged window; their highest with
    ``peak``) into ``row``, with its
    error against the truth where a simulation knows it and, on hardware, the error against
    the target from the estimate. Without ``blocks``: over the second half of the last segment
    (from block ``since``: the last event, or the start) and only from ``lag`` blocks after its
    start (:meth:`Rig.estimate_lag`), so that no window holds the plant before it (a 2 Hz
    window of 0.5 s would still hold the finger lifted); ``estimate_window`` says whether any
    was left (if not, ``estimated_um`` stays None)."""
    if not n_blocks or "estimated_tip_um" not in reader.units:
        return
    est = reader.signal("estimated_um", ch)[:n_blocks]
    m = max(1, int(round(analysis_window(n_blocks * period, freqs) / period)))
    if since:  # after an event: only the last segment's second half (what it settled to)
        m = max(1, min(m, (n_blocks - since) // 2))
    if blocks is None and lag is not None:
        m = min(m, n_blocks - since - lag)
        row["estimate_window"] = m > 0
        if m <= 0:
            return
    seg = est[-m:] if blocks is None else est[max(0, blocks[0]):max(blocks[0] + 1, blocks[1])]
    seg = seg[np.isfinite(seg)]
    if not seg.size:
        return
    row["estimated_um"] = float(np.max(seg) if peak else np.median(seg))
    if row["true_um"]:
        row["estimate_error_pct"] = 100.0 * (row["estimated_um"] / row["true_um"] - 1.0)
    elif target_m and math.isfinite(target_m):
        row["error_pct"] = 100.0 * (row["estimated_um"] * 1e-6 - target_m) / target_m


def _um(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else x * 1e6


def _fmt(v, spec: str) -> str:
    width = int(spec.split(".")[0] or 0)
    return f"{'-':>{width}}" if v is None else format(v, spec)


def freq_label(row: dict, spec: str) -> str:
    """A summary row's frequency as the table and the plot show it: a channel of several tones
    lists their frequencies ("40+250"), each once (a played signal's voices often share one)."""
    tones = list(dict.fromkeys(row.get("tones_hz") or ()))
    return _fmt(row["freq_hz"], spec) if len(tones) < 2 else "+".join(f"{x:g}" for x in tones)


def print_table(summary: dict) -> None:
    """The per-channel table ``rtctl run`` prints."""
    print(f"{summary['scene']}: {summary['duration_s']:g} s at {summary['fs']:g} Hz, block {summary['block']}, "
          f"real-time factor {summary['realtime_factor']:.1f}, block time p99 "
          f"{summary['block_time_us']['p99']:.1f} us, deadline misses {summary['deadline_misses']}")
    freqs = [freq_label(r, ".1f") for r in summary["channels"]]  # the column widens only for a list
    w = max([9] + [len(f) + 1 for f in freqs])
    head = f"{'channel':<12}{'receptor':<10}{'freq Hz':>{w}}{'V peak':>8}{'true um':>10}{'thresh um':>10}" \
           f"{'target um':>10}{'error %':>9}{'settle ms':>10}  felt"
    print(head)
    print("-" * len(head))
    for r, freq in zip(summary["channels"], freqs):
        felt = {None: "-", True: "yes", False: "NO" if r["contact"] else "NO (no contact)"}[r["felt"]]
        if r.get("saturated"):
            reach = r.get("reachable_um")
            share = r.get("share_v")
            cap = ("max_voltage" if not share else
                   f"{'its share' if len(share) == 1 else 'their shares'} of max_voltage, "
                   f"{'+'.join(format(v, '.3g') for v in share)} V")
            note = (f" (saturated at {cap}: reaches {_fmt(reach, '.3g')} um)" if reach is not None else
                    f" (saturated at {cap}; no observer window fits in the run's last segment)"
                    if r.get("estimate_window") is False else f" (saturated at {cap})")
        elif r["limited"]:
            note = " (limited: " + ", ".join(r.get("limited_by") or ["?"]) + ")"
        else:
            note = ""
        if r.get("at_floor"):
            note += (f" (held at the drive's floor for {r['floor_s']:.3g} s: the estimate asked for less than any "
                     "load needs)")
        print(f"{r['name']:<12}{(r['receptor'] or '-'):<10}{freq:>{w}}{r['v_peak']:8.1f}"
              f"{_fmt(r['true_um'], '10.3g')}{_fmt(r['threshold_um'], '10.3g')}{_fmt(r['target_um'], '10.3g')}"
              f"{_fmt(r['error_pct'], '9.1f')}{_fmt(r['settle_ms'], '10.0f')}  {felt}{note}")
    for r in summary["channels"]:
        j = r.get("judged")
        if j:  # a played signal: say what its row was judged over (docs/stimulus.md)
            a, b = j["active_s"]
            print(f"{r['name']}: judged over {j['from_s']:.3f}-{j['to_s']:.3f} s ({JUDGED[j['by']]}; "
                  f"the signal plays {a:.3f}-{b:.3f} s)")


def limited_by(limiter, ch: int) -> list[str]:
    """Which of the limiter's bounds changed channel ``ch``'s drive (its per-channel counts)."""
    from ..safety import MEAN_DC

    mean = "dc offset" if limiter.mean_kind[ch] == MEAN_DC else "duty"
    names = ("voltage", "slew/current", mean)
    return [n for n, k in zip(names, limiter.counts[:, ch]) if k > 0]


def _envelope(t: np.ndarray, x: np.ndarray, points: int = 20000):
    """At most ``points`` points that keep each bucket's minimum and maximum, so a long run plots
    quickly and still shows its true envelope (plain striding would alias the oscillation)."""
    if x.size <= points:
        return t, x
    k = x.size // (points // 2)
    m = (x.size // k) * k
    xb = x[:m].reshape(-1, k)
    tt = np.repeat(t[:m].reshape(-1, k)[:, 0], 2)
    xx = np.column_stack([xb.min(axis=1), xb.max(axis=1)]).reshape(-1)
    return tt, xx


def plot_channels(rows: list[dict], max_rows: int = 8) -> tuple[list[int], str]:
    """The channels plot.png gives a panel, in panel order, and the caption that says so.

    Driven channels (a drive other than 0 V in the run, or a stimulus tone) come first, in
    channel order, then idle ones fill the panels left. The caption is "" when every channel
    has a panel, else e.g. "8 of 9 channels shown (driven first)".
    """
    if len(rows) <= max_rows:
        return list(range(len(rows))), ""
    driven = [r["v_peak"] > 0 or r["freq_hz"] is not None for r in rows]
    order = [i for i, d in enumerate(driven) if d] + [i for i, d in enumerate(driven) if not d]
    chosen = order[:max_rows]
    return chosen, f"{len(chosen)} of {len(rows)} channels shown (driven first)"


def amplitude_track(t, x, freqs, start: float = 0.0):
    """The amplitude of ``x`` at ``freqs`` (summed: a beat pair's envelope peak) over time: fits
    over windows of :func:`fit_window` at half-window steps; returns (window centres,
    amplitudes)."""
    w = fit_window(freqs)
    edges = np.arange(start, t[-1] - w, w / 2)
    amps = np.full(edges.size, np.nan)
    lo, hi = np.searchsorted(t, edges, "left"), np.searchsorted(t, edges + w, "left")  # t sorted
    for k, (i, j) in enumerate(zip(lo, hi)):
        if np.all(np.isfinite(x[i:j])):
            amps[k] = fit_amplitudes(x[i:j], t[i:j], freqs).sum()
    return edges + w / 2, amps


def against_target(x, t, freqs, t0: float, t1: float, target: float) -> dict:
    """A tone's amplitude in ``x`` from ``t0`` (its start or an event) to ``t1`` against ``target``
    (the unit of ``x``), with the windows of :func:`settle_time`: ``settle_ms``, how long until it
    stays within SETTLE_BAND of the target (None if it is not there by ``t1``), and
    ``overshoot_pct``, the highest windowed amplitude above the target (negative: never above)."""
    seg = (t >= t0) & (t < t1)
    st = settle_time(x[seg], t[seg], freqs, t0, target)
    _, amps = amplitude_track(t[seg], x[seg], freqs, t0)
    peak = float(np.nanmax(amps)) if np.any(np.isfinite(amps)) else math.nan
    return {"settle_ms": None if st is None else 1e3 * st, "overshoot_pct": 100.0 * (peak / target - 1.0)}


def _amplitude_panel(ax, r, reader, ch, t, n, has_tip) -> None:
    """A controlled channel: true amplitude (windowed fits of the truth) and the observer's
    estimate over time against the target and its +-2 % band."""
    tgt = reader.signal("target_um", ch)[: n // reader.block] if "target_um" in reader.units else None
    tb = np.arange(tgt.size) * reader.block / reader.fs if tgt is not None else None
    if tgt is not None and np.any(np.isfinite(tgt)):
        ax.fill_between(tb, 0.98 * tgt, 1.02 * tgt, color="0.85", step="post", label="target +-2 %")
        ax.plot(tb, tgt, color="k", lw=0.7, drawstyle="steps-post")
    if has_tip and r.get("freqs_hz"):
        tc, amp = amplitude_track(t, reader.signal("tip_um", ch)[:n], r["freqs_hz"])
        ax.plot(tc, amp, color="C1", lw=1.3, label="true", zorder=3)
    if "estimated_um" in reader.units:
        est = reader.signal("estimated_um", ch)[: n // reader.block]
        te = np.arange(est.size) * reader.block / reader.fs
        est = np.where(te >= r.get("observer_window_s", 0.0), est, np.nan)  # a window not yet full
        ax.plot(te, est, color="C2", lw=0.6, alpha=0.7, label="estimated")
    if r.get("threshold_um") is not None:
        ax.axhline(r["threshold_um"], ls="--", color="k", lw=0.6, label="threshold")
    ax.set_ylabel("amplitude um")
    ax.set_ylim(bottom=0)


def plot(summary: dict, reader, path, n_run_blocks: int, max_rows: int = 8) -> None:
    """plot.png: drive voltage and true tip displacement against the threshold and target lines
    for up to ``max_rows`` channels (:func:`plot_channels`), and a bar chart of every channel's
    amplitude against its threshold."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = summary["channels"]
    chosen, caption = plot_channels(rows, max_rows)
    shown = [rows[ch] for ch in chosen]
    n = n_run_blocks * reader.block
    t = reader.time()[:n]
    has_tip = "tip_um" in reader.units
    from .timing_plot import has_timing, timing_panels

    paced = has_timing(reader)  # a paced run: a last row of block-time and lateness histograms
    fig = plt.figure(figsize=(11, 2.0 * len(shown) + 3.2 + 2.4 * paced), layout="constrained")
    gs = fig.add_gridspec(len(shown) + 1 + paced, 2, height_ratios=[1] * len(shown) + [1.6] + [1.4] * paced)
    for i, (ch, r) in enumerate(zip(chosen, shown)):
        ax = fig.add_subplot(gs[i, 0])
        ax.plot(*_envelope(t, reader.signal("drive", ch)[:n]), lw=0.6, color="C0")
        ax.set_ylabel("drive V")
        ax.set_title(f"{r['name']}  {freq_label(r, '.0f')} Hz  {r['receptor'] or ''}", fontsize=9, loc="left")
        if r.get("controlled"):
            bx = fig.add_subplot(gs[i, 1], sharex=ax)
            _amplitude_panel(bx, r, reader, ch, t, n, has_tip)
            if i == 0:
                bx.legend(fontsize=7, loc="upper right")
        elif has_tip:
            bx = fig.add_subplot(gs[i, 1], sharex=ax)
            bx.plot(*_envelope(t, reader.signal("tip_um", ch)[:n]), lw=0.6, color="C1", label="true tip")
            for key, style, label in (("threshold_um", "--", "threshold"), ("target_um", ":", "target")):
                if r[key] is not None:
                    bx.axhline(r[key], ls=style, color="k", lw=0.8, label=label)
                    bx.axhline(-r[key], ls=style, color="k", lw=0.8)
            bx.set_ylabel("tip um")
            if i == 0:
                bx.legend(fontsize=7, loc="upper right")
        j = r.get("judged")
        if j and (r.get("controlled") or has_tip):  # a played signal: the window its row was judged over
            bx.axvspan(j["from_s"], j["to_s"], color="C2", alpha=0.2, lw=0)
        for ev in summary.get("events", ()):  # when the finger or a target changed
            for a in fig.axes[-2:] if (r.get("controlled") or has_tip) else fig.axes[-1:]:
                a.axvline(ev["at"], color="C3", lw=0.8, alpha=0.7)
    ax.set_xlabel("time s")
    cx = fig.add_subplot(gs[len(shown), :])
    if paced:
        timing_panels(fig.add_subplot(gs[-1, 0]), fig.add_subplot(gs[-1, 1]), summary, reader, n_run_blocks)
    x = np.arange(len(rows))
    true = [r["true_um"] or np.nan for r in rows]
    thr = [r["threshold_um"] or np.nan for r in rows]
    cx.bar(x - 0.2, true, 0.4, label="true amplitude", color="C1")
    cx.bar(x + 0.2, thr, 0.4, label="perception threshold", color="0.6")
    cx.set_yscale("log")
    cx.set_xticks(x, [f"{r['name']}\n{r['receptor'] or ''}" for r in rows], fontsize=7)
    cx.set_ylabel("amplitude um (log)")
    cx.legend(fontsize=8)
    fig.suptitle(f"{summary['scene']}: true tip amplitude against the perception thresholds"
                 + (f"\n{caption}" if caption else ""), fontsize=11)
    fig.savefig(path, dpi=90)
    plt.close(fig)
