"""The worker process of the jobs beside the tracking (re-anchors' band fits and deferred full
measurements, docs/tracking.md, "Jobs beside the tracking"): one long-lived process per
tracker, its frames handed over through a block of shared memory.

Why not :mod:`cutterpose.parallel`'s pool (a map of one function over many images): here one
job at a time runs beside a tracking loop that must not wait for it, on a 12-MP frame per job
(pickling it would cost more than the copy out of shared memory), and the process lives as
long as the tracker, warmed up with the outline templates before the first job needs them.
Why not the service's :class:`~cutterpose.service.workers.WorkerPool` (deadlines, a bounded
queue, crash isolation for many requests): the core may not import the service, and a
tracker has one job in flight and its own answer to a dead worker (the frame falls back to a
full measurement with the reason, and the next job starts a new process).
"""

from __future__ import annotations

import weakref
from concurrent.futures import Future, ProcessPoolExecutor

import numpy as np

from ..errors import InputError
from ..geometry.camera import Camera
from ..geometry.holder import Holder
from ..image import FeatureParams
from ..image.region import prepare_outline_search

__all__ = ["AnchorProcess"]


def _run_shared(fn, shm_name: str, shape: tuple, *args):
    """``fn(frame, *args)`` in the worker process, on the frame in shared memory
    ``shm_name`` (``fn``: :func:`band_fit` or :func:`full_measurement`)."""
    from multiprocessing import shared_memory

    # attached, not owned: the tracker's process unlinks it (a spawned worker shares its
    # resource tracker, which holds the name once however often it is registered)
    shm = shared_memory.SharedMemory(name=shm_name)
    try:
        # copied out (~2 ms for 12 MP): a measurement keeps views of its frame, which must
        # outlive the block (pickling a view of a closed block crashes the worker), and the
        # block is free for the next job
        img = np.ndarray(shape, np.uint8, buffer=shm.buf).copy()
    finally:
        shm.close()
    return fn(img, *args)


def _warm_worker(camera: Camera | None = None, holder: Holder | None = None,
                 params: FeatureParams | None = None) -> None:
    """Import the band fit in the worker before the first re-anchor needs it, and build the
    full measurement's outline templates before the first fall-back does."""
    from ..solvers import edge_band  # noqa: F401

    if camera is not None:
        prepare_outline_search(camera, holder, params)


class AnchorProcess:
    """One worker process for the deferred re-anchors and fall-backs
    (``anchor_worker="process"``): the frame goes through a shared-memory block of its size
    (one pending job at a time, so one block, which the job copies its frame out of; a job
    dropped by a fall-back and still queued may read the next job's frame: its result is
    never read), the rest of the arguments by pickle. A process, not a thread: the band fit is
    ~120 ms of mostly small NumPy calls that hold the interpreter lock, which a thread would
    take from the tracking (spawned, not forked: the caller may have threads of its own; as
    for any spawned process, a script's main module must be importable, i.e. not read from
    standard input: else the worker fails, and each re-anchor falls back to a full
    measurement with that reason)."""

    def __init__(self, shape: tuple, *warm):
        """``warm``: ``(camera, holder, params)`` of the full measurements it may run."""
        import multiprocessing
        from multiprocessing import shared_memory

        self.shape = tuple(shape)
        self._shm = shared_memory.SharedMemory(create=True, size=int(np.prod(self.shape)))
        self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
        self.warm = self._pool.submit(_warm_worker, *warm)
        # a tracker dropped without close(): the worker and the block go with it
        self._finalizer = weakref.finalize(self, _release_worker, self._pool, self._shm)

    def submit(self, fn, img: np.ndarray, *args) -> Future:
        """``fn(img, *args)`` in the worker (``fn`` a module-level function)."""
        if img.shape != self.shape or img.dtype != np.uint8:
            raise InputError(f"frame {img.shape} {img.dtype} is not the {self.shape} uint8 "
                             "frames of this tracker")
        np.ndarray(self.shape, np.uint8, buffer=self._shm.buf)[:] = img
        return self._pool.submit(_run_shared, fn, self._shm.name, self.shape, *args)

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        self._finalizer.detach()
        _release_worker(self._pool, self._shm, wait, cancel_futures)


def _release_worker(pool, shm, wait: bool = False, cancel_futures: bool = True) -> None:
    pool.shutdown(wait=wait, cancel_futures=cancel_futures)
    shm.close()
    try:
        shm.unlink()
    except FileNotFoundError:
        pass

