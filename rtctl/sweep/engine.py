"""Where a sweep's tasks run: a Dask cluster (``dask.distributed``), or this process.

Without a scheduler address, a :class:`~distributed.LocalCluster` of worker processes, one
thread each (the models are numpy/scipy on small matrices: processes, not threads, give the
cores); with one, the existing cluster behind it. Dask does what a hand-written pool would have
to: it reschedules the tasks of a worker that dies (a lost process loses no point), restarts a
local worker, balances tasks across machines. ``workers=0`` computes in this process, without
Dask (a baseline, and small sweeps without a cluster's start-up).

Dask is imported here only, so only ``rtctl sweep`` pays for it.
"""

from __future__ import annotations

import logging
import os
import uuid

from ..errors import RtctlError

#: How long to wait for a scheduler to answer and for its first worker, s.
CONNECT_TIMEOUT_S = 20.0


def cores() -> int:
    """Cores this process may run on (the local cluster's default size)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


def _check_address(address: str) -> None:
    """Refuse a scheduler address Dask could not connect to at all (before trying, which for a
    malformed one means a long wait for nothing)."""
    from distributed.comm import registry
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, loc = parse_address(address)
        if scheme not in registry.backends:
            raise ValueError(f"unknown protocol {scheme!r} (have {', '.join(registry.backends)})")
        parse_host_port(loc)
    except ValueError as e:
        raise RtctlError(f"--scheduler {address!r}: not a scheduler address like tcp://host:8786 ({e})") from None


class Engine:
    """A context manager that runs tasks and reports each as it finishes.

    Parameters
    ----------
    scheduler : str, optional
        Address of a running Dask scheduler (``tcp://host:8786``).
    workers : int, optional
        Worker processes of the local cluster (default: one per core); 0: this process.
    """

    def __init__(self, scheduler: str | None = None, workers: int | None = None):
        if scheduler and workers is not None:
            raise RtctlError("--workers sets the size of the local cluster; the cluster behind --scheduler "
                             "has its own workers")
        if workers is not None and workers < 0:
            raise RtctlError(f"--workers must be >= 0 (0: compute in this process), got {workers}")
        if scheduler:
            _check_address(scheduler)
        self.scheduler, self.workers = scheduler, workers
        self.client = self.cluster = None
        self._log_level = None

    def __enter__(self):
        if self.workers == 0:
            return self
        # Dask's own log lines (a worker restarted, a task rescheduled) are not the user's
        # concern while the sweep goes on; a point that fails for good is a row with its error.
        log = logging.getLogger("distributed")
        self._log_level = log.level
        log.setLevel(logging.ERROR)
        from dask.distributed import Client, LocalCluster

        try:
            if self.scheduler:
                self.client = Client(self.scheduler, timeout=f"{CONNECT_TIMEOUT_S}s", set_as_default=False)
            else:
                self.cluster = LocalCluster(n_workers=self.workers or cores(), threads_per_worker=1,
                                            processes=True, host="127.0.0.1", dashboard_address=None,
                                            silence_logs=logging.ERROR)
                self.client = Client(self.cluster, set_as_default=False)
            self.client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError) as e:
            self.__exit__(None, None, None)
            where = f"--scheduler {self.scheduler}" if self.scheduler else "local cluster"
            raise RtctlError(f"{where}: {type(e).__name__}: {' '.join(str(e).split())}") from None
        return self

    def everywhere(self, fn, *args) -> None:
        """``fn(*args)`` on every worker there is (here without a cluster), before the tasks: a
        worker that cannot run it (no rtctl where it runs) refuses the sweep in one line."""
        if self.client is None:
            fn(*args)
            return
        try:
            self.client.run(fn, *args)
        except Exception as e:
            where = f"--scheduler {self.scheduler}" if self.scheduler else "local cluster"
            raise RtctlError(f"{where}: a worker cannot run rtctl ({type(e).__name__}: {' '.join(str(e).split())}); "
                             "install rtctl where the workers run") from None

    def __exit__(self, *exc):
        if self.client is not None:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()
        self.client = self.cluster = None
        if self._log_level is not None:
            logging.getLogger("distributed").setLevel(self._log_level)
            self._log_level = None
        return False

    @property
    def n_workers(self) -> int:
        if self.client is None:
            return 1
        return max(1, len(self.client.scheduler_info()["workers"]))

    def describe(self) -> str:
        if self.client is None:
            return "this process"
        if self.cluster is not None:
            return f"local Dask cluster, {self.n_workers} worker processes"
        return f"Dask scheduler {self.scheduler}, {self.n_workers} workers"

    def map(self, fn, tasks: list, on_done) -> None:
        """``fn(task)`` for every task; ``on_done(task, result, error)`` as each finishes (result
        None and error a one-line message when the task itself was lost, e.g. its worker died
        more often than the scheduler's ``allowed-failures``)."""
        if self.client is None:
            for task in tasks:
                on_done(task, fn(task), None)
            return
        from dask.distributed import as_completed

        run = uuid.uuid4().hex[:8]
        futures = {self.client.submit(fn, t, key=f"rtctl-sweep-{run}-{i}", pure=False): t
                   for i, t in enumerate(tasks)}
        try:
            for fut in as_completed(list(futures), loop=self.client.loop):
                task = futures[fut]
                if fut.status == "finished":
                    on_done(task, fut.result(), None)
                else:
                    e = fut.exception()
                    on_done(task, None, f"task lost: {type(e).__name__}: {' '.join(str(e).split())}")
                fut.release()
        except OSError as e:  # the scheduler went away (CommClosedError is an OSError)
            where = f"--scheduler {self.scheduler}" if self.scheduler else "local cluster"
            raise RtctlError(f"{where}: lost in the middle of the sweep ({type(e).__name__}: {e}); the "
                             "finished points are kept: rerun with the same --out to resume") from None
        finally:
            self.client.cancel([f for f in futures if not f.done()])
