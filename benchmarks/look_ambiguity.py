"""How far the design edge moves between edge-model looks that fit the band equally well, at the
true pose: the part of the depth that one image cannot tell (issue 10, "new holders: |Z bias|
<= 0.05 mm"; docs/notes/edge_band.md, "What limits it").

At the true pose of each image every look of ``dm+b`` (``band_looks``: 2 shapes x the
photometric variants, each at the three blurs) is fitted to every segment with the radius and the
shift free (the fine scan, from its own coarse scan). A look is *as good as the best* when its
trimmed cost is within ``--tie`` (default 5 %) of the best look's: with ~80 segments of ~240
samples each, such looks are not told apart by the image. For those looks the script reports
the mean design-edge shift (px, outward positive; 0 = the true design edge) and the depth the
pose fit gives to their design-edge points (``Z`` error against the truth, mm): the spread over
equally good looks is a floor on the depth bias of any look chosen from this family by the
image alone.

    PYTHONPATH=src python benchmarks/look_ambiguity.py /work/data/pbr_new_s200 "range(0, 50, 5)"
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import cv2
import numpy as np

from cutterpose.geometry.camera import camera_from_dict
from cutterpose.geometry.holder import holder_from_dict
from cutterpose.geometry.pose import Pose
from cutterpose.image import edge_model as em
from cutterpose.image.edge_band import (
    BLURS_PX,
    BandFit,
    _fit_looks,
    _ModelBank,
    band_looks,
    model_grid_px,
    sample_band,
)
from cutterpose.solvers.edge_band import design_pose


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("set_dir")
    ap.add_argument("which", help='images, e.g. "range(0, 50, 5)"')
    ap.add_argument("--tie", type=float, default=0.05, help="cost within this fraction")
    a = ap.parse_args()
    doc = json.load(open(f"{a.set_dir}/truth.json"))
    cam = camera_from_dict(doc["camera"])
    holder = holder_from_dict(doc["holder"])
    spans_px, spans_z = [], []
    print(f"{'image':14s} {'best look':34s} {'ties':>4s} {'shift px (best; range of ties)':>32s}"
          f" {'Z err mm (best; range of ties)':>32s}")
    for i in eval(a.which, {"range": range}):
        im = doc["images"][i]
        img = cv2.imread(f"{a.set_dir}/{im['file']}", cv2.IMREAD_GRAYSCALE)
        R, t = np.array(im["R_cam_holder"]), np.array(im["t_cam_holder_mm"])
        dof_true = Pose(R, t).dof
        bp = sample_band(img, cam, holder, R, t, n_seg=4, positions=12)
        grid = model_grid_px(bp)
        bank = _ModelBank(em.edge_views(R, t, cam.K, holder), grid)
        rows = []
        for lk in band_looks():
            coarse = _fit_looks(bp, bank, [lk])[0]
            for lf in _fit_looks(bp, bank, [replace(lk, blur_sigma_px=b) for b in BLURS_PX],
                                 coarse):
                v = bp.valid & np.isfinite(lf.shift_var_px2) & np.isfinite(lf.cost)
                if v.sum() < 6:
                    continue
                dof = design_pose(BandFit(lf, [], bp), lf, cam.K, dof_true, v)
                rows.append((lf.total, lf, float(np.median(lf.shift_px[v])),
                             float(dof[5] - dof_true[5])))
        rows.sort(key=lambda r: r[0])
        best = rows[0]
        ties = [r for r in rows if r[0] <= (1 + a.tie) * best[0]]
        sh = [r[2] for r in ties]
        dz = [r[3] for r in ties]
        spans_px.append(max(sh) - min(sh))
        spans_z.append(max(dz) - min(dz))
        lk = best[1].look
        name = (f"{lk.shape} s{lk.specular:g} m{lk.shininess:g} fa{lk.face_albedo:g} "
                f"wa{lk.wall_albedo:g} b{lk.blur_sigma_px:g}")
        print(f"{im['file']:14s} {name:34s} {len(ties):4d} "
              f"{best[2]:+7.2f}; {min(sh):+6.2f} .. {max(sh):+6.2f}      "
              f"{best[3]:+7.3f}; {min(dz):+6.3f} .. {max(dz):+6.3f}", flush=True)
    print(f"\nover {len(spans_z)} images: range of the design edge's shift over looks within "
          f"{100 * a.tie:.0f} % of the best cost: median {np.median(spans_px):.2f} px, max "
          f"{np.max(spans_px):.2f} px; of the depth: median {np.median(spans_z):.3f} mm, max "
          f"{np.max(spans_z):.3f} mm")


if __name__ == "__main__":
    main()
