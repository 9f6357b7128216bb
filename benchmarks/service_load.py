"""Load run of the measurement service (issue 12): the real server (uvicorn subprocess on
127.0.0.1), ``--clients`` concurrent clients sending ``--total`` measurements, against the
single-process ``measure`` time of the same images.

    python benchmarks/service_load.py --factor 1     # full-size Table 1 camera (4112 x 3008)
    python benchmarks/service_load.py --factor 4     # the test's 4x4-binned camera

Prints one JSON object: throughput, latency percentiles (per answered attempt, and end to end
with the 503 retries), 503 count, errors, the database check (every answer stored once and
unchanged, PRAGMA integrity_check) and the single-process measure time (median over the
images, decode included, in this process while the server is idle).
"""

from __future__ import annotations

import argparse
import json
import sqlite3
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from cutterpose.geometry.camera import camera_from_dict, default_camera
from cutterpose.pipeline import measure
from cutterpose.service.loadtest import (
    ServerProcess,
    reduced_camera_dict,
    render_images,
    run_load,
    write_cell,
)
from cutterpose.service.store import DB_NAME


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--factor", type=int, default=4, help="camera binning (1 = full size)")
    ap.add_argument("--clients", type=int, default=100)
    ap.add_argument("--total", type=int, default=500)
    ap.add_argument("--images", type=int, default=5, help="distinct rendered images")
    ap.add_argument("--workers", type=int, default=0, help="0 = one per core")
    ap.add_argument("--queue", type=int, default=32)
    args = ap.parse_args(argv)

    camera = (default_camera("table1") if args.factor == 1
              else camera_from_dict(reduced_camera_dict(args.factor)))
    t0 = time.perf_counter()
    images = render_images(camera, args.images, seed=3)
    render_s = time.perf_counter() - t0
    single = []
    for b in images:
        t = time.perf_counter()
        measure(cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_GRAYSCALE), camera)
        single.append(time.perf_counter() - t)
    token = "bench-token"
    with tempfile.TemporaryDirectory() as tmp:
        cell = write_cell(tmp, factor=args.factor, token=token, workers=args.workers,
                          queue_size=args.queue, image_cap_mb=512)
        with ServerProcess(cell) as s:
            workers = len(s.ready()["workers"])
            res = run_load(s.url, token, images, args.clients, args.total, timeout_s=1800)
        con = sqlite3.connect(Path(tmp) / "data" / DB_NAME)
        integrity = con.execute("PRAGMA integrity_check").fetchone()[0]
        stored = {rid: json.loads(rec) for rid, rec in
                  con.execute("SELECT request_id, record FROM measurements")}
        con.close()
    same = all(stored.get(rid) == a for rid, a in res.answers.items())
    out = {"camera_px": list(camera.image_size_px), "png_bytes_mean":
           int(statistics.mean(len(b) for b in images)), "workers": workers,
           "clients": args.clients, "total": args.total, **res.summary(),
           "stored": len(stored), "stored_equal_answers": same, "integrity_check": integrity,
           "single_process_measure_ms_median": round(statistics.median(single) * 1e3, 1),
           "ideal_throughput_per_s": round(workers / statistics.median(single), 2),
           "render_s": round(render_s, 1), "errors_sample": res.errors[:3]}
    print(json.dumps(out, indent=1))
    return 0 if not res.errors and same and integrity == "ok" else 1


if __name__ == "__main__":
    sys.exit(main())
