"""A small pool of worker processes for CPU-bound jobs, with what an unattended service needs:
a bounded queue, a deadline per job, and one crashed worker costing one job.

Why not a library pool: :class:`concurrent.futures.ProcessPoolExecutor` marks itself broken and
fails *every* pending job when one worker dies (``BrokenProcessPool``); loky's executor does the
same (``TerminatedWorkerError``) before respawning; :class:`multiprocessing.pool.Pool` replaces a
dead worker but never answers its job (the caller waits forever). None can stop one job at its
deadline. Here each worker is a process with its own pipe, driven by one thread in the parent,
so the parent knows which job each pid runs: a dead worker fails only that job
(:class:`WorkerCrashedError`) and is replaced; a job past its deadline is answered at once
(:class:`DeadlineExceededError`) and its worker killed and replaced only if the job itself runs
longer than a whole deadline (stuck), so time lost in the queue never costs a worker's work. A
job expected to finish after half its deadline (from the recent job times and the jobs ahead)
is refused at submission like a full queue (:class:`QueueFullError`), which keeps an overloaded
pool from spending its time on answers nobody will receive.

Protocol on a worker's pipe (pickled tuples): the worker sends ``("ready", pid)`` after its
initializer, then answers each ``(fn, args)`` with ``("ok", result)``, ``("error", (type name,
message))`` for an expected :class:`~cutterpose.errors.CutterposeError`, or ``("internal",
text)`` for anything else; ``None`` asks it to exit. The job function is called as
``fn(state, *args)``, ``state`` being what the initializer returned.

Convention:
    Times in seconds of :func:`time.monotonic`; a job's deadline counts from its submission
    (queue wait included).
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import queue
import signal
import threading
import time
import traceback
from concurrent.futures import Future
from dataclasses import dataclass, field
from multiprocessing.connection import wait

from ..errors import CutterposeError

__all__ = ["WorkerPool", "PoolError", "QueueFullError", "DeadlineExceededError",
           "WorkerCrashedError", "JobError", "PoolClosedError"]


class PoolError(CutterposeError):
    """A job could not be run to its end by the pool."""


class QueueFullError(PoolError):
    """Every worker is busy and the queue is full, or the expected wait would pass the job's
    deadline; ``retry_after_s`` estimates when to retry."""

    def __init__(self, message: str, retry_after_s: float):
        super().__init__(message)
        self.retry_after_s = retry_after_s


class DeadlineExceededError(PoolError):
    """The job's deadline passed (waiting in the queue or running; a job running longer than a
    whole deadline has its worker killed and replaced)."""


class WorkerCrashedError(PoolError):
    """The worker process died while running the job (it is replaced)."""

    def __init__(self, message: str, pid: int, exitcode):
        super().__init__(message)
        self.pid, self.exitcode = pid, exitcode


class PoolClosedError(PoolError):
    """The pool is shutting down."""


class JobError(PoolError):
    """The job raised: ``kind`` is the exception's class name (a CutterposeError subclass for
    an expected failure, ``internal`` otherwise)."""

    def __init__(self, kind: str, message: str, internal: bool = False):
        super().__init__(message)
        self.kind, self.internal = kind, internal


def _worker_main(conn, initializer, initargs) -> None:
    """Body of a worker process (module doc for the protocol)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    try:
        state = initializer(*initargs) if initializer is not None else None
    except BaseException as e:  # noqa: BLE001 - reported to the parent, which decides
        conn.send(("init_failed", f"{type(e).__name__}: {e}"))
        return
    conn.send(("ready", os.getpid()))
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return  # the parent is gone
        if msg is None:
            return
        fn, args = msg
        try:
            reply = ("ok", fn(state, *args))
        except CutterposeError as e:
            reply = ("error", (type(e).__name__, str(e)))
        except Exception as e:  # noqa: BLE001 - a bug: reported, the worker lives on
            traceback.print_exc()
            reply = ("internal", f"{type(e).__name__}: {e}")
        try:
            conn.send(reply)
        except (BrokenPipeError, OSError):
            return


@dataclass
class _Job:
    fn: object
    args: tuple
    deadline_s: float
    deadline: float
    future: Future = field(default_factory=Future)
    pid: int | None = None


_STOP = object()


class _Slot:
    """One worker process and the parent thread that feeds it."""

    def __init__(self, pool: WorkerPool, index: int):
        self.pool, self.index = pool, index
        self.proc = None
        self.conn = None
        self.ready = False
        self.busy_since: float | None = None
        self.restarts = 0
        self.last_error = ""
        self.last_exitcode = None
        self.thread = threading.Thread(target=self._run, name=f"cutterpose-worker-{index}",
                                       daemon=True)

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    def alive(self) -> bool:
        return self.proc is not None and self.proc.is_alive()

    # -- process life -------------------------------------------------------------------
    def _spawn(self) -> bool:
        ctx = self.pool.ctx
        parent, child = ctx.Pipe(duplex=True)
        proc = ctx.Process(target=_worker_main, args=(child, self.pool.initializer,
                                                      self.pool.initargs),
                           name=f"cutterpose-worker-{self.index}", daemon=True)
        proc.start()
        child.close()
        self.proc, self.conn = proc, parent
        deadline = time.monotonic() + self.pool.start_timeout_s
        while time.monotonic() < deadline and not self.pool.closing:
            ready = wait([parent, proc.sentinel], timeout=0.5)
            if parent in ready:
                try:
                    kind, value = parent.recv()
                except (EOFError, OSError):
                    break
                if kind == "ready":
                    self.ready = True
                    return True
                self.last_error = str(value)
                break
            if proc.sentinel in ready:
                break
        if not self.last_error and not self.pool.closing:
            self.last_error = f"worker did not start (exit code {proc.exitcode})"
        self._reap()
        return False

    def _reap(self) -> None:
        self.ready = False
        if self.proc is not None:
            if self.proc.is_alive():
                self.proc.kill()
            self.proc.join(5)
        if self.conn is not None:
            self.conn.close()
        self.proc = self.conn = None

    def _ensure(self) -> bool:
        """A live, ready worker (respawned if needed, with a back-off on repeated failures)."""
        backoff = 0.2
        while not self.pool.closing:
            if self.ready and self.alive():
                return True
            if self.proc is not None:
                self._reap()
                self.restarts += 1
            if self._spawn():
                return True
            time.sleep(backoff)
            backoff = min(backoff * 2, 5.0)
        return False

    # -- jobs ---------------------------------------------------------------------------
    def _run(self) -> None:
        pool = self.pool
        self._ensure()
        while True:
            try:
                job = pool._queue.get(timeout=0.5)
            except queue.Empty:
                if pool.closing:
                    break
                if not (self.ready and self.alive()):
                    self._ensure()  # an idle worker died: replace it now, not at the next job
                continue
            if job is _STOP:
                break
            try:
                self._execute(job)
            finally:
                pool._done()
        if self.conn is not None and self.alive():
            try:
                self.conn.send(None)
            except OSError:
                pass
            self.proc.join(2)
        self._reap()

    def _execute(self, job: _Job) -> None:
        if not job.future.set_running_or_notify_cancel():
            return
        if time.monotonic() >= job.deadline:
            job.future.set_exception(DeadlineExceededError("deadline passed while waiting in the "
                                                      "queue"))
            return
        if not self._ensure():
            job.future.set_exception(PoolClosedError("the service is shutting down"))
            return
        try:
            self.conn.send((job.fn, job.args))
        except (BrokenPipeError, OSError):
            # died while idle, before the job reached it: the job never ran, run it anew
            self._reap()
            self.restarts += 1
            if not self._ensure():
                job.future.set_exception(PoolClosedError("the service is shutting down"))
                return
            self.conn.send((job.fn, job.args))
        job.pid = self.pid
        self.busy_since = t0 = time.monotonic()
        pool = self.pool
        try:
            kind, value = self._reply(job.deadline)
            if kind == "timeout":
                # answer now; the worker may finish (its result is dropped): killing it at the
                # request's deadline would waste its work whenever the queue wait, not the job,
                # used up the time. Only a job running longer than a whole deadline is stuck.
                job.future.set_exception(DeadlineExceededError(
                    f"no answer within the deadline of {job.deadline_s:g} s"))
                pool.timeouts += 1
                kind, value = self._reply(t0 + job.deadline_s)
                if kind == "timeout":
                    self._replace()  # stuck: kill it
                elif kind == "crashed":
                    self._crashed()
                return
        finally:
            self.busy_since = None
        if kind == "ok":
            pool._record_service_time(time.monotonic() - t0)
            job.future.set_result(value)
        elif kind == "error":
            job.future.set_exception(JobError(value[0], value[1]))
        elif kind == "internal":
            job.future.set_exception(JobError("internal", value, internal=True))
        else:
            pid, how = self._crashed()
            job.future.set_exception(WorkerCrashedError(
                f"worker process {pid} died during the request ({how}); it was replaced",
                pid, self.last_exitcode))

    def _reply(self, until: float):
        """The worker's reply, ``("crashed", None)`` if it died, ``("timeout", None)`` if
        nothing came by ``until`` (monotonic)."""
        ready = wait([self.conn, self.proc.sentinel],
                     timeout=max(until - time.monotonic(), 0.0))
        if self.conn in ready:
            try:
                return self.conn.recv()
            except (EOFError, OSError):
                return "crashed", None
        return ("crashed", None) if ready else ("timeout", None)

    def _replace(self) -> None:
        """Kill the worker and start another."""
        self._reap()
        self.restarts += 1
        self._ensure()

    def _crashed(self) -> tuple[int, str]:
        """Reap a dead worker, start another; its pid and how it ended."""
        pid = self.pid
        self.proc.join(5)
        code = self.last_exitcode = self.proc.exitcode
        self.pool.crashes += 1
        self._replace()
        how = (f"killed by signal {-code}" if isinstance(code, int) and code < 0
               else f"exit code {code}")
        return pid, how


class WorkerPool:
    """Worker processes with a bounded queue (module doc).

    Parameters
    ----------
    n_workers : processes.
    queue_size : jobs that may wait beyond the ``n_workers`` running ones; one more is
        refused with :class:`QueueFullError`.
    initializer, initargs : ``state = initializer(*initargs)`` once per worker process.
    start_timeout_s : how long a worker may take to start.
    context : multiprocessing start method; ``forkserver`` forks workers from a clean
        single-threaded server (the parent runs an event loop and threads), fast after the
        first start with ``preload``.
    preload : modules the fork server imports once.
    """

    def __init__(self, n_workers: int, queue_size: int, initializer=None, initargs=(),
                 start_timeout_s: float = 120.0, context: str = "forkserver",
                 preload: tuple[str, ...] = ()):
        if n_workers < 1 or queue_size < 0:
            raise ValueError("n_workers >= 1 and queue_size >= 0")
        self.n_workers, self.queue_size = n_workers, queue_size
        self.initializer, self.initargs = initializer, initargs
        self.start_timeout_s = start_timeout_s
        self.ctx = mp.get_context(context)
        if context == "forkserver" and preload:
            self.ctx.set_forkserver_preload(list(preload))
        self._queue: queue.Queue = queue.Queue()
        self._lock = threading.Lock()
        self._pending = 0          # submitted and not finished (queued + running)
        self._service_s = 0.0      # moving average of a job's run time (for Retry-After)
        self.closing = False
        self.crashes = self.timeouts = self.refused = 0
        self._slots = [_Slot(self, i) for i in range(n_workers)]
        self._started = False

    # -- life ----------------------------------------------------------------------------
    def start(self) -> WorkerPool:
        """Start the workers (returns at once; :meth:`wait_ready` waits for them)."""
        if not self._started:
            self._started = True
            for s in self._slots:
                s.thread.start()
        return self

    def wait_ready(self, timeout_s: float = 120.0) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self.ready:
                return True
            time.sleep(0.05)
        return self.ready

    def close(self, timeout_s: float = 10.0) -> None:
        """Stop taking jobs, let running ones end (up to ``timeout_s``), stop the workers; jobs
        still queued fail with :class:`PoolClosedError`."""
        self.closing = True
        while True:
            try:
                job = self._queue.get_nowait()
            except queue.Empty:
                break
            if job is not _STOP and job.future.set_running_or_notify_cancel():
                job.future.set_exception(PoolClosedError("the service is shutting down"))
                self._done()
        for _ in self._slots:
            self._queue.put(_STOP)
        end = time.monotonic() + timeout_s
        for s in self._slots:
            if s.thread.is_alive():
                s.thread.join(max(end - time.monotonic(), 0.1))
            s._reap()

    # -- state ---------------------------------------------------------------------------
    @property
    def ready(self) -> bool:
        return (not self.closing and self._started
                and all(s.ready and s.alive() for s in self._slots))

    @property
    def pending(self) -> int:
        return self._pending

    @property
    def running(self) -> int:
        return sum(s.busy_since is not None for s in self._slots)

    @property
    def queued(self) -> int:
        return max(self._pending - self.running, 0)

    @property
    def restarts(self) -> int:
        return sum(s.restarts for s in self._slots)

    def workers(self) -> list[dict]:
        """Per worker: pid, alive, busy, restarts (``/ready``)."""
        return [{"pid": s.pid, "alive": s.alive(), "ready": s.ready,
                 "busy": s.busy_since is not None, "restarts": s.restarts,
                 **({"last_error": s.last_error} if s.last_error and not s.ready else {})}
                for s in self._slots]

    # -- jobs ----------------------------------------------------------------------------
    def submit(self, fn, *args, deadline_s: float) -> Future:
        """Queue ``fn(state, *args)`` for a worker.

        Raises
        ------
        QueueFullError
            ``n_workers + queue_size`` jobs are already pending.
        PoolClosedError
            The pool is shutting down.
        """
        with self._lock:
            refusal = self._refusal(deadline_s)
            if refusal is not None:
                self.refused += 1
                raise refusal
            self._pending += 1
        job = _Job(fn, args, deadline_s, time.monotonic() + deadline_s)
        self._queue.put(job)
        return job.future

    def admit(self, deadline_s: float) -> None:
        """Raise what :meth:`submit` would raise now, without queueing anything (to refuse a
        request before its body is read)."""
        with self._lock:
            refusal = self._refusal(deadline_s)
        if refusal is not None:
            raise refusal

    def _refusal(self, deadline_s: float) -> PoolError | None:
        if self.closing:
            return PoolClosedError("the service is shutting down")
        ahead = self._pending - self.n_workers + 1   # jobs that would wait before this one
        wait_s = max(ahead, 0) * self._service_s / self.n_workers
        full = self._pending >= self.n_workers + self.queue_size
        # a job expected to finish late would only spend a worker's time on an answer nobody
        # receives; half the deadline leaves room for the estimate's error under varying load
        hopeless = (self._service_s > 0 and ahead > 0
                    and wait_s + self._service_s > 0.5 * deadline_s)
        if not (full or hopeless):
            return None
        why = (f"all {self.n_workers} workers busy and {self.queue_size} requests waiting"
               if full else f"expected wait {wait_s:.1f} s: the answer would come too close "
               f"to the deadline of {deadline_s:g} s")
        est = max(ahead, 1) * max(self._service_s, 0.05) / self.n_workers
        return QueueFullError(why, retry_after_s=max(1.0, math.ceil(est)))

    def _done(self) -> None:
        with self._lock:
            self._pending -= 1

    def _record_service_time(self, seconds: float) -> None:
        a = 0.2
        prev = self._service_s
        self._service_s = seconds if prev == 0 else (1 - a) * prev + a * seconds
