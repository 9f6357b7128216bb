"""Every trial where dm or dm+ fails grossly: what its initial pose was, whether the ML estimate
(opencv-ippe-lm, known correspondences) fails there too, and whether dm started at the truth
would have succeeded (a wrong basin) or not (the data themselves mislead).

Usage: ``nice .venv/bin/python docs/dm-analysis/failures.py RUN_DIR [--trials 1000] [--seed 0]``
where RUN_DIR holds the ``trials.csv`` of ``cutterpose experiment synthetic`` run with (at least)
the methods initial, dm, dm+ and opencv-ippe-lm. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict
from pathlib import Path

import numpy as np

from cutterpose.experiments.synthetic import generate_trials
from cutterpose.geometry.holder import default_holder
from cutterpose.geometry.pose import pose_errors
from cutterpose.geometry.working_range import pose_dof
from cutterpose.solvers.matching import distance_image, distance_match, dm_score
from cutterpose.solvers.vanishing import initial_pose


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run_dir")
    ap.add_argument("--trials", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    rows = defaultdict(dict)
    with open(Path(a.run_dir) / "trials.csv") as f:
        for r in csv.DictReader(f):
            rows[(float(r["sigma_px"]), int(r["trial"]))][r["method"]] = r
    bad = sorted(k for k, v in rows.items()
                 if any(v.get(m, {}).get("failed") == "1" for m in ("dm", "dm+")))
    holder = default_holder()
    print(f"{len(bad)} trials where dm or dm+ fails (of {len(rows)})\n")
    print("| sigma | trial | initial rot / trans err | dm rot / trans err | dm+ failed | "
          "ML failed | dm from truth rot / trans | D(dm) / D(true pose) px | verdict |")
    print("|---|---|---|---|---|---|---|---|---|")
    cache = {}
    for sigma, i in bad:
        if sigma not in cache:
            cache[sigma] = generate_trials(a.trials, sigma, seed=a.seed)
        tr = cache[sigma]
        v = rows[(sigma, i)]
        px = np.roll(tr.points_px[i], -int(tr.shift[i]), axis=0)
        if tr.reverse[i]:
            px = px[::-1]
        cam = tr.camera
        init = initial_pose(px, cam, holder)
        ei = pose_errors(tr.R_cam_holder[i], tr.t_cam_holder_mm[i], init.R_cam_holder,
                         init.t_cam_holder_mm)
        dm = distance_match(px, cam, holder, init)
        ed = pose_errors(tr.R_cam_holder[i], tr.t_cam_holder_mm[i], dm.R_cam_holder,
                         dm.t_cam_holder_mm)
        tru = distance_match(px, cam, holder, (tr.R_cam_holder[i], tr.t_cam_holder_mm[i]))
        et = pose_errors(tr.R_cam_holder[i], tr.t_cam_holder_mm[i], tru.R_cam_holder,
                         tru.t_cam_holder_mm)
        dimg = distance_image(px, bilinear=True)
        d_true = dm_score(pose_dof(tr.R_cam_holder[i], tr.t_cam_holder_mm[i])[None], dimg, cam,
                          holder)[0]
        if et.failed[0]:
            verdict = "noise: the DM optimum next to the truth is itself beyond the threshold"
        elif dm.residual_px > tru.residual_px + 1e-9:
            verdict = "wrong basin: the search from the truth ends better and within threshold"
        else:
            verdict = "the wrong pose scores better than the basin of the truth"
        print(f"| {sigma} | {i} | {ei.rot_deg[0]:.2f} / {ei.trans_mm[0]:.1f} | "
              f"{ed.rot_deg[0]:.2f} / {ed.trans_mm[0]:.1f} | {v.get('dm+', {}).get('failed')} | "
              f"{v.get('opencv-ippe-lm', {}).get('failed')} | {et.rot_deg[0]:.2f} / "
              f"{et.trans_mm[0]:.1f} | {dm.residual_px:.2f} / {d_true:.2f} | {verdict} |")


if __name__ == "__main__":
    main()
