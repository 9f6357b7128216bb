"""The service's worker pool: one crashed worker costs one job, deadlines kill only their job's
worker, a full queue refuses at once (issue 12)."""

import os
import signal
import time

import pytest

from cutterpose.errors import InputError
from cutterpose.service.workers import (
    DeadlineExceededError,
    JobError,
    QueueFullError,
    WorkerCrashedError,
    WorkerPool,
)


def _init(tag):
    return tag


def _sleep(state, seconds):
    time.sleep(seconds)
    return state, os.getpid()


def _fail(state, expected):
    if expected:
        raise InputError("bad value")
    raise ZeroDivisionError("a bug")


@pytest.fixture(scope="module")
def pool():
    p = WorkerPool(2, 1, _init, ("tag",)).start()
    assert p.wait_ready(60), p.workers()
    yield p
    p.close()
    assert all(w["pid"] is None for w in p.workers())


def _busy_pid(pool, timeout_s=5.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        busy = [w["pid"] for w in pool.workers() if w["busy"]]
        if busy:
            return busy
        time.sleep(0.005)
    raise AssertionError("no worker became busy")


def test_state_from_initializer_and_distinct_processes(pool):
    pids = {pool.submit(_sleep, 0.2, deadline_s=10).result()[1]}
    a, b = pool.submit(_sleep, 0.3, deadline_s=10), pool.submit(_sleep, 0.3, deadline_s=10)
    ra, rb = a.result(), b.result()
    assert ra[0] == rb[0] == "tag"
    assert ra[1] != rb[1] and ra[1] != os.getpid()  # two processes, not this one
    assert pids <= {w["pid"] for w in pool.workers()}


def test_killed_worker_fails_only_its_job_and_is_replaced(pool):
    before = pool.restarts
    slow = pool.submit(_sleep, 3.0, deadline_s=30)
    pid = _busy_pid(pool)[0]
    other = pool.submit(_sleep, 0.2, deadline_s=30)   # runs on the other worker
    os.kill(pid, signal.SIGKILL)
    with pytest.raises(WorkerCrashedError) as e:
        slow.result(20)
    assert e.value.pid == pid and e.value.exitcode == -signal.SIGKILL
    assert str(pid) in str(e.value)
    assert other.result(20)[0] == "tag"
    after = [pool.submit(_sleep, 0.0, deadline_s=30).result(20) for _ in range(3)]
    assert all(r[0] == "tag" and r[1] != pid for r in after)
    assert pool.restarts == before + 1
    assert pool.wait_ready(30) and pid not in {w["pid"] for w in pool.workers()}


def test_deadline_kills_the_stuck_worker_only(pool):
    stuck = pool.submit(_sleep, 30.0, deadline_s=0.5)
    t0 = time.monotonic()
    with pytest.raises(DeadlineExceededError):
        stuck.result(20)
    assert time.monotonic() - t0 < 5.0
    assert pool.submit(_sleep, 0.0, deadline_s=30).result(20)[0] == "tag"


def test_queue_full_refuses_at_once_with_a_retry_time(pool):
    assert pool.wait_ready(30)
    # an earlier test's job may still count as pending (a deadline's kill is settled by the
    # pool's own thread, later under load): the "2 run, 1 waits" below needs an empty pool
    end = time.monotonic() + 30
    while pool.pending and time.monotonic() < end:
        time.sleep(0.01)
    assert pool.pending == 0
    running = [pool.submit(_sleep, 1.0, deadline_s=30) for _ in range(3)]  # 2 run, 1 waits
    t0 = time.monotonic()
    with pytest.raises(QueueFullError) as e:
        pool.submit(_sleep, 0.0, deadline_s=30)
    assert time.monotonic() - t0 < 0.1 and e.value.retry_after_s >= 1
    assert [f.result(20)[0] for f in running] == ["tag"] * 3
    assert pool.pending == 0
    pool.submit(_sleep, 0.0, deadline_s=30).result(20)  # room again


def test_job_errors_are_typed_and_the_worker_lives_on(pool):
    restarts = pool.restarts
    with pytest.raises(JobError) as e:
        pool.submit(_fail, True, deadline_s=30).result(20)
    assert e.value.kind == "InputError" and not e.value.internal and "bad value" in str(e.value)
    with pytest.raises(JobError) as e:
        pool.submit(_fail, False, deadline_s=30).result(20)
    assert e.value.internal and "ZeroDivisionError" in str(e.value)
    assert pool.restarts == restarts  # an exception does not cost the worker
    assert pool.submit(_sleep, 0.0, deadline_s=30).result(20)[0] == "tag"


def test_an_idle_worker_that_dies_is_replaced(pool):
    assert pool.wait_ready(30)
    pid = pool.workers()[0]["pid"]
    os.kill(pid, signal.SIGKILL)
    end = time.monotonic() + 20
    while time.monotonic() < end and (pid in {w["pid"] for w in pool.workers()}
                                       or not pool.ready):
        time.sleep(0.05)
    assert pool.ready and pid not in {w["pid"] for w in pool.workers()}


def test_deadline_spent_waiting_refuses_or_answers_without_killing():
    """One worker: a job expected to end after half its deadline is refused at once; a job
    whose deadline passes because it waited is answered 'deadline', its worker not killed."""
    p = WorkerPool(1, 5, _init, ("x",)).start()
    try:
        assert p.wait_ready(60)
        p.submit(_sleep, 0.4, deadline_s=30).result(20)       # the pool learns a job's time
        b = p.submit(_sleep, 1.0, deadline_s=30)
        _busy_pid(p)
        with pytest.raises(QueueFullError, match="expected wait"):
            p.submit(_sleep, 0.0, deadline_s=0.3)             # would wait ~0.4 s: hopeless
        # expected end 0.4 + 0.4 s <= half of 1.8 s: admitted; it waits ~1 s, then runs 1.5 s
        d = p.submit(_sleep, 1.5, deadline_s=1.8)
        with pytest.raises(DeadlineExceededError):
            d.result(20)
        assert b.result(20)[0] == "x"
        pid = p.workers()[0]["pid"]
        time.sleep(1.0)                                       # d finishes within its run limit
        assert p.restarts == 0 and p.workers()[0]["pid"] == pid
        assert p.submit(_sleep, 0.0, deadline_s=30).result(20)[1] == pid
    finally:
        p.close()
