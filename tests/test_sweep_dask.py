"""Sweeps on Dask: a LocalCluster of worker processes, and a real ``dask scheduler`` with a
``dask worker`` started as separate processes on 127.0.0.1 (reached through ``rtctl sweep
--scheduler``), give the same table as the points computed one by one in this process; killing
a worker process in the middle of a sweep loses no point."""

import functools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from sweep_workers import slow_compute

from rtctl import scene
from rtctl.cli import main
from rtctl.sweep import points
from rtctl.sweep.job import sweep
from rtctl.sweep.spec import parse, product

THICK = "actuator.lateral.beam.layers.0.thickness,actuator.lateral.beam.layers.1.thickness"
VARY = ["actuator.lateral.beam.length=10e-3:20e-3:3", f"{THICK}=[0.2e-3, 0.3e-3]"]
WHAT = ("model", "reach")


def table(out) -> list[dict]:
    return pq.read_table(Path(out) / "table.parquet").to_pylist()


def one_by_one() -> list[dict]:
    """Each point loaded and computed here, as `rtctl model` / the reach metric would one at a time."""
    varies = [parse(v) for v in VARY]
    rows = []
    for p in product(varies):
        m = points.metrics(scene.load("line-bimorph-5", list(p.overrides)), WHAT)
        rows.append({"point": p.index, **{v.name: x for v, x in zip(varies, p.values)}, **m, "error": None})
    return rows


@pytest.fixture(scope="module")
def reference():
    return one_by_one()


def test_local_cluster_gives_the_points_computed_one_by_one(tmp_path, reference):
    res = sweep("line-bimorph-5", VARY, WHAT, out=tmp_path / "local", workers=2, chunk=2, plot=False)
    assert res.meta["engine"] == "local Dask cluster, 2 worker processes"
    assert res.meta["computed"] == 6 and res.meta["failed"] == 0
    assert table(tmp_path / "local") == reference
    here = sweep("line-bimorph-5", VARY, WHAT, out=tmp_path / "here", workers=0, plot=False)
    assert here.meta["engine"] == "this process" and table(tmp_path / "here") == reference


@pytest.fixture
def dask_cluster(tmp_path):
    """A `dask scheduler` and a `dask worker` (2 processes) as separate processes on 127.0.0.1."""
    dask = [sys.executable, "-m", "dask"]
    info = tmp_path / "scheduler.json"
    logs = [open(tmp_path / f"{name}.log", "w") for name in ("scheduler", "worker")]
    procs = [subprocess.Popen([*dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(info)], stdout=logs[0], stderr=subprocess.STDOUT)]
    try:
        deadline = time.monotonic() + 60
        while not (info.is_file() and info.stat().st_size):
            assert time.monotonic() < deadline and procs[0].poll() is None, (tmp_path / "scheduler.log").read_text()
            time.sleep(0.1)
        address = json.loads(info.read_text())["address"]
        procs.append(subprocess.Popen([*dask, "worker", address, "--nworkers", "2", "--nthreads", "1",
                                       "--host", "127.0.0.1", "--no-dashboard"],
                                      stdout=logs[1], stderr=subprocess.STDOUT))
        yield address
    finally:  # the workers first, while their scheduler is there to let them go
        for p in reversed(procs):
            p.terminate()
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
        for f in logs:
            f.close()


def test_scheduler_and_worker_processes_through_the_command_line(tmp_path, capsys, dask_cluster, reference):
    out = tmp_path / "remote"
    args = ["sweep", "line-bimorph-5", "--what", ",".join(WHAT), "--scheduler", dask_cluster, "--out", str(out),
            "--json", "--no-plot"]
    for v in VARY:
        args += ["--vary", v]
    code = main(args)
    text, err = capsys.readouterr()
    assert code == 0, err
    doc = json.loads(text)
    assert doc["summary"]["engine"].startswith(f"Dask scheduler {dask_cluster}")
    assert table(out) == reference
    assert [r["lateral.f1_hz"] for r in doc["rows"]] == [r["lateral.f1_hz"] for r in reference]
    # the same directory again: every point is reused, none computed (and no cluster needed)
    assert main(args) == 0
    doc = json.loads(capsys.readouterr()[0])
    assert doc["summary"]["reused"] == 6 and doc["summary"]["computed"] == 0 and table(out) == reference


def test_killing_a_worker_mid_sweep_loses_no_point(tmp_path):
    log = tmp_path / "log"
    log.mkdir()
    vary = ["actuator.lateral.beam.length=10e-3:21e-3:12"]
    killed = {}

    def kill_a_busy_worker():
        # once two points are done, kill the process that holds a started, unfinished point
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not killed:
            names = [f.name.split("-") for f in log.iterdir()]
            done = {(i, pid) for kind, i, pid in names if kind == "done"}
            busy = [(i, pid) for kind, i, pid in names if kind == "start" and (i, pid) not in done]
            if len(done) >= 2 and busy:
                i, pid = busy[0]
                os.kill(int(pid), signal.SIGKILL)
                killed.update(point=int(i), pid=int(pid))
            time.sleep(0.02)

    killer = threading.Thread(target=kill_a_busy_worker, daemon=True)
    killer.start()
    res = sweep("line-bimorph-5", vary, "reach", out=tmp_path / "s", workers=2, chunk=1, plot=False,
                compute=functools.partial(slow_compute, str(log)))
    killer.join(timeout=5)
    assert killed, "no worker was killed: the sweep ended first"
    starts = sorted(f.name for f in log.iterdir() if f.name.startswith(f"start-{killed['point']}-"))
    assert len(starts) >= 2 and f"start-{killed['point']}-{killed['pid']}" in starts  # rescheduled elsewhere
    assert len(res.rows) == 12 and not res.failed and res.meta["computed"] == 12
    sweep("line-bimorph-5", vary, "reach", out=tmp_path / "ref", workers=0, plot=False)
    assert table(tmp_path / "s") == table(tmp_path / "ref")
