"""A sweep task for the worker-loss test: the real point computation, made slow, leaving a file
per point started and finished (named ``start-INDEX-PID``, ``done-INDEX-PID``) so the test can
see which worker process holds an unfinished point and kill that one."""

import os
import time
from pathlib import Path

from rtctl.sweep import points

#: Seconds each point takes on top of its computation: long enough to kill a worker mid-point.
DELAY_S = 0.4


def slow_compute(log_dir, task):
    out = []
    for index, sets in task["points"]:
        (Path(log_dir) / f"start-{index}-{os.getpid()}").touch()
        time.sleep(DELAY_S)
        res = points.compute({**task, "points": [[index, sets]]})
        (Path(log_dir) / f"done-{index}-{os.getpid()}").touch()
        out += res
    return out
