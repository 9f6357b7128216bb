"""``measure`` on pbr ``sharp`` images next to analytic renders at the same poses
(docs/notes/render_pbr.md): is it as accurate on the path-traced images?

Reads a pbr image set (``render-set --engine pbr --preset sharp``), renders the analytic
``easy`` image of each pose (same seed), measures both with ``dm+`` and prints the error
figures of the protocol (bias and std per DOF, p95 rotation and translation errors) and the
RMS of the detected corners against the truth.

    PYTHONPATH=src python benchmarks/pbr_measure_sharp.py /work/data/pbr_sharp_s100
"""

import argparse
from pathlib import Path

import cv2
import numpy as np

from cutterpose.errors import CutterposeError
from cutterpose.experiments.images import corner_rms, load_image_set
from cutterpose.geometry.pose import Pose, pose_errors
from cutterpose.pipeline import QualityLimits, measure
from cutterpose.render.analytic import render_holder


def summary(name, rows):
    ok = [r for r in rows if r["ok"]]
    line = f"{name}: {len(ok)}/{len(rows)} accepted"
    if ok:
        e = pose_errors(np.array([r["R"] for r in ok]), np.array([r["t"] for r in ok]),
                        np.array([r["Re"] for r in ok]), np.array([r["te"] for r in ok]))
        line += ("\n  bias " + " ".join(f"{x:+.3f}" for x in np.mean(e.dof, 0))
                 + "\n  std  " + " ".join(f"{x:.3f}" for x in np.std(e.dof, 0))
                 + f"\n  p95 rot {np.percentile(e.rot_deg, 95):.3f} deg, p95 trans "
                 f"{np.percentile(e.trans_mm, 95):.3f} mm, corner RMS median "
                 f"{np.median([r['rms'] for r in ok]):.3f} px")
    refused = [r["reason"] for r in rows if not r["ok"]]
    if refused:
        line += f"\n  refused: {refused}"
    return line


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("folder")
    ap.add_argument("--method", default="dm+")
    ap.add_argument("--limit", type=int, default=None)
    a = ap.parse_args()
    folder = Path(a.folder)
    camera, holder, entries = load_image_set(folder)
    rows = {"pbr": [], "analytic": []}
    for e in entries[: a.limit]:
        R, t = np.array(e["R_cam_holder"]), np.array(e["t_cam_holder_mm"])
        truth = np.array(e["corners_px"])
        img_pbr = cv2.imread(str(folder / e["file"]), cv2.IMREAD_GRAYSCALE)
        img_ana = render_holder(Pose(R, t), camera, holder, "easy", seed=e["seed"]).image
        for name, img in (("pbr", img_pbr), ("analytic", img_ana)):
            try:
                # the sharp preset's edge, declared for the corner methods' verdict
                m = measure(img, camera, holder, a.method, limits=QualityLimits(edge_break_mm=0))
                ok, reason = m.ok, m.quality.reason
            except CutterposeError as ex:
                m, ok, reason = None, False, str(ex)
            row = {"ok": bool(ok and m.pose is not None), "reason": reason, "R": R, "t": t}
            if row["ok"]:
                row.update(Re=m.pose.R, te=m.pose.t_mm, rms=corner_rms(m.corners_px, truth))
            rows[name].append(row)
    for name in rows:
        print(summary(f"{name} ({a.method})", rows[name]))


if __name__ == "__main__":
    main()
