"""What a scene needs, and what it leaves out.

Pure bookkeeping on the validated scene: imports nothing (whether an optional package is
installed is asked of the import system without importing it). :func:`rtctl.engine.rig.build` constructs,
imports and compiles exactly the components listed here, and ``rtctl check`` prints them.
"""

from __future__ import annotations

from dataclasses import dataclass

#: component -> (what it is, the modules it brings in)
COMPONENTS: dict[str, tuple[str, tuple[str, ...]]] = {
    "safety.limiter": ("final limiter: voltage, slew/current, temperature (always)", ("rtctl.safety",)),
    "dsp.oscillator": ("phase-continuous oscillator bank for tones and beat pairs", ("rtctl.dsp",)),
    "dsp.pulse": ("pulse trains for binary pins", ("rtctl.dsp",)),
    "dsp.lockin": ("lock-in demodulation of the sensed currents", ("rtctl.dsp",)),
    "plant.bimorph": ("finite-element bimorph with amplifier and current sense (simulated)", ("rtctl.plant",)),
    "plant.finger": ("generalized Maxwell finger load at each tip (simulated)", ("rtctl.plant",)),
    "plant.pvdf": ("PVDF film cells on a plate (simulated)", ("rtctl.plant",)),
    "plant.em": ("electromagnetic pin (simulated)", ("rtctl.plant",)),
    "plant.solenoid": ("solenoid pin with end stops (simulated)", ("rtctl.plant",)),
    "plant.dot": ("latching Dot Braille pin (simulated)", ("rtctl.plant",)),
    "plant.sma": ("SMA antagonistic taxel (simulated)", ("rtctl.plant",)),
    "selfsense": ("transfer-matrix self-sensing observer", ("rtctl.selfsense",)),
    "control": ("closed-loop amplitude control to the perception targets", ("rtctl.control",)),
    "render": ("image rendering to per-pin stimuli", ("rtctl.render", "cv2")),
    "render.braille": ("Braille text to pin frames", ("rtctl.render",)),
    "io.sim": ("simulated rig behind the block I/O contract", ("rtctl.io.sim",)),
    "io.audio": ("audio interface", ("rtctl.io.audio", "sounddevice")),
    "io.daq": ("DAQ (National Instruments, nidaqmx)", ("rtctl.io.daq", "nidaqmx")),
    "io.serial": ("serial pin controller", ("rtctl.io.serial", "serial")),
    "io.replay": ("replay of a recorded trace", ("rtctl.io.replay",)),
}

#: components that exist in this version of rtctl; the others are refused with a clear message.
AVAILABLE = frozenset({
    "safety.limiter", "dsp.oscillator", "dsp.pulse", "dsp.lockin",
    "plant.bimorph", "plant.finger", "io.sim", "render", "render.braille", "plant.sma", "plant.pvdf", "plant.em",
    "plant.dot", "plant.solenoid",
    "selfsense", "io.audio", "io.serial", "io.daq", "control",
})

#: components whose package is an optional extra of rtctl: (the package's module, how to install it).
#: Without it the component is unavailable on this machine, refused as one this version lacks.
OPTIONAL = {"io.daq": ("nidaqmx", "pip install 'rtctl[daq]'")}


def _missing(component: str) -> bool:
    """True when ``component``'s optional package is not installed."""
    import importlib.util
    import sys

    if component not in OPTIONAL:
        return False
    module = OPTIONAL[component][0]
    if module in sys.modules:  # imported already (None: an import that failed, or is blocked)
        return sys.modules[module] is None
    try:
        return importlib.util.find_spec(module) is None
    except (ImportError, ValueError):  # a parent package that fails to import
        return True


@dataclass(frozen=True)
class Needs:
    """Components a scene needs (with the reason) and the ones it leaves out."""

    needed: dict[str, str]
    left_out: tuple[str, ...]

    @property
    def modules(self) -> tuple[str, ...]:
        """Modules a run of this scene imports."""
        return tuple(sorted({m for c in self.needed for m in COMPONENTS[c][1]}))

    @property
    def unavailable(self) -> tuple[str, ...]:
        """Needed components a run cannot have: not in this version, or their optional package
        not installed. A scene needing one is refused by ``rtctl run`` and so by ``rtctl check``."""
        return tuple(c for c in self.needed if c not in AVAILABLE or _missing(c))

    def to_dict(self) -> dict:
        return {
            "needs": [{"component": c, "what": COMPONENTS[c][0], "why": why} for c, why in self.needed.items()],
            "leaves_out": [{"component": c, "what": COMPONENTS[c][0]} for c in self.left_out],
            "unavailable": list(self.unavailable),
        }


def needs(scene) -> Needs:
    """The components ``scene`` uses, each with the key that asks for it."""
    need: dict[str, str] = {"safety.limiter": "every output passes the limiter"}
    st = scene.stimulus
    if st.kind == "tones":
        sines = sum(t.shape == "sine" for t in st.tones)
        if sines:
            need["dsp.oscillator"] = f"stimulus.kind = 'tones' ({sines} sine tone(s))"
        elif st.play:
            need["dsp.oscillator"] = f"stimulus.play ({len(st.play)} signal(s))"
        if len(st.tones) > sines:
            need["dsp.pulse"] = f"stimulus.tones with shape square/pulse ({len(st.tones) - sines})"
    elif st.kind == "braille":
        need["render.braille"] = "stimulus.kind = 'braille'"
        need["dsp.pulse"] = "Braille pins are held levels"
    else:  # image (OpenCV) or shape (drawn with OpenCV)
        need["render"] = f"stimulus.kind = {st.kind!r}" + (f", method {st.method!r}" if st.kind == "image" else "")
        if st.kind == "image" and st.method == "beat":
            need["dsp.oscillator"] = "beat rendering drives sines (cell pairs at f_c -+ f_b/2)"
        else:
            need["dsp.pulse"] = "binary pins and pin frequencies are pulse trains / held levels"
    if scene.control.mode == "closed":
        need["selfsense"] = "control.mode = 'closed'"
        need["dsp.lockin"] = "control.mode = 'closed'"
        need["control"] = "control.mode = 'closed'"
    elif scene.control.observe:
        need["selfsense"] = "control.observe = true"
        need["dsp.lockin"] = "control.observe = true (lock-in of drive and segment currents)"
    if scene.control.calibrate == "auto":
        need.setdefault("selfsense", "control.calibrate = 'auto' (the model fitted to the measured currents)")
    backend = scene.io.backend
    need[f"io.{backend}"] = f"io.backend = {backend!r}"
    if backend == "sim":
        for a in scene.actuator:
            need.setdefault(f"plant.{a.type}", f"actuator {a.name!r} is type {a.type!r} (io.backend = 'sim')")
        if scene.finger.contact:
            need["plant.finger"] = "finger.contact = true (io.backend = 'sim')"
    left = tuple(c for c in COMPONENTS if c not in need)
    return Needs(need, left)


def unavailable_message(component: str, why: str) -> str:
    """One line telling the user that ``component`` is not in this version (or its optional
    package is not installed), and what to do."""
    if component in AVAILABLE:
        module, how = OPTIONAL[component]
        return (f"{why} needs the {COMPONENTS[component][0]} ({component}), and its package {module} is not "
                f"installed ({how})")
    fixes = {
        "selfsense": "use control.mode = 'open' for now",
        "dsp.lockin": "use control.mode = 'open' for now",
        "render": "use stimulus.kind = 'tones' for now",
        # a recorded run is replayed by a command, against the simulated plant or offline
        "io.replay": "replay a recorded trace with `rtctl replay TRACE [--mode resim|plant|observer]`",
    }
    fix = fixes.get(component, "use io.backend = 'sim' with a bimorph actuator for now"
                    if component.startswith(("io.", "plant.")) else "")
    return (f"{why} needs the {COMPONENTS[component][0]} ({component}), "
            f"which this version of rtctl does not have yet; {fix}")
