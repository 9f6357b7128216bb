"""``cutterpose records export``: the service's stored measurements as CSV or JSON.

CSV: one row per measurement, oldest first, columns :data:`CSV_COLUMNS` (camera-frame pose and
its 1-sigma per DOF, the verdict, the flange pose sent, the image hash and the times). JSON: a
list of the stored answers, unchanged. The database is opened read-only, so an export may run
beside a live service.

Convention:
    Angles in degrees, lengths in mm, times in ms, ``created_at`` ISO 8601 UTC; the pose is
    ``T_cam_holder`` (PROTOCOL.md); ``flange_*`` is ``T_base_flange`` as sent.
"""

from __future__ import annotations

import csv
import io
import json
import sqlite3
from datetime import UTC, datetime
from pathlib import Path

from ..errors import InputError
from .store import DB_NAME

__all__ = ["export_records", "CSV_COLUMNS", "parse_since"]

_DOF = ("alpha_deg", "beta_deg", "gamma_deg", "X_mm", "Y_mm", "Z_mm")
_FLANGE = ("flange_x_mm", "flange_y_mm", "flange_z_mm", "flange_qx", "flange_qy", "flange_qz",
           "flange_qw")
CSV_COLUMNS = (("id", "request_id", "created_at", "ok", "verdict", "verdict_basis", "method",
                "quality_ok", "quality_reason", "rms_residual_px") + _DOF
               + tuple(f"std_{d}" for d in _DOF) + _FLANGE
               + ("robot_available", "grasp_verdict", "holder", "image_sha256", "image_bytes",
                  "measure_ms", "total_ms"))


def parse_since(since: str | None) -> str:
    """An ISO 8601 time (UTC when it has no zone) as the store's text form; None: ``""``."""
    if not since:
        return ""
    try:
        t = datetime.fromisoformat(since)
    except ValueError:
        raise InputError(f"--since {since!r}: not an ISO 8601 time (e.g. 2025-01-31T08:00:00Z"
                         " or 2025-01-31)") from None
    t = t if t.tzinfo else t.replace(tzinfo=UTC)
    return t.astimezone(UTC).isoformat(timespec="microseconds")


def _row(rec: dict) -> dict:
    m = rec["measurement"]
    pose = m.get("pose") or {}
    std = m.get("std") or {}
    q = m.get("quality") or {}
    flange = rec.get("flange_pose") or [None] * 7
    robot = rec.get("robot") or {}
    out = {"id": rec["id"], "request_id": rec.get("request_id"),
           "created_at": rec["created_at"], "ok": int(rec["ok"]), "verdict": rec["verdict"],
           "verdict_basis": rec.get("verdict_basis"), "method": m.get("method"),
           "quality_ok": int(bool(q.get("ok"))), "quality_reason": q.get("reason", ""),
           "rms_residual_px": q.get("rms_residual_px")}
    out |= {d: pose.get(d) for d in _DOF}
    out |= {f"std_{d}": std.get(d) for d in _DOF}
    out |= dict(zip(_FLANGE, flange))
    out |= {"robot_available": int(bool(robot.get("available"))),
            "grasp_verdict": (robot.get("grasp") or {}).get("verdict"),
            "holder": rec.get("holder"), "image_sha256": rec["image"]["sha256"],
            "image_bytes": rec["image"]["bytes"],
            "measure_ms": rec["timings_ms"]["measure_ms"],
            "total_ms": rec["timings_ms"]["total_ms"]}
    return out


def export_records(data_dir, since: str | None = None, fmt: str = "csv") -> tuple[str, int]:
    """The records with ``created_at >= since`` as CSV or JSON text, and their count.

    Raises
    ------
    InputError
        Unknown format, a bad ``since``, or no database in ``data_dir``.
    """
    if fmt not in ("csv", "json"):
        raise InputError(f"--format {fmt!r}: choose csv or json")
    since_text = parse_since(since)
    db = Path(data_dir) / DB_NAME
    if not db.is_file():
        raise InputError(f"{db}: no measurement database (wrong --data-dir / cell file?)")
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        rows = con.execute("SELECT record FROM measurements WHERE created_at >= ? "
                           "ORDER BY created_at, seq", (since_text,)).fetchall()
    finally:
        con.close()
    recs = [json.loads(r[0]) for r in rows]
    if fmt == "json":
        return json.dumps(recs, indent=1) + "\n", len(recs)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, lineterminator="\n")
    w.writeheader()
    for rec in recs:
        w.writerow(_row(rec))
    return buf.getvalue(), len(recs)
