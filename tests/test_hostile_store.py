"""The service's record when its disk fails it (issue 32): a full or read-only data directory
answers 503 with the reason and writes nothing half; the next request after space returns is
stored; a locked, corrupt or foreign database stops the start with a clear message and is never
replaced by a new empty record."""

import errno
import sqlite3
import time
import warnings

import cv2
import pytest
from typer.testing import CliRunner

from cutterpose.cli import app as cli_app
from cutterpose.errors import StoreError
from cutterpose.geometry.pose import Pose
from cutterpose.render.analytic import render_holder
from cutterpose.service.app import create_app
from cutterpose.service.config import load_cell
from cutterpose.service.loadtest import write_cell
from cutterpose.service.store import DB_NAME, Store

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from starlette.testclient import TestClient

TOKEN = "store-test-token-55aa"
AUTH = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "image/png"}


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    folder = tmp_path_factory.mktemp("store")
    cell = load_cell(write_cell(folder, factor=4, workers=1), env={"CUTTERPOSE_TOKEN": TOKEN})
    img = render_holder(Pose.from_euler(1, -2, 3, 4, -5, 605), cell.camera, None, "easy",
                        seed=2).image
    with TestClient(create_app(cell)) as client:
        yield client, cell, cv2.imencode(".png", img)[1].tobytes()


def _files(cell) -> list[str]:
    return sorted(p.name for p in (cell.service.data_dir / "images").iterdir())


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EROFS, errno.EDQUOT])
def test_full_or_read_only_disk_is_503_with_the_reason_and_nothing_half_written(
        service, monkeypatch, code):
    client, cell, png = service
    store = client.app.state.store
    n0, files0 = store.count(), _files(cell)

    def fail(path, data):       # half the image written, then the disk refuses
        path.write_bytes(data[: len(data) // 2])
        raise OSError(code, errno.errorcode[code])

    monkeypatch.setattr(store, "write_file", fail)
    r = client.post("/v1/measurements", content=png, headers=AUTH)
    assert r.status_code == 503 and r.headers["retry-after"], r.text
    body = r.json()
    assert body["error"] == "storage_unavailable" and "\n" not in body["message"]
    assert {errno.ENOSPC: "disk is full", errno.EROFS: "read-only",
            errno.EDQUOT: "quota"}[code] in body["message"]
    assert store.count() == n0 and _files(cell) == files0       # nothing half written
    monkeypatch.undo()                                          # space is back
    r = client.post("/v1/measurements", content=png, headers=AUTH)
    assert r.status_code == 200 and store.get(r.json()["id"]) == r.json()


def test_database_full_removes_the_image_it_wrote(service, monkeypatch):
    """The image is written, then SQLite finds the disk full: 503, the image removed."""
    client, cell, png = service
    store = client.app.state.store
    n0, files0 = store.count(), _files(cell)
    real = store._db

    class FullDb:
        def execute(self, sql, *a):
            if sql.startswith("INSERT"):
                raise sqlite3.OperationalError("database or disk is full")
            return real.execute(sql, *a)

    monkeypatch.setattr(store, "_db", FullDb())
    r = client.post("/v1/measurements", content=png, headers=AUTH)
    assert r.status_code == 503 and "disk is full" in r.json()["message"], r.text
    monkeypatch.undo()
    assert store.count() == n0 and _files(cell) == files0
    assert client.post("/v1/measurements", content=png, headers=AUTH).status_code == 200


def _serve(tmp_path):
    """``cutterpose serve`` on a cell whose data directory is ``tmp_path/data``: exit code,
    output, seconds."""
    cell = write_cell(tmp_path, factor=4, token=TOKEN, workers=1)
    t0 = time.perf_counter()
    r = CliRunner().invoke(cli_app, ["serve", "--config", str(cell), "--port", "1"],
                           env={"CUTTERPOSE_TOKEN": TOKEN})
    return r.exit_code, r.output, time.perf_counter() - t0


@pytest.mark.parametrize("content, words", [
    (b"this is not a database at all" * 100, "not an SQLite database"),
    (None, "not a cutterpose record"),
])
def test_corrupt_or_foreign_database_stops_the_start(tmp_path, content, words):
    data = tmp_path / "data"
    data.mkdir()
    db = data / DB_NAME
    if content is None:                          # a valid SQLite file of something else
        con = sqlite3.connect(db)
        con.execute("CREATE TABLE other (x)")
        con.commit()
        con.close()
    else:
        db.write_bytes(content)
    before = db.read_bytes()
    code, out, dt = _serve(tmp_path)
    assert code == 2 and words in out and "Traceback" not in out, out
    assert len(out.strip().splitlines()) <= 4 and dt < 5.0      # the cell log line + error
    assert db.read_bytes() == before                            # never replaced


def test_locked_database_is_named_at_start(tmp_path):
    """Another process holds the database's write lock: the store says so within its open
    timeout, instead of starting and failing every measurement later."""
    data = tmp_path / "data"
    Store(data, 0).close()
    other = sqlite3.connect(data / DB_NAME, isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")
    try:
        t0 = time.perf_counter()
        with pytest.raises(StoreError, match="locked by another process"):
            Store(data, 0, open_timeout_s=0.5)
        assert time.perf_counter() - t0 < 2.0
    finally:
        other.execute("ROLLBACK")
        other.close()
    Store(data, 0).close()                       # and it opens once the lock is gone
