"""Are the errors of several views of one holder independent, and what does fusing them give?

    PYTHONPATH=src python benchmarks/view_fusion.py VIEWS.json [VIEWS.json ...] [--rho R ...]
        [--scale S ...] [--birge]

Input: ``benchmarks/view_errors.py`` runs on sets rendered with ``render-set --views``. The
robot's frame is taken as the true holder frame (``T_base_holder = I``), so the robot and the
hand-eye are exact here and every view's estimate of ``T_base_holder`` is its error.

Prints (PROTOCOL.md error figures; the grasp point is the holder origin, as the budget's):
* the intra-class correlation of the errors (holder frame, per component) over the holders
  whose views all have a pose: the share of the error that belongs to the holder, not the view;
* per number of views k: holders whose fused pose the verdict accepts (3 sigma within 1 mm /
  0.3 deg), errors of the accepted ones, wrong acceptances (> 1 mm or 0.5 deg) and how often
  the fused 3 sigma covers the error, fused with ``cutterpose.robot.fuse_poses`` under the
  given inter-view correlation.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from cutterpose.geometry.pose import Pose
from cutterpose.robot.frames import PoseCov, cov_from_own_axes
from cutterpose.robot.fuse import fuse_poses, sqrt_psd

POS_TOL_MM, ANG_TOL_DEG = 1.0, 0.3
WRONG_MM, WRONG_DEG = 1.0, 0.5
BUDGET_REASONS = ("error budget", "pose too uncertain")


def view_estimate(rec: dict) -> PoseCov | None:
    """``T_base_holder`` of one view with its covariance (base = the true holder frame)."""
    if rec["R_est"] is None or rec["covariance_cam"] is None:
        return None
    T_cam_h = Pose(np.array(rec["R_est"]), np.array(rec["t_est_mm"]), "cam", "holder")
    T_cam_true = Pose(np.array(rec["R_true"]), np.array(rec["t_true_mm"]), "cam", "base")
    T_base_cam = PoseCov.exact(T_cam_true.inverse())
    m = PoseCov(T_cam_h, cov_from_own_axes(T_cam_h, np.array(rec["covariance_cam"])))
    return T_base_cam @ m


def error6(pc: PoseCov) -> np.ndarray:
    """The error of an estimate of ``T_base_holder`` (base = the true holder frame): its
    translation (mm) and rotation vector (rad), in the convention of its covariance."""
    return np.concatenate([pc.pose.t_mm, Rotation.from_matrix(pc.pose.R).as_rotvec()])


def errors(pc: PoseCov) -> tuple[float, float, np.ndarray]:
    """(rotation error deg, translation error at the origin mm, 6-vector t mm, rotvec deg)."""
    e = error6(pc)
    e[3:] = np.degrees(e[3:])
    return float(np.linalg.norm(e[3:])), float(np.linalg.norm(e[:3])), e


def fusable(rec: dict) -> bool:
    """A view that enters a fusion: accepted, or refused by its budget only (a pose whose
    uncertainty is known)."""
    return rec["accepted"] or any(s in (rec["reason"] or "") for s in BUDGET_REASONS)


def icc(groups: list[np.ndarray]) -> np.ndarray:
    """One-way random-effects intra-class correlation per column (groups of equal size k)."""
    X = np.stack(groups)  # (g, k, d)
    g, k, _ = X.shape
    gm = X.mean(axis=1)
    msb = k * ((gm - X.mean(axis=(0, 1))) ** 2).sum(axis=0) / (g - 1)
    msw = ((X - gm[:, None, :]) ** 2).sum(axis=(0, 1)) / (g * (k - 1))
    return (msb - msw) / (msb + (k - 1) * msw)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--rho", type=float, nargs="+", default=[0.0, 0.5],
                    help="inter-view correlation of the measurement errors to fuse with")
    ap.add_argument("--scale", type=float, nargs="+", default=[1.0],
                    help="variance factor on the measurement's covariance to fuse with")
    ap.add_argument("--birge", action="store_true",
                    help="scale each fused covariance by max(1, chi2 / dof) of its views' "
                         "residuals (the weighted mean's Birge ratio)")
    a = ap.parse_args(argv)
    for path in a.runs:
        doc = json.loads(open(path).read())
        by_h = defaultdict(dict)      # holder -> view -> (record, estimate or None)
        for rec in doc["images"]:
            by_h[rec["holder_index"]][rec["view"]] = (rec, view_estimate(rec))
        n_views = max(len(v) for v in by_h.values())
        print(f"\n## {doc['set']} ({doc['method']}, look {doc['edge_look'] or 'generic'}): "
              f"{len(by_h)} holders x {n_views} views")
        # single views
        acc1 = [pc for h in by_h.values() for r, pc in h.values() if r["accepted"]]
        print(f"single views accepted: {len(acc1)} of {sum(len(h) for h in by_h.values())}")
        acc1 = [pc for pc in acc1 if pc is not None]
        out_r = out_p = 0
        for pc in acc1:
            er, et, _ = errors(pc)
            out_r += int(er > pc.angle_3sigma_deg)
            out_p += int(et > pc.position_3sigma_mm)
        print(f"accepted single views with an error beyond their own 3 sigma: rotation {out_r}, "
              f"position {out_p} of {len(acc1)}")
        # intra-class correlation of the holder-frame errors
        groups = []
        for h in by_h.values():
            pcs = [h[v][1] for v in sorted(h)]
            if len(pcs) == n_views and all(p is not None for p in pcs):
                groups.append(np.stack([errors(p)[2] for p in pcs]))
        if len(groups) > 2:
            c = icc(groups)
            print(f"ICC over {len(groups)} holders (t_x, t_y, t_z, r_x, r_y, r_z; holder "
                  "frame): " + " ".join(f"{v:+.2f}" for v in c))
            E = np.concatenate(groups)
            print("error std (mm, deg): " + " ".join(f"{v:.3f}" for v in E.std(axis=0)))
        # the same in the budget's metric: whitened errors z_i = S_i^-1 e_i; under the fusion's
        # model E[z_i z_j^T] = rho I (i != j) and E[z_i z_i^T] = I
        zs = []
        for h in by_h.values():
            z = [np.linalg.solve(sqrt_psd(pc.cov), error6(pc)) for r, pc in h.values()
                 if pc is not None and fusable(r)]
            if len(z) >= 2:
                zs.append(np.stack(z))
        if zs:
            same = np.mean([float(z @ z) / 6 for g in zs for z in g])
            cross = np.mean([float(g[i] @ g[j]) / 6 for g in zs for i in range(len(g))
                             for j in range(len(g)) if i != j])
            print(f"whitened errors over {len(zs)} holders: E[z_i.z_i]/6 = {same:.2f} "
                  f"(1 if the budget is the error's covariance), E[z_i.z_j]/6 = {cross:.2f}, "
                  f"their ratio (the views' correlation in the budget's metric) "
                  f"{cross / same:.2f}")
        for rho, scale in [(r, c) for c in a.scale for r in a.rho]:
            print(f"\nfused with inter-view correlation {rho}, variance x {scale}:")
            print("| views | holders with a fused pose | accepted | p95 rot / trans over "
                  "accepted | max | wrong (> 1 mm or 0.5 deg) | 3 sigma covers (all) | "
                  "median error / 3 sigma, rot / pos (all) |")
            print("|---|---|---|---|---|---|---|---|")
            for k in range(1, n_views + 1):
                n_pose = n_acc = wrong = covered = 0
                rots, trans, q_rot, q_pos = [], [], [], []
                for h in by_h.values():
                    pcs = [PoseCov(pc.pose, scale * pc.cov)
                           for r, pc in (h[v] for v in sorted(h)[:k])
                           if pc is not None and fusable(r)]
                    if not pcs:
                        continue
                    f = fuse_poses(pcs, rho=rho)
                    if a.birge and f.dof:
                        f = replace(f, fused=PoseCov(f.fused.pose,
                                                     max(1.0, f.chi2 / f.dof) * f.fused.cov))
                    n_pose += 1
                    er, et, _ = errors(f.fused)
                    ok = f.position_3sigma_mm <= POS_TOL_MM and f.angle_3sigma_deg <= ANG_TOL_DEG
                    covered += int(et <= f.position_3sigma_mm and er <= f.angle_3sigma_deg)
                    q_rot.append(er / f.angle_3sigma_deg)
                    q_pos.append(et / f.position_3sigma_mm)
                    if ok:
                        n_acc += 1
                        rots.append(er)
                        trans.append(et)
                        wrong += int(et > WRONG_MM or er > WRONG_DEG)
                p95 = (f"{np.percentile(rots, 95):.3f} / {np.percentile(trans, 95):.3f}"
                       if rots else "-")
                mx = f"{max(rots):.3f} / {max(trans):.3f}" if rots else "-"
                print(f"| {k} | {n_pose} | {n_acc} of {len(by_h)} | {p95} | {mx} | {wrong} | "
                      f"{covered} of {n_pose} | {np.median(q_rot):.2f} / "
                      f"{np.median(q_pos):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
