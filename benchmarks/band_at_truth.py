"""The band fit at the true pose of pbr images: how far each segment's design-edge point lies
from the true design edge, with the radius fitted and with the true radius imposed
(docs/notes/edge_band.md, "What limits it").

Usage: python benchmarks/band_at_truth.py IMAGE_SET "range(1, 50, 8)"
"""

from __future__ import annotations

import json
import sys

import cv2
import numpy as np
from worn_floor import shifts_radius_known, true_radius_at_segments

from cutterpose.geometry.camera import camera_from_dict
from cutterpose.geometry.holder import holder_from_dict
from cutterpose.image import edge_model as em
from cutterpose.image.edge_band import fit_band, sample_band


def main(setdir: str, which: str):
    d = json.load(open(f"{setdir}/truth.json"))
    cam = camera_from_dict(d["camera"])
    holder = holder_from_dict(d["holder"])
    free_all, known_all = [], []
    for i in eval(which, {"range": range}):
        im = d["images"][i]
        img = cv2.imread(f"{setdir}/{im['file']}", cv2.IMREAD_GRAYSCALE)
        R, t = np.array(im["R_cam_holder"]), np.array(im["t_cam_holder_mm"])
        bp = sample_band(img, cam, holder, R, t, n_seg=4, positions=12)
        f = fit_band(bp, cam, holder, R, t)
        rt = true_radius_at_segments(im, holder, bp)
        view = em.edge_views(R, t, cam.K, holder)
        known = shifts_radius_known(bp, f, view, rt, len(holder.corners_mm))
        v = bp.valid & np.isfinite(f.best.shift_var_px2)
        print(f"{im['file']} {f.best.look.shape}: shift with r fitted: mean "
              f"{f.best.shift_px[v].mean():+.2f} sd {f.best.shift_px[v].std():.2f} px; r known: "
              f"mean {known[v].mean():+.2f} sd {known[v].std():.2f} px; r error sd "
              f"{np.std(f.best.radius_mm[v] - rt[v]):.2f} mm")
        free_all += list(f.best.shift_px[v])
        known_all += list(known[v])

    def mad(x):
        x = np.asarray(x)
        return 1.4826 * np.median(np.abs(x - np.median(x)))

    print(f"all: r fitted sd {np.std(free_all):.2f} (MAD {mad(free_all):.2f}) px; r known sd "
          f"{np.std(known_all):.2f} (MAD {mad(known_all):.2f}) px")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
