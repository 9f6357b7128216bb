"""Where independent jobs run: in this process, in local worker processes, or on a Dask cluster.

The one place that chooses the executor of ``experiment synthetic``, ``experiment images`` and
``render-set``. Every job is a picklable argument for a module-level function; the results come
back **in job order** whatever the order in which they complete, so an output built from them
does not depend on where the jobs ran (a single process, ``workers`` processes, or any number
of Dask workers). Each job carries its own seed, so no result depends on which worker ran it.

On a Dask distributed cluster (``scheduler="tcp://host:8786"``) the jobs are submitted with
``Client.map`` and collected with ``distributed.as_completed``; the scheduler re-runs the tasks
of a worker that dies (up to ``distributed.scheduler.allowed-failures`` times, 3 by default)
on the surviving or restarted workers, so a lost worker costs time, not results.

The package's other two process pools do a different job, and are kept apart on purpose:

- :class:`cutterpose.service.workers.WorkerPool`: the service's long-lived workers, which
  must keep answering unattended: a bounded queue, a deadline per job, and a crashed worker
  costing one request (a :class:`~concurrent.futures.ProcessPoolExecutor` fails every
  pending job when one worker dies; a batch here may fail whole, and a Dask cluster re-runs
  lost tasks itself);
- :class:`cutterpose.tracking.worker.AnchorProcess`: one process that lives as long as a
  tracker and runs one job at a time beside its frame loop, the 12-MP frame handed over
  through shared memory instead of pickled with the job.

This one is a map over a list of independent jobs whose results come back in job order.

Convention:
    ``on_done(index, result)`` is called in *completion* order (progress bars); the returned
    list is in *job* order. Workers must run the same cutterpose version as the client
    (``pip install 'cutterpose[cluster]'`` on every node).

References:
    Dask distributed documentation: "Futures" (``Client.map``, ``as_completed``) and
    "Resilience" (re-running the tasks of lost workers).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any

from .errors import ClusterError, DependencyError, InputError

__all__ = ["JobRunner", "run_jobs", "require_distributed"]

CONNECT_TIMEOUT_S = 20


def require_distributed():
    """Import ``dask.distributed`` or say how to install it."""
    try:
        import distributed
    except ImportError:
        raise DependencyError("--scheduler needs Dask distributed: pip install "
                              "'cutterpose[cluster]' (or 'dask[distributed]')") from None
    return distributed


class JobRunner:
    """An executor kept open across several :meth:`map` calls (one pool / one client).

    Parameters
    ----------
    workers : local worker processes when no scheduler is given (1: run in this process).
    scheduler : address of a running Dask scheduler (``tcp://host:8786``), or a
        ``distributed.Client``; overrides ``workers``.
    initializer, initargs : run once in every local worker process (state the jobs share,
        sent once instead of with every job); local processes only.
    """

    def __init__(self, workers: int = 1, scheduler: Any = None,
                 initializer: Callable | None = None, initargs: tuple = ()):
        if int(workers) < 1:
            raise InputError(f"workers must be >= 1, got {workers}")
        if initializer is not None and scheduler is not None:
            raise InputError("a worker initializer needs local processes, not a Dask scheduler")
        self.workers = int(workers)
        self.scheduler = scheduler
        self.initializer, self.initargs = initializer, tuple(initargs)
        self._pool = None
        self._client = None
        self._own_client = False

    # -- context ------------------------------------------------------------------------
    def __enter__(self) -> JobRunner:
        if self.scheduler is not None:
            self._client, self._own_client = _connect(self.scheduler)
        elif self.workers > 1:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            # fork: the workers inherit the imported package (and sys.path) at no cost
            ctx = mp.get_context("fork") if os.name == "posix" else None
            self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx,
                                             initializer=self.initializer,
                                             initargs=self.initargs)
        return self

    def __exit__(self, *exc) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None
        if self._client is not None and self._own_client:
            self._client.close()
        self._client = None

    @property
    def where(self) -> str:
        """A short description for logs: ``in process``, ``2 processes``, ``dask tcp://...``."""
        if self._client is not None:
            return f"dask {self._client.scheduler.address}"
        return f"{self.workers} processes" if self.workers > 1 else "in process"

    # -- running ------------------------------------------------------------------------
    def map(self, fn: Callable, jobs: Sequence, on_done: Callable | None = None,
            store: Callable | None = None) -> list:
        """``[fn(job) for job in jobs]``, computed where this runner runs.

        ``on_done(i, result)`` is called after each job completes; ``store(result)``, when
        given, is kept instead of the result (e.g. drop an image once it is written). A job
        that raises re-raises here (the first one to fail).
        """
        jobs = list(jobs)
        out: list = [None] * len(jobs)

        def finish(i, result):
            if on_done is not None:
                on_done(i, result)
            out[i] = result if store is None else store(result)

        if self._client is not None:
            self._map_dask(fn, jobs, finish)
        elif self._pool is not None and len(jobs) > 1:
            from concurrent.futures import as_completed

            index = {self._pool.submit(fn, job): i for i, job in enumerate(jobs)}
            for fut in as_completed(index):
                finish(index[fut], fut.result())
        else:
            for i, job in enumerate(jobs):
                finish(i, fn(job))
        return out

    def _map_dask(self, fn, jobs, finish) -> None:
        distributed = require_distributed()
        # pure=False: every job is run (no hashing of the arguments), keys are unique
        futures = self._client.map(fn, jobs, pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        try:
            for fut in distributed.as_completed(futures, loop=self._client.loop):
                i = index[fut.key]
                try:
                    result = fut.result()
                except distributed.KilledWorker as e:
                    raise ClusterError(f"job {i} killed its worker too often, giving up: "
                                       f"{e}") from None
                except ModuleNotFoundError as e:
                    raise ClusterError(f"a Dask worker cannot import {e.name!r}: install "
                                       "cutterpose (same version) on every worker") from None
                finish(i, result)
                fut.release()
        finally:
            self._client.cancel([f for f in futures if not f.done()])


def _connect(scheduler):
    """A ``distributed.Client`` for an address (owned: closed on exit) or the client given."""
    distributed = require_distributed()
    if isinstance(scheduler, distributed.Client):
        return scheduler, False
    address = str(scheduler).strip()
    if not address:
        raise InputError("--scheduler: empty address (expected e.g. tcp://host:8786)")
    try:
        client = distributed.Client(address, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as e:
        raise ClusterError(f"cannot reach the Dask scheduler at {address!r} within "
                           f"{CONNECT_TIMEOUT_S} s: {e}") from None
    return client, True


def run_jobs(fn: Callable, jobs: Sequence, workers: int = 1, scheduler: Any = None,
             on_done: Callable | None = None, runner: JobRunner | None = None,
             store: Callable | None = None) -> list:
    """Run ``fn`` over ``jobs`` (see :meth:`JobRunner.map`); results in job order.

    Uses ``runner`` when given (already open), else opens one for this call.
    """
    if runner is not None:
        return runner.map(fn, jobs, on_done, store)
    with JobRunner(workers, scheduler) as r:
        return r.map(fn, jobs, on_done, store)
