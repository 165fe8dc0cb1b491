"""rtctl bench realtime: cyclictest's histogram read and turned into the loop's currency, and the
bench going on, in one line each, without cyclictest or stress-ng."""

import json

import pytest

from rtctl.engine import bench_realtime as br

# cyclictest -q -h 8 output of one thread (rt-tests 2.5), shortened: 10 wake-ups, two overflows
CANNED = """# /dev/cpu_dma_latency set to 0us
# Histogram
000000 000000
000001 000003
000002 000002
000003 000000
000004 000001
000005 000000
000006 000001
000007 000001
# Total: 000000010
# Min Latencies: 00001
# Avg Latencies: 00005
# Max Latencies: 00031
# Histogram Overflows: 00002
# Histogram Overflow at cycle number:
# Thread 0: 00004 00009
"""


def test_the_histogram_is_read_whole():
    p = br.parse_cyclictest(CANNED)
    assert p["hist"] == [0, 3, 2, 0, 1, 0, 1, 1] and p["overflows"] == 2 and p["max"] == 31 and p["total"] == 10
    with pytest.raises(ValueError):
        br.parse_cyclictest("cyclictest: unrecognized option\n")


def test_late_wakeups_and_the_blocks_they_cost():
    p = br.parse_cyclictest(CANNED)
    assert br.late_wakeups(p, 4.0) == 1 + 1 + 1 + 2  # buckets 4, 6, 7 and the overflows
    assert br.late_wakeups(p, 3.5) == 5  # a threshold between buckets rounds up
    # slack 3 us: a wake-up L late costs ceil(L / 3) - 1 blocks (this one and the catch-up)
    assert [br.blocks_missed(x, 3.0) for x in (0, 2, 3, 3.5, 6, 7, 31)] == [0, 0, 0, 1, 1, 2, 10]
    # buckets 4 (1 x 1), 6 (1 x 1), 7 (1 x 2), overflows at the histogram's end, 8 us (2 x 2)
    assert br.cyclictest_blocks(p, 3.0) == 1 + 1 + 2 + 4
    q = br.hist_percentiles(p)
    assert q["p50"] == 2 and q["max"] == 31 and q["p99"] == 31  # the overflows are the top 20 %


def test_the_bench_goes_on_without_cyclictest_or_stress_ng(monkeypatch, capsys):
    monkeypatch.setattr(br.shutil, "which", lambda name: None)
    code = br.main(["--seconds", "0.3", "--rounds", "1", "--policy", "other", "--load", "1", "--json"])
    out, err = capsys.readouterr()
    assert code == 0
    notes = err.strip().splitlines()
    assert len(notes) == 2 and "cyclictest not installed (Debian: rt-tests)" in notes[0]
    assert "stress-ng not installed (Debian: stress-ng)" in notes[1]
    res = json.loads(out)
    (row,) = res["runs"]
    assert row["cyclictest"] is None and "bound" not in row
    loop = row["loop"]
    assert loop["blocks"] == 450 and loop["deadline_misses"] >= 0 and "p99" in loop["wake_late_us"]


def test_bad_arguments_are_one_line(capsys):
    assert br.main(["--seconds", "0"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


@pytest.mark.skipif(br.shutil.which("cyclictest") is None, reason="cyclictest not installed (Debian: rt-tests)")
@pytest.mark.parametrize("policy", ["other", "fifo"])
def test_cyclictest_measures_under_the_policy_asked(policy):
    # its -p switches cyclictest to SCHED_FIFO even as -p 0: the comparison must run as asked
    r = br._cyclictest(br.shutil.which("cyclictest"), policy, 80, 1000, 400, -1)
    if policy == "fifo" and "error" in r and "ran" not in r["error"]:
        pytest.skip(f"SCHED_FIFO not permitted here: {r['error']}")
    assert "error" not in r, r
    assert r["thread_policy"] == policy and r["parsed"]["total"] == 400
