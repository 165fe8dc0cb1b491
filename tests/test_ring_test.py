"""bench/ring_test.py: the test of which load rings in the first block read after a finger event.
Its premise is checked against the simulated device (a finite-element beam the test's
transfer-matrix predictions were not made from): the load in use explains a steady block of the
low tones' currents to the sensor noise, and the first block read after an event names the free
tip after a lift-off and a finger after a press or a landing."""

import pytest
from bench_module import load

sweep = load("control_sweep")
load("control_oracle")  # the bench imports it by name
ring = load("ring_test")


@pytest.fixture(scope="module")
def rows():
    return ring.device_rows({})


#: The load in use before each event of the sweep (the model's finger sets by their k0).
IN_USE = {"200 g": "finger k0 300 N/m", "lifted": "finger k0 750 N/m", "back": "free"}


def test_the_load_in_use_explains_a_steady_block_to_the_noise(rows):
    """The single tones of 10-120 Hz at their small targets (the drive's currents there are a few
    times the noise): the calibrated model's currents for the load in use leave 2.5 sigma at most."""
    low = [r for r in rows if r["read"] == "last before" and r["freq_hz"] <= 120 and not r["beat_hz"]
           and r["target_um"] < 10.0]
    assert len(low) == 5 * 3
    for r in low:
        assert r["rms_sigma"][IN_USE[r["event"]]] < 2.5, r


def test_the_first_block_read_names_the_event(rows):
    """Every tone below 500 Hz (the beat pairs too): the right side explains the block at least
    1.3 times better (rms) than the other."""
    first = [r for r in rows if r["read"] == "first after" and r["freq_hz"] < 500]
    assert len(first) == 11 * 3
    for r in first:
        if r["event"] == "lifted":
            assert r["verdict"] == "free" and r["free_over_finger"] < 1 / 1.3, r
        else:
            assert r["verdict"] != "free" and r["free_over_finger"] > 1.3, r
