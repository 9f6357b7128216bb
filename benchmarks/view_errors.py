"""Measure every image of a set rendered with ``--views`` and keep, per image, the pose, its
covariance and the truth: the input of ``benchmarks/view_fusion.py``.

    PYTHONPATH=src python benchmarks/view_errors.py SET OUT.json [--method dm+b]
        [--edge-look LOOK.json] [--limit N]

Each record: file, holder_index, view, accepted, reason, R/t estimated and true (cam_holder),
``covariance_cam`` (PROTOCOL.md order, own axes for the rotation) or null.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from cutterpose.image_set import load_image_set
from cutterpose.pipeline import measure

try:
    from tqdm import tqdm
except ImportError:  # pragma: no cover
    def tqdm(x, **_):
        return x


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("set")
    ap.add_argument("out")
    ap.add_argument("--method", default="dm+b")
    ap.add_argument("--edge-look", default=None)
    ap.add_argument("--limit", type=int, default=None)
    a = ap.parse_args(argv)
    folder = Path(a.set)
    camera, holder, entries = load_image_set(folder)
    look = None
    if a.edge_look:
        from cutterpose.calibration.edge_look import load_edge_look
        look = load_edge_look(a.edge_look)
    images = entries[: a.limit]
    out = []
    for im in tqdm(images, desc="measure", unit="image"):
        m = measure(folder / im["file"], camera, holder, method=a.method, edge_look=look)
        C = m.covariance_cam
        out.append({
            "file": im["file"], "holder_index": im.get("holder_index"), "view": im.get("view"),
            "accepted": bool(m.ok), "reason": m.quality.reason,
            "R_est": None if m.pose is None else m.pose.R.tolist(),
            "t_est_mm": None if m.pose is None else m.pose.t_mm.tolist(),
            "R_true": im["R_cam_holder"], "t_true_mm": im["t_cam_holder_mm"],
            "covariance_cam": None if C is None or not np.all(np.isfinite(C)) else C.tolist(),
            "position_3sigma_mm": None if m.quality.budget is None
            else m.quality.budget.position_3sigma_mm,
            "angle_3sigma_deg": None if m.quality.budget is None
            else m.quality.budget.angle_3sigma_deg,
        })
    Path(a.out).write_text(json.dumps({"set": str(folder), "method": a.method,
                                       "edge_look": a.edge_look, "images": out}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
