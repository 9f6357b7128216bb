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

from cutterpose.geometry.camera import camera_from_dict
from cutterpose.geometry.holder import holder_from_dict
from cutterpose.image import edge_model as em
from cutterpose.image.edge_band import STEP_PX, _scan, fit_band, sample_band


def true_radius(im, holder, bp):
    out = []
    for e, fr in zip(bp.edge, bp.frac):
        E = im["edges"][e]
        rs = np.array(E["radius_samples_mm"])
        L = np.linalg.norm(np.subtract(holder.corners_mm[(e + 1) % len(holder.corners_mm)],
                                       holder.corners_mm[e]))
        out.append(np.interp(fr * L, np.arange(len(rs)) * E["radius_step_mm"], rs))
    return np.array(out)


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
        rt = true_radius(im, holder, bp)
        view = em.edge_views(R, t, cam.K, holder)
        S, n = len(bp.edge), len(holder.corners_mm)
        w_idx = np.rint(bp.w_px / STEP_PX).astype(int)
        Y = np.where(bp.valid[:, None], bp.values, 0.0)
        known = np.zeros(S)
        for j in range(S // n):
            sel = np.arange(j, S, S // n)
            per_end = np.zeros((n, 2, 1))
            per_end[:, 1, 0], per_end[:, 0, 0] = rt[sel], np.roll(rt[sel], 1)
            w0, _, bl = em.profiles(per_end, view, f.best.look, half_width_px=60.0,
                                    step_px=STEP_PX)
            k, fr = bp.edge[sel], bp.frac[sel][:, None, None]
            models = (1 - fr) * bl[k, 1] + fr * bl[(k + 1) % n, 0]
            shifts = np.arange(-30, 31)
            cost, _ = _scan(Y[sel], models, int(round(-w0[0] / STEP_PX)), w_idx, shifts)
            known[sel] = shifts[np.argmin(cost[:, 0, :], axis=1)] * STEP_PX
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
