"""Big runs on a Dask cluster (issue 13, item 3): the same outputs as one worker, and a lost
worker's jobs re-run. A LocalCluster of 2 worker processes (1 thread each) stands in for a real
cluster; the commands get its address exactly as they would a real scheduler's."""

from __future__ import annotations

import csv
import json
import os
import signal
import time

import distributed
import numpy as np
import pytest
from typer.testing import CliRunner

from cutterpose.cli import app
from cutterpose.errors import InputError
from cutterpose.experiments.synthetic import _solve_chunk, generate_trials
from cutterpose.geometry.camera_files import save_camera
from cutterpose.geometry.holder import default_holder
from cutterpose.parallel import JobRunner, run_jobs
from cutterpose.render.sets import render_set
from test_features import small_camera

runner = CliRunner()


@pytest.fixture(scope="module")
def cluster():
    # the workers are new processes: they find the package the way this process did
    os.environ["PYTHONPATH"] = os.pathsep.join(
        p for p in [os.path.dirname(os.path.dirname(__import__("cutterpose").__file__)),
                    os.environ.get("PYTHONPATH", "")] if p)
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1,
                                  dashboard_address=None, silence_logs=40) as c:
        yield c


def _rows_without_time(path):
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert rows, f"{path} is empty"
    for r in rows:
        r.pop("time_ms")
    return rows


def test_synthetic_on_cluster_matches_one_worker(cluster, tmp_path):
    args = ["experiment", "synthetic", "--methods", "opencv-ippe-lm,initial,epnp", "--trials",
            "60", "--sigmas", "0,2", "--no-progress"]
    r1 = runner.invoke(app, args + ["--out", str(tmp_path / "one"), "--workers", "1"])
    assert r1.exit_code == 0, r1.output
    r2 = runner.invoke(app, args + ["--out", str(tmp_path / "dask"), "--scheduler",
                                    cluster.scheduler_address])
    assert r2.exit_code == 0, r2.output
    a = _rows_without_time(tmp_path / "one" / "trials.csv")
    b = _rows_without_time(tmp_path / "dask" / "trials.csv")
    assert len(a) == 60 * 2 * 3
    assert a == b
    assert any(float(r["rot_err_deg"] or "nan") > 0 for r in a)


def test_render_set_and_images_on_cluster_match_one_worker(cluster, tmp_path):
    cam_file = tmp_path / "small.json"
    save_camera(small_camera(0.25), cam_file)
    for name, extra in (("one", ["--workers", "1"]),
                        ("dask", ["--scheduler", cluster.scheduler_address])):
        r = runner.invoke(app, ["render-set", "--out", str(tmp_path / name), "--count", "3",
                                "--seed", "5", "--camera", str(cam_file), "--preset", "easy"]
                          + extra)
        assert r.exit_code == 0, r.output
    for f in ("img_0000.png", "img_0001.png", "img_0002.png", "truth.json"):
        assert (tmp_path / "one" / f).read_bytes() == (tmp_path / "dask" / f).read_bytes(), f
    for name, extra in (("one", ["--workers", "1"]),
                        ("dask", ["--scheduler", cluster.scheduler_address])):
        r = runner.invoke(app, ["experiment", "images", str(tmp_path / "one"), "--methods",
                                "dm+,epnp", "--out", str(tmp_path / f"res_{name}")] + extra)
        assert r.exit_code == 0, r.output
    a = _rows_without_time(tmp_path / "res_one" / "trials.csv")
    b = _rows_without_time(tmp_path / "res_dask" / "trials.csv")
    assert len(a) == 6 and a == b
    assert (tmp_path / "res_one" / "corners.csv").read_text() == \
        (tmp_path / "res_dask" / "corners.csv").read_text()


def test_unreachable_scheduler_is_a_clean_error(tmp_path, monkeypatch):
    monkeypatch.setattr("cutterpose.parallel.CONNECT_TIMEOUT_S", 2)
    r = runner.invoke(app, ["experiment", "synthetic", "--trials", "2", "--sigmas", "0",
                            "--no-progress", "--out", str(tmp_path),
                            "--scheduler", "tcp://127.0.0.1:9"])
    assert r.exit_code == 2, r.output
    assert "cannot reach the Dask scheduler" in r.output and "Traceback" not in r.output
    with pytest.raises(InputError):
        JobRunner(scheduler=" ").__enter__()


def test_lost_worker_jobs_are_rerun(cluster):
    """Kill one worker process (SIGKILL, as a crashed node) as soon as the first job is back:
    its running and queued jobs are re-run elsewhere and the results are those of one worker."""
    tr = generate_trials(40, 1.0, seed=3)
    jobs = [(["dm+"], tr.camera, tr.points_holder_mm, default_holder(),
             tr.points_px[i:i + 4], tr.shift[i:i + 4], tr.reverse[i:i + 4])
            for i in range(0, 40, 4)]
    serial = run_jobs(_solve_chunk, jobs)
    with distributed.Client(cluster.scheduler_address, set_as_default=False) as client:
        pids = client.run(os.getpid)
        killed = {}

        def kill_one(i, _):
            if not killed:
                addr, pid = sorted(pids.items())[0]
                os.kill(pid, signal.SIGKILL)
                killed[addr] = pid

        t0 = time.perf_counter()
        with JobRunner(scheduler=client) as jr:
            got = jr.map(_solve_chunk, jobs, on_done=kill_one)
        assert time.perf_counter() - t0 < 120
        assert killed
        # the nanny restarted the killed worker: a new process
        deadline = time.time() + 30
        while len(client.scheduler_info()["workers"]) < 2 and time.time() < deadline:
            time.sleep(0.2)
        assert list(killed.values())[0] not in client.run(os.getpid).values()
    # the scheduler took the dead worker's running jobs back and queued them again
    requeued = {e[0] for e in cluster.scheduler.transition_log
                if e[1] == "processing" and e[2] == "released"
                and str(e[-2]).startswith("handle-worker-cleanup")}
    assert requeued
    for a, b in zip(serial, got):
        R0, t0_, _, why0 = a["dm+"]
        R1, t1, _, why1 = b["dm+"]
        np.testing.assert_array_equal(R0, R1)
        np.testing.assert_array_equal(t0_, t1)
        assert why0 == why1


def test_render_set_writes_from_the_caller(tmp_path):
    """Workers return the PNG bytes: the caller writes them, so a cluster needs no shared
    output folder; the files are those a single process writes."""
    cam = small_camera(0.25)
    p1 = render_set(2, 9, tmp_path / "a", cam, mix=(("easy", 1.0),))
    p2 = render_set(2, 9, tmp_path / "b", cam, mix=(("easy", 1.0),), workers=2)
    assert json.loads(p1.read_text()) == json.loads(p2.read_text())
    assert (tmp_path / "a" / "img_0001.png").read_bytes() == \
        (tmp_path / "b" / "img_0001.png").read_bytes()


def test_missing_dask_says_which_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "distributed", None)
    r = runner.invoke(app, ["render-set", "--out", str(tmp_path), "--count", "1",
                            "--scheduler", "tcp://127.0.0.1:8786"])
    assert r.exit_code == 2, r.output
    assert "cutterpose[cluster]" in r.output and "Traceback" not in r.output
