"""Tracking through the service (``/v1/tracks``, issue 13 with issue 12's service): a
rendered approach sent frame by frame as raw 8-bit bodies to a real ``cutterpose serve``
(uvicorn subprocess, full-size Table 1 camera, the bundled cell with the edge break declared
as the sequence's truth says), against the same frames tracked in this process.

Per frame: the round trip (request to answer, the body's upload included), the service's
own ``track_ms`` and the tracker's ``total`` stage; the poses must be the same as in-process
(the service runs the same tracker). ``--fps F`` sends frame ``i`` at ``i / F`` s (a camera's
pace; a frame waits while the previous one is answered).

    PYTHONPATH=src python benchmarks/service_track.py SEQ_DIR [--fps 10] [--method dm+]
        [--edge-break-mm 0]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from cutterpose.client import Client
from cutterpose.frames import load_frame
from cutterpose.geometry.camera import camera_from_dict
from cutterpose.service.loadtest import ServerProcess
from cutterpose.tracking import Tracker, approach_limits

TOKEN = "bench-service-track-0123456789"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--fps", type=float, default=None)
    ap.add_argument("--method", default="dm+b")
    ap.add_argument("--edge-break-mm", type=float, default=None)
    ap.add_argument("--frames", type=int, default=None, help="only the first N frames")
    a = ap.parse_args()
    truth = json.loads((a.sequence / "truth.json").read_text())
    cam = camera_from_dict(truth["camera"])
    frames = [load_frame(a.sequence / e["file"]) for e in truth["images"][:a.frames]]
    # in-process reference: the same tracker the service builds from the cell below
    tr = Tracker(cam, None, a.method, limits=replace(approach_limits(),
                                                     edge_break_mm=a.edge_break_mm))
    ref = [tr.update(f) for f in frames]
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "camera.json").write_text(json.dumps(truth["camera"]))
        lines = ['name = "service_track bench"', 'camera = "camera.json"',
                 f'method = "{a.method}"', "", "[service]", "workers = 1",
                 f'data_dir = "{tmp}/data"']
        if a.edge_break_mm is not None:
            lines[3:3] = ["[tolerances]", f"edge_break_mm = {a.edge_break_mm!r}", ""]
        (Path(tmp) / "cell.toml").write_text("\n".join(lines) + "\n")
        with ServerProcess(Path(tmp) / "cell.toml", token=TOKEN) as server, \
                Client(server.url, token=TOKEN) as c, c.track(filter=False) as t:
            rows = []
            t0 = time.perf_counter()
            for i, f in enumerate(frames):
                if a.fps:
                    time.sleep(max(t0 + i / a.fps - time.perf_counter(), 0.0))
                s = time.perf_counter()
                r = t.frame(f)
                rows.append((r, (time.perf_counter() - s) * 1e3))
    same = all(r["mode"] == q.mode and (q.pose is None or np.allclose(
        [r["pose"][k] for k in ("alpha_deg", "beta_deg", "gamma_deg", "X_mm", "Y_mm", "Z_mm")],
        q.pose.dof, atol=1e-9)) for (r, _), q in zip(rows, ref))
    tracked = [(r, ms) for r, ms in rows if r["mode"] == "track"]
    rt = np.array([ms for _, ms in tracked])
    own = np.array([r["timings_ms"]["track_ms"] for r, _ in tracked])
    trk = np.array([r["timings_ms"]["total"] for r, _ in tracked])
    srv = np.array([r["timings_ms"]["total_ms"] for r, _ in tracked])
    dec = np.array([r["timings_ms"]["decode_ms"] for r, _ in tracked])
    print(f"{a.sequence.name}: {len(rows)} frames, {len(tracked)} tracked; poses as "
          f"in-process: {same}")
    print(f"  tracked frames, median (p90) ms: round trip {np.median(rt):.1f} "
          f"({np.percentile(rt, 90):.1f}), service track_ms {np.median(own):.1f}, the "
          f"tracker's total {np.median(trk):.1f}; upload + decode + HTTP: "
          f"{np.median(rt - trk):.1f}, of which in the handler: reading the body "
          f"{np.median(srv - own - dec):.1f}, decoding {np.median(dec):.1f}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
