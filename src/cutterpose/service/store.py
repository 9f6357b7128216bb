"""The service's record: every answered measurement in an embedded SQLite database, the images in
a folder with a size cap.

Durability: the database is in WAL mode with ``synchronous = FULL`` (each commit is on disk
before :meth:`Store.insert` returns, and the service answers only after that), so neither a
killed process nor a power cut loses an answered measurement. Images are written to a temporary
file and renamed into place before the row that names them is committed; when the folder grows
past its cap the oldest images are deleted first (their rows stay, with ``image_file`` NULL).

Idempotency: ``request_id`` (the client's) is UNIQUE; :meth:`Store.insert` of a second row with
the same one returns the first row instead (a retried request gets the first answer).

Convention:
    ``created_at``: ISO 8601 UTC with microseconds (``2025-01-31T12:00:00.123456+00:00``),
    which sorts as text; ``seq`` is the insertion order.
"""

from __future__ import annotations

import errno
import json
import os
import sqlite3
import threading
from collections import deque
from pathlib import Path

from ..errors import StoreError

__all__ = ["Store", "DB_NAME", "StoreError"]

DB_NAME = "measurements.sqlite3"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS measurements (
    seq          INTEGER PRIMARY KEY AUTOINCREMENT,
    id           TEXT NOT NULL UNIQUE,
    request_id   TEXT UNIQUE,
    created_at   TEXT NOT NULL,
    image_sha256 TEXT NOT NULL,
    image_bytes  INTEGER NOT NULL,
    image_format TEXT NOT NULL,
    image_file   TEXT,
    width_px     INTEGER,
    height_px    INTEGER,
    holder       TEXT,
    flange_pose  TEXT,
    ok           INTEGER NOT NULL,
    verdict      TEXT NOT NULL,
    method       TEXT,
    total_ms     REAL,
    record       TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS measurements_created ON measurements(created_at);
"""


class Store:
    """SQLite record and image folder under ``data_dir`` (module doc). Thread-safe: one
    connection behind a lock (the service calls it from a thread pool)."""

    def __init__(self, data_dir: Path, image_cap_bytes: int, open_timeout_s: float = 5.0):
        self.data_dir = Path(data_dir)
        self.images_dir = self.data_dir / "images"
        self.db_path = self.data_dir / DB_NAME
        self.image_cap_bytes = int(image_cap_bytes)
        self._lock = threading.Lock()
        try:
            self.images_dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise StoreError(f"{self.images_dir}: cannot be created ({e.strerror})") from None
        self._db = self._open(open_timeout_s)
        # images oldest first (names carry no order: the file times do)
        files = [(p.stat().st_mtime_ns, p.name, p.stat().st_size)
                 for p in self.images_dir.iterdir() if p.is_file() and not p.name.startswith(".")]
        for p in self.images_dir.glob(".tmp-*"):
            p.unlink(missing_ok=True)  # left by a kill between write and rename
        files.sort()
        self._images = deque((name, size) for _, name, size in files)
        self.images_bytes = sum(s for _, s in self._images)

    def _open(self, timeout_s: float) -> sqlite3.Connection:
        """The database, checked: an existing file must be an intact cutterpose record (never
        silently replaced by a new empty one), and writable now (not locked by another
        process)."""
        existed = self.db_path.is_file() and self.db_path.stat().st_size > 0
        db = sqlite3.connect(self.db_path, check_same_thread=False, isolation_level=None,
                             timeout=timeout_s)
        try:
            if existed:                       # checked before anything is written
                names = {r[0] for r in db.execute("SELECT name FROM sqlite_master")}
                if "measurements" not in names:
                    raise StoreError(f"{self.db_path}: an SQLite file without a measurements "
                                     "table: not a cutterpose record (move it away or choose "
                                     "another data_dir); nothing was changed")
                check = db.execute("PRAGMA quick_check(1)").fetchone()[0]
                if check != "ok":
                    raise StoreError(f"{self.db_path}: the record is corrupt ({check}); "
                                     "restore it from a backup or move it away")
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=FULL")
            db.executescript(_SCHEMA)
            db.execute("BEGIN IMMEDIATE")     # can we write? (locked / read-only)
            db.execute("ROLLBACK")
            db.execute("PRAGMA busy_timeout = 30000")
        except sqlite3.Error as e:
            db.close()
            raise StoreError(f"{self.db_path}: {_why(e, timeout_s)}") from None
        except StoreError:
            db.close()
            raise
        return db

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # -- writing -------------------------------------------------------------------------
    def insert(self, record: dict, row: dict, image: bytes | None, ext: str) -> dict:
        """Store a measurement: the image (if kept), then the row, committed.

        Parameters
        ----------
        record : the answer (JSON object), stored as it is sent.
        row : the indexed columns (``id``, ``request_id``, ``created_at``, ``image_sha256``,
            ``image_bytes``, ``image_format``, ``width_px``, ``height_px``, ``holder``,
            ``flange_pose``, ``ok``, ``verdict``, ``method``, ``total_ms``).
        image : the body to keep (None: not kept).
        ext : file extension of the image.

        Returns
        -------
        dict : the stored answer: ``record``, or the first one stored under the same
            ``request_id``.
        """
        text = json.dumps(record, allow_nan=False, separators=(",", ":"))
        name = None
        keep = image is not None and 0 < len(image) <= self.image_cap_bytes
        with self._lock:
            if row.get("request_id") is not None:
                first = self._by_request_id(row["request_id"])
                if first is not None:
                    return first
            if keep:
                name = f"{row['id']}{ext}"
                self._write_image(name, image)
            cols = dict(row, image_file=name, record=text)
            try:
                self._db.execute(
                    f"INSERT INTO measurements ({', '.join(cols)}) "
                    f"VALUES ({', '.join('?' * len(cols))})", tuple(cols.values()))
            except sqlite3.IntegrityError:
                self._unlink(name)
                first = self._by_request_id(row.get("request_id"))
                if first is None:
                    raise
                return first
            except sqlite3.Error as e:
                self._unlink(name)                   # nothing half written
                raise StoreError(f"{self.db_path}: the row was not written "
                                 f"({_why(e, 30)})", transient=True) from None
            if name:
                self._images.append((name, len(image)))
                self.images_bytes += len(image)
                self._evict()
        return record

    def write_file(self, path: Path, data: bytes) -> None:
        """Write ``data`` to ``path`` (the one place the store writes an image file; tests
        replace it to simulate a full or read-only disk)."""
        path.write_bytes(data)

    def _write_image(self, name: str, image: bytes) -> None:
        """The image under its name, whole or not at all (temporary file, then renamed)."""
        tmp = self.images_dir / f".tmp-{name}"
        try:
            self.write_file(tmp, image)
            os.replace(tmp, self.images_dir / name)
        except OSError as e:
            self._unlink(tmp.name)
            raise StoreError(f"{self.images_dir}: the image was not written "
                             f"({_os_why(e)})", transient=True) from None

    def _unlink(self, name: str | None) -> None:
        if name:
            try:
                (self.images_dir / name).unlink(missing_ok=True)
            except OSError:
                pass                                 # read-only: left for the next start

    def _evict(self) -> None:
        gone = []
        while self.images_bytes > self.image_cap_bytes and self._images:
            name, size = self._images.popleft()
            self._unlink(name)
            self.images_bytes -= size
            gone.append(name)
        if gone:
            self._db.executemany("UPDATE measurements SET image_file = NULL WHERE image_file = ?",
                                 [(n,) for n in gone])

    # -- reading -------------------------------------------------------------------------
    def _by_request_id(self, request_id) -> dict | None:
        if request_id is None:
            return None
        r = self._db.execute("SELECT record FROM measurements WHERE request_id = ?",
                             (request_id,)).fetchone()
        return json.loads(r[0]) if r else None

    def by_request_id(self, request_id: str) -> dict | None:
        """The stored answer of a client request id, or None."""
        with self._lock:
            return self._by_request_id(request_id)

    def row(self, request_id: str) -> dict | None:
        """The indexed columns of a client request id (to compare a retried request)."""
        with self._lock:
            cur = self._db.execute("SELECT image_sha256, flange_pose, holder FROM measurements "
                                   "WHERE request_id = ?", (request_id,))
            r = cur.fetchone()
        return None if r is None else dict(zip(("image_sha256", "flange_pose", "holder"), r))

    def get(self, measurement_id: str) -> dict | None:
        with self._lock:
            r = self._db.execute("SELECT record FROM measurements WHERE id = ?",
                                 (measurement_id,)).fetchone()
        return json.loads(r[0]) if r else None

    def image(self, measurement_id: str) -> tuple[Path, str, tuple[int, int], str | None] | None:
        """``(path, format, (width, height), holder)`` of a kept image, or None (unknown id or
        evicted)."""
        with self._lock:
            r = self._db.execute("SELECT image_file, image_format, width_px, height_px, holder "
                                 "FROM measurements WHERE id = ?", (measurement_id,)).fetchone()
        if r is None or r[0] is None:
            return None
        path = self.images_dir / r[0]
        return (path, r[1], (r[2], r[3]), r[4]) if path.is_file() else None

    def since(self, since: str, limit: int) -> list[dict]:
        """Answers with ``created_at >= since`` (ISO 8601 UTC), oldest first, at most
        ``limit``."""
        with self._lock:
            rows = self._db.execute("SELECT record FROM measurements WHERE created_at >= ? "
                                    "ORDER BY created_at, seq LIMIT ?", (since, limit)).fetchall()
        return [json.loads(r[0]) for r in rows]

    def count(self) -> int:
        with self._lock:
            return self._db.execute("SELECT COUNT(*) FROM measurements").fetchone()[0]

    def integrity_check(self) -> str:
        with self._lock:
            return self._db.execute("PRAGMA integrity_check").fetchone()[0]


def _os_why(e: OSError) -> str:
    names = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is used up",
             errno.EROFS: "the file system is read-only",
             errno.EACCES: "no permission to write", errno.EPERM: "no permission to write"}
    return f"{names.get(e.errno, 'cannot be written')}: {e.strerror or e}"


def _why(e: sqlite3.Error, timeout_s: float) -> str:
    text = str(e)
    if "locked" in text or "busy" in text:
        return (f"the database is locked by another process for more than {timeout_s:g} s "
                f"(another cutterpose serve on this data_dir?) ({text})")
    if "not a database" in text or "malformed" in text:
        return f"not an SQLite database, or a corrupt one ({text}); nothing was changed"
    if "full" in text:
        return f"the disk is full ({text})"
    if "readonly" in text or "read-only" in text:
        return f"the database cannot be written: read-only ({text})"
    if "unable to open" in text:
        return f"the database cannot be opened ({text})"
    return text
